"""The neural-network comparison (ch. 6.4.1, 6.6): scaled inputs (eq. 6.3), sigmoidal hidden layers, linear output."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol, TypeAlias, TypedDict, Unpack, cast

import numpy as np
import pandas as pd
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor
from threadpoolctl import threadpool_limits

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.vocabulary import AXES, TERMS

if TYPE_CHECKING:
    from driftlab.models.standard_model import BundleLike


def scale_inputs(X: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Return inputs mapped to [-0.9, 0.9] over the training range (eq. 6.3)."""
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    return 1.8 * (np.asarray(X, float) - lo) / span - 0.9


@dataclass
class NeuralModel:
    """A trained network with the training range of its inputs (to know when it extrapolates)."""

    inputs: list[str]
    lo: np.ndarray
    hi: np.ndarray
    y_mean: float
    y_scale: float
    net: MLPRegressor

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """Return the network's estimate (eqs. 6.4-6.6) for the rows of ``X``."""
        Z = scale_inputs(X[self.inputs].to_numpy(float), self.lo, self.hi)
        with threadpool_limits(limits=1):
            return self.y_mean + self.y_scale * self.net.predict(Z)

    def outside_training_range(self, X: pd.DataFrame) -> np.ndarray:
        """Return a boolean per row: True where any input is beyond its training range."""
        A = X[self.inputs].to_numpy(float)
        return np.any((A < self.lo) | (A > self.hi), axis=1)


def fit_network(
    X: pd.DataFrame,
    y: np.ndarray,
    *,
    hidden: Sequence[int] = (30, 15, 7),
    max_samples: int = 10_000,
    seed: int = 0,
    max_iter: int = 400,
) -> NeuralModel:
    """Return a network trained on up to ``max_samples`` random rows (ch. 6.6: 30-15-7 tanh nodes)."""
    y = np.asarray(y, float)
    if len(X) != y.size or y.size < 20:
        raise ValidationError("the network needs at least 20 samples with matching inputs")
    rng = np.random.default_rng(seed)
    idx = rng.choice(y.size, size=min(max_samples, y.size), replace=False)
    A = X.to_numpy(float)
    lo, hi = A.min(axis=0), A.max(axis=0)
    y_mean, y_scale = float(y.mean()), float(y.std()) or 1.0
    # tanh is eq. 6.5 up to a factor 2 in the argument; lbfgs stands in for Levenberg-Marquardt (eq. 6.7)
    net = MLPRegressor(
        hidden_layer_sizes=tuple(hidden),
        activation="tanh",
        solver="lbfgs",
        max_iter=max_iter,
        alpha=1e-5,
        random_state=seed,
        tol=1e-7,
    )
    # small dense products: one BLAS thread is fastest, and keeps a shared machine responsive
    with warnings.catch_warnings(), threadpool_limits(limits=1):
        warnings.simplefilter("ignore", ConvergenceWarning)
        net.fit(scale_inputs(A[idx], lo, hi), (y[idx] - y_mean) / y_scale)
    return NeuralModel(list(X.columns), lo, hi, y_mean, y_scale, net)


@dataclass
class ExtrapolationResult:
    """The ch. 6.6 experiment: both models scored on data beyond the training range."""

    regression_mm: float
    network_mm: float
    regression_in_range_mm: float
    network_in_range_mm: float
    shift_degC: float
    n: int

    def to_dict(self) -> dict[str, float]:
        """Return the JSON form of the report's ``extrapolation`` field (the fields, in order)."""
        return asdict(self)


def extrapolation_errors(
    y_in: np.ndarray,
    reg_in: np.ndarray,
    net_in: np.ndarray,
    y_out: np.ndarray,
    reg_out: np.ndarray,
    net_out: np.ndarray,
    shift_degC: float,
) -> ExtrapolationResult:
    """Return the RMS prediction errors of both models in and beyond the training range."""
    return ExtrapolationResult(
        regression_mm=rmse(np.asarray(y_out) - reg_out),
        network_mm=rmse(np.asarray(y_out) - net_out),
        regression_in_range_mm=rmse(np.asarray(y_in) - reg_in),
        network_in_range_mm=rmse(np.asarray(y_in) - net_in),
        shift_degC=float(shift_degC),
        n=int(len(y_out)),
    )


# ----------------------------------------------------------------------------- the fair comparison (ch. 6.6)
#
# The thesis compared its regression with a network on Z position and found the network better in
# range and far worse beyond it (a room 2 degC warmer: 15 um against 5 um). A comparison says
# something only if it is fair:
#
# - the same inputs: one feature matrix (the standard model's columns, spec section 2: position,
#   position^2, position^3 and dT of a channel set fixed beforehand) goes to both models;
# - the target fixed in advance (a parameter), never the term that happens to suit one model;
# - both extrapolation directions: train on the earlier part and test on the later, and the reverse
#   (or one campaign against another, both ways), so a result is not an accident of which side was
#   warmer;
# - no zeroed campaign as an absolute target. A reading's datum is what its zero means: ``absolute``
#   (bundle v2 setup against a stable artefact: one datum shared by every campaign), a laser session
#   (v2 ``datum: session``: zeroed at mount, an unknown offset per session) or a v1 campaign (the
#   project's convention, spec section 2: errors and dT count from the campaign's start, so the
#   campaign is zeroed at its start). Across campaigns only absolute readings are targets; within
#   campaigns each other datum gets an offset column in the shared matrix, the same for both models;
# - one temperature reference for every row (eq. 3.1), so a warm campaign's inputs are not zeroed.

SPLIT_MODES = ("auto", "time", "campaign")
ABSOLUTE = "absolute"


@dataclass
class ComparisonData:
    """The rows of one target term over the campaigns and the one feature matrix both models get."""

    target: str  # "AXIS/term"
    X: pd.DataFrame  # position, position^2, position^3, dT[c]..., datum[g]... (one row per reading)
    y: np.ndarray  # the measured error (mm or rad)
    t_s: np.ndarray  # seconds since the first campaign's start
    campaign: np.ndarray  # index into ``campaigns``
    datum: np.ndarray  # each row's datum group: "absolute", a v1 campaign's name, or "campaign/setup#session"
    campaigns: list[str]
    channels: list[str]
    reference: dict[str, float]  # degC: each channel's first reading of the earliest campaign

    @property
    def absolute(self) -> np.ndarray:
        """Return True for rows read against an absolute datum (targets across campaigns)."""
        return self.datum == ABSOLUTE


def _parse_target(target: str) -> tuple[str, str]:
    """Return (axis, term) of "AXIS/term", or raise ValidationError."""
    axis, _, term = str(target).partition("/")
    if axis not in AXES or term not in TERMS:
        raise ValidationError(f"neural comparison target {target!r}: give AXIS/term, e.g. Z/dz")
    return axis, term


def _datum_groups(b: Any, name: str, e: pd.DataFrame) -> np.ndarray:
    """Return each reading's datum group (see the module notes): absolute, the v1 campaign, or the laser session."""
    setups = getattr(b.meta, "setups", None) or {}
    if not setups or "setup" not in e.columns:
        return np.full(len(e), name, dtype=object)  # v1: zeroed at the campaign's start
    out = np.full(len(e), ABSOLUTE, dtype=object)
    order = np.argsort(e["time_s"].to_numpy(float), kind="stable")
    sid = e["setup"].to_numpy(object)[order]
    run = np.concatenate([[0], np.cumsum(sid[1:] != sid[:-1])]) if sid.size else sid
    for i, s, r in zip(order, sid, run):  # a session: a maximal run, in time order, of one zeroed setup
        if getattr(setups.get(s), "datum", ABSOLUTE) == "session":
            out[i] = f"{name}/{s}#{r}"
    return out


def comparison_data(bundles: Sequence[BundleLike], target: str, channels: Sequence[str]) -> ComparisonData:
    """Return the target's readings over the campaigns with the one feature matrix both models get."""
    axis, term = _parse_target(target)
    if not bundles:
        raise ValidationError("the neural comparison needs at least one campaign")
    chans = [c for c in dict.fromkeys(channels) if all(c in b.temperatures.columns for b in bundles)]
    order = sorted(range(len(bundles)), key=lambda i: bundles[i].meta.started_at)
    origin = bundles[order[0]].meta.started_at
    reference: dict[str, float] = {}
    for c in chans:  # eq. 3.1: one fixed reference temperature, the same for every campaign
        for i in order:
            v = bundles[i].temperatures[c].to_numpy(float)
            if np.isfinite(v).any():
                reference[c] = float(v[np.isfinite(v)][0])
                break
    chans = [c for c in chans if c in reference]
    names = [str(getattr(bundles[i], "name", "") or f"campaign {k}") for k, i in enumerate(order)]
    parts: list[pd.DataFrame] = []
    for k, i in enumerate(order):
        b = bundles[i]
        e = b.errors
        m = (e["axis"] == axis).to_numpy() & (e["term"] == term).to_numpy() & np.isfinite(e["value"].to_numpy(float))
        if not m.any():
            continue
        e = e[m]
        t = e["time_s"].to_numpy(float)
        tt = b.temperatures["time_s"].to_numpy(float)
        frame: dict[str, Any] = {"position": e["position"].to_numpy(float)}
        for c in chans:
            v = b.temperatures[c].to_numpy(float)
            ok = np.isfinite(v)
            frame[f"dT[{c}]"] = np.interp(t, tt[ok], v[ok]) - reference[c] if ok.any() else np.full(t.size, np.nan)
        part = pd.DataFrame(frame)
        part["_y"] = e["value"].to_numpy(float)
        part["_t"] = (b.meta.started_at - origin).total_seconds() + t
        part["_c"] = k
        part["_g"] = _datum_groups(b, names[k], e)
        parts.append(part)
    if not parts:
        raise ValidationError(f"neural comparison on {target}: no readings of {target} in these campaigns")
    data = pd.concat(parts, ignore_index=True).dropna().sort_values("_t", kind="stable").reset_index(drop=True)
    pos = data["position"].to_numpy(float)
    X = pd.DataFrame({"position": pos, "position^2": pos**2, "position^3": pos**3})
    X = pd.concat([X, data[[f"dT[{c}]" for c in chans]]], axis=1)
    return ComparisonData(
        target,
        X,
        data["_y"].to_numpy(float),
        data["_t"].to_numpy(float),
        data["_c"].to_numpy(int),
        data["_g"].to_numpy(object),
        names,
        chans,
        reference,
    )


#: the JSON form of a :class:`DirectionResult`: its fields, in order (text, counts, figures, the inputs' names)
DirectionRecord: TypeAlias = dict[str, str | float | list[str]]


class NeuralComparisonRecord(TypedDict):
    """The JSON form of a :class:`NeuralComparison`: one entry of the report's ``neural_comparison``."""

    target: str
    status: str
    unit: str
    split: str
    channels: list[str]
    campaigns: list[str]
    excluded: dict[str, str]
    offsets: list[str]
    network_hidden: list[int]
    note: str
    directions: list[DirectionRecord]  # last: the fields above in order, then the directions


@dataclass
class DirectionResult:
    """One extrapolation direction: both models trained on one side, scored on the other."""

    direction: str  # "earlier -> later" or "later -> earlier"
    train: str
    test: str
    n_train: int
    n_test: int
    inputs: list[str]  # the columns both models were given (constant ones on the training side left out)
    regression_train: float
    network_train: float
    regression_test: float
    network_test: float
    #: share of test rows with an input beyond its training range, and the largest temperature excess (degC)
    beyond_range: float
    max_excess_degC: float

    def to_dict(self) -> DirectionRecord:
        """Return the JSON form."""
        return dict(self.__dict__)


@dataclass
class NeuralComparison:
    """The ch. 6.6 comparison of one target: the same inputs, both directions, no zeroed absolute targets."""

    target: str
    status: str  # "compared", "refused" (with the reason in ``note``) or "too few readings"
    unit: str = "mm"
    split: str = ""
    channels: list[str] = field(default_factory=list)
    campaigns: list[str] = field(default_factory=list)
    #: readings that are no target of this split, and why (a zeroed campaign or session across campaigns)
    excluded: dict[str, str] = field(default_factory=dict)
    #: datums other than absolute, each given an offset column in the shared matrix (time split)
    offsets: list[str] = field(default_factory=list)
    directions: list[DirectionResult] = field(default_factory=list)
    network_hidden: list[int] = field(default_factory=list)
    note: str = ""

    def to_dict(self) -> NeuralComparisonRecord:
        """Return the JSON form of one entry of the report's ``neural_comparison``."""
        out = {k: v for k, v in self.__dict__.items() if k != "directions"}
        out["directions"] = [d.to_dict() for d in self.directions]
        return cast("NeuralComparisonRecord", out)


Direction = tuple[str, np.ndarray, np.ndarray, str, str]


def _splits(data: ComparisonData, mode: str) -> tuple[str, list[Direction], dict[str, str]]:
    """Return the split used, its two directions (name, train rows, test rows, texts) and the excluded datums."""
    names = data.campaigns
    absolute = sorted(set(data.campaign[data.absolute].tolist()))
    zeroed = {g: c for g, c in zip(data.datum, data.campaign) if g != ABSOLUTE}
    if mode == "campaign" or (mode == "auto" and len(absolute) >= 2):
        if len(absolute) < 2:
            kinds = {
                g: "laser zeroed at mount, datum: session" if "/" in g else "v1: zeroed at its start" for g in zeroed
            }
            why = "; ".join(sorted(f"{g} ({kind})" for g, kind in kinds.items()))
            raise ValidationError(
                f"neural comparison on {data.target}: a split by campaign needs two campaigns read "
                f"against an absolute datum; zeroed: {why or 'none'}: a zeroed campaign is not an "
                "absolute target"
            )
        excluded = {
            g: ("datum: session (laser zeroed at mount)" if "/" in g else "v1 campaign, zeroed at its start")
            + ": not an absolute target across campaigns"
            for g in sorted(zeroed)
        }
        first, last = absolute[0], absolute[-1]
        early = data.absolute & np.isin(data.campaign, absolute[:-1])
        late = data.absolute & np.isin(data.campaign, absolute[1:])
        return (
            "campaign",
            [
                (
                    "earlier -> later",
                    early,
                    data.absolute & (data.campaign == last),
                    ", ".join(names[c] for c in absolute[:-1]),
                    names[last],
                ),
                (
                    "later -> earlier",
                    late,
                    data.absolute & (data.campaign == first),
                    ", ".join(names[c] for c in absolute[1:]),
                    names[first],
                ),
            ],
            excluded,
        )
    # by time, within each datum: its earlier half against its later half, both ways (times only, never values)
    early = np.zeros(data.y.size, bool)
    for g in set(data.datum.tolist()):
        m = data.datum == g
        early[m] = data.t_s[m] < np.median(data.t_s[m])
    return (
        "time",
        [
            ("earlier -> later", early, ~early, "earlier half of each datum", "later half"),
            ("later -> earlier", ~early, early, "later half of each datum", "earlier half"),
        ],
        {},
    )


@dataclass
class LinearModel:
    """Least squares with an intercept on the comparison's columns (the regression side of ch. 6.6)."""

    inputs: list[str]
    coef: np.ndarray  # intercept first

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """Return the fitted values for the rows of ``X``."""
        return self.coef[0] + X[self.inputs].to_numpy(float) @ self.coef[1:]


def fit_linear(X: pd.DataFrame, y: np.ndarray) -> LinearModel:
    """Return the least-squares fit of ``y`` on the columns of ``X`` plus an intercept (unit-scaled solve)."""
    A = np.column_stack([np.ones(len(y)), X.to_numpy(float)])
    scale = np.sqrt(np.mean(A**2, axis=0))
    scale[scale == 0] = 1.0
    c, *_ = np.linalg.lstsq(A / scale, np.asarray(y, float), rcond=None)
    return LinearModel(list(X.columns), c / scale)


class Predictor(Protocol):
    """A fitted model of the comparison: least squares or the network."""

    def predict(self, X: pd.DataFrame) -> np.ndarray: ...


#: how a model of the comparison is fitted: the training frame and target in, a predictor out
Fitter = Callable[[pd.DataFrame, np.ndarray], Predictor]


@dataclass(frozen=True)
class ComparisonOptions:
    """How the ch. 6.6 comparison is run: the split, the network (ch. 6.6: 30-15-7 nodes) and the two fitters."""

    #: "auto" (by campaign when two or more have absolute readings, else by time), "time" or "campaign"
    split: str = "auto"
    hidden: Sequence[int] = (30, 15, 7)
    max_samples: int = 4000
    max_iter: int = 300
    seed: int = 0
    #: the fewest training readings of a direction (its test side needs a sixth of it, at least 5)
    min_rows: int = 30
    fit_regression: Fitter = fit_linear
    #: None: ``fit_network`` with ``hidden``, ``max_samples``, ``max_iter`` and ``seed``
    fit_net: Fitter | None = None

    def network_fitter(self) -> Fitter:
        """Return the network's fitter."""
        if self.fit_net is not None:
            return self.fit_net

        def fit_net(X: pd.DataFrame, y: np.ndarray) -> NeuralModel:
            return fit_network(
                X, y, hidden=self.hidden, max_samples=self.max_samples, seed=self.seed, max_iter=self.max_iter
            )

        return fit_net


class ComparisonKeywords(TypedDict, total=False):
    """``ComparisonOptions``' fields as keywords of ``compare_models`` and ``neural_comparisons``."""

    split: str
    hidden: Sequence[int]
    max_samples: int
    max_iter: int
    seed: int
    min_rows: int
    fit_regression: Fitter
    fit_net: Fitter | None


def _with_offsets(data: ComparisonData, mode: str) -> tuple[pd.DataFrame, list[str]]:
    """Return the matrix both models get and the datums given an offset column in it (time split only).

    Each datum other than absolute carries its own unknown offset: one column for it (with no absolute
    reading the intercept holds the first datum's).
    """
    if mode != "time":
        return data.X, []
    groups = list(dict.fromkeys(g for g in data.datum if g != ABSOLUTE))
    offsets = groups if data.absolute.any() else groups[1:]
    if not offsets:
        return data.X, offsets
    cols = pd.DataFrame({f"datum[{g}]": (data.datum == g).astype(float) for g in offsets})
    return pd.concat([data.X, cols], axis=1), offsets


def _direction(X: pd.DataFrame, y: np.ndarray, direction: Direction, fitters: tuple[Fitter, Fitter]) -> DirectionResult:
    """Return both models trained on one side of ``direction`` and scored on both sides."""
    name, tr, te, tr_text, te_text = direction
    fit_regression, fit_net = fitters
    # columns constant on the training side carry nothing either model could learn from
    keep = [c for c in X.columns if float(X.loc[tr, c].std()) > 0]
    Xtr = X.loc[tr, keep].reset_index(drop=True)
    Xte = X.loc[te, keep].reset_index(drop=True)
    ytr, yte = y[tr], y[te]
    reg = fit_regression(Xtr, ytr)
    net = fit_net(Xtr, ytr)
    A, B = Xte.to_numpy(float), Xtr.to_numpy(float)
    lo, hi = B.min(axis=0), B.max(axis=0)
    temp = np.array([c.startswith("dT[") for c in keep], bool)
    excess = np.maximum(A - hi, lo - A)[:, temp] if temp.any() else np.zeros((len(A), 1))
    return DirectionResult(
        name,
        tr_text,
        te_text,
        int(tr.sum()),
        int(te.sum()),
        keep,
        rmse(ytr - reg.predict(Xtr)),
        rmse(ytr - net.predict(Xtr)),
        rmse(yte - reg.predict(Xte)),
        rmse(yte - net.predict(Xte)),
        float(((A < lo) | (A > hi)).any(axis=1).mean()),
        float(max(0.0, excess.max())),
    )


def compare_models(
    data: ComparisonData, options: ComparisonOptions | None = None, **keywords: Unpack[ComparisonKeywords]
) -> NeuralComparison:
    """Return the comparison of least squares and the network on the same matrix, in both directions.

    ``options`` (``ComparisonOptions``; each field also accepted by keyword): ``fit_regression`` and
    ``fit_net`` (default: ``fit_linear`` and ``fit_network`` with ``hidden``, ``max_samples``,
    ``max_iter``, ``seed``) each get the very same training frame and target.
    Raises ValidationError when the split asks for a zeroed campaign as an absolute target.
    """
    opts = replace(options or ComparisonOptions(), **keywords)
    if opts.split not in SPLIT_MODES:
        raise ValidationError(f"split {opts.split!r}: one of {', '.join(SPLIT_MODES)}")
    _, term = _parse_target(data.target)
    unit = "rad" if term in ("alpha", "beta", "gamma") else "mm"
    fitters = (opts.fit_regression, opts.network_fitter())
    mode, directions, excluded = _splits(data, opts.split)
    X, offsets = _with_offsets(data, mode)
    out = NeuralComparison(
        data.target,
        "compared",
        unit,
        mode,
        list(data.channels),
        list(data.campaigns),
        excluded,
        offsets,
        [],
        list(opts.hidden),
    )
    results = []
    for direction in directions:
        name, tr, te = direction[:3]
        if tr.sum() < opts.min_rows or te.sum() < max(5, opts.min_rows // 6):
            out.status = "too few readings"
            out.note = f"{name}: {int(tr.sum())} training and {int(te.sum())} test readings"
            return out
        results.append(_direction(X, data.y, direction, fitters))
    out.directions = results
    return out


def neural_comparisons(
    bundles: Sequence[BundleLike],
    targets: Sequence[str],
    channels: Sequence[str],
    **keywords: Unpack[ComparisonKeywords],
) -> list[NeuralComparison]:
    """Return one comparison per target fixed in advance ("all": every term the campaigns measured).

    A target the split cannot use honestly (only zeroed readings across campaigns) comes back
    ``refused`` with the reason, not compared. ``keywords``: ``ComparisonOptions``' fields.
    """
    opts = ComparisonOptions(**keywords)
    if list(targets) == ["all"]:
        seen = pd.concat([b.errors[["axis", "term"]] for b in bundles]).drop_duplicates()
        targets = [f"{a}/{t}" for a, t in sorted(map(tuple, seen.to_numpy().tolist()))]
    out = []
    for target in targets:
        try:
            out.append(compare_models(comparison_data(bundles, target, channels), opts))
        except ValidationError as exc:
            out.append(NeuralComparison(str(target), "refused", note=str(exc), network_hidden=list(opts.hidden)))
    return out
