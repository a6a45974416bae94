"""On-line model: recursive least squares with a forgetting factor (ch. 6.4.3, eqs. 6.10-6.13).

The on-line model predicts what the off-line model leaves in the work space (probe measurements
at the work-space extremes minus the off-line prediction) and is kept separate from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.models.document import predict_workspace_errors, validate_document
from driftlab.vocabulary import TRANSLATIONS

if TYPE_CHECKING:
    import os

    from driftlab.models.document import ModelDocument


class RLSStateRecord(TypedDict):
    """The JSON form of an :class:`RLSState`: theta, the matrix P (rows), lambda, the update count."""

    theta: list[float]
    P: list[list[float]]
    lam: float
    n_updates: int


@dataclass
class RLSState:
    """The only memory the recursion carries: the coefficients theta and the matrix P."""

    theta: np.ndarray
    P: np.ndarray
    lam: float
    n_updates: int = 0

    def to_dict(self) -> RLSStateRecord:
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


#: P(0) of a fresh on-line model, in observations' inverse weight: 1e3 makes the start diffuse (the first
#: probe cycle's residuals set theta; Ljung 1987, whom ch. 6.4.3 follows). The thesis set P(0) "equal to a
#: small constant" and then ran the cutting test once "to allow the on-line parameters a chance to establish
#: themselves" (ch. 7.3); a diffuse start establishes them at the first cycle instead of that extra run.
#: With P(0) = 1 (as before 2026-11-27) theta0 = 0 weighed as one probe: the first cycle took half of a
#: 30 um wear (lambda 0.98), and a cut on a worn machine carried the rest for several cycles.
ONLINE_P0 = 1e3


def rls_init(n: int, lam: float = 0.98, p0: float = ONLINE_P0, theta0: Sequence[float] | None = None) -> RLSState:
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
        return rmse(self.prior_error)


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


# ------------------------------------------------------------- probe updates (stored by driftlab.jobs.online)

ONLINE_JOB = "online"
#: the forgetting factor of a new on-line state (eq. 6.12)
DEFAULT_FORGETTING = 0.98
PROBE_TERMS: tuple[str, ...] = TRANSLATIONS
PROBE_COLUMNS: tuple[str, ...] = ("time_s", "x", "y", "z", "a", "b", "dx", "dy", "dz")


def read_probe_csv(path: str | os.PathLike[str]) -> pd.DataFrame:
    """Return the probe measurements of a CSV (time_s, x, y, z, a, b in mm/deg, dx, dy, dz in mm, one column
    per channel)."""
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


class OnlineReportRecord(TypedDict):
    """The JSON form of an :class:`OnlineReport` (also what the store keeps as the on-line state)."""

    machine: str
    model_version: int | None
    n: int
    terms: dict[str, dict[str, float]]
    states: dict[str, RLSStateRecord]


@dataclass
class OnlineReport:
    """What an on-line update did: per term the off-line residual before and after the on-line model."""

    machine: str
    model_version: int | None
    n: int
    terms: dict[str, dict[str, float]]
    states: dict[str, RLSState]

    def to_dict(self) -> OnlineReportRecord:
        """Return the JSON form (also what the store keeps as the on-line state)."""
        return {
            "machine": self.machine,
            "model_version": self.model_version,
            "n": self.n,
            "terms": self.terms,
            "states": {k: v.to_dict() for k, v in self.states.items()},
        }


def online_residuals(document: Mapping[str, Any] | ModelDocument, probe: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Return (time_s, (N, 3) measured minus off-line predicted dx, dy, dz) for probe measurements."""
    q = np.column_stack([probe["x"], probe["y"], probe["z"], np.deg2rad(probe["a"]), np.deg2rad(probe["b"])])
    temps = probe.drop(columns=[c for c in PROBE_COLUMNS if c != "time_s"])
    W = predict_workspace_errors(document, temps, q)
    measured = probe[list(PROBE_TERMS)].to_numpy(float)
    return probe["time_s"].to_numpy(float), measured - W[:, 3:]


def online_update_document(
    document: Mapping[str, Any] | ModelDocument,
    probe: pd.DataFrame,
    states: Mapping[str, RLSState] | None = None,
    lam: float = 0.98,
) -> tuple[OnlineReport, dict[str, np.ndarray]]:
    """Return the report and per-term one-step predictions of the on-line model (phi = [1], eq. 6.10) on the probes."""
    doc = validate_document(document)
    _, resid = online_residuals(doc, probe)
    return online_update_residuals(doc.machine, doc.version, resid, states, lam)


def online_update_residuals(
    machine: str, model_version: int | None, resid: np.ndarray, states: Mapping[str, RLSState] | None, lam: float
) -> tuple[OnlineReport, dict[str, np.ndarray]]:
    """Return :func:`online_update_document`'s result from the probes' residuals (N, 3) against the off-line model."""
    out_states: dict[str, RLSState] = {}
    terms: dict[str, dict[str, float]] = {}
    preds: dict[str, np.ndarray] = {}
    for k, term in enumerate(PROBE_TERMS):
        st = (states or {}).get(term) or rls_init(1, lam=lam, p0=ONLINE_P0)
        run = rls_run(st, online_regressors(len(resid)), resid[:, k])
        out_states[term] = run.state
        preds[term] = run.prior_prediction
        terms[term] = {
            "offline_rms_mm": rmse(resid[:, k]),
            "online_rms_mm": run.rmse_prior,
            "correction_mm": float(run.state.theta[0]),
        }
    return OnlineReport(machine, model_version, len(resid), terms, out_states), preds


def probe_times(probe: pd.DataFrame, start: datetime | None = None) -> list[datetime]:
    """Return each probe row's wall-clock time: a ``measured_at`` column, else ``start`` + time_s, else
    counted back from now (the last row measured now); rows sharing a time_s are 1 us apart."""
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
    out: list[datetime] = []
    seen: set[datetime] = set()
    for x in t:
        at = origin + timedelta(seconds=float(x))
        while at in seen:  # several poses probed in one cycle share a time stamp: keep them apart by 1 us
            at += timedelta(microseconds=1)
        seen.add(at)
        out.append(at)
    return out
