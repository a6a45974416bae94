"""On-line model: recursive least squares with a forgetting factor (ch. 6.4.3, eqs. 6.10-6.13).

The on-line model predicts what the off-line model leaves in the work space (probe measurements
at the work-space extremes minus the off-line prediction) and is kept separate from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC
from typing import Any

import numpy as np

from driftlab.errors import ValidationError


@dataclass
class RLSState:
    """The only memory the recursion carries: the coefficients theta and the matrix P."""

    theta: np.ndarray
    P: np.ndarray
    lam: float
    n_updates: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {"theta": self.theta.tolist(), "P": self.P.tolist(), "lam": self.lam, "n_updates": self.n_updates}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RLSState:
        """Rebuild a state from its JSON form."""
        theta = np.asarray(d["theta"], float)
        P = np.asarray(d["P"], float)
        if P.shape != (theta.size, theta.size):
            raise ValidationError("on-line state: P does not match theta")
        return cls(theta=theta, P=P, lam=float(d["lam"]), n_updates=int(d.get("n_updates", 0)))


def rls_init(n: int, lam: float = 0.98, p0: float = 1e3, theta0: Sequence[float] | None = None) -> RLSState:
    """Return a fresh state: theta0 (zeros by default) and P(0) = p0 I (ch. 6.4.3)."""
    if not 0.0 < lam <= 1.0:
        raise ValidationError(f"forgetting factor must be in (0, 1], got {lam}")
    theta = np.zeros(n) if theta0 is None else np.asarray(theta0, float).copy()
    return RLSState(theta=theta, P=p0 * np.eye(n), lam=float(lam))


def rls_update(state: RLSState, phi: np.ndarray, y: float) -> tuple[RLSState, float]:
    """Return the state after one sample and the a-priori prediction error y - phi^T theta(t-1)."""
    phi = np.asarray(phi, float)
    P = state.P
    Pphi = P @ phi
    denom = state.lam + float(phi @ Pphi)
    L = Pphi / denom  # eq. 6.12
    err = float(y - phi @ state.theta)
    theta = state.theta + L * err  # eq. 6.11
    P = (P - np.outer(Pphi, Pphi) / denom) / state.lam  # eq. 6.13
    P = 0.5 * (P + P.T)  # keep P symmetric, or round-off makes it diverge
    return RLSState(theta=theta, P=P, lam=state.lam, n_updates=state.n_updates + 1), err


@dataclass
class OnlineRun:
    """The outcome of a run over a sequence of samples: predictions before each update, final state."""

    state: RLSState
    prior_prediction: np.ndarray
    prior_error: np.ndarray
    theta_history: np.ndarray = field(repr=False)

    @property
    def rmse_prior(self) -> float:
        """Return the RMS of the one-step-ahead prediction errors (the honest on-line figure)."""
        return float(np.sqrt(np.mean(self.prior_error**2))) if self.prior_error.size else float("nan")


def rls_run(state: RLSState, Phi: np.ndarray, y: np.ndarray) -> OnlineRun:
    """Return the run of eqs. 6.10-6.13 over the rows of ``Phi`` against ``y``, starting from ``state``."""
    Phi = np.atleast_2d(np.asarray(Phi, float))
    y = np.asarray(y, float)
    if Phi.shape[0] != y.size or Phi.shape[1] != state.theta.size:
        raise ValidationError(f"on-line data shape {Phi.shape} does not fit {state.theta.size} coefficients")
    pred = np.empty(y.size)
    errs = np.empty(y.size)
    hist = np.empty((y.size, state.theta.size))
    for i in range(y.size):
        pred[i] = Phi[i] @ state.theta
        state, errs[i] = rls_update(state, Phi[i], y[i])
        hist[i] = state.theta
    return OnlineRun(state=state, prior_prediction=pred, prior_error=errs, theta_history=hist)


def online_regressors(n: int, dT: Mapping[str, np.ndarray] | None = None, channels: Sequence[str] = ()) -> np.ndarray:
    """Return the on-line regressor matrix phi = [1, dT_k ...] (eq. 6.10) for ``n`` samples."""
    cols = [np.ones(n)]
    for c in channels:
        if dT is None or c not in dT:
            raise ValidationError(f"on-line model needs channel {c}")
        cols.append(np.asarray(dT[c], float))
    return np.column_stack(cols)


# ----------------------------------------------------------------------------- probe updates against the store

ONLINE_JOB = "online"
PROBE_TERMS: tuple[str, ...] = ("dx", "dy", "dz")
PROBE_COLUMNS: tuple[str, ...] = ("time_s", "x", "y", "z", "a", "b", "dx", "dy", "dz")


def read_probe_csv(path: Any) -> Any:
    """Return the probe measurements of a CSV (time_s, x, y, z, a, b in mm/deg, dx, dy, dz in mm, one column
    per channel)."""
    import pandas as pd

    try:
        df = pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise ValidationError(f"probe file {path}: {exc}") from None
    missing = [c for c in PROBE_COLUMNS if c not in df.columns]
    if missing:
        raise ValidationError(f"probe file {path}: missing column(s) {', '.join(missing)}")
    if df.empty:
        raise ValidationError(f"probe file {path}: no measurements")
    bad = ~np.isfinite(df[list(PROBE_COLUMNS)].to_numpy(float))
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0]) + 2
        raise ValidationError(f"probe file {path}:{row}: empty or non-numeric value")
    return df.sort_values("time_s", kind="stable").reset_index(drop=True)


@dataclass
class OnlineReport:
    """What an on-line update did: per term the off-line residual before and after the on-line model."""

    machine: str
    model_version: int | None
    n: int
    terms: dict[str, dict[str, float]]
    states: dict[str, RLSState]

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (also what the store keeps as the on-line state)."""
        return {
            "machine": self.machine,
            "model_version": self.model_version,
            "n": self.n,
            "terms": self.terms,
            "states": {k: v.to_dict() for k, v in self.states.items()},
        }


def online_residuals(document: Any, probe: Any) -> tuple[np.ndarray, np.ndarray]:
    """Return (time_s, (N, 3) measured minus off-line predicted dx, dy, dz) for probe measurements."""
    from driftlab.models.registry import predict_workspace_errors

    q = np.column_stack([probe["x"], probe["y"], probe["z"], np.deg2rad(probe["a"]), np.deg2rad(probe["b"])])
    temps = probe.drop(columns=[c for c in PROBE_COLUMNS if c != "time_s"])
    W = predict_workspace_errors(document, temps, q)
    measured = probe[list(PROBE_TERMS)].to_numpy(float)
    return probe["time_s"].to_numpy(float), measured - W[:, 3:]


def online_update_document(
    document: Any, probe: Any, states: Mapping[str, RLSState] | None = None, lam: float = 0.98
) -> tuple[OnlineReport, dict[str, np.ndarray]]:
    """Return the report and per-term one-step predictions of the on-line model (phi = [1], eq. 6.10) over
    the probe data."""
    from driftlab.models.registry import validate_document

    doc = validate_document(document)
    _, resid = online_residuals(doc, probe)
    out_states: dict[str, RLSState] = {}
    terms: dict[str, dict[str, float]] = {}
    preds: dict[str, np.ndarray] = {}
    for k, term in enumerate(PROBE_TERMS):
        st = (states or {}).get(term) or rls_init(1, lam=lam, p0=1.0)
        run = rls_run(st, online_regressors(len(resid)), resid[:, k])
        out_states[term] = run.state
        preds[term] = run.prior_prediction
        terms[term] = {
            "offline_rms_mm": float(np.sqrt(np.mean(resid[:, k] ** 2))),
            "online_rms_mm": run.rmse_prior,
            "correction_mm": float(run.state.theta[0]),
        }
    return OnlineReport(doc.machine, doc.version, len(resid), terms, out_states), preds


def _legacy_states(store: Any, machine: str, model_version: int | None) -> dict[str, RLSState]:
    """Return the states kept before the ``online_states`` table: the last finished ``online`` job's result."""
    from sqlalchemy import select

    from driftlab.campaigns.schema import Job

    store.ensure_schema()
    with store.engine.connect() as conn:
        row = conn.execute(
            select(Job.result).where(Job.kind == ONLINE_JOB, Job.machine_id == machine, Job.state == "done")
            .order_by(Job.id.desc()).limit(1)
        ).first()
    if row is None or not row[0] or row[0].get("model_version") != model_version:
        return {}
    return {k: RLSState.from_dict(v) for k, v in row[0].get("states", {}).items()}


def _states_of(row: Any) -> dict[str, RLSState]:
    """Return the per-term states of an ``online_states`` row."""
    return {k: RLSState(theta=np.asarray(row.theta[k], float), P=np.asarray(row.p[k], float), lam=row.lam,
                        n_updates=row.n_updates) for k in row.theta}


def read_online_states(store: Any, machine: str, model_version: int | None) -> tuple[dict[str, RLSState], int | None]:
    """Return (the machine's on-line states for this model version, the row version they were read at).

    States of another model version are not continued (empty). Before the machine's first row in
    ``online_states``, a state kept the old way (as an ``online`` job's result) is read once; the
    next update writes it to the table.
    """
    row = store.online_state(machine)
    if row is None:
        return _legacy_states(store, machine, model_version), None
    if row.model_version != model_version:
        return {}, row.version
    return _states_of(row), row.version


def latest_online_states(store: Any, machine: str, model_version: int | None) -> dict[str, RLSState]:
    """Return the on-line states last stored for this machine and model version (empty when none)."""
    return read_online_states(store, machine, model_version)[0]


@dataclass
class StoredUpdate:
    """An on-line update as stored: the report, the one-step predictions, the residuals and the probe ids."""

    report: OnlineReport
    prior: dict[str, np.ndarray]
    residual: np.ndarray  # (N, 3) measured minus off-line prediction
    probe_ids: list[int]
    attempts: int


def store_update(store: Any, machine: str, probe: Any, measured_at: Sequence[Any], lam: float | None = None,
                 temperatures: Sequence[Mapping[str, float]] | None = None, max_attempts: int = 50) -> StoredUpdate:
    """Update the machine's on-line state with probe measurements; store the state and the probes together.

    Optimistic concurrency: the state is read with its version, the update computed, and both the
    new state and the probe rows are written in one transaction only if the version is unchanged;
    otherwise the update is recomputed from the state that landed first (so no update is lost).
    ``lam`` is the forgetting factor of a new state (default 0.98); choosing another one for a
    running state is refused. ``measured_at`` gives each probe row's time (aware datetimes).
    """
    from driftlab.campaigns.store import StaleOnlineState
    from driftlab.errors import ConflictError, NotFoundError
    from driftlab.models.registry import validate_document

    if len(measured_at) != len(probe):
        raise ValidationError(f"{len(measured_at)} measurement times for {len(probe)} probe rows")
    if len(set(measured_at)) != len(measured_at):
        raise ValidationError("two probe measurements at the same time")
    chans = [c for c in probe.columns if c not in PROBE_COLUMNS]
    for attempt in range(1, max_attempts + 1):
        info = store.current_model(machine)
        if info is None:
            raise NotFoundError(f"machine {machine!r} has no current model: run `driftlab fit` first")
        doc = validate_document(info.document).model_copy(update={"version": info.version})
        states, seen = read_online_states(store, machine, doc.version)
        if states and lam is not None and float(lam) != next(iter(states.values())).lam:
            raise ConflictError(f"the on-line state of model version {doc.version} has forgetting factor "
                                f"{next(iter(states.values())).lam}; it can only be chosen when the state starts")
        _, residual = online_residuals(doc, probe)
        report, prior = online_update_document(doc, probe, states, DEFAULT_FORGETTING if lam is None else lam)
        for st in report.states.values():
            if not (np.all(np.isfinite(st.theta)) and np.all(np.isfinite(st.P))):
                raise ValidationError("the on-line update diverged (non-finite state); check the inputs")
        rows = []
        for i, (_, r) in enumerate(probe.iterrows()):
            temps = dict(temperatures[i]) if temperatures is not None else {c: float(r[c]) for c in chans}
            rows.append({"measured_at": measured_at[i], "x": float(r["x"]), "y": float(r["y"]), "z": float(r["z"]),
                         "a_deg": float(r["a"]), "b_deg": float(r["b"]), "dx": float(r["dx"]), "dy": float(r["dy"]),
                         "dz": float(r["dz"]), "temperatures": temps})
        first = report.states[PROBE_TERMS[0]]
        try:
            _, ids = store.save_online_state(
                machine, seen, model_version_id=info.id, model_version=int(doc.version or 0), lam=first.lam,
                n_updates=first.n_updates, theta={k: v.theta.tolist() for k, v in report.states.items()},
                p={k: v.P.tolist() for k, v in report.states.items()}, probes=rows)
        except StaleOnlineState:
            continue
        return StoredUpdate(report, prior, residual, ids, attempt)
    raise ConflictError(f"machine {machine!r}: the on-line state kept changing under {max_attempts} attempts; retry")


DEFAULT_FORGETTING = 0.98


def reset_online_state(store: Any, machine: str) -> bool:
    """Start the machine's on-line model afresh (after maintenance or a re-calibration); False when it had none.

    The state row stays (its version moves on, so a concurrent update recomputes) with no terms:
    the next probe starts a new RLS from the current off-line model (eq. 6.13, P(0)). Probe history stays.
    """
    from driftlab.campaigns.store import StaleOnlineState
    from driftlab.errors import ConflictError

    for _ in range(50):
        row = store.online_state(machine)
        if row is None or not row.theta:
            return False
        try:
            store.save_online_state(machine, row.version, model_version_id=row.model_version_id,
                                    model_version=row.model_version, lam=row.lam, n_updates=0, theta={}, p={})
            return True
        except StaleOnlineState:
            continue
    raise ConflictError(f"machine {machine!r}: the on-line state kept changing; retry the reset")


def probe_times(probe: Any, start: Any = None) -> list[Any]:
    """Return each probe row's wall-clock time: a ``measured_at`` column, else ``start`` + time_s, else
    counted back from now (the last row measured now); rows sharing a time_s are 1 us apart."""
    from datetime import datetime, timedelta

    import pandas as pd

    if "measured_at" in probe.columns:
        try:
            ts = pd.to_datetime(probe["measured_at"], utc=True)
        except (ValueError, TypeError) as exc:
            raise ValidationError(f"probe measured_at: {exc}") from None
        return [t.to_pydatetime() for t in ts]
    t = probe["time_s"].to_numpy(float)
    if start is None:
        origin = datetime.now(UTC) - timedelta(seconds=float(t.max()))
    else:
        origin = start if start.tzinfo else start.replace(tzinfo=UTC)
    out: list[Any] = []
    seen: set[Any] = set()
    for x in t:
        at = origin + timedelta(seconds=float(x))
        while at in seen:  # several poses probed in one cycle share a time stamp: keep them apart by 1 us
            at += timedelta(microseconds=1)
        seen.add(at)
        out.append(at)
    return out


def online_update(store: Any, machine: str, probe: Any, lam: float | None = None, start: Any = None) -> OnlineReport:
    """Update the machine's on-line model with probe measurements and keep its state in the store.

    The on-line model is kept apart from the off-line document (ch. 4.3, 6.4.3): its state is the
    machine's row of ``online_states`` (continued while the model version stays current), and each
    probe measurement is a row of ``probe_measurements`` written in the same transaction.
    """
    times = probe_times(probe, start)
    data = probe.drop(columns=["measured_at"]) if "measured_at" in probe.columns else probe
    return store_update(store, machine, data, times, lam).report
