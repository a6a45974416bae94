"""On-line model update (ch. 6.4.3): probe measurements feed a per-machine RLS state (eqs. 6.10-6.13).

The on-line model predicts what the current off-line model leaves in the work space: for each of
dx, dy, dz one recursive least-squares fit with forgetting of the residual (probe measurement minus
off-line prediction) on phi = [1, dT_k ...] (eq. 6.10). The state belongs to one model version: a
new current model starts a new on-line state. Each update is persisted with its probe measurement.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Request

from driftlab.api.deps import ApiState, get_state, require_token
from driftlab.api.routes.machines import MachineId
from driftlab.api.schemas import OnlineOut, ProbeIn, Vector3
from driftlab.campaigns import api_queries
from driftlab.errors import ConflictError, NotFoundError, ValidationError
from driftlab.models import registry
from driftlab.models.online import RLSState, rls_init, rls_update

router = APIRouter(tags=["online"])

COMPONENTS = ("dx", "dy", "dz")
DEFAULT_FORGETTING = 0.98
#: work-space error vector slots of dx, dy, dz (PARAMS order alpha, beta, gamma, dx, dy, dz)
SLOTS = {"dx": 3, "dy": 4, "dz": 5}


def _vec(v: np.ndarray | dict[str, float]) -> Vector3:
    """Return a Vector3 from a (3,) array or a mapping."""
    vals = [float(v[c]) for c in COMPONENTS] if isinstance(v, dict) else [float(x) for x in v]
    if not all(math.isfinite(x) for x in vals):
        raise ValidationError("the on-line update produced a non-finite value; check the inputs")
    return Vector3(dx=vals[0], dy=vals[1], dz=vals[2])


def _current(state: ApiState, machine_id: str) -> api_queries.ModelRow:
    """Return the machine's current model row, read from the store (not the cache)."""
    row = api_queries.current_model(state.store, machine_id)
    if row is None:
        api_queries.get_machine(state.store, machine_id)
        raise NotFoundError(f"machine {machine_id!r} has no current model")
    return row


def _out(machine_id: str, row: api_queries.ModelRow, st: dict[str, Any], **extra: Any) -> OnlineOut:
    """Return the response model of a persisted on-line state."""
    return OnlineOut(machine_id=machine_id, model_version=row.version, channels=list(st["channels"]),
                     forgetting=float(st["forgetting"]), n_updates=int(st["n_updates"]),
                     theta={c: [float(x) for x in st["states"][c]["theta"]] for c in COMPONENTS}, **extra)


@router.get("/machines/{machine_id}/online", response_model=OnlineOut, response_model_exclude_none=True,
            summary="The machine's on-line (RLS) state")
def get_online(machine_id: MachineId, state: Annotated[ApiState, Depends(get_state)]) -> OnlineOut:
    """Return the on-line state of the machine's current model version (404 before its first update)."""
    row = _current(state, machine_id)
    st = api_queries.online_state(state.store, machine_id, row.id)
    if st is None:
        raise NotFoundError(f"machine {machine_id!r} has no on-line updates for model version {row.version} yet")
    return _out(machine_id, row, st)


@router.post("/machines/{machine_id}/online/probe", response_model=OnlineOut, response_model_exclude_none=True,
             dependencies=[Depends(require_token)], summary="Post a probe measurement; returns the new correction")
def post_probe(machine_id: MachineId, body: ProbeIn, request: Request,
               state: Annotated[ApiState, Depends(get_state)]) -> OnlineOut:
    """Update the machine's RLS state with one probe measurement and return the correction at that pose."""
    row = _current(state, machine_id)
    doc = registry.validate_document(row.document)
    temps = dict(body.temperatures)
    q = np.array([[body.x, body.y, body.z, math.radians(body.a_deg), math.radians(body.b_deg)]])
    offline_w = registry.predict_workspace_errors(doc, temps, q)[0]
    offline = np.array([offline_w[SLOTS[c]] for c in COMPONENTS])
    measured = {"dx": body.dx, "dy": body.dy, "dz": body.dz}

    prior = api_queries.online_state(state.store, machine_id, row.id)
    if prior is None:
        channels = list(dict.fromkeys(body.channels or []))
        forgetting = DEFAULT_FORGETTING if body.forgetting is None else float(body.forgetting)
        missing = [c for c in channels if c not in temps]
        if missing:
            raise ValidationError(f"temperatures lack on-line channel(s) {', '.join(missing)}")
        refs = {c: (doc.inputs[c].reference if c in doc.inputs else float(temps[c])) for c in channels}
        states = {c: rls_init(1 + len(channels), lam=forgetting) for c in COMPONENTS}
        n_before = 0
    else:
        channels, forgetting, refs = list(prior["channels"]), float(prior["forgetting"]), dict(prior["refs"])
        if body.channels is not None and list(dict.fromkeys(body.channels)) != channels:
            raise ConflictError(f"the on-line state of model version {row.version} reads {channels}; "
                                "channels can only be chosen when the state starts")
        if body.forgetting is not None and float(body.forgetting) != forgetting:
            raise ConflictError(f"the on-line state of model version {row.version} has forgetting factor "
                                f"{forgetting}; it can only be chosen when the state starts")
        states = {c: RLSState.from_dict(prior["states"][c]) for c in COMPONENTS}
        n_before = int(prior["n_updates"])
    missing = [c for c in channels if c not in temps]
    if missing:
        raise ValidationError(f"temperatures lack on-line channel(s) {', '.join(missing)}")

    phi = np.array([1.0, *[float(temps[c]) - refs[c] for c in channels]])  # eq. 6.10
    prior_err, online = np.zeros(3), np.zeros(3)
    new_states: dict[str, RLSState] = {}
    for k, c in enumerate(COMPONENTS):
        residual = measured[c] - offline[k]
        new_states[c], prior_err[k] = rls_update(states[c], phi, residual)  # eqs. 6.11-6.13
        online[k] = float(phi @ new_states[c].theta)
    for st in new_states.values():
        if not (np.all(np.isfinite(st.theta)) and np.all(np.isfinite(st.P))):
            raise ValidationError("the on-line update diverged (non-finite state); check the inputs")
    measured_at = body.measured_at or datetime.now(UTC)
    if measured_at.tzinfo is None:
        measured_at = measured_at.replace(tzinfo=UTC)
    saved = {"model_version_id": row.id, "model_version": row.version, "channels": channels, "refs": refs,
             "forgetting": forgetting, "n_updates": n_before + 1,
             "states": {c: new_states[c].to_dict() for c in COMPONENTS},
             "last": {"offline": offline.tolist(), "online": online.tolist(), "prior_error": prior_err.tolist()}}
    pose = {"x": body.x, "y": body.y, "z": body.z, "a_deg": body.a_deg, "b_deg": body.b_deg}
    params = {**pose, **measured, "measured_at": measured_at.isoformat(), "temperatures": temps}
    update_id = api_queries.save_online_update(state.store, machine_id, row.id, measured_at, pose, measured,
                                               n_before, saved, params)
    return _out(machine_id, row, saved, update_id=update_id, offline_prediction=_vec(offline),
                prior_error=_vec(prior_err), online_prediction=_vec(online), correction=_vec(-(offline + online)))
