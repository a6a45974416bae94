"""On-line model update (ch. 6.4.3): probe measurements feed the machine's RLS state (eqs. 6.10-6.13).

The on-line model (``driftlab.models.online``) predicts what the current off-line model leaves in
the work space: for each of dx, dy, dz a recursive least-squares fit with forgetting of the residual
(probe measurement minus off-line prediction). Its state belongs to one model version (a new current
model starts a new state) and is the same state ``driftlab online`` continues from the command line.
The state is the machine's row of ``online_states``; each update posted here is persisted, with its
probe measurement (a ``probe_measurements`` row), in one transaction.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Annotated, Any

import numpy as np
import pandas as pd
from fastapi import APIRouter, Depends, Response

from driftlab.api.deps import ApiState, get_state, require_token
from driftlab.api.routes.machines import MachineId
from driftlab.api.schemas import OnlineOut, ProbeIn, Vector3
from driftlab.api.strict import StrictJsonRoute
from driftlab.campaigns.store import ModelVersionInfo
from driftlab.errors import NotFoundError, ValidationError
from driftlab.jobs import online

router = APIRouter(tags=["online"], route_class=StrictJsonRoute)

TERMS = online.PROBE_TERMS  # dx, dy, dz
DEFAULT_FORGETTING = online.DEFAULT_FORGETTING


def _vec(values: Any) -> Vector3:
    """Return a Vector3 from three numbers in dx, dy, dz order."""
    vals = [float(x) for x in values]
    if not all(math.isfinite(x) for x in vals):
        raise ValidationError("the on-line update produced a non-finite value; check the inputs")
    return Vector3(dx=vals[0], dy=vals[1], dz=vals[2])


def _measured_at(value: datetime | None) -> datetime:
    """Return the measurement time in UTC (naive means UTC, None means now); refuse times outside 1970-2200."""
    if value is None:
        return datetime.now(UTC)
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    if not datetime(1970, 1, 2, tzinfo=UTC) <= value <= datetime(2200, 1, 1, tzinfo=UTC):
        raise ValidationError(f"measured_at must lie between 1970 and 2200, not {value.isoformat()}")
    return value.astimezone(UTC)


def _current(state: ApiState, machine_id: str) -> ModelVersionInfo:
    """Return the machine's current model row, read from the store (not the cache)."""
    row = state.store.models.current(machine_id)
    if row is None:
        state.store.campaigns.machine(machine_id)
        raise NotFoundError(f"machine {machine_id!r} has no current model")
    return row


def _out(machine_id: str, version: int, states: dict[str, online.RLSState], **extra: Any) -> OnlineOut:
    """Return the response model of an on-line state."""
    first = states[TERMS[0]]
    return OnlineOut(
        machine_id=machine_id,
        model_version=version,
        forgetting=first.lam,
        n_updates=first.n_updates,
        theta={t: [float(x) for x in states[t].theta] for t in TERMS},
        **extra,
    )


@router.get(
    "/machines/{machine_id}/online",
    response_model=OnlineOut,
    response_model_exclude_none=True,
    summary="The machine's on-line (RLS) state",
)
def get_online(machine_id: MachineId, state: Annotated[ApiState, Depends(get_state)]) -> OnlineOut:
    """Return the on-line state of the machine's current model version (404 before its first update)."""
    row = _current(state, machine_id)
    states = online.latest_online_states(state.store, machine_id, row.version)
    if not states:
        raise NotFoundError(f"machine {machine_id!r} has no on-line updates for model version {row.version} yet")
    return _out(machine_id, row.version, states)


@router.post(
    "/machines/{machine_id}/online/probe",
    response_model=OnlineOut,
    response_model_exclude_none=True,
    dependencies=[Depends(require_token)],
    summary="Post a probe measurement; returns the new correction",
)
def post_probe(machine_id: MachineId, body: ProbeIn, state: Annotated[ApiState, Depends(get_state)]) -> OnlineOut:
    """Update the machine's RLS state with one probe measurement and return the correction at that pose.

    correction = -(off-line prediction + on-line prediction), in mm, to add to the commanded position.
    The new state and the probe row are written in one transaction; a concurrent update of the same
    machine makes this one recompute from the state that landed first (none is lost).
    """
    measured_at = _measured_at(body.measured_at)
    clash = sorted(set(body.temperatures) & set(online.PROBE_COLUMNS))
    if clash:
        raise ValidationError(f"temperature channel name(s) {', '.join(clash)} clash with the probe columns")
    _current(state, machine_id)  # 404 for an unknown machine or one without a model
    probe = pd.DataFrame(
        [
            {
                "time_s": 0.0,
                "x": body.x,
                "y": body.y,
                "z": body.z,
                "a": body.a_deg,
                "b": body.b_deg,
                "dx": body.dx,
                "dy": body.dy,
                "dz": body.dz,
                **body.temperatures,
            }
        ]
    )
    done = online.store_update(
        state.store,
        machine_id,
        probe,
        [measured_at],
        None if body.forgetting is None else float(body.forgetting),
        [dict(body.temperatures)],
    )
    report = done.report
    residual = done.residual[0]
    measured = np.array([body.dx, body.dy, body.dz])
    offline = measured - residual
    on = np.array([float(report.states[t].theta @ np.ones(report.states[t].theta.size)) for t in TERMS])
    prior_error = residual - np.array([done.prior[t][0] for t in TERMS])
    return _out(
        machine_id,
        int(report.model_version or 0),
        report.states,
        update_id=done.probe_ids[0],
        offline_prediction=_vec(offline),
        prior_error=_vec(prior_error),
        online_prediction=_vec(on),
        correction=_vec(-(offline + on)),
    )


@router.delete(
    "/machines/{machine_id}/online",
    status_code=204,
    response_class=Response,
    dependencies=[Depends(require_token)],
    summary="Start the on-line model afresh",
)
def delete_online(machine_id: MachineId, state: Annotated[ApiState, Depends(get_state)]) -> Response:
    """Reset the machine's on-line (RLS) state, e.g. after maintenance: the next probe starts from the off-line model.

    404 when the machine has no on-line state to reset. The probe history is kept.
    """
    _current(state, machine_id)
    if not online.reset_online_state(state.store, machine_id):
        raise NotFoundError(f"machine {machine_id!r} has no on-line state to reset")
    return Response(status_code=204)
