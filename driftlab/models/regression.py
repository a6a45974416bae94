"""Stepwise multiple linear regression on statsmodels OLS (ch. 6.4.2, eqs. 6.8-6.9)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Protocol, TypedDict

import numpy as np
import pandas as pd
import statsmodels.api as sm
from scipy import stats

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.models.features import Feature, Inputs, design_matrix


class StepRecord(TypedDict):
    """The JSON form of a :class:`Step`."""

    action: str
    term: str
    statistic: float
    p_value: float


@dataclass
class Step:
    """One stepwise move: a term entered (with its partial F) or left (with its p-value)."""

    action: str
    term: str
    statistic: float
    p_value: float

    def to_dict(self) -> StepRecord:
        """Return the JSON form."""
        return {"action": self.action, "term": self.term, "statistic": self.statistic, "p_value": self.p_value}


@dataclass
class StepwiseResult:
    """A stepwise fit: the chosen features, the statsmodels OLS results and the path taken."""

    features: list[Feature]
    ols: Any  # statsmodels RegressionResultsWrapper
    steps: list[Step] = field(default_factory=list)
    collinear: list[str] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        """Return the term names in model order."""
        return [f.name for f in self.features]

    @property
    def params(self) -> pd.Series:
        """Return the coefficients by term name."""
        return pd.Series(np.asarray(self.ols.params), index=self.names)

    @property
    def bse(self) -> pd.Series:
        """Return the standard errors by term name."""
        return pd.Series(np.asarray(self.ols.bse), index=self.names)

    @property
    def pvalues(self) -> pd.Series:
        """Return the coefficient p-values by term name."""
        return pd.Series(np.asarray(self.ols.pvalues), index=self.names)

    @property
    def rsquared(self) -> float:
        """Return R^2 on the training data."""
        return float(self.ols.rsquared) if len(self.features) > 1 else 0.0

    @property
    def fvalue(self) -> float:
        """Return the regression F statistic (nan for an intercept-only model)."""
        return float(self.ols.fvalue) if len(self.features) > 1 else float("nan")

    @property
    def rmse(self) -> float:
        """Return the training RMSE of the residuals."""
        return rmse(self.ols.resid)

    @property
    def nobs(self) -> int:
        """Return the number of training samples."""
        return int(self.ols.nobs)

    @property
    def condition_number(self) -> float:
        """Return the condition number of the chosen design (the collinearity guard's figure)."""
        return float(self.ols.condition_number)

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """Return predictions for a design matrix holding at least the chosen terms."""
        return X[self.names].to_numpy(float) @ np.asarray(self.ols.params, float)


def _ols(y: np.ndarray, X: np.ndarray) -> Any:
    """Return a statsmodels OLS fit."""
    return sm.OLS(y, X, hasconst=True).fit()


class StepwiseKnobs(Protocol):
    """What a stepwise fit reads from a caller's options (``FitOptions`` has them all)."""

    @property
    def p_enter(self) -> float: ...
    @property
    def p_remove(self) -> float: ...
    @property
    def min_gain(self) -> float: ...
    @property
    def max_terms(self) -> int: ...
    @property
    def vif_max(self) -> float: ...
    @property
    def tiered(self) -> bool: ...


@dataclass(frozen=True)
class StepwiseOptions:
    """The rules of a stepwise fit (ch. 6.4.2): when a term enters, when it leaves, how many, how collinear."""

    #: a candidate enters when its partial F's p-value is below this ...
    p_enter: float = 1e-4
    #: ... a chosen term leaves when its OLS p-value is above this
    p_remove: float = 1e-3
    #: the share of the remaining sum of squares a term must remove to enter
    min_gain: float = 0.01
    max_terms: int = 10
    #: a candidate whose variance inflation factor against the chosen terms exceeds this is refused
    vif_max: float = 30.0
    #: offer the physically recast terms first, then single channels, then lags
    tiered: bool = True

    @classmethod
    def of(cls, knobs: StepwiseKnobs, **changes: float) -> StepwiseOptions:
        """Return the stepwise rules of a caller's options (e.g. ``FitOptions``), with ``changes`` applied."""
        base = cls(knobs.p_enter, knobs.p_remove, knobs.min_gain, knobs.max_terms, knobs.vif_max, knobs.tiered)
        return base.updated(changes)

    def updated(self, changes: Mapping[str, float]) -> StepwiseOptions:
        """Return these rules with the named ones changed (the keyword form of ``stepwise``'s old signature)."""
        unknown = sorted(set(changes) - {f.name for f in fields(self)})
        if unknown:
            raise TypeError(f"unknown stepwise option(s): {', '.join(unknown)}")
        if not changes:
            return self
        get = changes.get
        return StepwiseOptions(
            float(get("p_enter", self.p_enter)),
            float(get("p_remove", self.p_remove)),
            float(get("min_gain", self.min_gain)),
            int(get("max_terms", self.max_terms)),
            float(get("vif_max", self.vif_max)),
            bool(get("tiered", self.tiered)),
        )


#: the tier of each feature kind when the stepwise fit is tiered (recast terms, single channels, lags)
TIER_OF: Mapping[str, int] = {
    "position": 0,
    "direction": 0,
    "pos_dT": 0,
    "lever": 0,
    "mean": 0,
    "gradient": 0,
    "intercept": 0,
    "dT": 1,
    "lag": 2,
}


class _Projection:
    """Gram-Schmidt state of a stepwise fit: every column and y with the chosen terms projected out."""

    def __init__(self, A: np.ndarray, y: np.ndarray) -> None:
        self.A, self.y = A, y
        self.Cr = A.copy()
        self.r = y.copy()
        self.selected: list[int] = []

    def enter(self, j: int) -> bool:
        """Project column j out of everything; return False when it is (numerically) dependent."""
        v = self.Cr[:, j]
        nv = float(np.sqrt(v @ v))
        if nv <= 1e-12 * max(1.0, float(np.sqrt(self.A[:, j] @ self.A[:, j]))):
            return False
        qv = v / nv
        self.Cr[:] -= np.outer(qv, qv @ self.Cr)
        self.r = self.r - qv * (qv @ self.r)
        self.selected.append(j)
        return True

    def rebuild(self) -> None:
        """Recompute the projections from scratch (after a backward step)."""
        keep = list(self.selected)
        self.selected.clear()
        self.Cr = self.A.copy()
        self.r = self.y.copy()
        for j in keep:
            self.enter(j)


@dataclass(frozen=True)
class _Pick:
    """The candidate a forward step enters: its place in the pool, partial F and p-value."""

    index: int
    F: float
    p: float


def _forward_pick(
    proj: _Projection, pool: np.ndarray, tiers: np.ndarray, total2: np.ndarray, options: StepwiseOptions
) -> tuple[_Pick | None, np.ndarray]:
    """Return the candidate of ``pool`` a forward step enters (None: none qualifies) and the collinear mask.

    The collinear mask marks the candidates refused by the VIF guard (True: refused).
    """
    n = proj.y.size
    r, Cr = proj.r, proj.Cr
    sse = float(r @ r)
    norm2 = (Cr[:, pool] ** 2).sum(axis=0)
    # VIF of each candidate against the chosen terms = total2 / norm2 (scale-free per column)
    ok = (norm2 > total2[pool] / options.vif_max) & (total2[pool] > 0)
    if not ok.any() or sse <= 0:
        return None, ~ok
    gain = np.where(ok, (Cr[:, pool].T @ r) ** 2 / np.where(ok, norm2, 1.0), -np.inf)
    dof = n - len(proj.selected) - 1
    # physically recast terms are offered first, then single channels, then lags (ch. 6.4.2:
    # a correlated input entered early masks a more relevant one)
    for t in sorted(set(tiers[pool].tolist())):
        gt = np.where(tiers[pool] == t, gain, -np.inf)
        b = int(np.argmax(gt))
        gb = float(gt[b])
        if not np.isfinite(gb):
            continue
        Fb = gb / max((sse - gb) / dof, 1e-300)
        pb = float(stats.f.sf(Fb, 1, dof))
        if pb < options.p_enter and gb >= options.min_gain * sse:
            return _Pick(b, Fb, pb), ~ok
    return None, ~ok


def _backward(proj: _Projection, n_forced: int, p_remove: float, names: Sequence[str]) -> dict[int, Step]:
    """Drop the least significant non-forced terms while their OLS p-value exceeds ``p_remove``.

    Returns the removals (column -> step, in order); the projections are rebuilt when there is any.
    """
    steps: dict[int, Step] = {}
    selected = proj.selected
    while len(selected) > n_forced + 1:
        res = _ols(proj.y, proj.A[:, selected])
        pv = np.asarray(res.pvalues)[n_forced:]
        worst = int(np.argmax(pv))
        if pv[worst] <= p_remove:
            break
        k = selected.pop(n_forced + worst)
        steps[k] = Step("remove", names[k], float(res.tvalues[n_forced + worst] ** 2), float(pv[worst]))
    if steps:
        proj.rebuild()
    return steps


def stepwise(
    X: pd.DataFrame,
    y: np.ndarray,
    candidates: Sequence[Feature],
    *,
    forced: Sequence[Feature] = (),
    options: StepwiseOptions | None = None,
    **changes: float,
) -> StepwiseResult:
    """Return a forward/backward stepwise OLS fit of ``y`` on the columns of ``X``.

    Forward steps add the candidate with the largest partial F (computed for all candidates at
    once by projecting them off the current design) if its p-value is below ``p_enter`` and it
    removes at least ``min_gain`` of the remaining sum of squares; with ``tiered``, physically
    recast terms (position shape, direction, position x dT, structure means and gradients) are
    offered before single channels, and those before lags; candidates whose variance
    inflation factor against the current terms exceeds ``vif_max`` are refused (correlated
    inputs mask each other, ch. 6.4.2). Backward steps drop the least significant non-forced
    term while its OLS p-value exceeds ``p_remove``.

    The rules are ``options`` (``StepwiseOptions``' defaults when None), with any of them also
    accepted by keyword (``p_enter=...``: the older signature).
    """
    opts = (options or StepwiseOptions()).updated(changes)
    y = np.asarray(y, float)
    n = y.size
    feats = list(forced) + [c for c in candidates if c not in forced]
    names = [f.name for f in feats]
    if len(set(names)) != len(names):
        raise ValidationError("duplicate candidate terms")
    A = X[names].to_numpy(float)
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(y)):
        raise ValidationError("non-finite values in the regression data")
    n_forced = len(forced)
    steps: list[Step] = []
    collinear: set[str] = set()
    total2 = ((A - A.mean(axis=0)) ** 2).sum(axis=0)
    tried_out: set[int] = set()
    proj = _Projection(A, y)
    selected = proj.selected
    tiers = np.array([TIER_OF.get(f.kind, 1) if opts.tiered else 0 for f in feats], int)
    for j in range(n_forced):
        proj.enter(j)
    for _ in range(4 * opts.max_terms + 4):
        pool = np.array([j for j in range(n_forced, len(feats)) if j not in selected and j not in tried_out], int)
        if pool.size == 0 or len(selected) >= opts.max_terms or n - len(selected) - 2 < 1:
            break
        pick, refused = _forward_pick(proj, pool, tiers, total2, opts)
        collinear.update(names[j] for j in pool[refused])
        if pick is None:
            break
        j = int(pool[pick.index])
        if not proj.enter(j):
            tried_out.add(j)
            continue
        steps.append(Step("add", names[j], pick.F, pick.p))
        removed = _backward(proj, n_forced, opts.p_remove, names)
        tried_out.update(removed)
        steps.extend(removed.values())
    if not selected:
        raise ValidationError("stepwise regression needs at least one forced term (the intercept)")
    res = _ols(y, A[:, selected])
    chosen = [feats[j] for j in selected]
    return StepwiseResult(
        features=chosen, ols=res, steps=steps, collinear=sorted(collinear - set(f.name for f in chosen))
    )


@dataclass
class TermFit:
    """The model of one error parameter of one link or joint (one row of tables 6.1/6.2).

    ``features``/``coef`` default to the whole stepwise result; they hold a part of it when one
    regression was split between a link and the joint measured with it (see ``split``).
    """

    element: str
    param: str
    result: StepwiseResult
    rmse_holdout: float = float("nan")
    n_holdout: int = 0
    features: list[Feature] | None = None
    coef: np.ndarray | None = None
    seeded_by: str | None = None

    @property
    def terms(self) -> list[Feature]:
        """Return the features this model evaluates."""
        return self.result.features if self.features is None else self.features

    @property
    def coefficients(self) -> np.ndarray:
        """Return the coefficients matching ``terms``."""
        return np.asarray(self.result.ols.params, float) if self.coef is None else self.coef

    @property
    def std_errors(self) -> np.ndarray:
        """Return the standard errors matching ``terms``."""
        se = self.result.bse
        return np.asarray([se[f.name] for f in self.terms], float)

    @property
    def p_values(self) -> np.ndarray:
        """Return the p-values matching ``terms``."""
        pv = self.result.pvalues
        return np.asarray([pv[f.name] for f in self.terms], float)

    def coefficient(self, name: str) -> float:
        """Return the coefficient of the term called ``name`` (KeyError when it was not chosen)."""
        return float(dict(zip([f.name for f in self.terms], self.coefficients))[name])

    def predict(
        self, inputs: Inputs, position: np.ndarray | None = None, direction: np.ndarray | None = None
    ) -> np.ndarray:
        """Return this term's prediction for every sample of ``inputs``."""
        X = design_matrix(self.terms, inputs, position, direction)
        return X.to_numpy(float) @ self.coefficients

    def split(self, belongs: Callable[[Feature], bool], other_element: str) -> tuple[TermFit, TermFit | None]:
        """Return (this model without the features ``belongs`` picks, a model of ``other_element`` with them)."""
        feats, coef = self.terms, self.coefficients
        mine = [i for i, f in enumerate(feats) if not belongs(f)]
        theirs = [i for i, f in enumerate(feats) if belongs(f)]
        keep = TermFit(
            self.element,
            self.param,
            self.result,
            self.rmse_holdout,
            self.n_holdout,
            [feats[i] for i in mine],
            coef[mine],
            self.seeded_by,
        )
        if not theirs:
            return keep, None
        other = TermFit(
            other_element,
            self.param,
            self.result,
            float("nan"),
            0,
            [feats[i] for i in theirs],
            coef[theirs],
            seeded_by=self.element,
        )
        return keep, other


def r_squared(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Return the coefficient of determination of a prediction."""
    y = np.asarray(y, float)
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return float(1.0 - np.sum((y - y_hat) ** 2) / ss_tot) if ss_tot > 0 else float("nan")
