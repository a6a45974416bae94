"""The campaign advisor: the next stages that most reduce the predicted variance of the correction (I-optimal).

A campaign pins each link's model only as far as its stages moved the model's regressors apart
(eq. 6.9: the estimate needs sum phi phi^T well conditioned, and "special attention was paid when
setting up the test conditions to ensure that the input data presented was as uncorrelated as
possible", ch. 6.4.2). The advisor says which staged single-heat-source tests (ch. 5.2, 6.3: one
heat source at a time, then a cool-down, with one instrument setup mounted) would pin it best:

1. **Parameters.** Every coefficient of the model document's link and joint terms, plus the
   physically recast terms the stepwise regression may have left out (each link's structure
   means, eq. 3.3, and side-to-side gradients, eqs. 3.4-3.5, on all six parameters, and the link's
   constant). Each coefficient has a weak prior: its term contributes at most about
   ``CONSTANT_PRIOR`` (fitting's prior on constants that only zeroed sessions see).
2. **Information.** The measured points of the campaign through the linearised chain
   (``W = sum_e Ad_e(q) p_e``, eq. 4.12 to first order, the joint adjustment's model), each
   measured component weighted by its noise: ``F = A^T A + prior`` (eq. 6.9's matrix). A laser
   zeroed at its mounting (``datum: session``) reads every error less an unknown constant of
   the session; its rows are taken relative to their session mean, which is exactly what the
   session offsets of the fit leave.
3. **Target.** The correction's prediction variance integrated over the work space (a grid of
   poses within the measured travel of every axis) and over the machine's warm-up under all heat
   sources (the operating states): ``phi = trace(F^-1 M)``, ``M`` the mean of ``a a^T`` over the
   grid's translation rows (I-optimal design).
4. **Candidates.** Each mounted setup of the campaign, each heat source the campaign ran (spindle,
   each axis drive), heated for 1, 2 or 4 h then cooled as long: the temperatures it would
   produce come from a thermal response fitted per channel to the campaign's own stages (a sum
   of two first-order lags of every heat source, ch. 5.3 Fig. 5.4, ``physics.lag``), and with them
   the regressor rows its sweeps would add.
5. **Greedy selection** under the hours budget: the candidate with the largest reduction of
   ``phi`` per machine hour (``(F + C^T C)^-1`` through the Woodbury identity), the thermal state
   carried from one chosen stage to the next, until the budget is spent or no stage gains 1 %.

Pure: arrays and bundles in, an :class:`Advice` out (its ``plan()`` is a ``driftlab-plan/1`` document).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, TypedDict, Unpack

import numpy as np
import pandas as pd
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import threadpool_limits

from driftlab.errors import ValidationError
from driftlab.models.document import ModelDocument
from driftlab.models.features import Feature, Inputs, candidate_features, channel_columns, evaluate
from driftlab.models.fitting import CONSTANT_PRIOR, build_samples, chain_dims
from driftlab.models.structures import STRUCTURE_ELEMENT
from driftlab.physics.kinematics import ELEMENTS, LINKS, PARAMS, parameter_jacobian
from driftlab.physics.lag import first_order_lag
from driftlab.vocabulary import AXES

if TYPE_CHECKING:
    from driftlab.models.standard_model import BundleLike

#: the heat sources of the staged tests (ch. 5.2): the spindle and each axis drive
SOURCES: tuple[str, ...] = ("spindle", *AXES)
#: time constants the thermal response may use (s): 15 min to 8 h, the thesis' range (ch. 6.3: "three hours or more")
TAU_GRID_S: tuple[float, ...] = (900.0, 1800.0, 3600.0, 7200.0, 14400.0, 28800.0)
#: heating durations of a candidate stage (h); each is followed by a cool-down as long
DURATIONS_H: tuple[float, ...] = (1.0, 2.0, 4.0)
#: stated noise when a bundle states none (the joint adjustment's defaults): angle rad, length mm
DEFAULT_NOISE = (5e-7, 0.0005)
#: a chosen stage must cut the integrated variance by at least this fraction
MIN_GAIN = 0.01
ROTARY = ("A", "B")


# ----------------------------------------------------------------------------- heat sources


def stage_sources(heat_source: str, axis: str | None) -> np.ndarray:
    """Return the (6,) on/off state of the heat sources (spindle, X..B drives) of one stage as run.

    Bundle stages name their sources by kind (``spindle``, ``axis``, ``spindle+axis``, ``none``);
    an axis source is the stage's own axis (the plan's convention, ch. 5.2).
    """
    u = np.zeros(len(SOURCES))
    for kind in str(heat_source).lower().split("+"):
        kind = kind.strip()
        if kind == "spindle":
            u[0] = 1.0
        elif kind in ("axis", "feed", "motor_hold") and axis in AXES:
            u[1 + AXES.index(str(axis))] = 1.0
    return u


def source_inputs(stages: Sequence[Any], t_s: np.ndarray) -> np.ndarray:
    """Return (N, 6) heat-source states at times ``t_s``: the state over the interval ending at each time."""
    t = np.asarray(t_s, float)
    out = np.zeros((t.size, len(SOURCES)))
    for st in stages:
        u = stage_sources(getattr(st, "heat_source", "none"), getattr(st, "axis", None))
        if not u.any():
            continue
        # held input: the reading at t reports the interval ending at t (physics.lag's convention)
        m = (t > float(st.start_s)) & (t <= float(st.end_s))
        out[m] = np.maximum(out[m], u)
    return out


# ----------------------------------------------------------------------------- thermal response


@dataclass
class ThermalState:
    """Where the machine stands thermally: lags of every source and of every channel's dT."""

    source_lags: dict[float, np.ndarray]  # tau -> (6,)
    channel_lags: dict[tuple[str, float], float]  # (channel, tau) -> lagged dT
    days: float  # days since the model's time origin


@dataclass
class ThermalResponse:
    """dT of each channel as a sum of two first-order lags of every heat source (ch. 5.3, Fig. 5.4).

    ``dT_c(t) = sum_s g1_cs L_tau1(u_s)(t) + g2_cs L_tau2(u_s)(t) + g_room dT_room(t) + g0_c``,
    the pair of time constants chosen per channel from ``TAU_GRID_S`` by least squares
    (eq. 6.9) on the campaign's own stages; the room air is held at its last day's mean.
    """

    channels: list[str]
    taus_s: np.ndarray  # (C, 2)
    gains: np.ndarray  # (C, 2 * 6 + 2): tau1 gains, tau2 gains, room, constant
    room_mean: float
    rmse_degC: np.ndarray  # (C,)
    #: the room channels, each held at its last day's mean dT
    room_levels: dict[str, float] = field(default_factory=dict)

    @property
    def outputs(self) -> list[str]:
        """Return the channels :meth:`predict` returns: the modelled ones, then the room's."""
        return [*self.channels, *self.room_levels]

    def predict(self, lags: Mapping[float, np.ndarray]) -> np.ndarray:
        """Return (n, C + rooms) dT from source lags ``{tau: (n, 6)}`` (the room at its mean)."""
        n = next(iter(lags.values())).shape[0]
        out = np.empty((n, len(self.channels) + len(self.room_levels)))
        out[:, len(self.channels) :] = np.array(list(self.room_levels.values()))
        for c in range(len(self.channels)):
            t1, t2 = self.taus_s[c]
            g = self.gains[c]
            k = len(SOURCES)
            out[:, c] = lags[t1] @ g[:k] + lags[t2] @ g[k : 2 * k] + g[2 * k] * self.room_mean + g[2 * k + 1]
        return out


def fit_response(
    times_s: np.ndarray, dT: pd.DataFrame, sources: np.ndarray, room: Sequence[str] = ()
) -> ThermalResponse:
    """Return the thermal response of every channel of ``dT`` to the heat ``sources`` (N, 6) (ch. 5.3)."""
    t = np.asarray(times_s, float)
    chans = [c for c in dT.columns if c not in room]
    Y = dT[chans].to_numpy(float)
    Y = np.where(np.isfinite(Y), Y, 0.0)
    room_cols = [c for c in room if c in dT.columns]
    room_dT = dT[room_cols].to_numpy(float).mean(axis=1) if room_cols else np.zeros(t.size)
    room_dT = np.where(np.isfinite(room_dT), room_dT, 0.0)
    day = t >= t[-1] - 86400.0
    room_mean = float(room_dT[day].mean()) if room_cols else 0.0
    lagged = {tau: first_order_lag(sources, t, tau) for tau in TAU_GRID_S}
    best_sse = np.full(len(chans), np.inf)
    taus = np.zeros((len(chans), 2))
    gains = np.zeros((len(chans), 2 * len(SOURCES) + 2))
    for i, t1 in enumerate(TAU_GRID_S):
        for t2 in TAU_GRID_S[i + 1 :]:
            Z = np.column_stack([lagged[t1], lagged[t2], room_dT, np.ones(t.size)])
            G, *_ = np.linalg.lstsq(Z, Y, rcond=None)
            sse = ((Y - Z @ G) ** 2).sum(axis=0)
            better = sse < best_sse
            best_sse[better] = sse[better]
            taus[better] = (t1, t2)
            gains[better] = G.T[better]
    levels = {c: float(np.nanmean(dT[c].to_numpy(float)[day])) for c in room_cols}
    return ThermalResponse(chans, taus, gains, room_mean, np.sqrt(best_sse / max(t.size, 1)), levels)


def simulate(
    response: ThermalResponse,
    state: ThermalState,
    schedule: Sequence[tuple[float, np.ndarray]],
    at_s: np.ndarray,
    channel_taus: Sequence[tuple[str, float]],
    step_s: float = 300.0,
) -> tuple[Inputs, ThermalState]:
    """Return the inputs (dT, lagged dT, days) at times ``at_s`` into ``schedule`` and the state at its end.

    ``schedule`` is a list of (duration s, (6,) source states) run from ``state``; the lags are
    exact for inputs held over each step (``physics.lag.first_order_lag``).
    """
    total = float(sum(d for d, _ in schedule))
    n = max(int(np.ceil(total / step_s)), 1)
    grid = np.linspace(0.0, total, n + 1)
    U = np.zeros((grid.size, len(SOURCES)))
    edges = np.cumsum([0.0, *(d for d, _ in schedule)])
    for (_, u), a, b in zip(schedule, edges[:-1], edges[1:]):
        U[(grid > a) & (grid <= b + 1e-9)] = u
    lags = {tau: first_order_lag(U, grid, tau, y0=state.source_lags[tau]) for tau in TAU_GRID_S}
    dT_grid = response.predict(lags)
    at = np.asarray(at_s, float)
    outs = response.outputs
    dT = pd.DataFrame({c: np.interp(at, grid, dT_grid[:, k]) for k, c in enumerate(outs)})
    lagged: dict[tuple[str, float], np.ndarray] = {}
    ends: dict[tuple[str, float], float] = {}
    for c, tau in channel_taus:
        if c not in outs:
            continue
        k = outs.index(c)
        series = first_order_lag(dT_grid[:, k], grid, tau, y0=state.channel_lags.get((c, tau), dT_grid[0, k]))
        lagged[(c, tau)] = np.interp(at, grid, series)
        ends[(c, tau)] = float(series[-1])
    days = state.days + at / 86400.0
    new = ThermalState({tau: v[-1].copy() for tau, v in lags.items()}, ends, state.days + total / 86400.0)
    return Inputs(dT=dT, lagged=lagged, days=days), new


# ----------------------------------------------------------------------------- parameters and rows


@dataclass(frozen=True)
class Parameter:
    """One coefficient the advisor tracks: a term of one parameter of one link or joint."""

    element: str
    param: str
    feature: Feature


def advisor_parameters(
    document: ModelDocument | None,
    structures: Mapping[str, str],
    locations: Mapping[str, str],
    channels: Sequence[str],
    room: Sequence[str] = (),
    structure_terms: bool = True,
) -> list[Parameter]:
    """Return the coefficients to pin: the document's terms plus each link's recast structure terms.

    Per link: its constant and, for every structure on it (``structures.STRUCTURE_ELEMENT``), the
    mean over its sites (eq. 3.3) and the side-to-side gradients (eqs. 3.4-3.5), on all six
    parameters; the stepwise regression may have dropped exactly the ones a campaign left collinear.
    """
    out: list[Parameter] = []
    seen: set[tuple[str, str, str]] = set()

    def add(element: str, param: str, f: Feature) -> None:
        key = (element, param, f.name)
        if key not in seen:
            seen.add(key)
            out.append(Parameter(element, param, f))

    for term in document.terms if document is not None else []:
        for fd in term.features:
            f = fd.feature()
            if f.kind == "session" or any(c not in channels for c in f.channels):
                continue
            add(term.element, term.param, f)
    by_link: dict[str, dict[str, list[str]]] = {}
    for c in channels if structure_terms else ():
        s = structures.get(c, "")
        el = STRUCTURE_ELEMENT.get(s)
        if el in LINKS and c not in room:
            by_link.setdefault(el, {}).setdefault(s, []).append(c)
    for el in LINKS:
        for s, cs in by_link.get(el, {}).items():
            feats = candidate_features(cs, structures, structure_members={s: cs}, locations=locations)
            extra = [f for f in feats if f.kind == "mean" or (f.kind == "gradient" and f.label)]
            for param in PARAMS:
                for f in extra:
                    add(el, param, f)
    # every element parameter with a term has its constant (the fit forces one in each stage fit)
    for el, param in list(dict.fromkeys((p.element, p.param) for p in out)):
        add(el, param, Feature("intercept"))
    order = {e: i for i, e in enumerate(ELEMENTS)}
    out.sort(key=lambda p: (order[p.element], PARAMS.index(p.param)))
    return out


def jacobians(
    q: np.ndarray, keys: Sequence[tuple[str, str]], dims: Mapping[str, tuple[float, float, float]]
) -> dict[tuple[str, str], np.ndarray]:
    """Return dW/dp (N, 6) of every (element, parameter) at poses ``q`` (eq. 4.12 to first order)."""
    return {(e, p): parameter_jacobian(q, e, PARAMS.index(p), dims) for e, p in keys}


class RowBuilder:
    """Builds rows of the linearised chain: component t of W at each pose, over all tracked coefficients."""

    def __init__(self, params: Sequence[Parameter], dims: Mapping[str, tuple[float, float, float]]) -> None:
        self.params = list(params)
        self.dims = dims
        self.keys = list(dict.fromkeys((p.element, p.param) for p in self.params))
        self.cols = {k: [i for i, p in enumerate(self.params) if (p.element, p.param) == k] for k in self.keys}
        self.unique = list(dict.fromkeys(p.feature for p in self.params))
        where = {f: i for i, f in enumerate(self.unique)}
        self.feature_of = np.array([where[p.feature] for p in self.params])

    def features(self, inputs: Inputs, q: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return (N, P) the regressor of every tracked coefficient at every sample (each term evaluated once)."""
        U = np.column_stack([evaluate(f, inputs, q, direction) for f in self.unique])
        return U[:, self.feature_of]

    def rows(
        self,
        inputs: Inputs,
        q: np.ndarray,
        direction: np.ndarray,
        components: Sequence[int],
        jac: Mapping[tuple[str, str], np.ndarray] | None = None,
    ) -> np.ndarray:
        """Return (len(components), N, P): for each component, the design of W_t at every sample."""
        jac = jac if jac is not None else jacobians(q, self.keys, self.dims)
        F = self.features(inputs, q, direction)
        out = np.zeros((len(components), q.shape[0], len(self.params)))
        for k in self.keys:
            cols = self.cols[k]
            for j, t in enumerate(components):
                out[j][:, cols] = jac[k][:, t][:, None] * F[:, cols]
        return out

    def time_part(self, inputs: Inputs) -> np.ndarray:
        """Return (n_states, P): the part of every term that reads the temperatures (1 where none)."""
        Ft = np.ones((len(inputs), len(self.unique)))
        for i, f in enumerate(self.unique):
            if f.kind == "pos_dT":  # position x dT of the screw, eq. 3.2
                Ft[:, i] = evaluate(Feature("dT", f.channels), inputs)
            elif f.kind not in ("intercept", "position", "direction"):
                Ft[:, i] = evaluate(f, inputs)
        return Ft[:, self.feature_of]

    def pose_part(self, q: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return (n_poses, P): the part of every term that reads the pose (1 where none)."""
        Fx = np.ones((q.shape[0], len(self.unique)))
        bare = Inputs(dT=pd.DataFrame())
        for i, f in enumerate(self.unique):
            if f.kind in ("position", "direction"):
                Fx[:, i] = evaluate(f, bare, q, direction)
            elif f.kind == "pos_dT":
                Fx[:, i] = evaluate(Feature("position", label=f.label), bare, q, direction)
        return Fx[:, self.feature_of]

    def lever(self, jac: Mapping[tuple[str, str], np.ndarray], component: int) -> np.ndarray:
        """Return (n_poses, P): dW_component / d(element parameter) of each coefficient's element parameter."""
        n = next(iter(jac.values())).shape[0]
        J = np.empty((n, len(self.params)))
        for k in self.keys:
            J[:, self.cols[k]] = jac[k][:, component][:, None]
        return J

    def separable(self, Ft: np.ndarray, pose_lever: np.ndarray) -> np.ndarray:
        """Return (n_states * n_poses, P): every pose at every thermal state.

        A term is the product of a part that reads the temperatures and a part that reads the pose
        (``pos_dT``: position x dT, eq. 3.2); ``pose_lever`` is the pose part times the chain's lever.
        """
        return (Ft[:, None, :] * pose_lever[None, :, :]).reshape(Ft.shape[0] * pose_lever.shape[0], -1)

    def feature_rms(self, inputs: Inputs, q: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return the RMS of every coefficient's regressor over the samples (1 for a constant)."""
        return np.sqrt(np.mean(self.features(inputs, q, direction) ** 2, axis=0))


def _q(axis: str, positions: np.ndarray, pose: Mapping[str, float]) -> np.ndarray:
    """Return (N, 5) joint coordinates: the moved axis at ``positions``, the others at ``pose`` (deg -> rad)."""
    q = np.zeros((positions.size, 5))
    for k, ax in enumerate(AXES):
        v = positions if ax == axis else np.full(positions.size, float(pose.get(ax, 0.0)))
        q[:, k] = np.deg2rad(v) if ax in ROTARY else v
    return q


def session_demean(rows: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Return rows less their mean over each session label ('' = against a stable artefact: kept as is)."""
    out = rows.copy()
    for lab in dict.fromkeys(labels):
        if lab:
            m = labels == lab
            out[m] -= out[m].mean(axis=0)
    return out


# ----------------------------------------------------------------------------- candidates and result


@dataclass(frozen=True)
class SetupInfo:
    """A mounted setup of the campaign as the advisor may mount it again."""

    name: str
    entry: dict[str, Any]  # the plan's setup (driftlab-plan/1)
    axis: str
    terms: tuple[str, ...]
    session: bool  # a zeroed laser (datum: session)
    positions: tuple[float, ...]
    pose: dict[str, float]


@dataclass(frozen=True)
class Candidate:
    """A staged test: one setup mounted, one heat source for ``heat_h``, then a cool-down of ``cool_h``."""

    setup: str
    source: str
    heat_h: float
    cool_h: float

    @property
    def hours(self) -> float:
        """Return the machine time of the stage and its cool-down."""
        return self.heat_h + self.cool_h


@dataclass
class AdvisedStage:
    """One chosen stage and the integrated variance before and after it (um^2 per translation component)."""

    candidate: Candidate
    variance_before_um2: float
    variance_after_um2: float

    @property
    def rms_before_um(self) -> float:
        """Return the RMS predicted standard deviation of the correction before the stage (um)."""
        return float(np.sqrt(self.variance_before_um2))

    @property
    def rms_after_um(self) -> float:
        """Return the RMS predicted standard deviation of the correction after the stage (um)."""
        return float(np.sqrt(self.variance_after_um2))


class PlanSweepRecord(TypedDict):
    """A stage's sweep in a ``driftlab-plan/1`` document."""

    positions: list[float]
    interval_s: float
    point_s: float


class PlanStageRecord(TypedDict):
    """One stage of a ``driftlab-plan/1`` document written by the advisor (heat, or its cool-down)."""

    name: str
    heat: list[dict[str, object]]  # the plan's heat entries (none in a cool-down)
    axis: str
    setup: str
    duration_s: float
    sweep: PlanSweepRecord


class PlanRecord(TypedDict):
    """The ``driftlab-plan/1`` document of the advised stages (docs/plans.md)."""

    format: str
    name: str
    description: str
    machine: dict[str, str]
    scan_interval_s: float
    setups: dict[str, dict[str, object]]  # the plan's setups, as the campaign states them
    stages: list[PlanStageRecord]


class AdvisedStageRecord(TypedDict):
    """One row of :meth:`Advice.table`: an advised stage and what it buys."""

    stage: str
    setup: str
    source: str
    heat_h: float
    cool_h: float
    hours: float
    variance_before_um2: float
    variance_after_um2: float
    reduction_um2: float
    rms_before_um: float
    rms_after_um: float


class AdviceDetails(TypedDict, total=False):
    """The advisor's options echoed in the advice's JSON."""

    operating_h: float
    grid_poses: int
    durations_h: list[float]


class AdviceRecord(AdviceDetails):
    """The JSON form of an :class:`Advice`."""

    campaign: str
    machine: str
    hours_budget: float
    hours_used: float
    variance_before_um2: float
    variance_after_um2: float
    rms_before_um: float
    rms_after_um: float
    parameters: int
    candidates: int
    response_rmse_degC: float
    stages: list[AdvisedStageRecord]


@dataclass
class Advice:
    """The advisor's answer: the stages, what each buys, and the plan that runs them."""

    campaign: str
    machine: str
    hours: float
    stages: list[AdvisedStage]
    variance_before_um2: float
    variance_after_um2: float
    n_parameters: int
    n_candidates: int
    setups: dict[str, SetupInfo]
    scan_interval_s: float
    sweep_interval_s: float
    heat: dict[str, dict[str, Any]]  # source -> plan heat entry
    response_rmse_degC: float
    details: AdviceDetails = field(default_factory=AdviceDetails)
    #: the campaign's information and the target (for checks; not part of the JSON)
    design: Design | None = field(default=None, repr=False)

    @property
    def used_h(self) -> float:
        """Return the machine hours the advised stages take."""
        return float(sum(s.candidate.hours for s in self.stages))

    def stage_names(self, prefix: str = "advice") -> list[tuple[str, str]]:
        """Return (heating stage name, cool-down stage name) of every advised stage."""
        return [
            (
                f"{s.candidate.setup}.{prefix}{i + 1}.{s.candidate.source.lower()}",
                f"{s.candidate.setup}.{prefix}{i + 1}.cool",
            )
            for i, s in enumerate(self.stages)
        ]

    def plan(self, name: str | None = None, prefix: str = "advice") -> PlanRecord:
        """Return the advised stages as a ``driftlab-plan/1`` document (each: heat, then cool-down)."""
        stages: list[PlanStageRecord] = []
        for s, (hot, cool) in zip(self.stages, self.stage_names(prefix)):
            c = s.candidate
            st = self.setups[c.setup]
            sweep: PlanSweepRecord = {
                "positions": list(st.positions),
                "interval_s": self.sweep_interval_s,
                "point_s": _point_s(self.sweep_interval_s, len(st.positions)),
            }
            for stage, heat, hours in ((hot, [dict(self.heat[c.source])], c.heat_h), (cool, [], c.cool_h)):
                stages.append(
                    {
                        "name": stage,
                        "heat": heat,
                        "axis": st.axis,
                        "setup": c.setup,
                        "duration_s": hours * 3600.0,
                        "sweep": {**sweep, "positions": list(st.positions)},
                    }
                )
        used = {s.candidate.setup for s in self.stages}
        return {
            "format": "driftlab-plan/1",
            "name": name or f"advice-{self.campaign}",
            "description": (
                f"advised next stages for campaign {self.campaign}: predicted RMS of the correction "
                f"{np.sqrt(self.variance_before_um2):.2f} -> {np.sqrt(self.variance_after_um2):.2f} um "
                f"in {self.used_h:g} h (driftlab plan advise)"
            ),
            "machine": {"id": self.machine},
            "scan_interval_s": self.scan_interval_s,
            "setups": {k: copy.deepcopy(self.setups[k].entry) for k in self.setups if k in used},
            "stages": stages or [],
        }

    def table(self) -> list[AdvisedStageRecord]:
        """Return one row per advised stage: setup, source, hours, variance and RMS before/after."""
        return [
            {
                "stage": hot,
                "setup": s.candidate.setup,
                "source": s.candidate.source,
                "heat_h": s.candidate.heat_h,
                "cool_h": s.candidate.cool_h,
                "hours": s.candidate.hours,
                "variance_before_um2": s.variance_before_um2,
                "variance_after_um2": s.variance_after_um2,
                "reduction_um2": s.variance_before_um2 - s.variance_after_um2,
                "rms_before_um": s.rms_before_um,
                "rms_after_um": s.rms_after_um,
            }
            for s, (hot, _) in zip(self.stages, self.stage_names())
        ]

    def to_dict(self) -> AdviceRecord:
        """Return the advice as JSON-ready data."""
        return {
            "campaign": self.campaign,
            "machine": self.machine,
            "hours_budget": self.hours,
            "hours_used": self.used_h,
            "variance_before_um2": self.variance_before_um2,
            "variance_after_um2": self.variance_after_um2,
            "rms_before_um": float(np.sqrt(self.variance_before_um2)),
            "rms_after_um": float(np.sqrt(self.variance_after_um2)),
            "parameters": self.n_parameters,
            "candidates": self.n_candidates,
            "response_rmse_degC": self.response_rmse_degC,
            "stages": self.table(),
            **self.details,
        }

    def summary(self) -> str:
        """Return the advice as a table: stage, hours, predicted variance of the correction before/after."""
        head = (
            f"campaign {self.campaign} ({self.machine}): {self.n_parameters} coefficients, "
            f"{self.n_candidates} candidate stages, budget {self.hours:g} h"
        )
        lines = [
            head,
            "predicted variance of the correction: mean over the work space and the warm-up, per translation component",
            f"{'stage':<36} {'hours':>5} {'before um2':>11} {'after um2':>10} {'RMS um':>15}",
        ]
        for row in self.table():
            lines.append(
                f"{row['stage']:<36} {row['hours']:>5g} {row['variance_before_um2']:>11.2f} "
                f"{row['variance_after_um2']:>10.2f} {row['rms_before_um']:>6.2f} -> {row['rms_after_um']:<6.2f}"
            )
        if not self.stages:
            lines.append("(no stage within the budget cuts the variance by 1 % or more)")
        lines.append(
            f"total {self.used_h:g} h: {self.variance_before_um2:.2f} -> {self.variance_after_um2:.2f} um2 "
            f"(RMS {np.sqrt(self.variance_before_um2):.2f} -> {np.sqrt(self.variance_after_um2):.2f} um)"
        )
        return "\n".join(lines)


def _point_s(interval_s: float, n_positions: int) -> float:
    """Return the time per sweep point: 6 s (the shipped plans') unless two passes would not fit the interval."""
    return float(min(6.0, np.floor(interval_s / max(2 * n_positions, 1) * 10) / 10))


# ----------------------------------------------------------------------------- the design


@dataclass
class Design:
    """The information of a campaign about the tracked coefficients and the target of the correction."""

    builder: RowBuilder
    information: np.ndarray  # (P, P) F = A^T A + prior
    target: np.ndarray  # (P, P) M, mm^2 per translation component
    prior: np.ndarray  # (P,) prior precision

    def covariance(self, info: np.ndarray | None = None) -> np.ndarray:
        """Return F^-1 (the coefficients' covariance) of ``info`` (default: the campaign's)."""
        F = self.information if info is None else info
        d = 1.0 / np.sqrt(np.diag(F))
        inv = np.linalg.inv(F * np.outer(d, d))
        return inv * np.outer(d, d)

    def variance_um2(self, info: np.ndarray | None = None) -> float:
        """Return the integrated prediction variance trace(F^-1 M) in um^2 (F = A^T A + prior, eq. 6.9)."""
        F = self.information if info is None else info
        # scaled to unit diagonal: F and M hold terms from constants to position^3 (many decades apart)
        d = 1.0 / np.sqrt(np.diag(F))
        D = np.outer(d, d)
        X = cho_solve(cho_factor(F * D), self.target * D)
        return float(np.trace(X)) * 1e6


def reduction_um2(
    design: Design, info: np.ndarray, phi_um2: float, rows: np.ndarray, step: Step | None = None
) -> float:
    """Return how much adding ``rows`` C (n, P) cuts trace(F^-1 M) of ``info``, in um^2.

    With fewer rows than coefficients, through the Woodbury identity from the step's
    ``S = F^-1`` and ``S M S``: trace((I + C S C^T)^-1 C S M S C^T); otherwise by solving again.
    """
    if rows.shape[0] == 0:
        return 0.0
    if step is not None and rows.shape[0] < rows.shape[1]:
        SC = step.cov @ rows.T
        K = np.eye(rows.shape[0]) + rows @ SC
        return float(np.trace(np.linalg.solve(K, rows @ step.smss @ rows.T))) * 1e6
    return phi_um2 - design.variance_um2(info + rows.T @ rows)


@dataclass
class Step:
    """What one greedy step shares between its candidates: S = F^-1 and S M S."""

    cov: np.ndarray
    smss: np.ndarray

    @classmethod
    def of(cls, design: Design, info: np.ndarray) -> Step:
        """Return the step's matrices for the information ``info``."""
        cov = design.covariance(info)
        return cls(cov, cov @ design.target @ cov)


@dataclass(frozen=True)
class AdviseOptions:
    """What the advisor is asked: the budget, the candidates' durations, the target's operating states."""

    #: machine time the advised stages may take, heating and cool-down included
    hours: float = 8.0
    #: the advice's campaign name ('' : the last bundle's)
    campaign: str = ""
    #: heating durations of a candidate stage (h), each followed by a cool-down as long
    durations_h: Sequence[float] = DURATIONS_H
    #: how long the target's warm-up under every source runs (h)
    operating_h: float = 2.0
    #: points per axis of the target's work-space grid
    grid_levels: int = 3
    holdout_fraction: float = 0.25
    #: the greedy choice stops when the best stage cuts the integrated variance by less than this share
    min_gain: float = MIN_GAIN
    #: False: the document's terms alone (no recast structure terms beside them)
    structure_terms: bool = True


class AdviseKeywords(TypedDict, total=False):
    """``AdviseOptions``' fields as keywords of ``advise`` and ``advise_design``."""

    hours: float
    campaign: str
    durations_h: Sequence[float]
    operating_h: float
    grid_levels: int
    holdout_fraction: float
    min_gain: float
    structure_terms: bool


def advise(
    bundles: Sequence[BundleLike],
    document: ModelDocument | None = None,
    options: AdviseOptions | None = None,
    **keywords: Unpack[AdviseKeywords],
) -> Advice:
    """Return the stages (setup, heat source, duration) that most cut the correction's integrated variance.

    See :func:`advise_design` for the options; one BLAS thread (the matrices are small and the
    machine is shared, as in ``fitting.fit_bundles``).
    """
    with threadpool_limits(limits=1):
        return advise_design(bundles, document, options, **keywords)


@dataclass(frozen=True)
class _Campaign:
    """What the advisor reads of the campaigns: their setups and the coefficients to pin."""

    setups: dict[str, SetupInfo]
    params: list[Parameter]
    #: the channels the parameters read, and the (channel, time constant) of their lags
    read: list[str]
    lags: list[tuple[str, float]]


def _campaign(bundles: Sequence[Any], document: ModelDocument | None, structure_terms: bool) -> _Campaign:
    """Return the campaigns' setups and the parameters to pin (ValidationError when there is nothing to do)."""
    if not bundles:
        raise ValidationError("no campaign to advise on")
    last = bundles[-1]
    setups = _setups(bundles)
    if not setups:
        raise ValidationError(
            "the campaign states no instrument setups (bundle v2 'setups'): nothing to mount for a next stage"
        )
    chan_meta = {c: ch for b in bundles for c, ch in b.meta.channels.items()}
    structures = {c: ch.structure for c, ch in chan_meta.items()}
    locations = {c: ch.location for c, ch in chan_meta.items()}
    room = [c for b in bundles for c in b.meta.room_channels]
    channels = [c for c in channel_columns(last.temperatures) if all(c in b.temperatures.columns for b in bundles)]
    if document is not None:
        channels = [c for c in channels if c in document.inputs or structures.get(c, "")]
    params = advisor_parameters(document, structures, locations, channels, room, structure_terms)
    if not params:
        raise ValidationError("the campaign's channels name no structure and no model is given: nothing to pin")
    read = list(dict.fromkeys(c for p in params for c in p.feature.channels))
    lags = list(
        dict.fromkeys((p.feature.channels[0], float(p.feature.tau_s or 0)) for p in params if p.feature.kind == "lag")
    )
    return _Campaign(setups, params, read, lags)


def _information(builder: RowBuilder, sub: Any, noise: np.ndarray) -> np.ndarray:
    """Return A^T A of the campaign's training points (each component weighted by its noise, sessions demeaned)."""
    d_sub = _directions(sub.frame, sub.q)
    rows = builder.rows(sub.inputs, sub.q, d_sub, range(6))
    W = sub.frame[list(PARAMS)].to_numpy(float)
    labels = sub.inputs.session if sub.inputs.session is not None else np.full(len(sub.frame), "", dtype=object)
    labels = np.asarray(labels, dtype=object)
    P = len(builder.params)
    info = np.zeros((P, P))
    for t in range(6):
        ok = np.isfinite(W[:, t])
        if not ok.any():
            continue
        A = session_demean(rows[t][ok], labels[ok]) / noise[t]
        info += A.T @ A
    return info


@dataclass(frozen=True)
class _Thermal:
    """The campaign's thermal response (ch. 5.3), its state at the campaign's end and what it was fitted on."""

    resp: ThermalResponse
    state: ThermalState
    scan_s: float
    lags: list[tuple[str, float]]


def _design(
    bundles: Sequence[Any], camp: _Campaign, opts: AdviseOptions, noise: np.ndarray
) -> tuple[Design, _Thermal, int]:
    """Return the campaign's design (information, target, prior), its thermal response and the grid's size."""
    dims = chain_dims(bundles)
    builder = RowBuilder(camp.params, dims)
    origin = min(b.meta.started_at for b in bundles)
    sample = build_samples(bundles, camp.read, None, camp.lags, opts.holdout_fraction, origin)
    frame = sample.frame
    sub = sample.take((frame["role"] == "train").to_numpy())
    info = _information(builder, sub, noise)
    # the thermal response of every channel to every source, from the campaign's own stages (ch. 5.3)
    resp, state, scan_s = _response(bundles, camp.read, camp.lags, origin)
    # the target: the work space within the measured travel, warming up under every source at once
    grid_q, grid_d = _grid(frame, sample.q, opts.grid_levels)
    cold = ThermalState({tau: np.zeros(len(SOURCES)) for tau in TAU_GRID_S}, {}, state.days)
    n_states = 9
    at = np.linspace(0.0, opts.operating_h * 3600.0, n_states)
    op_inputs, _ = simulate(resp, cold, [(opts.operating_h * 3600.0, _sources_on(bundles))], at, camp.lags)
    jac_grid = jacobians(grid_q, builder.keys, dims)
    Ft_op, Fx_grid = builder.time_part(op_inputs), builder.pose_part(grid_q, grid_d)
    R = np.vstack([builder.separable(Ft_op, Fx_grid * builder.lever(jac_grid, t)) for t in (3, 4, 5)])
    target = R.T @ R / R.shape[0]
    # the prior: no term contributes more than about CONSTANT_PRIOR, in the campaign or in use
    rms_use = np.sqrt(np.mean(Ft_op**2, axis=0) * np.mean(Fx_grid**2, axis=0))
    rms = np.maximum(builder.feature_rms(sub.inputs, sub.q, _directions(sub.frame, sub.q)), rms_use)
    spread = np.array([CONSTANT_PRIOR[0] if p.param in PARAMS[:3] else CONSTANT_PRIOR[1] for p in camp.params])
    prior = (np.maximum(rms, 1e-12) / spread) ** 2
    info += np.diag(prior)
    return Design(builder, info, target, prior), _Thermal(resp, state, scan_s, camp.lags), int(grid_q.shape[0])


@dataclass(frozen=True)
class _Choice:
    """The greedy selection's fixed inputs: the design, the candidates and how their rows are made."""

    design: Design
    thermal: _Thermal
    setups: dict[str, SetupInfo]
    levers: dict[str, list[np.ndarray]]
    sweep_s: float
    #: the share of a candidate's points that trains the model, as a weight on its rows
    weight: float


def _best(
    choice: _Choice, fits: Sequence[Candidate], info: np.ndarray, state: ThermalState, phi: float
) -> tuple[float, Candidate, np.ndarray, ThermalState] | None:
    """Return (reduction per hour, candidate, its rows, the thermal state after it) of the best of ``fits``."""
    design, builder, th = choice.design, choice.design.builder, choice.thermal
    sims: dict[tuple[str, float, float], tuple[np.ndarray, ThermalState]] = {}
    step = Step.of(design, info)
    best: tuple[float, Candidate, np.ndarray, ThermalState] | None = None
    for c in fits:
        key = (c.source, c.heat_h, c.cool_h)
        if key not in sims:
            times = np.arange(0.0, c.hours * 3600.0 - 1e-6, choice.sweep_s)
            u = np.zeros(len(SOURCES))
            u[SOURCES.index(c.source)] = 1.0
            inp, end = simulate(th.resp, state, [(c.heat_h * 3600.0, u), (c.cool_h * 3600.0, 0 * u)], times, th.lags)
            sims[key] = (builder.time_part(inp), end)
        Ft, end = sims[key]
        C = _candidate_rows(choice.setups[c.setup], Ft, choice.levers[c.setup], builder) * choice.weight
        gain = reduction_um2(design, info, phi, C, step)
        score = gain / c.hours
        if best is None or score > best[0]:
            best = (score, c, C, end)
    return best


def _greedy(choice: _Choice, cands: Sequence[Candidate], opts: AdviseOptions) -> tuple[list[AdvisedStage], float]:
    """Return the stages chosen greedily within the budget (largest variance cut per hour) and the variance left."""
    info, state = choice.design.information, choice.thermal.state
    phi = choice.design.variance_um2()
    chosen: list[AdvisedStage] = []
    remaining = float(opts.hours)
    while True:
        fits = [c for c in cands if c.hours <= remaining + 1e-9]
        if not fits:
            break
        best = _best(choice, fits, info, state, phi)
        if best is None:
            break
        score, c, C, end = best
        if score * c.hours < opts.min_gain * phi:
            break
        info = info + C.T @ C
        after = choice.design.variance_um2(info)
        chosen.append(AdvisedStage(c, phi, after))
        phi = after
        state = end
        remaining -= c.hours
    return chosen, phi


def advise_design(
    bundles: Sequence[BundleLike],
    document: ModelDocument | None = None,
    options: AdviseOptions | None = None,
    **keywords: Unpack[AdviseKeywords],
) -> Advice:
    """Return the stages (setup, heat source, duration) that most cut the correction's integrated variance.

    ``bundles`` are the campaigns of one machine (bundle v2: their setups are what may be mounted
    again); ``document`` the model fitted to them (None: the recast structure terms alone;
    ``structure_terms=False``: the document's terms alone). The greedy choice stays within
    ``hours`` of machine time, heating and cool-down included; it stops when the best stage cuts the
    integrated variance by less than ``min_gain`` of it. The options are ``options``
    (``AdviseOptions``), each also accepted by keyword.
    """
    opts = replace(options or AdviseOptions(), **keywords)
    hours = opts.hours
    if not hours > 0 or not np.isfinite(hours):
        raise ValidationError(f"--hours must be a positive number of hours, got {hours:g}")
    camp = _campaign(bundles, document, opts.structure_terms)
    noise = _noise(bundles)
    design, thermal, n_grid = _design(bundles, camp, opts, noise)
    sweep_s = _sweep_interval(bundles)
    heat = _heat_entries(bundles)
    sources = [s for s in SOURCES if s in heat]
    setups = camp.setups
    cands = [
        Candidate(sid, src, float(h), float(h))
        for sid in setups
        for src in sources
        for h in opts.durations_h
        if 2 * h <= hours + 1e-9
    ]
    weight = float(np.sqrt(max(1.0 - opts.holdout_fraction, 0.0)))
    levers = _setup_levers(design.builder, setups, noise)
    chosen, phi = _greedy(_Choice(design, thermal, setups, levers, sweep_s, weight), cands, opts)
    resp = thermal.resp
    return Advice(
        campaign=opts.campaign or bundles[-1].name,
        machine=bundles[-1].meta.machine.id,
        hours=float(hours),
        stages=chosen,
        variance_before_um2=design.variance_um2(),
        variance_after_um2=phi,
        n_parameters=len(camp.params),
        n_candidates=len(cands),
        setups=setups,
        scan_interval_s=thermal.scan_s,
        sweep_interval_s=sweep_s,
        heat=heat,
        response_rmse_degC=float(np.sqrt(np.mean(resp.rmse_degC**2))) if resp.rmse_degC.size else 0.0,
        details={"operating_h": opts.operating_h, "grid_poses": n_grid, "durations_h": list(opts.durations_h)},
        design=design,
    )


# ----------------------------------------------------------------------------- helpers


def _directions(frame: pd.DataFrame, q: np.ndarray) -> np.ndarray:
    """Return (N, 5) approach directions: each point's direction in the column of its moved axis."""
    d = np.zeros_like(q)
    ax = frame["axis"].to_numpy(str)
    dr = frame["direction"].to_numpy(float)
    for k, a in enumerate(AXES):
        m = ax == a
        d[m, k] = dr[m]
    return d


def _noise(bundles: Sequence[Any]) -> np.ndarray:
    """Return the (6,) stated noise of each work-space component (angles rad, lengths mm)."""
    ang, ln = DEFAULT_NOISE
    meta = bundles[0].meta.noise
    if meta is not None:
        ang = float(meta.angle_rad or ang)
        ln = float(meta.length_mm or ln)
    return np.array([ang] * 3 + [ln] * 3)


def _setups(bundles: Sequence[Any]) -> dict[str, SetupInfo]:
    """Return the campaign's setups that can be mounted again, with the positions their sweeps visited."""
    out: dict[str, SetupInfo] = {}
    for b in bundles:
        for sid, s in (b.meta.setups or {}).items():
            if sid in out or s.instrument not in ("laser", "proximity", "probe") or s.axis is None:
                continue
            if s.instrument == "probe":
                continue  # the daemon drives laser and proximity setups (docs/plans.md)
            errs = b.errors
            here = errs[errs["setup"] == sid] if "setup" in errs.columns else errs.iloc[0:0]
            positions = tuple(float(p) for p in sorted(here["position"].unique())) if len(here) else ()
            if not positions:
                continue
            ref = dict(s.reference)
            pose = {k: float(v) for k, v in dict(ref.pop("pose", {}) or {}).items()}
            entry: dict[str, Any] = {"instrument": s.instrument, "axis": s.axis}
            if s.instrument == "laser":
                entry["optics"] = s.optics
            else:
                entry["fixture"] = s.fixture
            terms = tuple(c.partition("/")[2] for c in s.terms)
            entry["terms"] = list(terms)
            if s.counter_rotating:
                entry["counter_rotating"] = True
            if pose:
                entry["pose"] = pose
            if ref:
                entry["reference"] = ref
            out[sid] = SetupInfo(sid, entry, s.axis, terms, s.datum == "session", positions, pose)
    return out


def _sweep_interval(bundles: Sequence[Any]) -> float:
    """Return the campaign's sweep interval: the median time between visits of a setup's first point."""
    gaps: list[float] = []
    for b in bundles:
        e = b.errors
        if e.empty:
            continue
        keys = ["setup"] if "setup" in e.columns else ["axis"]
        for _, g in e.groupby(keys):
            p0 = g["position"].min()
            t = np.unique(g.loc[(g["position"] == p0) & (g["direction"] == g["direction"].max()), "time_s"])
            if t.size > 1:
                gaps += list(np.diff(t))
    return float(np.median(gaps)) if gaps else 1800.0


def _heat_entries(bundles: Sequence[Any]) -> dict[str, dict[str, Any]]:
    """Return the plan heat entry of every source the campaign ran (its speed; an axis over its measured travel)."""
    out: dict[str, dict[str, Any]] = {}
    extents: dict[str, tuple[float, float]] = {}
    for b in bundles:
        for ax, g in b.errors.groupby("axis"):
            lo, hi = float(g["position"].min()), float(g["position"].max())
            a, z = extents.get(str(ax), (lo, hi))
            extents[str(ax)] = (min(a, lo), max(z, hi))
    for b in bundles:
        for st in b.meta.stages:
            u = stage_sources(st.heat_source, st.axis)
            if u[0]:
                rpm = float(st.spindle_rpm) or 10000.0
                out.setdefault("spindle", {"kind": "spindle", "rpm": rpm})
            if u[1:].any():
                ax = AXES[int(np.argmax(u[1:]))]
                lo, hi = extents.get(ax, (0.0, 0.0))
                if st.feed_mm_min > 0 and hi > lo:
                    out.setdefault(
                        ax,
                        {
                            "kind": "axis",
                            "axis": ax,
                            "feed_mm_min": float(st.feed_mm_min),
                            "from_pos": lo,
                            "to_pos": hi,
                        },
                    )
    return out


def _sources_on(bundles: Sequence[Any]) -> np.ndarray:
    """Return the (6,) state with every source the campaign ran switched on (the operating condition)."""
    u = np.zeros(len(SOURCES))
    for b in bundles:
        for st in b.meta.stages:
            u = np.maximum(u, stage_sources(st.heat_source, st.axis))
    return u


def _response(
    bundles: Sequence[Any], read: Sequence[str], lags: Sequence[tuple[str, float]], origin: Any
) -> tuple[ThermalResponse, ThermalState, float]:
    """Return the thermal response fitted on the last campaign, its state at the campaign's end, the scan interval."""
    b = bundles[-1]
    temps = b.temperatures
    t = temps["time_s"].to_numpy(float)
    cols = [c for c in temps.columns if c != "time_s"]
    ref = {}
    for c in cols:
        v = temps[c].to_numpy(float)
        ok = np.isfinite(v)
        ref[c] = float(v[ok][0]) if ok.any() else 0.0
    dT = pd.DataFrame({c: temps[c].to_numpy(float) - ref[c] for c in cols})
    dT = dT.interpolate(limit_direction="both")
    room = list(b.meta.room_channels)
    U = source_inputs(b.meta.stages, t)
    resp = fit_response(t, dT[[c for c in cols if c in read or c in room]], U, room)
    src = {tau: first_order_lag(U, t, tau)[-1] for tau in TAU_GRID_S}
    chl = {}
    for c, tau in lags:
        if c in dT.columns:
            chl[(c, tau)] = float(first_order_lag(dT[c].to_numpy(float), t, tau)[-1])
    days = ((b.meta.started_at - origin).total_seconds() + float(t[-1])) / 86400.0
    scan = float(np.median(np.diff(t))) if t.size > 1 else 60.0
    return resp, ThermalState(src, chl, days), scan


def _grid(frame: pd.DataFrame, q: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Return work-space poses (every axis at ``levels`` points of its measured range) and alternating directions."""
    axes_levels = []
    for k, ax in enumerate(AXES):
        on = frame["axis"].to_numpy(str) == ax
        if on.any():
            lo, hi = float(q[on, k].min()), float(q[on, k].max())
            axes_levels.append(np.linspace(lo, hi, levels) if hi > lo else np.array([lo]))
        else:
            axes_levels.append(np.array([0.0]))
    mesh = np.meshgrid(*axes_levels, indexing="ij")
    gq = np.column_stack([m.ravel() for m in mesh])
    sign = np.where(np.arange(gq.shape[0]) % 2 == 0, 1.0, -1.0)
    return gq, np.repeat(sign[:, None], 5, axis=1)


def _setup_levers(
    builder: RowBuilder, setups: Mapping[str, SetupInfo], noise: np.ndarray
) -> dict[str, list[np.ndarray]]:
    """Return, per setup, the weighted pose part x lever (n_points, P) of each term it reads (one chain pass)."""
    poses = {}
    for sid, st in setups.items():
        pos = np.array(st.positions * 2)
        q = _q(st.axis, pos, st.pose)
        d = np.zeros_like(q)
        d[:, AXES.index(st.axis)] = np.repeat([1.0, -1.0], len(st.positions))
        poses[sid] = (q, d)
    q_all = np.vstack([q for q, _ in poses.values()])
    jac_all = jacobians(q_all, builder.keys, builder.dims)
    out: dict[str, list[np.ndarray]] = {}
    start = 0
    for sid, (q, d) in poses.items():
        sl = slice(start, start + q.shape[0])
        start += q.shape[0]
        jac = {k: v[sl] for k, v in jac_all.items()}
        Fx = builder.pose_part(q, d)
        comps = [PARAMS.index(x) for x in setups[sid].terms]
        out[sid] = [Fx * builder.lever(jac, t) / noise[t] for t in comps]
    return out


def _candidate_rows(setup: SetupInfo, Ft: np.ndarray, levers: Sequence[np.ndarray], builder: RowBuilder) -> np.ndarray:
    """Return the weighted rows (n, P) a candidate's sweeps add: every point, both directions, every term.

    ``Ft`` is the temperature part of the terms at the sweeps' times (``RowBuilder.time_part``).
    """
    out = []
    for lever in levers:
        r = builder.separable(Ft, lever)
        if setup.session:
            r = r - r.mean(axis=0)  # one zeroed mounting: the session offset takes the mean
        out.append(r)
    return np.vstack(out)
