"""The on-line model's state in the store: read, update under the machine's lock, reset.

Joins ``models.online`` (the recursive least squares of ch. 6.4.3, pure) with the store's
``online_states`` and ``probe_measurements`` tables (``campaigns.store``): a probe update and the
state it produced are written in one transaction that holds the machine's lock from the read on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from driftlab.campaigns.online_repo import HeldOnlineState, OnlineUpdate, StaleOnlineState
from driftlab.errors import ConflictError, NotFoundError, ValidationError
from driftlab.models.document import validate_document
from driftlab.models.online import (
    DEFAULT_FORGETTING,
    ONLINE_JOB,
    PROBE_COLUMNS,
    PROBE_TERMS,
    OnlineReport,
    RLSState,
    online_residuals,
    online_update_residuals,
    probe_times,
)

if TYPE_CHECKING:
    from driftlab.campaigns.store import Store


def _legacy_states(store: Store, machine: str, model_version: int | None) -> dict[str, RLSState]:
    """Return the states kept before the ``online_states`` table: the last finished ``online`` job's result."""
    result = store.jobs.last_result(ONLINE_JOB, machine)
    if not result or result.get("model_version") != model_version:
        return {}
    return {k: RLSState.from_dict(v) for k, v in result.get("states", {}).items()}


def _states_of(row: Any) -> dict[str, RLSState]:
    """Return the per-term states of an ``online_states`` row."""
    return {
        k: RLSState(
            theta=np.asarray(row.theta[k], float), P=np.asarray(row.p[k], float), lam=row.lam, n_updates=row.n_updates
        )
        for k in row.theta
    }


def read_online_states(store: Store, machine: str, model_version: int | None) -> tuple[dict[str, RLSState], int | None]:
    """Return (the machine's on-line states for this model version, the row version they were read at).

    States of another model version are not continued (empty). Before the machine's first row in
    ``online_states``, a state kept the old way (as an ``online`` job's result) is read once; the
    next update writes it to the table.
    """
    row = store.online.get(machine)
    if row is None:
        return _legacy_states(store, machine, model_version), None
    if row.model_version != model_version:
        return {}, row.version
    return _states_of(row), row.version


def latest_online_states(store: Store, machine: str, model_version: int | None) -> dict[str, RLSState]:
    """Return the on-line states last stored for this machine and model version (empty when none)."""
    return read_online_states(store, machine, model_version)[0]


@dataclass
class StoredUpdate:
    """An on-line update as stored: the report, the one-step predictions, the residuals and the probe ids."""

    report: OnlineReport
    prior: dict[str, np.ndarray]
    residual: np.ndarray  # (N, 3) measured minus off-line prediction
    probe_ids: list[int]


def _probe_rows(
    probe: Any, measured_at: Sequence[Any], temperatures: Sequence[Mapping[str, float]] | None
) -> list[dict[str, Any]]:
    """Return the ``probe_measurements`` rows of the probe frame (temperatures: given, or the frame's channels)."""
    chans = [c for c in probe.columns if c not in PROBE_COLUMNS]
    rows = []
    columns = {"x": "x", "y": "y", "z": "z", "a_deg": "a", "b_deg": "b", "dx": "dx", "dy": "dy", "dz": "dz"}
    for i, (_, r) in enumerate(probe.iterrows()):
        temps = dict(temperatures[i]) if temperatures is not None else {c: float(r[c]) for c in chans}
        values = {k: float(r[c]) for k, c in columns.items()}
        rows.append({"measured_at": measured_at[i], **values, "temperatures": temps})
    return rows


def _states_under_lock(
    store: Store, held: HeldOnlineState, machine: str, model_version: int | None
) -> tuple[dict[str, RLSState], int | None]:
    """Return (the on-line states of this model version, the row version) read under the machine's lock."""
    row = held.current()
    if row is None:
        return _legacy_states(store, machine, model_version), None
    if row.model_version != model_version:
        return {}, row.version
    return _states_of(row), row.version


def _checked(report: OnlineReport) -> OnlineReport:
    """Return the report, refusing a diverged (non-finite) state."""
    for st in report.states.values():
        if not (np.all(np.isfinite(st.theta)) and np.all(np.isfinite(st.P))):
            raise ValidationError("the on-line update diverged (non-finite state); check the inputs")
    return report


def store_update(
    store: Store,
    machine: str,
    probe: Any,
    measured_at: Sequence[Any],
    lam: float | None = None,
    temperatures: Sequence[Mapping[str, float]] | None = None,
) -> StoredUpdate:
    """Update the machine's on-line state with probe measurements; store the state and the probes together.

    The state is held (``store.online.hold``: the machine's lock) while it is read, the update
    computed and both the new state and the probe rows written, in one transaction: concurrent
    updates of one machine queue for the lock and each is computed once, from the state the one
    before it left (none is lost). ``lam`` is the forgetting factor of a new state (default 0.98);
    choosing another one for a running state is refused. ``measured_at`` gives each probe row's time
    (aware datetimes).
    """
    if len(measured_at) != len(probe):
        raise ValidationError(f"{len(measured_at)} measurement times for {len(probe)} probe rows")
    if len(set(measured_at)) != len(measured_at):
        raise ValidationError("two probe measurements at the same time")
    info = store.models.current(machine)
    if info is None:
        raise NotFoundError(f"machine {machine!r} has no current model: run `driftlab fit` first")
    doc = validate_document(info.document).model_copy(update={"version": info.version})
    _, residual = online_residuals(doc, probe)
    rows = _probe_rows(probe, measured_at, temperatures)
    with store.online.hold(machine) as held:
        states, seen = _states_under_lock(store, held, machine, doc.version)
        if states and lam is not None and float(lam) != next(iter(states.values())).lam:
            raise ConflictError(
                f"the on-line state of model version {doc.version} has forgetting factor "
                f"{next(iter(states.values())).lam}; it can only be chosen when the state starts"
            )
        report, prior = online_update_residuals(
            doc.machine, doc.version, residual, states, DEFAULT_FORGETTING if lam is None else lam
        )
        first = _checked(report).states[PROBE_TERMS[0]]
        new = OnlineUpdate(
            model_version_id=info.id,
            model_version=int(doc.version or 0),
            lam=first.lam,
            n_updates=first.n_updates,
            theta={k: v.theta.tolist() for k, v in report.states.items()},
            p={k: v.P.tolist() for k, v in report.states.items()},
        )
        _, ids = held.save(seen, new, rows)
    return StoredUpdate(report, prior, residual, ids)


def reset_online_state(store: Store, machine: str) -> bool:
    """Start the machine's on-line model afresh (after maintenance or a re-calibration); False when it had none.

    The state row stays (its version moves on, so a concurrent update recomputes) with no terms:
    the next probe starts a new RLS from the current off-line model (eq. 6.13, P(0)). Probe history stays.
    """

    for _ in range(50):
        row = store.online.get(machine)
        if row is None or not row.theta:
            return False
        try:
            fresh = OnlineUpdate(row.model_version_id, row.model_version, row.lam, n_updates=0, theta={}, p={})
            store.online.save(machine, row.version, fresh)
            return True
        except StaleOnlineState:
            continue
    raise ConflictError(f"machine {machine!r}: the on-line state kept changing; retry the reset")


def online_update(store: Store, machine: str, probe: Any, lam: float | None = None, start: Any = None) -> OnlineReport:
    """Update the machine's on-line model with probe measurements and keep its state in the store.

    The on-line model is kept apart from the off-line document (ch. 4.3, 6.4.3): its state is the
    machine's row of ``online_states`` (continued while the model version stays current), and each
    probe measurement is a row of ``probe_measurements`` written in the same transaction.
    """
    times = probe_times(probe, start)
    data = probe.drop(columns=["measured_at"]) if "measured_at" in probe.columns else probe
    return store_update(store, machine, data, times, lam).report
