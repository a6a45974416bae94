"""On-line model: recursive least squares with a forgetting factor (ch. 6.4.3, eqs. 6.10-6.13).

The on-line model predicts what the off-line model leaves in the work space (probe measurements
at the work-space extremes minus the off-line prediction) and is kept separate from it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
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
    def from_dict(cls, d: Mapping[str, Any]) -> "RLSState":
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
