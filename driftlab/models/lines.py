"""The measuring-line layer: what the link models leave along each measured line, in the standard form.

The per-link models (ch. 4.3, 6.4) only offer the physically recast terms that suit a machine
whose errors come from its links. A machine whose drift is plainly linear in its thermocouples
along each measured line (the standard model of the bundle spec, section 2: a cubic in position
plus dT of the line's channels) is not of that form: the lines' home values need not agree, and
each line has its own temperature coefficients. So after the link models, each measured line
(moving axis, term) gets a candidate correction fitted to the link models' residual by the same
stepwise regression, over the union of the plain standard terms (position^1..3, dT_k of the
line's channels, position x dT_k) and the recast ones (structure means, gradients, lags).

Whether a line keeps its correction is decided inside the training part alone, by time-ordered
validation (rolling origin: fit on the first half, check the next quarter; fit on the first three
quarters, check the last): the correction is kept only when it lowers the checked RMSE by
``min_gain`` (10 %). The held-out part is never read here.

For compensation every line's correction goes to the first link (T1) of the chain, whose error
reaches the work space through a constant similarity transform (eq. 4.12 with the fixed T1 of
eq. 4.13): its position-dependent part (``pos``, ``pos^2``, ``pos^3``, ``pos x dT``, ``dir`` of
the line's own axis) as it is, its home part (the terms that do not vary along the line) as the
mean over the measured lines of that term. How far each line's home part is from that mean is
kept as the line's ``home_deviation``: a model evaluated on that line (validation) adds it; the
compensator, which cannot know which line a pose belongs to, cannot.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict, Unpack

import numpy as np
import pandas as pd
import statsmodels.api as sm
from scipy.linalg import qr

from driftlab.models.features import INTERCEPT, Feature, Inputs, design_matrix, session_terms
from driftlab.models.regression import StepwiseOptions, stepwise
from driftlab.physics.kinematics import PARAMS, TABLE_A1, allocate
from driftlab.vocabulary import AXES

if TYPE_CHECKING:
    from driftlab.models.features import FeatureRecord
    from driftlab.models.regression import StepwiseKnobs, StepwiseResult

#: the element that carries the lines' corrections (its error reaches the tool through a fixed transform)
LINE_ELEMENT = "T1"
#: kinds that vary along a line (evaluated at the line axis' coordinate): the position-dependent part
ALONG = frozenset({"position", "pos_dT", "direction", "lever"})
#: rolling-origin folds inside the training part, within each stage in time order: (fit on the rows
#: before, check the rows up to) as fractions of the stage's training rows. The held-out part is the
#: last quarter of each stage, so the folds check what it checks: the late part of every stage.
FOLDS: tuple[tuple[float, float], ...] = ((0.5, 0.75), (0.75, 1.0))
#: the last fold is the final training block of the gate against the standard model
FINAL_BLOCK = FOLDS[-1]


class LineRecord(TypedDict):
    """The JSON form of a :class:`LineFit` kept in the model document (``lines``)."""

    axis: str
    term: str
    form: str
    why: str
    checked_rmse: dict[str, float]
    n_fit: int
    n_checked: int
    #: the final-block gate: block_rows, chosen, chosen_rmse, standard_rmse, standard_plain_rmse, verdict
    gate: dict[str, float | int | str]
    features: list[FeatureRecord]
    coefficients: list[float]
    #: added by the fit's document: the line's deviation at the home position (None: none)
    home_deviation: NotRequired[HomeDeviationRecord | None]


class HomeDeviationRecord(TypedDict):
    """A line's deviation at the home position in the model document: its features and coefficients."""

    features: list[FeatureRecord]
    coefficients: list[float]


@dataclass
class LineFit:
    """The correction of one measured line (moving axis, term) and why it was kept or not."""

    axis: str
    term: str
    form: str  # "link" (the link models alone) or "link+line" (plus this correction)
    features: list[Feature] = field(default_factory=list)
    coef: np.ndarray = field(default_factory=lambda: np.zeros(0))
    std_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))
    p_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: time-ordered validation inside the training part: checked RMSE of each form
    checked: dict[str, float] = field(default_factory=dict)
    n_fit: int = 0
    n_checked: int = 0
    why: str = ""
    #: the final-block gate against plain least squares on the standard model: RMSE of each, and the verdict
    gate: dict[str, Any] = field(default_factory=dict)
    #: the line's zeroed-session offsets (campaign nuisances: validation adds them, the document does not)
    session_features: list[Feature] = field(default_factory=list)
    session_coef: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the statsmodels result of the kept correction (its covariance: ``cov_params()``), None for ``link``
    result: Any = None

    def along(self) -> list[int]:
        """Return the indices of the position-dependent terms (the rest is the line's home part)."""
        return [i for i, f in enumerate(self.features) if f.kind in ALONG]

    def to_dict(self) -> LineRecord:
        """Return the JSON form kept in the model document (``lines``)."""
        return {
            "axis": self.axis,
            "term": self.term,
            "form": self.form,
            "why": self.why,
            "checked_rmse": dict(self.checked),
            "n_fit": self.n_fit,
            "n_checked": self.n_checked,
            "gate": dict(self.gate),
            "features": [f.to_dict() for f in self.features],
            "coefficients": [float(c) for c in self.coef],
        }


def _correction(
    X: pd.DataFrame, y: np.ndarray, pool: Sequence[Feature], forced: Sequence[Feature], rules: StepwiseOptions
) -> StepwiseResult:
    """Return the stepwise fit of a line's residual (the rules of the link models)."""
    return stepwise(X.reset_index(drop=True), y, pool, forced=forced, options=rules)


def independent(A: np.ndarray, rtol: float = 1e-9) -> list[int]:
    """Return the columns of ``A`` (scaled to unit norm) that a pivoted QR finds independent, in order."""
    norms = np.linalg.norm(A, axis=0)
    ok = np.flatnonzero(norms > 0)
    if ok.size == 0:
        return []
    _, R, piv = qr(A[:, ok] / norms[ok], mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    rank = int(np.sum(d > rtol * d[0])) if d.size else 0
    return sorted(int(ok[j]) for j in piv[:rank])


@dataclass
class _Form:
    """One candidate form of a line's correction, fitted: its terms, coefficients and statsmodels result."""

    features: list[Feature]
    coef: np.ndarray
    ols: Any
    #: per term, its standard error and p-value (the link models' projection is an identity: 0 and 0)
    bse: np.ndarray
    pvalues: np.ndarray
    #: where ``ols``' parameters sit among ``features`` (None: one for one)
    own: list[int] | None = None

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        return X[[f.name for f in self.features]].to_numpy(float) @ self.coef


def scaled_lstsq(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Return least-squares coefficients of ``y`` on ``A``, solved on unit-norm columns.

    Position^3 in mm reaches 1e8 where a dT column is 1: unscaled, the solver's rank cut-off drops
    the small columns' information and the fit is off by far more than the noise.
    """
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    return np.linalg.lstsq(A / s, y, rcond=None)[0] / s


def _ols_form(features: list[Feature], A: np.ndarray, y: np.ndarray) -> _Form:
    """Return plain least squares of ``y`` on the independent columns of ``A`` (its terms ``features``).

    Solved on unit-norm columns (``scaled_lstsq``); the result's ``scale`` brings its parameters and
    covariance back to the terms' units (params / scale, cov / outer(scale, scale)).
    """
    keep = independent(A)
    feats = [features[j] for j in keep]
    A = A[:, keep]
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    ols = sm.OLS(y, A / scale, hasconst=True).fit()
    ols.scale_of_columns = scale
    params = np.asarray(ols.params, float) / scale
    return _Form(feats, params, ols, np.asarray(ols.bse, float) / scale, np.asarray(ols.pvalues, float))


@dataclass(frozen=True)
class LineRows:
    """One measured line's training rows: what its correction is fitted to and checked on."""

    #: the link models' residual (measured less what they predict)
    residual: np.ndarray
    time_s: np.ndarray
    #: the design matrix: the intercept, the session offsets and every term of the line's forms
    X: pd.DataFrame
    #: the campaign session of each row (None: one session)
    sessions: np.ndarray | None = None
    #: the measured values themselves (what the final gate's plain least squares fits)
    measured: np.ndarray | None = None
    #: the stage of each row (the folds run within each stage, in time order)
    stages: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.residual.size)

    def take(self, rows: np.ndarray) -> LineRows:
        """Return the rows the boolean mask ``rows`` picks."""

        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[rows]

        return LineRows(
            self.residual[rows],
            self.time_s[rows],
            self.X[rows],
            pick(self.sessions),
            pick(self.measured),
            pick(self.stages),
        )


@dataclass(frozen=True)
class LineTerms:
    """The candidate terms of a line's correction, one set per form."""

    #: the stepwise correction's candidates
    pool: Sequence[Feature]
    #: the plain least-squares correction's terms (empty: that form is not tried)
    full: Sequence[Feature] = ()
    #: the standard model's terms (spec section 2) that the final gate compares with (empty: no gate)
    standard: Sequence[Feature] = ()


def _fit_form(form: str, rows: LineRows, terms: LineTerms, forced: Sequence[Feature], rules: StepwiseOptions) -> _Form:
    """Return a fitted form of a line's correction of the link models' residual (``rows.residual``).

    ``stepwise`` over ``terms.pool``; ``full``: least squares on every term of ``terms.full``;
    ``standard``: the correction that turns the line's prediction into plain least squares on the
    standard model (spec section 2, ``terms.standard``) of the measured values: that fit less the
    link models' prediction (``measured - residual``) written in the line's terms (``terms.full``,
    an identity when they hold what the links read along the line).
    """
    X, y = rows.X, rows.residual
    if form == "stepwise":
        res = _correction(X, y, terms.pool, forced, rules)
        params = np.asarray(res.ols.params, float)
        return _Form(list(res.features), params, res.ols, np.asarray(res.ols.bse, float), np.asarray(res.ols.pvalues))
    if form == "full":
        feats = list(dict.fromkeys([*forced, *terms.full]))
        return _ols_form(feats, X[[f.name for f in feats]].to_numpy(float), y)
    measured = rows.measured
    assert measured is not None
    s_feats = list(dict.fromkeys([*forced, *terms.standard]))
    plain = _ols_form(s_feats, X[[f.name for f in s_feats]].to_numpy(float), measured)
    l_feats = list(dict.fromkeys([*forced, *terms.full]))
    B = X[[f.name for f in l_feats]].to_numpy(float)
    kb = independent(B)
    link_coef = scaled_lstsq(B[:, kb], measured - y)
    feats = list(dict.fromkeys([*plain.features, *(l_feats[j] for j in kb)]))
    coef, bse, pv = np.zeros(len(feats)), np.zeros(len(feats)), np.zeros(len(feats))
    for i, f in enumerate(plain.features):
        j = feats.index(f)
        coef[j] += plain.coef[i]
        bse[j], pv[j] = plain.bse[i], plain.pvalues[i]
    for c, j in zip(link_coef, kb):
        coef[feats.index(l_feats[j])] -= c
    return _Form(feats, coef, plain.ols, bse, pv, [feats.index(f) for f in plain.features])


#: lag-1 autocorrelation of a correction's residuals above which its standard errors are HAC (Newey-West)
HAC_RHO = 0.1


def _hac(fitted: _Form, n: int) -> None:
    """Replace a fitted form's standard errors by Newey-West (HAC) ones where its residuals are autocorrelated.

    The rows are the line's readings in time order; laser residuals are serially correlated from one
    sweep to the next, which makes the iid standard errors too small. The lag window is the usual
    floor(4 (n / 100)^(2/9)).
    """
    r = np.asarray(fitted.ols.resid, float)
    if r.size < 10:
        return
    rho = float(np.dot(r[1:] - r.mean(), r[:-1] - r.mean()) / max(float(np.sum((r - r.mean()) ** 2)), 1e-300))
    if rho <= HAC_RHO:
        return
    hac = fitted.ols.get_robustcov_results(cov_type="HAC", maxlags=int(4 * (n / 100.0) ** (2 / 9)))
    scale = getattr(fitted.ols, "scale_of_columns", None)
    bse = np.asarray(hac.bse, float) / (scale if scale is not None else 1.0)
    own = fitted.own if fitted.own is not None else list(range(fitted.bse.size))
    if len(own) == bse.size:
        fitted.bse = fitted.bse.copy()
        fitted.bse[own] = bse
        fitted.ols = hac


def stage_blocks(time_s: np.ndarray, groups: np.ndarray | None, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (fit rows, checked rows): within each group (stage) in time order, its first ``lo`` and next ``hi``."""
    n = time_s.size
    fit_rows, check = np.zeros(n, bool), np.zeros(n, bool)
    g = np.zeros(n, dtype=object) if groups is None else np.asarray(groups, dtype=object)
    for label in dict.fromkeys(g.tolist()):
        idx = np.flatnonzero(g == label)
        idx = idx[np.argsort(time_s[idx], kind="stable")]
        m = idx.size
        fit_rows[idx[: int(lo * m)]] = True
        check[idx[int(lo * m) : int(hi * m)]] = True
    return fit_rows, check


@dataclass
class _Checks:
    """The rolling-origin checks of a line's forms: squared errors summed over the checked rows."""

    #: form -> squared error over every fold
    sse: dict[str, float]
    #: form -> squared error over the last fold (the final training block), plus ``standard_plain`` and ``n``
    final: dict[str, float] = field(default_factory=dict)
    n_checked: int = 0


def _standard_plain(train: LineRows, held: LineRows, terms: LineTerms, forced: Sequence[Feature]) -> float:
    """Return the squared error on ``held`` of plain least squares on the standard model (the links aside)."""
    feats = [*forced, *terms.standard]
    assert train.measured is not None and held.measured is not None
    plain = _ols_form(feats, train.X[[f.name for f in feats]].to_numpy(float), train.measured)
    return float(np.sum((held.measured - plain.predict(held.X)) ** 2))


def _check_forms(rows: LineRows, terms: LineTerms, rules: StepwiseOptions, forms: Sequence[str]) -> _Checks:
    """Return the squared errors of the link models alone and of each of ``forms`` over the folds (``FOLDS``)."""
    checks = _Checks({"link": 0.0, **{f: 0.0 for f in forms}})
    sess = None if rows.sessions is None else np.asarray(rows.sessions, dtype=object)
    for fold, (lo, hi) in enumerate(FOLDS):
        fit_rows, check = stage_blocks(rows.time_s, rows.stages, lo, hi)
        forced = [INTERCEPT, *session_terms(rows.sessions, fit_rows)]
        # a session first seen in the checked block has no offset to predict it with: leave it out
        if sess is not None:
            check &= np.isin(sess, list(set(sess[fit_rows])))
        if check.sum() < 5 or fit_rows.sum() < 20:
            continue
        train, held = rows.take(fit_rows), rows.take(check)
        errors = {"link": float(np.sum(held.residual**2))}
        for form in forms:
            fitted = _fit_form(form, train, terms, forced, rules)
            errors[form] = float(np.sum((held.residual - fitted.predict(held.X)) ** 2))
        for form, e in errors.items():
            checks.sse[form] += e
        if fold == len(FOLDS) - 1:
            checks.final.update(errors)
            if "standard" in forms:
                checks.final["standard_plain"] = _standard_plain(train, held, terms, forced)
                checks.final["n"] = float(check.sum())
        checks.n_checked += int(check.sum())
    return checks


def _choose(checked: Mapping[str, float], forms: Sequence[str], min_gain: float) -> tuple[str, str]:
    """Return (the form kept, why): a form is kept when it cuts the checked RMSE of the simpler one by ``min_gain``."""
    best = "link"
    for form in forms:
        if checked[form] <= (1.0 - min_gain) * checked[best]:
            best = form
    if best == "link":
        ratio = min(checked[f] for f in forms) / checked["link"] if checked["link"] > 0 else 1.0
        return best, (
            f"no correction cuts the checked RMSE by {min_gain:.0%} (the best one's is {ratio:.2f}x "
            f"the link models' alone)"
        )
    return best, (
        f"{best} correction: checked RMSE {checked[best]:.3g} against {checked['link']:.3g} for the link models alone"
    )


def _gate(out: LineFit, final: Mapping[str, float], best: str, why: str) -> tuple[str, str]:
    """Return (the form kept, why) after the final-block gate against the standard model; record it in ``out.gate``."""
    nb = final["n"]
    chosen = float(np.sqrt(final[best] / nb))
    std = float(np.sqrt(final["standard"] / nb))
    out.gate = {
        "block_rows": int(nb),
        "chosen": best,
        "chosen_rmse": chosen,
        "standard_rmse": std,
        "standard_plain_rmse": float(np.sqrt(final["standard_plain"] / nb)),
    }
    if std < chosen:
        out.gate["verdict"] = "standard"
        why = (
            f"plain least squares on the standard model predicts the final training block better "
            f"({std:.3g} against {chosen:.3g} for {'the link models alone' if best == 'link' else best}): "
            f"it replaces it"
        )
        return "standard", why
    out.gate["verdict"] = "kept"
    return best, why


def _keep(out: LineFit, form: str, rows: LineRows, terms: LineTerms, rules: StepwiseOptions) -> None:
    """Fit ``form`` on all the line's training rows and record it in ``out`` (session offsets apart)."""
    n = len(rows)
    fitted = _fit_form(form, rows, terms, [INTERCEPT, *session_terms(rows.sessions, np.ones(n, bool))], rules)
    _hac(fitted, n)
    keep = [i for i, f in enumerate(fitted.features) if f.kind != "session"]
    offsets = [i for i, f in enumerate(fitted.features) if f.kind == "session"]
    out.form = f"link+{form}"
    out.features = [fitted.features[i] for i in keep]
    out.coef = fitted.coef[keep]
    out.std_errors = fitted.bse[keep]
    out.p_values = fitted.pvalues[keep]
    out.session_features = [fitted.features[i] for i in offsets]
    out.session_coef = fitted.coef[offsets]
    out.result = fitted.ols
    out.n_fit = n


def fit_line(
    axis: str, k: int, rows: LineRows, terms: LineTerms, options: StepwiseKnobs, min_gain: float = 0.10
) -> LineFit:
    """Return the correction of one line's residual (training rows only), kept if validation shows it helps.

    ``rows`` holds the line's training rows only. Two forms are tried against the link models
    alone: a stepwise regression over ``terms.pool`` (few terms, the recast ones among them; the
    stepwise rules of ``options``) and plain least squares on every term of ``terms.full`` (the
    standard model and what the links read: a drift linear in many correlated channels, which the
    stepwise regression's collinearity rule would refuse). A form is kept only when it lowers the
    checked RMSE by ``min_gain`` against the simpler one (link < stepwise < full). The checks are
    rolling-origin folds within each stage (``FOLDS``).

    A last gate (with ``rows.measured`` and ``terms.standard``): on the final training block
    (``FINAL_BLOCK``, the late part of every stage, never the held-out part) the chosen form is
    compared with plain least squares on the standard model (spec section 2: position^1..3 and dT
    of the line's channels); where the standard model predicts the block better, the line falls
    back to it.
    """
    n = len(rows)
    out = LineFit(axis, PARAMS[k], "link")
    if n < 40:
        out.why = f"{n} training points: too few to check a correction"
        return out
    gated = rows.measured is not None and bool(terms.standard)
    forms = ["stepwise", "full"] if terms.full else ["stepwise"]
    rules = StepwiseOptions.of(options)
    checks = _check_forms(rows, terms, rules, [*forms, "standard"] if gated else forms)
    if checks.n_checked == 0:
        out.why = "no checked block with a known datum"
        return out
    out.checked = {f: float(np.sqrt(v / checks.n_checked)) for f, v in checks.sse.items()}
    out.n_checked = checks.n_checked
    best, why = _choose(out.checked, forms, min_gain)
    if gated and "n" in checks.final:
        best, why = _gate(out, checks.final, best, why)
    out.why = why
    if best != "link":
        _keep(out, best, rows, terms, rules)
    return out


def levered(axis: str, link_terms: Sequence[Feature]) -> list[Feature]:
    """Return what the chain's lever arm makes of the links' thermal terms along a line of linear ``axis``.

    To first order a link's error reaches the work space through the chain's Jacobian (eq. 4.12),
    which along a linear axis, the other axes at home, is affine in the axis' position (an angle
    acts through a lever arm that grows with it). So a link term f arrives on the line as f and as
    position x f. The standard terms hold position x dT; for a lag and a screw's position x dT the
    line needs position x lag and position^2 x dT, else what the links put on the line cannot be
    undone there, and it is extrapolated wherever the training part left that channel still.
    Terms that do not vary in time (position^4, position x direction) are left out.
    """
    if axis not in ("X", "Y", "Z"):
        return []
    out: list[Feature] = []
    for f in link_terms:
        if f.kind == "lag":
            out.append(Feature("lever", f.channels, power=1, tau_s=f.tau_s, label=axis))
        elif f.kind == "pos_dT" and f.label == axis:
            out.append(Feature("lever", f.channels, power=2, label=axis))
    return list(dict.fromkeys(out))


def line_pool(axis: str, channels: Sequence[str], recast: Sequence[Feature]) -> list[Feature]:
    """Return the candidates of a line: the standard terms (spec section 2) plus position x dT and the recast ones."""
    out = [Feature("position", power=p, label=axis) for p in (1, 2, 3)]
    out += [Feature("dT", (c,)) for c in channels]
    out += [Feature("pos_dT", (c,), label=axis) for c in channels]
    names = {f.name for f in out}
    for f in recast:
        if f.kind == "time" or f.name in names:
            continue
        if f.kind in ALONG and f.label != axis:
            continue
        out.append(f)
        names.add(f.name)
    return out


class LineHooks(TypedDict, total=False):
    """The optional keywords of ``fit_lines``."""

    #: called with "<axis> <term>" after each line (progress)
    on_line: Callable[[str], None] | None
    #: the terms of a line's plain least-squares correction (None: that form is not tried)
    full_of: Callable[[str], Sequence[Feature]] | None
    #: the terms of the standard model (spec section 2) the final gate compares with (None: no gate)
    standard_of: Callable[[str], Sequence[Feature]] | None


def _varying(feats: Sequence[Feature], X: pd.DataFrame, rows: np.ndarray) -> list[Feature]:
    """Return the terms of ``feats`` whose column varies over ``rows`` (a constant one cannot be fitted)."""
    return [f for f in feats if np.ptp(X[f.name].to_numpy(float)[rows]) > 0]


def fit_lines(
    frame: pd.DataFrame,
    q: np.ndarray,
    directions: np.ndarray,
    inputs: Inputs,
    W: np.ndarray,
    W_hat: np.ndarray,
    pool_of: Callable[[str], Sequence[Feature]],
    options: StepwiseKnobs,
    **hooks: Unpack[LineHooks],
) -> list[LineFit]:
    """Return the correction of every measured line (moving axis, term) from the training rows alone.

    ``W`` holds the measured work-space errors (NaN where a term was not measured) and ``W_hat``
    what the link models predict at the same points; ``pool_of(axis)`` the candidate terms of a
    line's stepwise correction (chosen by the stepwise rules of ``options``); ``hooks``: see
    ``LineHooks``.
    """
    on_line, full_of, standard_of = hooks.get("on_line"), hooks.get("full_of"), hooks.get("standard_of")
    role = frame["role"].to_numpy(object)
    axis_col = frame["axis"].to_numpy(str)
    stage = frame["stage"].to_numpy() if "stage" in frame.columns else np.zeros(len(frame), int)
    t = inputs.days * 86400.0 if inputs.days is not None else frame["time_s"].to_numpy(float)
    out: list[LineFit] = []
    for axis in AXES:
        on = (axis_col == axis) & (role == "train")
        if not on.any():
            continue
        pool = list(pool_of(axis))
        full = list(full_of(axis)) if full_of is not None else []
        standard = list(standard_of(axis)) if standard_of is not None else []
        names = {f.name for f in pool}
        sub = inputs.take(on)
        X = design_matrix(
            [
                INTERCEPT,
                *session_terms(sub.session, np.ones(int(on.sum()), bool)),
                *pool,
                *(f for f in full if f.name not in names),
                *(f for f in standard if f.name not in names and f not in full),
            ],
            sub,
            q[on],
            directions[on],
        )
        for k in range(len(PARAMS)):
            ok = np.isfinite(W[on, k])
            if ok.sum() == 0:
                continue
            rows = np.flatnonzero(ok)
            line = LineRows(
                (W[on, k] - W_hat[on, k])[rows],
                t[on][rows],
                X.iloc[rows],
                None if sub.session is None else sub.session[rows],
                W[on, k][rows],
                stage[on][rows],
            )
            terms = LineTerms(_varying(pool, X, rows), _varying(full, X, rows), _varying(standard, X, rows))
            out.append(fit_line(axis, k, line, terms, options))
            if on_line is not None:
                on_line(f"{axis} {PARAMS[k]}")
    return out


def t1_map(dims: Mapping[str, tuple[float, float, float]] = TABLE_A1) -> np.ndarray:
    """Return M (6, 6): the T1 error that produces a unit work-space error in each column (eq. 4.20).

    T1 is a fixed translation (eq. 4.13), so the map does not depend on the pose.
    """
    q = np.zeros((1, 5))
    M = np.zeros((6, 6))
    for k in range(6):
        w = np.zeros((1, 6))
        w[0, k] = 1e-6
        M[:, k] = allocate(w, q, None, LINE_ELEMENT, dims)[0] / 1e-6
    return M


def distinct(f: Feature, taken: dict[str, Feature]) -> Feature:
    """Return ``f``, or ``f`` named by its channels when another term already holds its name.

    A structure's mean or gradient is named by its structure; two lines reading different sites of
    one structure (their ``model_channels``) give two terms of one name, which a design matrix,
    keyed by name, cannot hold.
    """
    held = taken.get(f.name)
    if held is None or held == f:
        taken[f.name] = f
        return f
    g = replace(f, label="")
    taken.setdefault(g.name, g)
    return g


@dataclass
class Composed:
    """The lines' corrections as T1 terms (what the compensator applies) and each line's home deviation."""

    #: T1 parameter -> [(feature, coefficient, std error, p-value)]
    terms: dict[str, list[tuple[Feature, float, float, float]]]
    #: (axis, term) -> (features, coefficients): the line's home part less the mean of its term's lines
    home_deviation: dict[tuple[str, str], tuple[list[Feature], np.ndarray]]


def compose(lines: Sequence[LineFit], dims: Mapping[str, tuple[float, float, float]] = TABLE_A1) -> Composed:
    """Return the lines' corrections as T1 terms: position-dependent parts whole, home parts averaged."""
    M = t1_map(dims)
    by_term: dict[str, list[LineFit]] = {}
    for fit in lines:
        by_term.setdefault(fit.term, []).append(fit)
    # work-space term -> feature -> [coefficient, variance, p-value]
    work: dict[str, dict[Feature, list[float]]] = {}
    deviation: dict[tuple[str, str], tuple[list[Feature], np.ndarray]] = {}
    for term, fits in by_term.items():
        n_lines = len(fits)
        acc = work.setdefault(term, {})
        mean: dict[Feature, float] = {}
        for fit in fits:
            along = set(fit.along())
            for i, f in enumerate(fit.features):
                share = 1.0 if i in along else 1.0 / n_lines
                slot = acc.setdefault(f, [0.0, 0.0, 1.0])
                slot[0] += share * float(fit.coef[i])
                slot[1] += (share * float(fit.std_errors[i])) ** 2
                slot[2] = min(slot[2], float(fit.p_values[i]))
                if i not in along:
                    mean[f] = mean.get(f, 0.0) + float(fit.coef[i]) / n_lines
        for fit in fits:
            # this line's home part less the term's mean home part: what a point of this line adds
            own = {f: float(fit.coef[i]) for i, f in enumerate(fit.features) if i not in set(fit.along())}
            dev = {f: own.get(f, 0.0) - mean.get(f, 0.0) for f in dict.fromkeys([*own, *mean])}
            kept = {f: c for f, c in dev.items() if c != 0.0}
            # the line's zeroed-session offsets: what a point of that session adds (a campaign nuisance)
            kept.update({f: float(c) for f, c in zip(fit.session_features, fit.session_coef) if c != 0.0})
            if kept:
                taken: dict[str, Feature] = {}
                deviation[(fit.axis, term)] = ([distinct(f, taken) for f in kept], np.array(list(kept.values())))
    terms: dict[str, list[tuple[Feature, float, float, float]]] = {}
    for j, param in enumerate(PARAMS):
        out: dict[Feature, list[float]] = {}
        for k, term in enumerate(PARAMS):
            m = M[j, k]
            if abs(m) < 1e-12 or term not in work:
                continue
            for f, (c, var, p) in work[term].items():
                slot = out.setdefault(f, [0.0, 0.0, p])
                slot[0] += m * c
                slot[1] += m**2 * var
                slot[2] = min(slot[2], p)
        taken = {}
        rows = [(distinct(f, taken), c, float(np.sqrt(var)), p) for f, (c, var, p) in out.items() if c != 0.0]
        if rows:
            terms[param] = rows
    return Composed(terms, deviation)


def home_deviation(
    composed: Composed, frame: pd.DataFrame, inputs: Inputs, q: np.ndarray, directions: np.ndarray
) -> np.ndarray:
    """Return (N, 6): what each measured point's own line adds to the composed (compensator's) model."""
    out = np.zeros((q.shape[0], len(PARAMS)))
    axis_col = frame["axis"].to_numpy(str)
    for (axis, term), (feats, coef) in composed.home_deviation.items():
        on = axis_col == axis
        if on.any():
            X = design_matrix(feats, inputs.take(on), q[on], directions[on]).to_numpy(float)
            out[on, PARAMS.index(term)] += X @ coef
    return out
