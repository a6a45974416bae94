"""How well a campaign pinned the model: coefficient covariance, poorly pinned terms, prediction intervals.

The joint adjustment (``fitting.joint_adjust``) solves every element model's coefficients at once
through the linearised chain (eq. 4.12 to first order: W = sum_e Ad_e(q) p_e, p_e = F_e(x) c_e).
Its covariance, ``s^2 (A'A)^-1`` scaled for serial correlation, says how uncertain each coefficient
is and which coefficients trade off against each other: a spindle-link constant against a column
growth, an arm gradient against a base lag, when a campaign moves them together.

``JointFit`` is that result, statsmodels-style: ``params``, ``bse``, ``cov_params()``, the
regressors of each work-space component (``regressors``) and ``summary()``. The campaign advisor
reads it to predict how much a further stage would shrink the correction's variance.

Serial correlation: laser residuals are autocorrelated (AR(1)-like, one sweep to the next), so the
iid covariance is inflated by (1 + rho) / (1 - rho), rho the lag-1 autocorrelation of the
residuals in time order: the Newey-West (HAC) long-run variance of an AR(1) score with slowly
varying regressors.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
import pandas as pd

from driftlab.models.features import Feature
from driftlab.physics.kinematics import PARAMS

#: a pair of coefficients whose estimates correlate beyond this trades off (the campaign cannot tell them apart)
TRADE_OFF_CORR = 0.9
#: a term whose variance inflation factor exceeds this is poorly pinned (the stepwise rule's vif_max)
VIF_POOR = 30.0


def ar1_inflation(residual: np.ndarray) -> tuple[float, float]:
    """Return (rho, (1 + rho) / (1 - rho)): lag-1 autocorrelation of a residual series and its variance inflation."""
    r = np.asarray(residual, float)
    if r.size < 3 or not np.any(r):
        return 0.0, 1.0
    r = r - r.mean()
    rho = float(np.dot(r[1:], r[:-1]) / max(np.dot(r, r), 1e-300))
    rho = min(max(rho, 0.0), 0.95)
    return rho, (1.0 + rho) / (1.0 - rho)


def vif(F: np.ndarray) -> np.ndarray:
    """Return the variance inflation factor of each column of a design (inf for a column others reproduce).

    A constant column (an intercept) has no VIF of its own: NaN.
    """
    F = np.asarray(F, float)
    out = np.full(F.shape[1], np.nan)
    sd = F.std(axis=0)
    live = np.flatnonzero(sd > 0)
    if live.size == 0:
        return out
    if live.size == 1:
        out[live] = 1.0
        return out
    C = np.corrcoef(F[:, live], rowvar=False)
    try:
        inv = np.linalg.inv(C)
        out[live] = np.diag(inv)
    except np.linalg.LinAlgError:
        out[live] = np.inf
    return out


#: one pair of estimates that trade off: this term, the other ``element.param`` term, their correlation
#: (the functional form, since ``with`` is a keyword)
TradeOffRecord = TypedDict("TradeOffRecord", {"term": str, "with": str, "correlation": float})


class PinningRecord(TypedDict):
    """The JSON form of a :class:`Pinning` (fit report, ``pinning``)."""

    element: str
    param: str
    condition_number: float
    vif: dict[str, float | None]
    poorly_pinned: list[str]
    trade_offs: list[TradeOffRecord]


@dataclass
class Pinning:
    """How well one element model (link or joint parameter) was pinned by the campaign."""

    element: str
    param: str
    features: list[str]
    vif: list[float]
    condition_number: float
    #: (this term, the other element.param term, correlation of the two estimates)
    trade_offs: list[tuple[str, str, float]] = field(default_factory=list)

    @property
    def poor(self) -> list[str]:
        """Return the terms with a VIF above ``VIF_POOR`` or trading off with another."""
        out = [f for f, v in zip(self.features, self.vif) if np.isfinite(v) and v > VIF_POOR or v == np.inf]
        out += [a for a, _, _ in self.trade_offs if a not in out]
        return out

    def to_dict(self) -> PinningRecord:
        """Return the JSON form (fit report, ``pinning``)."""
        return {
            "element": self.element,
            "param": self.param,
            "condition_number": self.condition_number,
            "vif": {f: (None if not np.isfinite(v) else round(float(v), 2)) for f, v in zip(self.features, self.vif)},
            "poorly_pinned": self.poor,
            "trade_offs": [{"term": a, "with": b, "correlation": round(c, 3)} for a, b, c in self.trade_offs],
        }


@dataclass
class JointFit:
    """The joint adjustment's estimates with their covariance, statsmodels-style (see module docstring)."""

    #: one per coefficient: (element, param, feature)
    columns: list[tuple[str, str, Feature]]
    params: np.ndarray
    cov: np.ndarray
    #: per work-space component (PARAMS name): residual variance (mm^2 or rad^2) and lag-1 autocorrelation
    residual_variance: dict[str, float]
    rho: dict[str, float]
    inflation: float
    nobs: int
    #: per work-space component: the (n, P) regressors of the training rows (noise-weighted, datum-differenced)
    design: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    weights: dict[str, float] = field(default_factory=dict)

    @property
    def bse(self) -> np.ndarray:
        """Return the standard errors of the coefficients."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def names(self) -> list[str]:
        """Return each coefficient's name: ``element.param feature``."""
        return [f"{e}.{p} {f.name}" for e, p, f in self.columns]

    def cov_params(self) -> pd.DataFrame:
        """Return the coefficients' covariance as a named frame (statsmodels' ``cov_params()``)."""
        n = self.names()
        return pd.DataFrame(self.cov, index=n, columns=n)

    def regressors(self, component: str) -> np.ndarray:
        """Return the (n, P) regressors of one work-space component (``dz`` ...) in coefficient units.

        Each row is d W_component / d coefficient at a training reading (zeroed readings less their
        datum's), so ``regressors(t) @ cov @ regressors(t).T`` is the variance of the fit there.
        """
        A = self.design.get(component)
        if A is None:
            return np.zeros((0, len(self.columns)))
        return A / self.weights.get(component, 1.0)

    def block(self, element: str, param: str) -> tuple[list[int], np.ndarray]:
        """Return (indices, covariance) of one element model's coefficients."""
        idx = [i for i, (e, p, _) in enumerate(self.columns) if e == element and p == param]
        return idx, self.cov[np.ix_(idx, idx)]

    def correlation(self) -> np.ndarray:
        """Return the correlation matrix of the estimates."""
        sd = self.bse
        sd = np.where(sd > 0, sd, 1.0)
        return self.cov / np.outer(sd, sd)

    def pinning(self, designs: Mapping[tuple[str, str], np.ndarray]) -> list[Pinning]:
        """Return how well each element model was pinned: VIF of its design, condition number, trade-offs."""
        corr = self.correlation()
        names = self.names()
        out = []
        for (element, param), F in designs.items():
            idx, _ = self.block(element, param)
            if not idx:
                continue
            feats = [self.columns[i][2].name for i in idx]
            Fs = F / np.where(np.linalg.norm(F, axis=0) > 0, np.linalg.norm(F, axis=0), 1.0)
            cond = float(np.linalg.cond(Fs)) if Fs.size else float("nan")
            trades = []
            for i in idx:
                for j in np.flatnonzero(np.abs(corr[i]) > TRADE_OFF_CORR):
                    if j != i and self.columns[j][2].kind != "session":
                        trades.append((self.columns[i][2].name, names[j], float(corr[i, j])))
            out.append(Pinning(element, param, feats, list(vif(F)), cond, trades))
        return out

    def summary(self) -> str:
        """Return a plain-text table: coefficient, standard error, t, and the residual figures."""
        lines = [
            f"Joint adjustment: {len(self.columns)} coefficients, {self.nobs} readings, "
            f"serial-correlation inflation {self.inflation:.2f}",
            f"{'term':<48} {'coef':>12} {'std err':>12} {'t':>8}",
        ]
        for name, c, s in zip(self.names(), self.params, self.bse):
            t = c / s if s > 0 else float("nan")
            lines.append(f"{name:<48} {c:>12.4g} {s:>12.3g} {t:>8.2f}")
        for comp in PARAMS:
            if comp in self.residual_variance:
                lines.append(
                    f"residual {comp}: sd {np.sqrt(self.residual_variance[comp]):.3g}, lag-1 rho {self.rho[comp]:.2f}"
                )
        return "\n".join(lines)


def term_prediction_sd(X: np.ndarray, cov: np.ndarray, residual_variance: float = 0.0) -> np.ndarray:
    """Return the standard deviation of a term's prediction at rows ``X``: sqrt(x' C x + residual variance)."""
    X = np.atleast_2d(np.asarray(X, float))
    var = np.einsum("ij,jk,ik->i", X, np.asarray(cov, float), X) + max(residual_variance, 0.0)
    return np.sqrt(np.clip(var, 0.0, None))


def covariance_blocks(
    fit: JointFit, keys: Sequence[tuple[str, str]]
) -> dict[tuple[str, str], tuple[list[Feature], np.ndarray]]:
    """Return per element model its features and coefficient covariance (the document's ``covariance``)."""
    out = {}
    for key in keys:
        idx, C = fit.block(*key)
        if idx:
            out[key] = ([fit.columns[i][2] for i in idx], C)
    return out
