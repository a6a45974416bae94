"""The fitting pipeline: screening -> allocation through the HTM chain -> per-link stepwise models
-> validation (tables 6.1-6.3) -> neural comparison -> virtual sensors -> a model document.

Pure over bundles (``fit_bundles``); loading from the store, registering and jobs live in driftlab.jobs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict, TypeVar

import numpy as np
import pandas as pd
from threadpoolctl import threadpool_limits

from driftlab.errors import ValidationError
from driftlab.jsonsafe import strict_json
from driftlab.labels import display_unit
from driftlab.metrics import rmse
from driftlab.models.document import (
    MODEL_FORMAT,
    ModelDocument,
    document_json,
    now_iso,
    validate_document,
)
from driftlab.models.features import (
    INTERCEPT,
    Feature,
    Inputs,
    build_inputs,
    candidate_features,
    channel_columns,
    design_matrix,
    fill_gaps,
    session_terms,
)
from driftlab.models.findings import plan_findings
from driftlab.models.lines import (
    LINE_ELEMENT,
    Composed,
    LineFit,
    compose,
    distinct,
    fit_lines,
    home_deviation,
    levered,
    line_pool,
)
from driftlab.models.neural import NeuralComparison, neural_comparisons
from driftlab.models.physical_check import machine_geometry, physical_check, stated_geometries
from driftlab.models.regression import StepwiseOptions, TermFit, r_squared, stepwise
from driftlab.models.selection import ScreeningResult, screen_channels
from driftlab.models.split import SPLITS, STAGE_SPLIT, TIME_SPLIT, held_out_rows
from driftlab.models.structures import SCREW_STRUCTURES, STRUCTURE_ELEMENT, STRUCTURE_SPANS
from driftlab.models.uncertainty import JointFit, Pinning, ar1_inflation
from driftlab.models.virtual_sensor import fit_virtual_sensors
from driftlab.physics.geometry import GEOMETRY_LINKS
from driftlab.physics.kinematics import ELEMENTS, PARAMS, TABLE_A1, allocate, parameter_jacobian, workspace_error
from driftlab.physics.thermal import ALPHA_C
from driftlab.vocabulary import AXES, term_unit
from driftlab.vocabulary import ROTATIONS as ANGLES

if TYPE_CHECKING:
    from driftlab.models.findings import Extra, FindingOutcomeRecord, Findings, FindingsPlan
    from driftlab.models.lines import LineRecord
    from driftlab.models.neural import NeuralComparisonRecord
    from driftlab.models.physical_check import PhysicalCheck
    from driftlab.models.standard_model import BundleLike
    from driftlab.models.uncertainty import PinningRecord
    from driftlab.models.virtual_sensor import VirtualSensorRecord

log = logging.getLogger(__name__)

#: a plan's stage as any reader holds it (read by its ``heat_source`` and ``axis``), handed back as given
StageT = TypeVar("StageT")

ROTARY = ("A", "B")
#: the joint each axis drives
AXIS_JOINT: Mapping[str, str] = {"X": "phi_x", "Y": "phi_y", "Z": "phi_z", "A": "theta_x", "B": "theta_y"}
#: the axis of each joint
JOINT_OF: Mapping[str, str] = {j: a for a, j in AXIS_JOINT.items()}
#: the rotation about each axis (thesis notation: alpha about X, beta about Y, gamma about Z)
ROTATION_ABOUT: Mapping[str, str] = {"X": "alpha", "Y": "beta", "Z": "gamma", "A": "alpha", "B": "beta"}
#: pitch and yaw of a linear axis (Table 5.3: what the angular optics see; roll is the rotation about the axis)
PITCH_YAW: Mapping[str, tuple[str, str]] = {"X": ("beta", "gamma"), "Y": ("alpha", "gamma"), "Z": ("alpha", "beta")}
#: feature kinds that belong to a joint (position shape, reversal, ballscrew)
SEED_KINDS = frozenset({"position", "direction", "pos_dT"})
#: the element that carries terms of the room air alone: the frame (column on the base, eq. 3.3);
#: it has no test of its own, so its terms are re-estimated on every test
ROOM_ELEMENT = "T2"
#: the chain's fixed link lengths (a, b, c) per element (Table A.1, eq. 4.13; ``chain_dims``)
Dims = Mapping[str, tuple[float, float, float]]


@dataclass
class FitOptions:
    """Knobs of the pipeline (defaults follow the thesis' practice)."""

    holdout_fraction: float = 0.25
    #: which points are held out (``models.split``): "time", the last ``holdout_fraction`` of every measured
    #: line's rows (the diagnosis' split: the figures both state are the same), or "stage", the last part of
    #: every training stage
    split: str = STAGE_SPLIT
    lag_taus_s: tuple[float, ...] = (3600.0,)
    p_enter: float = 1e-4
    p_remove: float = 1e-3
    min_gain: float = 0.01
    max_terms: int = 16
    vif_max: float = 30.0
    network: bool = True
    network_hidden: tuple[int, ...] = (30, 15, 7)
    network_max_samples: int = 4000
    network_max_iter: int = 300
    #: the terms the neural comparison is run on, fixed before any result is seen ("all": every measured term)
    network_targets: tuple[str, ...] = ("Z/dz",)
    #: how its two extrapolation directions are formed: "auto" (by campaign when two or more have
    #: absolute readings, else by time), "time" or "campaign"
    network_split: str = "auto"
    joint_adjust: bool = True
    tiered: bool = False
    global_lengths: bool = True
    virtual_sensors: bool = True
    #: a correction per measured line over the standard terms, kept where validation in training shows it helps
    lines: bool = True
    seed: int = 0
    #: the recast terms of ch. 3.5 that the stated geometry says act (arm bending eqs. 3.4-3.5, link growth
    #: eqs. 3.1/3.3) enter the joint adjustment even where the staged selection chose a surrogate
    physical_terms: bool = True
    #: diagnosis findings to fold in (``driftlab.models.findings.Findings``); forced in, or candidates
    findings: Findings | None = None
    force_findings: bool = False

    def __post_init__(self) -> None:
        """Check the split's name (one line for a wrong one)."""
        if self.split not in SPLITS:
            raise ValidationError(f"split must be one of {', '.join(SPLITS)}, got {self.split!r}")


@dataclass
class Sample:
    """The error samples of the campaigns as poses: one row per (campaign, time, axis, position, direction)."""

    frame: pd.DataFrame  # campaign, time_s, axis, position, direction, stage, element, role + one column per term
    q: np.ndarray  # (N, 5) joint coordinates (mm, rad)
    inputs: Inputs  # dT and lags at each sample
    raw: pd.DataFrame | None = None  # the readings themselves (degC) at each sample

    def take(self, mask: np.ndarray) -> Sample:
        """Return the rows selected by a boolean mask."""
        raw = None if self.raw is None else self.raw[mask].reset_index(drop=True)
        return Sample(self.frame[mask].reset_index(drop=True), self.q[mask], self.inputs.take(mask), raw)


class FitTermRow(TypedDict):
    """One row of the fit report's ``terms``: a measured term's RMSE (tables 6.1/6.2) and the form that won."""

    axis: str
    term: str
    measurement: str
    link: str
    rmse_train: float | None
    rmse_holdout: float | None
    r2: float | None
    f: float | None
    form: str  # "link", "link+line" or "standard"
    form_why: str


class CampaignOffsetReport(TypedDict):
    """A later campaign's offset of one term in the fit report (the campaign by its name where known)."""

    campaign: str | int
    term: str
    offset: float
    std_error: float


class FitReport(TypedDict):
    """The JSON report of ``driftlab fit --json`` (and of a fit job, with the registered ``model_version``)."""

    model_version: int | None
    machine: str
    kept_channels: list[str]
    dropped_channels: dict[str, str]
    #: which points were held out and scored (``models.split``: "stage" or "time")
    split: str
    terms: list[FitTermRow]
    physical: list[dict[str, object]]  # table 6.3's rows (physical_check.COLUMNS)
    physical_check: Mapping[str, object]  # PhysicalCheckRecord; empty when there was no check
    timings_s: dict[str, float]
    pinning: NotRequired[list[PinningRecord]]  # only the poorly pinned
    serial_correlation_inflation: NotRequired[float]
    campaign_offsets: NotRequired[list[CampaignOffsetReport]]
    findings: NotRequired[list[FindingOutcomeRecord]]
    neural_comparison: NotRequired[list[NeuralComparisonRecord]]


@dataclass
class FitResult:
    """Everything a fit produced: the document plus the tables a metrologist reads."""

    document: ModelDocument
    screening: ScreeningResult
    models: dict[tuple[str, str], ElementModel]
    validation: pd.DataFrame  # tables 6.1/6.2 layout
    physical: pd.DataFrame  # table 6.3 layout
    neural: list[NeuralComparison]  # ch. 6.6: one per target fixed in advance, both directions each
    timings_s: dict[str, float] = field(default_factory=dict)
    physical_check: Mapping[str, object] = field(
        default_factory=dict
    )  # table 6.3 (PhysicalCheckRecord)'s status: compared / no geometry
    #: the joint adjustment's estimates and covariance (None without it): ``joint.cov_params()``, ``regressors``
    joint: JointFit | None = None
    #: per element model: VIF, condition number, the coefficients it trades off with
    pinning: list[Pinning] = field(default_factory=list)
    #: every reading with the document's prediction of it as the instrument reads it (``prediction_frame``)
    predictions: pd.DataFrame | None = None
    #: the pipeline's steps (what ``predict_without`` re-evaluates the model from)
    steps: FitSteps | None = field(default=None, repr=False, compare=False)
    #: which points were held out of the fit and scored (``models.split``)
    split: str = STAGE_SPLIT

    def report(self) -> FitReport:
        """Return the JSON report of ``driftlab fit --json``."""
        rows = []
        forms = {(ln["axis"], ln["term"]): ln for ln in self.document.lines}
        for r in self.validation.to_dict("records"):
            row = {k: r[k] for k in ("axis", "term", "measurement", "link", "rmse_train", "rmse_holdout", "r2", "f")}
            line = forms.get((r["axis"], r["term"]))
            # which form won on this line (link models alone, or plus its correction) and why
            row["form"] = line["form"] if line else "link"
            row["form_why"] = line["why"] if line else ""
            rows.append(row)
        out: dict[str, Any] = {
            "model_version": self.document.version,
            "machine": self.document.machine,
            "kept_channels": list(self.document.kept_channels),
            "dropped_channels": dict(self.screening.dropped),
            "split": self.split,
            "terms": rows,
            "physical": self.physical.to_dict("records"),
            "physical_check": self.physical_check,
            "timings_s": self.timings_s,
        }
        if self.pinning:
            # the parts of the model the campaign pinned poorly, per link or joint
            out["pinning"] = [p.to_dict() for p in self.pinning if p.poor]
        if self.joint is not None:
            out["serial_correlation_inflation"] = self.joint.inflation
        adj: dict[str, Any] = next(
            (a["joint_adjustment"] for a in self.document.allocation if "joint_adjustment" in a), {}
        )
        if adj.get("campaign_offsets"):
            # several campaigns: the offsets of each later campaign's absolute readings, kept apart
            names = list(self.document.source_campaigns)
            out["campaign_offsets"] = [
                {**o, "campaign": names[o["campaign"]] if o["campaign"] < len(names) else o["campaign"]}
                for o in adj["campaign_offsets"]
            ]
        if self.document.findings:
            out["findings"] = list(self.document.findings)
        if self.neural:
            out["neural_comparison"] = [c.to_dict() for c in self.neural]
        return strict_json(out)

    @classmethod
    def of(cls, steps: FitSteps, document: ModelDocument, timings_s: dict[str, float]) -> FitResult:
        """Return the result of a pipeline's steps and the document built from them."""
        check = steps.checked.check
        return cls(
            document,
            steps.screened.screening,
            steps.allocation.models,
            steps.checked.validation,
            check.table,
            steps.neural,
            timings_s,
            check.to_dict(),
            steps.joint.joint,
            list(steps.joint.pinning),
            prediction_frame(steps.samples.sample, steps.checked.W_hat),
            steps,
        )

    def to_document(self) -> ModelDocument:
        """Return the model document (validated; ``document_json`` gives it as strict JSON)."""
        return self.document

    def summary(self) -> str:
        """Return the fit as text: tables 6.1-6.3 with units (um, urad), the joint adjustment, the comparison."""
        rep = self.report()
        kept = rep["kept_channels"]
        out = [
            f"machine {rep['machine']}: model version {rep['model_version']}; "
            f"{len(kept)} thermocouples kept: {' '.join(kept)}",
            "Per-link models (tables 6.1-6.2): RMSE of the work-space error",
            f"{'axis':4} {'term':6} {'measurement':16} {'link':28} {'form':14} {'unit':4} "
            f"{'train':>9} {'held out':>9} {'R2':>7} {'F':>10}",
        ]
        for r in rep["terms"]:
            k, unit = display_unit(r["term"])
            out.append(
                f"{r['axis']:4} {r['term']:6} {r['measurement']:16} {r['link']:28} {r['form']:14} {unit:4} "
                f"{_num(r['rmse_train'], '9.2f', k)} {_num(r['rmse_holdout'], '9.2f', k)} "
                f"{_num(r['r2'], '7.3f')} {_num(r['f'], '10.4g')}"
            )
        check = rep["physical_check"] or {}
        if check.get("status") != "compared":
            out.append(f"Physical coefficients (table 6.3): {check.get('status')}: {check.get('note', '')}")
        else:
            out.append("Regression against physical coefficients (table 6.3)")
            for p in rep["physical"]:
                out.append(
                    f"  {p['term']}: regression {_num(p.get('regression'), '.4g')}, physical "
                    f"{_num(p.get('physical'), '.4g')}, ratio {_num(p.get('ratio'), '.2f')} {p.get('unit', '')}"
                )
        if "serial_correlation_inflation" in rep:
            out.append(f"Joint adjustment: serial correlation inflation {rep['serial_correlation_inflation']:.3g}")
        for pin in rep.get("pinning", []):
            weak = ", ".join(dict.fromkeys(pin["poorly_pinned"]))
            out.append(
                f"  poorly pinned: {pin['element']}.{pin['param']} {weak} (condition {pin['condition_number']:.3g})"
            )
        for c in rep.get("neural_comparison", []):
            for d in c.get("directions", []):
                k, unit = display_unit(str(c["target"]).partition("/")[2])
                out.append(
                    f"Neural comparison {c['target']} ({d['direction']}): regression test "
                    f"{_num(d['regression_test'], '.2f', k)} {unit}, "
                    f"network test {_num(d['network_test'], '.2f', k)} {unit}"
                )
            if c.get("status") != "compared":
                out.append(f"Neural comparison {c['target']}: {c.get('status')}: {c.get('note', '')}")
        return "\n".join(out)


def _num(v: Any, fmt: str, scale: float = 1.0) -> str:
    """Return a figure formatted (scaled to the display unit), or "-" where it is missing or not finite."""
    if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v):
        return format(v * scale, fmt)
    width = fmt.split(".")[0]
    return format("-", f">{width}") if width else "-"


# ----------------------------------------------------------------------------- stages -> elements


def stage_elements(stages: Sequence[StageT]) -> list[tuple[StageT, str | None, str]]:
    """Return (stage, element, role) in plan order: the element the stage's errors are allocated to (ch. 4.3).

    A single heat source names the element: the spindle its support structure (T1), an axis feed
    or motor hold that axis' joint. Cool-downs and power-off belong to the stage before them (a
    leading baseline to the first heat source); combined sources are kept for validation.
    """
    out: list[tuple[StageT, str | None, str]] = []
    last: tuple[str | None, str] | None = None
    for st in stages:
        hs = str(getattr(st, "heat_source", "")).lower()
        axis = getattr(st, "axis", None)
        if "+" in hs or hs == "combined":
            last = (None, "validation")
        elif hs == "spindle":
            last = ("T1", "train")
        elif hs in ("feed", "axis", "motor_hold") and axis is not None and axis in AXIS_JOINT:
            last = (AXIS_JOINT[axis], "train")
        elif last is None:
            out.append((st, None, "pending"))
            continue
        out.append((st, *last))
    first = next(((e, r) for _, e, r in out if r == "train"), (None, "skip"))
    return [(st, *first) if r == "pending" else (st, e, r) for st, e, r in out]


# ----------------------------------------------------------------------------- samples


def _points(errors: pd.DataFrame) -> pd.DataFrame:
    """Return one row per measured point with one column per term (NaN where not measured)."""
    if errors.empty:
        return pd.DataFrame(columns=["time_s", "axis", "position", "direction", *PARAMS])
    # bundle v2 states the full commanded pose of each reading: it is part of the point
    pose = [c for c in (*POSE, "setup") if c in errors.columns]
    wide = errors.pivot_table(
        index=["time_s", "axis", "position", "direction", *pose], columns="term", values="value", aggfunc="mean"
    ).reset_index()
    wide.columns.name = None
    for p in (*PARAMS, *HELD):
        if p not in wide.columns:
            wide[p] = np.nan
    return wide


#: the columns of a sample's frame holding the values the time split holds out (the fit never reads them)
HELD = tuple(f"held_{p}" for p in PARAMS)


def _mark_held(errors: pd.DataFrame, holdout_fraction: float) -> pd.DataFrame:
    """Return the errors frame with the time split's held-out rows renamed to their ``held_`` term."""
    held = held_out_rows(errors, holdout_fraction)
    if not held.any():
        return errors
    out = errors.copy()
    out.loc[held, "term"] = "held_" + out.loc[held, "term"].astype(str)
    return out


POSE = ("x", "y", "z", "a", "b")


def _pose_q(pts: pd.DataFrame) -> np.ndarray:
    """Return (N, 5) joint coordinates of the points: the bundle v2 pose where stated, else the moved axis only."""
    q = _q(pts["axis"].to_numpy(str), pts["position"].to_numpy(float))
    if all(c in pts.columns for c in POSE):
        pose = pts[list(POSE)].to_numpy(float)
        pose[:, 3:] = np.deg2rad(pose[:, 3:])
        q = np.where(np.isfinite(pose), pose, q)
    return q


def _q(axis: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Return (N, 5) joint coordinates: the moved axis at its position (deg -> rad for A/B), others home."""
    q = np.zeros((axis.size, 5))
    for k, ax in enumerate(AXES):
        m = axis == ax
        q[m, k] = np.deg2rad(position[m]) if ax in ROTARY else position[m]
    return q


def _sessions(pts: pd.DataFrame, setups: Mapping[str, Any] | None, campaign: int) -> np.ndarray:
    """Return each point's instrument session label ('' for readings against a stable artefact).

    A laser is zeroed when it is set up (bundle v2 ``datum: session``): its readings are the error
    less the error at that moment, an unknown constant per mounting (ch. 5.5). A session is a
    maximal run, in time order, of readings of one such setup.
    """
    out = np.full(len(pts), "", dtype=object)
    if not setups or "setup" not in pts.columns:
        return out
    order = np.argsort(pts["time_s"].to_numpy(float), kind="stable")
    sid = pts["setup"].to_numpy(object)[order]
    run = np.concatenate([[0], np.cumsum(sid[1:] != sid[:-1])]) if sid.size else sid
    for i, s, r in zip(order, sid, run):
        entry = setups.get(s)
        if entry is not None and getattr(entry, "datum", "absolute") == "session":
            out[i] = f"{campaign}.{s}.{r}"
    return out


def _assign_roles(pts: pd.DataFrame, stages: Sequence[Any], holdout_fraction: float) -> None:
    """Set each point's stage, element and role (train, holdout, skip) in place (ch. 4.3).

    The last ``holdout_fraction`` of each training stage's points (of the whole record when there
    is no plan) is held out.
    """
    t = pts["time_s"].to_numpy(float)
    pts["stage"] = -1
    pts["element"] = None
    pts["role"] = "skip"
    for si, (st, element, role) in enumerate(stage_elements(stages)):
        m = (t >= st.start_s) & (t <= st.end_s) & (pts["stage"].to_numpy() < 0)
        pts.loc[m, "stage"] = si
        pts.loc[m, "element"] = element
        pts.loc[m, "role"] = role
        if role == "train" and m.any():
            ts = np.sort(t[m])
            cut = (
                ts[min(int(np.floor((1 - holdout_fraction) * ts.size)), ts.size - 1)]
                if ts.size >= 8 and holdout_fraction > 0
                else np.inf
            )
            pts.loc[m & (t >= cut), "role"] = "holdout"
    if not stages:
        # no plan: everything is one stage allocated to the measured axis' joint
        pts["element"] = pts["axis"].map(AXIS_JOINT)
        ts = np.sort(t)
        cut = ts[min(int(np.floor((1 - holdout_fraction) * ts.size)), ts.size - 1)] if holdout_fraction > 0 else np.inf
        pts["role"] = np.where(t >= cut, "holdout", "train")


def _training_errors(
    errors: pd.DataFrame, stages: Sequence[Any], holdout_fraction: float, split: str = STAGE_SPLIT
) -> pd.DataFrame:
    """Return the rows of a campaign's errors frame that the fit trains on (held-out points never steer it)."""
    if errors.empty:
        return errors
    if split == TIME_SPLIT:
        errors = errors[~held_out_rows(errors, holdout_fraction)]
        holdout_fraction = 0.0
    pts = pd.DataFrame({"time_s": np.unique(errors["time_s"].to_numpy(float))})
    pts["axis"] = ""
    _assign_roles(pts, stages, holdout_fraction)
    train = pts.loc[pts["role"] == "train", "time_s"].to_numpy(float)
    return errors[np.isin(errors["time_s"].to_numpy(float), train)]


def _keep_gradient_corners(
    screening: ScreeningResult, plain: ScreeningResult, chan_meta: Mapping[str, Mapping[str, str]]
) -> None:
    """Keep, in ``screening``, the corners spanning a structure's gradient that ``plain`` keeps (eqs. 3.4-3.5).

    The errors pick one stand-in per group of near-duplicate sites; a structure whose corners
    differ (``plain``, the temperature screening, keeps both) still needs both for its gradient
    terms, whose coefficients are the physically recast ones (ch. 6.4.2).
    """
    structure = {c: m.get("structure", "") for c, m in chan_meta.items()}
    have = {structure.get(c, "") for c in screening.kept}
    for c in plain.kept:
        why = plain.kept_reason.get(c, "")
        if c not in screening.kept_reason and why.startswith("corner of") and structure.get(c, "") in have:
            screening.kept_reason[c] = why
            screening.dropped.pop(c, None)
    order = list(screening.matrix.columns)
    screening.kept = [c for c in order if c in screening.kept_reason]


def build_samples(
    bundles: Sequence[BundleLike],
    channels: Sequence[str],
    reference: Mapping[str, float] | None,
    lags: Sequence[tuple[str, float]],
    holdout_fraction: float,
    origin: datetime | None = None,
    split: str = STAGE_SPLIT,
) -> Sample:
    """Return the error points of all campaigns with their stage, element, role and inputs.

    dT is taken from ``reference`` when given, else from each campaign's own first readings (the
    laser is zeroed at the start of each campaign: spec section 2, eq. 3.1). ``inputs.days`` is the
    time since ``origin`` (default: the earliest campaign start) in days, for drift terms. With the
    time split (``models.split``) the held-out values sit in the ``held_`` columns, never in the terms'.
    """
    frames, qs, dts, lagged, raws, days, sessions = [], [], [], [], [], [], []
    origin = origin or min(b.meta.started_at for b in bundles)
    by_time = split == TIME_SPLIT
    for ci, b in enumerate(bundles):
        pts = _points(_mark_held(b.errors, holdout_fraction) if by_time else b.errors)
        if pts.empty:
            continue
        pts.insert(0, "campaign", ci)
        t = pts["time_s"].to_numpy(float)
        _assign_roles(pts, b.meta.stages, 0.0 if by_time else holdout_fraction)
        if by_time:  # the time split trains on every reading before it, the combined stages' too
            pts.loc[pts["role"] == "validation", "role"] = "train"
        ref = dict(reference) if reference is not None else _reference([b], channels)
        inp = build_inputs(b.temperatures, t, ref, channels, lags)
        days.append(((b.meta.started_at - origin).total_seconds() + t) / 86400.0)
        sessions.append(_sessions(pts, getattr(b.meta, "setups", None), ci))
        raws.append(inp.dT + pd.Series({c: ref[c] for c in channels}))
        frames.append(pts)
        qs.append(_pose_q(pts))
        dts.append(inp.dT)
        lagged.append(inp.lagged)
    if not frames:
        raise ValidationError("the campaigns hold no error measurements")
    frame = pd.concat(frames, ignore_index=True)
    lag_all = {k: np.concatenate([lg[k] for lg in lagged]) for k in lagged[0]}
    sess = np.concatenate(sessions)
    inputs = Inputs(pd.concat(dts, ignore_index=True), lag_all, np.concatenate(days), sess if any(sess) else None)
    return Sample(frame, np.vstack(qs), inputs, pd.concat(raws, ignore_index=True))


# ----------------------------------------------------------------------------- per-element fits


@dataclass
class ElementModel:
    """The model of one parameter of one link or joint, built up stage by stage (ch. 4.3)."""

    element: str
    param: str
    features: list[Feature] = field(default_factory=list)
    coef: list[float] = field(default_factory=list)
    std_errors: list[float] = field(default_factory=list)
    p_values: list[float] = field(default_factory=list)
    fits: list[TermFit] = field(default_factory=list)
    #: the coefficients' covariance of the joint adjustment, and the residual variance of its parameter
    cov: np.ndarray | None = None
    residual_variance: float | None = None

    def add(self, fit: TermFit, features: Sequence[Feature]) -> None:
        """Add the chosen ``features`` of a stage fit (coefficients of a repeated term are summed)."""
        res = fit.result
        for f in features:
            c, se, pv = float(res.params[f.name]), float(res.bse[f.name]), float(res.pvalues[f.name])
            if f in self.features:
                i = self.features.index(f)
                self.coef[i] += c
                self.std_errors[i] = float(np.hypot(self.std_errors[i], se))
                self.p_values[i] = min(self.p_values[i], pv)
            else:
                self.features.append(f)
                self.coef.append(c)
                self.std_errors.append(se)
                self.p_values.append(pv)
        if fit not in self.fits:
            self.fits.append(fit)

    def coefficient(self, name: str) -> float:
        """Return the coefficient of the term called ``name`` (KeyError when absent)."""
        return float(dict(zip([f.name for f in self.features], self.coef))[name])

    def predict(self, inputs: Inputs, q: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return this parameter's error for every sample ((N, 5) coordinates and directions)."""
        if not self.features:
            return np.zeros(q.shape[0])
        return design_matrix(self.features, inputs, q, direction).to_numpy(float) @ np.asarray(self.coef)

    @property
    def primary(self) -> TermFit:
        """Return the stage fit of this element's own heat source (else the first contributing one)."""
        own = [f for f in self.fits if f.element == self.element]
        return own[0] if own else self.fits[0]


def _directions(sample: Sample) -> np.ndarray:
    """Return (N, 5) approach directions: each point's direction in the column of its moved axis."""
    d = np.zeros_like(sample.q)
    ax = sample.frame["axis"].to_numpy(str)
    dr = sample.frame["direction"].to_numpy(float)
    for k, a in enumerate(AXES):
        m = ax == a
        d[m, k] = dr[m]
    return d


def feature_element(f: Feature, structures: Mapping[str, str], default: str) -> str:
    """Return the element a chosen term belongs to: a joint for its axis' shape, else where its thermocouples sit."""
    if (f.kind in SEED_KINDS or f.kind == "time") and f.label in AXIS_JOINT:
        return AXIS_JOINT[f.label]
    if f.channels and all(structures.get(c, "") == "room" for c in f.channels):
        return ROOM_ELEMENT
    owners = {STRUCTURE_ELEMENT.get(structures.get(c, ""), default) for c in f.channels}
    return owners.pop() if len(owners) == 1 else default


def predict_models(models: Mapping[tuple[str, str], ElementModel], sample: Sample) -> dict[str, np.ndarray]:
    """Return element errors (N, 6) predicted by the models at the sample poses."""
    n = sample.q.shape[0]
    d = _directions(sample)
    out: dict[str, np.ndarray] = {}
    for (element, param), m in models.items():
        arr = out.setdefault(element, np.zeros((n, 6)))
        arr[:, PARAMS.index(param)] += m.predict(sample.inputs, sample.q, d)
    return out


def _measured_w(sample: Sample, known: Mapping[str, np.ndarray], dims: Dims) -> tuple[np.ndarray, np.ndarray]:
    """Return W (N, 6) with unmeasured terms filled by the known model, and the measured mask."""
    W = sample.frame[list(PARAMS)].to_numpy(float)
    mask = np.isfinite(W)
    if not mask.all():
        W_known = workspace_error(sample.q, known, dims) if known else np.zeros_like(W)
        W = np.where(mask, W, W_known)
    return W, mask


@dataclass
class Candidates:
    """What a stage fit may choose from: channels, structure members, screws per axis, lags."""

    channels: list[str]
    structures: dict[str, str]
    locations: dict[str, str]
    members: dict[str, list[str]]
    screws: dict[str, list[str]]
    room: list[str]
    lag_taus_s: tuple[float, ...]
    #: terms from diagnosis findings (``findings.Extra``): per (axis, term), forced or candidates
    extras: list[Extra] = field(default_factory=list)

    def extra_features(self, axes: Sequence[str], have: Sequence[Feature] = ()) -> list[Feature]:
        """Return the findings' terms for rows moving ``axes`` that ``have`` does not hold (by name)."""
        names = {f.name for f in have}
        out = []
        for e in self.extras:
            if e.axis in axes and e.feature.name not in names:
                names.add(e.feature.name)
                out.append(e.feature)
        return out

    def split_pool(
        self, pool: Sequence[Feature], axes: Sequence[str], param: str, keep: Callable[[Feature], bool]
    ) -> tuple[list[Feature], list[Feature]]:
        """Return (forced terms, candidates): ``pool`` plus the findings' terms of (axes, param) that ``keep``
        admits."""
        forced: list[Feature] = []
        # a finding's lag at its measured tau replaces the pool's default-tau lags of that channel
        # (near-identical columns: the cruder one would mask the finding through the VIF rule)
        lagged = {
            e.feature.channels[0]
            for e in self.extras
            if e.axis in axes and e.term == param and e.feature.kind == "lag" and keep(e.feature)
        }
        cands = [f for f in pool if not (f.kind == "lag" and f.channels[0] in lagged)]
        names = {f.name for f in cands}
        for e in self.extras:
            if e.axis not in axes or e.term != param or not keep(e.feature):
                continue
            if e.forced:
                if e.feature.name not in {f.name for f in forced}:
                    forced.append(e.feature)
            elif e.feature.name not in names:
                cands.append(e.feature)
                names.add(e.feature.name)
        fnames = {f.name for f in forced}
        return forced, [f for f in cands if f.name not in fnames]

    def for_axes(self, axes: Sequence[str], allowed: Sequence[str] | None) -> list[Feature]:
        """Return the candidate terms for rows moving ``axes``, limited to ``allowed`` channels."""
        # the user's selection (bundle model_channels) is used as given; else the screened channels
        chans = (
            list(self.channels) if allowed is None else [c for c in allowed if c in self.structures or c in self.room]
        )
        members = {s: [c for c in cs if allowed is None or c in allowed] for s, cs in self.members.items()}
        return candidate_features(
            chans,
            self.structures,
            axes=axes,
            screw_channels=self.screws,
            lag_taus_s=self.lag_taus_s,
            lag_channels=[c for c in chans if c not in self.room],
            room_channels=[c for c in self.room if c in chans],
            structure_members=members,
            locations=self.locations,
        )


@dataclass(frozen=True)
class StageData:
    """The rows one stage of the staged allocation fits on, and their design (ch. 4.3)."""

    #: the rows of the element's tests and of every test before it in chain order
    sub: Sample
    train: np.ndarray
    hold: np.ndarray
    #: the axes those rows move; the channels the user allowed (None: the screened ones)
    axes: list[str]
    allowed: list[str] | None
    #: the candidate terms and the design matrix (intercept, session offsets, candidates, findings' terms)
    feats: list[Feature]
    X: pd.DataFrame


def _design(sample: Sample, cands: Candidates, axes: Sequence[str], feats: Sequence[Feature]) -> pd.DataFrame:
    """Return the design of a stage: intercept, the sessions' offsets, ``feats`` and the findings' terms."""
    offsets = session_terms(sample.inputs.session, np.ones(len(sample.frame), bool))
    return design_matrix(
        [INTERCEPT, *offsets, *feats, *cands.extra_features(axes, feats)], sample.inputs, sample.q, _directions(sample)
    )


def _stage_data(sub: Sample, element: str, cands: Candidates, model_channels: Mapping[str, Sequence[str]]) -> StageData:
    """Return the stage of ``element``: its rows' roles, axes, allowed channels, candidates and design."""
    train = (sub.frame["role"] == "train").to_numpy()
    hold = (sub.frame["role"] == "holdout").to_numpy()
    axes = [a for a in AXES if (sub.frame["axis"] == a).any()]
    allowed = None
    own_axis = JOINT_OF.get(element)
    if own_axis is not None and own_axis in model_channels:
        allowed = list(model_channels[own_axis])
    elif model_channels and all(a in model_channels for a in axes):
        allowed = sorted({c for a in axes for c in model_channels[a]})
    feats = cands.for_axes(axes, allowed)
    return StageData(sub, train, hold, axes, allowed, feats, _design(sub, cands, axes, feats))


@dataclass(frozen=True)
class _Admission:
    """Whether a stage fit may choose a term: not one the models already hold for the parameter, nor one
    belonging to an element already solved (a known relationship is not learnt again: refitting it on the
    residual would only fit the sensor noise it was evaluated with, errors in variables)."""

    used: frozenset[Feature]
    structures: Mapping[str, str]
    element: str
    solved: tuple[str, ...]

    def __call__(self, f: Feature) -> bool:
        return f not in self.used and feature_element(f, self.structures, self.element) not in self.solved


def _allocated(
    sub: Sample, models: Mapping[tuple[str, str], ElementModel], element: str, dims: Dims
) -> tuple[np.ndarray, np.ndarray]:
    """Return the errors allocated to ``element`` less its own model so far (eq. 4.20), and the measured mask."""
    known = predict_models(models, sub)
    own = known.pop(element, None)
    W, mask = _measured_w(sub, {**known, **({element: own} if own is not None else {})}, dims)
    E = allocate(W, sub.q, known, element, dims)  # eq. 4.20
    if own is not None:
        E = E - own
    return E, mask


def _give_to_owners(
    models: dict[tuple[str, str], ElementModel], fit: TermFit, structures: Mapping[str, str], default: str
) -> None:
    """Add each chosen term of ``fit`` to the element where it physically arises (``feature_element``)."""
    owners: dict[str, list[Feature]] = {}
    for f in fit.result.features:
        owners.setdefault(feature_element(f, structures, default), []).append(f)
    for owner, fs in owners.items():
        models.setdefault((owner, fit.param), ElementModel(owner, fit.param)).add(fit, fs)


def _fit_stage(
    stage: StageData,
    element: str,
    models: dict[tuple[str, str], ElementModel],
    cands: Candidates,
    solved: Sequence[str],
    options: FitOptions,
    dims: Dims,
) -> None:
    """Fit every parameter of ``element`` on its stage by stepwise regression; add the terms to ``models``."""
    sub = stage.sub
    E = mask = None
    for k, param in enumerate(PARAMS):
        if k in (0, 3):
            # angles first, then lengths re-allocated once the angles sit in their elements:
            # an angle acts through a different lever from each element (eq. 4.20)
            E, mask = _allocated(sub, models, element, dims)
        assert E is not None and mask is not None
        m_train = stage.train & mask[:, k]
        if m_train.sum() < 12:
            continue
        y = E[:, k]
        used = frozenset(f for (e, pp), m in models.items() if pp == param for f in m.features)
        admit = _Admission(used, cands.structures, element, tuple(solved))
        forced, pool = cands.split_pool([f for f in stage.feats if admit(f)], stage.axes, param, admit)
        res = stepwise(
            stage.X[m_train].reset_index(drop=True),
            y[m_train],
            pool,
            forced=[INTERCEPT, *session_terms(sub.inputs.session, m_train), *forced],
            options=StepwiseOptions.of(options),
        )
        fit = TermFit(element, param, res)
        m_hold = stage.hold & mask[:, k]
        if m_hold.any():
            fit.rmse_holdout = rmse(y[m_hold] - res.predict(stage.X[m_hold]))
            fit.n_holdout = int(m_hold.sum())
        _give_to_owners(models, fit, cands.structures, element)


def fit_elements(
    sample: Sample,
    cands: Candidates,
    model_channels: Mapping[str, Sequence[str]],
    options: FitOptions,
    dims: Dims = TABLE_A1,
    on_element: Callable[[str], None] | None = None,
) -> tuple[dict[tuple[str, str], ElementModel], list[AllocationRecord]]:
    """Return the model of every link and joint parameter, allocating stage by stage in chain order (eq. 4.20).

    For each heat source in turn (spindle structure first, then Z, Y, X, A, B), the errors of its
    stages less what the elements modelled so far predict are allocated to its element through
    the HTM chain; a stepwise regression explains them, and each chosen term goes to the element
    where it physically arises (a joint for its axis' shape, else where its thermocouples sit).
    """
    models: dict[tuple[str, str], ElementModel] = {}
    log_rows: list[AllocationRecord] = []
    elements = [e for e in ELEMENTS if (sample.frame["element"] == e).any()]
    solved: list[str] = []
    for gi, element in enumerate(elements):
        # what the solved elements do is known and stays; every other term (elements without a
        # test of their own, joint shapes seen through other tests) is estimated again on all the
        # tests so far, so the last estimate has seen every heat source
        for key in [k for k in models if k[0] not in solved]:
            del models[key]
        rows = sample.frame["element"].isin(elements[: gi + 1]).to_numpy()
        stage = _stage_data(sample.take(rows), element, cands, model_channels)
        _fit_stage(stage, element, models, cands, solved, options, dims)
        solved.append(element)
        log_rows.append(
            {
                "element": element,
                "axes": stage.axes,
                "n": int((sample.frame["element"] == element).sum()),
                "n_cumulative": int(rows.sum()),
                "n_train": int(stage.train.sum()),
                "stages": sorted({int(s) for s in stage.sub.frame["stage"]}),
                "channels": "model_channels" if stage.allowed is not None else "screened",
            }
        )
        if on_element is not None:
            on_element(element)
    if options.global_lengths:
        log_rows.append(_global_lengths(sample, models, cands, model_channels, options, dims))
    return models, log_rows


def _global_lengths(
    sample: Sample,
    models: dict[tuple[str, str], ElementModel],
    cands: Candidates,
    model_channels: Mapping[str, Sequence[str]],
    options: FitOptions,
    dims: Dims,
) -> AllocationRecord:
    """Re-select the length terms on all tests together, once the angles are allocated (returns a log row).

    A length error does not depend on where along the chain it arises (no lever), so after the
    staged allocation has placed every angle, the translations left in the work space are explained
    on every test at once: a term that only one test cannot tell from another (the column and the
    spindle warm together in the spindle test) is told apart by the others. Each chosen term still
    goes to the element where its thermocouples sit.
    """
    for key in [k for k in models if k[1] in ("dx", "dy", "dz")]:
        del models[key]
    train = (sample.frame["role"] == "train").to_numpy()
    known = predict_models(models, sample)
    W, mask = _measured_w(sample, known, dims)
    E = allocate(W, sample.q, known, "T1", dims)  # every length error seen at the spindle
    axes = [a for a in AXES if (sample.frame["axis"] == a).any()]
    allowed = (
        sorted({c for a in axes for c in model_channels[a]})
        if model_channels and all(a in model_channels for a in axes)
        else None
    )
    feats = cands.for_axes(axes, allowed)
    if model_channels:
        # a joint whose axis has the user's selection reads only those channels
        def honoured(f: Feature) -> bool:
            axis = JOINT_OF.get(feature_element(f, cands.structures, "T1"))
            return axis is None or axis not in model_channels or all(c in model_channels[axis] for c in f.channels)

        feats = [f for f in feats if honoured(f)]
    X = _design(sample, cands, axes, feats)
    rules = StepwiseOptions.of(options, min_gain=options.min_gain / 4, max_terms=2 * options.max_terms)
    chosen = 0
    for k, param in ((3, "dx"), (4, "dy"), (5, "dz")):
        m = train & mask[:, k]
        if m.sum() < 12:
            continue
        forced, pool = cands.split_pool(feats, axes, param, lambda f: True)
        res = stepwise(
            X[m].reset_index(drop=True),
            E[m, k],
            pool,
            forced=[INTERCEPT, *session_terms(sample.inputs.session, m), *forced],
            options=rules,
        )
        _give_to_owners(models, TermFit("T1", param, res), cands.structures, "T1")
        chosen += len(res.features)
    return {"element": "lengths, all tests", "terms": chosen, "n_train": int(train.sum())}


#: prior spread of a link's constant error (angle rad, length mm), an order above Tables A.3/A.4's
#: geometric errors: it decides only constants the measurements leave free (zeroed sessions)
CONSTANT_PRIOR = (1e-5, 0.01)
#: the prior's spread, as a fraction of CONSTANT_PRIOR, of a constant no cold absolute reading pins (1e-4:
#: 1 nrad, 1 nm - held at zero)
COLD_PRIOR = 1e-4
#: a reading is "cold" when no kept channel has risen by more than this from the reference (degC)
COLD_DT_DEGC = 1.0


def _cold_absolute(sample: Sample, D: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Return (6,) bool: whether some absolute training reading of each term was taken cold (max |dT| < 1 degC)."""
    dT = sample.inputs.dT.to_numpy(float)
    cold_row = np.nanmax(np.abs(dT), axis=1) < COLD_DT_DEGC if dT.shape[1] else np.ones(len(sample.frame), bool)
    W = sample.frame[list(PARAMS)].to_numpy(float)
    return np.array([bool((train & cold_row & (D[:, k] < 0) & np.isfinite(W[:, k])).any()) for k in range(len(PARAMS))])


def datum_rows(sample: Sample) -> np.ndarray:
    """Return (N, 6): for each reading of a zeroed session, the row of its datum (-1 for absolute readings).

    A laser zeroed when it is mounted reads the error less the error at that moment (ch. 5.5); the
    moment is the session's first reading of the term (which reads 0). So a zeroed reading is the
    model at its pose and time less the model at the datum's (eq. 4.12 at both): its offset is not a
    free constant but what the model predicts at the datum, which pins the slow structures the free
    offsets left to trade off (issue 21.2).
    """
    n = len(sample.frame)
    D = np.full((n, len(PARAMS)), -1, dtype=int)
    sess = sample.inputs.session
    if sess is None:
        return D
    s = np.asarray(sess, dtype=object)
    W = measured_values(sample.frame)
    t = sample.frame["time_s"].to_numpy(float)
    for label in dict.fromkeys(s.tolist()):
        if not label:
            continue
        rows = np.flatnonzero(s == label)
        for k in range(len(PARAMS)):
            r = rows[np.isfinite(W[rows, k])]
            if r.size:
                D[r, k] = r[np.argmin(t[r])]
    return D


def measured_values(frame: pd.DataFrame) -> np.ndarray:
    """Return (N, 6) every reading of the frame, the held-out ones included (the datum is a session's first)."""
    W = frame[list(PARAMS)].to_numpy(float)
    if all(h in frame.columns for h in HELD):
        H = frame[list(HELD)].to_numpy(float)
        W = np.where(np.isfinite(W), W, H)
    return W


def at_datum(W_hat: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Return ``W_hat`` as the zeroed instruments read it: less its value at each reading's datum row."""
    out = W_hat.copy()
    i, k = np.nonzero(D >= 0)
    out[i, k] -= W_hat[D[i, k], k]
    return out


#: the spread of a physical term's prior, as a fraction of its physical value (ch. 3.5's relationships hold
#: to the precision of the stated lengths and alpha_c: table 6.3 finds fitted/physical within 0.7-1.3)
PHYSICAL_PRIOR = 0.3


@dataclass(frozen=True)
class PhysicalPrior:
    """A physical relationship's prior on a term: value ~ N(value, spread^2) (``_physical_terms``).

    For a structure's mean (eqs. 3.1, 3.3) the prior is on the element's steady response to the
    structure warming evenly by 1 degC: the mean's coefficient plus those of the single sites of the
    structure (``sites``: dT or lag of one of them), which the staged selection may have chosen beside
    it and which would otherwise take back what the prior pins.
    """

    value: float
    spread: float
    sites: tuple[str, ...] = ()


def _physical_terms(
    models: dict[tuple[str, str], ElementModel],
    cands: Candidates,
    bundles: Sequence[BundleLike],
    priors: dict[tuple[str, str, Feature], PhysicalPrior] | None = None,
) -> list[str]:
    """Add the recast terms the machine's stated geometry says act; return their names (in place).

    The slow structures move together through a campaign (the arm warms with the spindle, the column
    with the room), so the staged stepwise selection may explain the spindle link's deflection by a
    lag of one site or the column's growth by a gradient: surrogates that hold during the campaign
    and not during a cut. Where ``machine.geometry`` states them, the physical terms are added:
    the bending gradient of a structure on its angle and its tip deflection (eqs. 3.4, 3.5), and the
    mean of a link's structure on each translation the link extends along (eqs. 3.1, 3.3).
    Each gets a prior (``priors``: mean, spread) at its physical value with spread ``PHYSICAL_PRIOR``:
    alpha_c L / H on the angle, alpha_c L^2 / 2H on the deflection, alpha_c L (signed as the link's
    extent) on the growth.
    """
    status, g, _ = machine_geometry(bundles)
    if g is None:
        return []
    pool = {f.name: f for f in cands.for_axes(list(AXES), None)}
    added: list[str] = []

    alpha_c = float(g.get("alpha_c_per_degC", ALPHA_C))

    def add(element: str, param: str, f: Feature, value: float) -> None:
        m = models.setdefault((element, param), ElementModel(element, param))
        # the same structure's term already chosen from the screened channels (a mean or gradient of
        # fewer of its sensors) is the same physical quantity: the prior goes on it, not on a second,
        # nearly collinear copy whose free coefficient would undo the prior
        f = next((h for h in m.features if h.kind == f.kind and h.label == f.label and h.power == f.power), f)
        if priors is not None and value != 0.0:
            sites = cands.members.get(f.label, list(f.channels)) if f.kind == "mean" else []
            priors[(element, param, f)] = PhysicalPrior(value, PHYSICAL_PRIOR * abs(value), tuple(sites))
        if f in m.features:
            return
        m.features.append(f)
        m.coef.append(0.0)
        m.std_errors.append(0.0)
        m.p_values.append(1.0)
        added.append(f"{element}.{param} {f.name}")

    for structure, bent in dict(g.get("bending") or {}).items():
        across = str(bent.get("across", "upper-lower"))
        f = pool.get(f"grad[{structure} {across}]")
        element = STRUCTURE_ELEMENT.get(structure)
        if f is None or element is None:
            continue
        L, H = float(bent["length_mm"]), float(bent["height_mm"])
        if bent.get("angle") in PARAMS:
            add(element, str(bent["angle"]), f, alpha_c * L / H)  # eq. 3.4
        if bent.get("deflection") in PARAMS:
            add(element, str(bent["deflection"]), f, alpha_c * L**2 / (2 * H))  # eq. 3.5
    for name, extent in dict(g.get("links_mm") or {}).items():
        element = GEOMETRY_LINKS.get(name)
        for structure, owner in STRUCTURE_ELEMENT.items():
            f = pool.get(f"mean[{structure}]")
            if owner != element or f is None:
                continue
            for k, param in enumerate(("dx", "dy", "dz")):
                length = float(list(extent)[k])
                if abs(length) > 0 and param in STRUCTURE_SPANS.get(structure, (param,)):
                    add(str(element), param, f, alpha_c * length)  # eqs. 3.1, 3.3
    return added


def _strip_sessions(models: Mapping[tuple[str, str], ElementModel]) -> int:
    """Remove the zeroed sessions' free offsets from the models (in place); return how many."""
    removed = 0
    for m in models.values():
        keep = [i for i, f in enumerate(m.features) if f.kind != "session"]
        removed += len(m.features) - len(keep)
        if len(keep) < len(m.features):
            m.features = [m.features[i] for i in keep]
            m.coef = [m.coef[i] for i in keep]
            m.std_errors = [m.std_errors[i] for i in keep]
            m.p_values = [m.p_values[i] for i in keep]
    return removed


@dataclass(frozen=True)
class JointDesign:
    """The joint adjustment's linearised chain at every sample (eq. 4.12 to first order) and what it reads."""

    #: training rows, datum rows (``datum_rows``), the measured terms (N, 6) and which are measured
    train: np.ndarray
    D: np.ndarray
    W: np.ndarray
    mask: np.ndarray
    #: each work-space component's weight: 1 / its noise
    w: np.ndarray
    #: per element model its design matrix, in ``keys`` order; the solve's columns (model, feature index)
    blocks: list[tuple[tuple[str, str], np.ndarray]]
    cols: list[tuple[tuple[str, str], int]]
    #: d W / d p_(e,k) at every pose, per (element, parameter index)
    jac: dict[tuple[str, int], np.ndarray]
    #: each sample's campaign and the (campaign, term) offsets kept apart (a later campaign's absolute readings)
    camp: np.ndarray
    nuis: list[tuple[int, int]]

    @property
    def n_coefficients(self) -> int:
        """Return P, the number of model coefficients (the nuisances follow them)."""
        return len(self.cols)


def _noise_weights(noise: Mapping[str, float] | None) -> np.ndarray:
    """Return (6,) weights 1 / noise of the work-space components (angles, then lengths)."""
    sig = {"len": 0.0005, "ang": 5e-7, **(noise or {})}
    return np.array([1 / sig["ang"]] * 3 + [1 / sig["len"]] * 3)


def _chain_jacobians(sample: Sample, keys: Sequence[tuple[str, str]], dims: Dims) -> dict[tuple[str, int], np.ndarray]:
    """Return d W / d p_(e,k) at every pose (first order, around zero error), per modelled (element, param)."""
    return {
        (e, k): parameter_jacobian(sample.q, e, k, dims)
        for e in sorted({k[0] for k in keys})
        for k in sorted({PARAMS.index(kk[1]) for kk in keys if kk[0] == e})
    }


def _campaign_nuisances(camp: np.ndarray, train: np.ndarray, mask: np.ndarray, D: np.ndarray) -> list[tuple[int, int]]:
    """Return the (campaign, term) offsets of every campaign after the first with absolute training readings.

    Several campaigns of one machine (seasons apart): each campaign's absolute readings get an offset of
    their own per term (its artefact re-mounted, its own datum), a nuisance kept apart and reported.
    """
    nuis: list[tuple[int, int]] = []
    for t in range(6):
        absolute = train & mask[:, t] & (D[:, t] < 0)
        nuis += [(int(ci), t) for ci in sorted(set(camp[absolute].tolist()))[1:]]
    return nuis


def joint_design(
    sample: Sample,
    models: Mapping[tuple[str, str], ElementModel],
    keys: Sequence[tuple[str, str]],
    dims: Dims,
    noise: Mapping[str, float] | None,
    D: np.ndarray,
) -> JointDesign:
    """Return the linearised chain of the joint adjustment over every row (a datum may precede its training rows)."""
    train = (sample.frame["role"] == "train").to_numpy()
    W = sample.frame[list(PARAMS)].to_numpy(float)
    mask = np.isfinite(W)
    d = _directions(sample)
    jac = _chain_jacobians(sample, keys, dims)
    cols: list[tuple[tuple[str, str], int]] = []
    blocks = []
    for key in keys:
        F = design_matrix(models[key].features, sample.inputs, sample.q, d).to_numpy(float)
        blocks.append((key, F))
        cols += [(key, i) for i in range(F.shape[1])]
    camp = sample.frame["campaign"].to_numpy()
    nuis = _campaign_nuisances(camp, train, mask, D)
    return JointDesign(train, D, W, mask, _noise_weights(noise), blocks, cols, jac, camp, nuis)


@dataclass(frozen=True)
class NormalEquations:
    """The weighted normal equations of the joint adjustment and each work-space component's system."""

    AtA: np.ndarray
    Atb: np.ndarray
    #: (component, weighted design, weighted target), built once
    systems: list[tuple[int, np.ndarray, np.ndarray]]
    #: the weighted sum of squares at the staged coefficients
    before: float


def normal_equations(design: JointDesign, models: Mapping[tuple[str, str], ElementModel]) -> NormalEquations:
    """Return the normal equations: zeroed readings less the model at their datum, campaigns' offsets apart."""
    P, Q = design.n_coefficients, len(design.nuis)
    AtA = np.zeros((P + Q, P + Q))
    Atb = np.zeros(P + Q)
    c0 = np.concatenate([np.asarray(models[key].coef, float) for key, _ in design.blocks] + [np.zeros(Q)])
    before = 0.0
    systems = []
    D, w, camp = design.D, design.w, design.camp
    for t in range(6):
        ok = design.mask[:, t] & design.train
        if not ok.any():
            continue
        A_all = np.concatenate(
            [design.jac[(key[0], PARAMS.index(key[1]))][:, t][:, None] * F for key, F in design.blocks], axis=1
        )
        A = A_all[ok]
        dz = D[ok, t]
        A[dz >= 0] -= A_all[dz[dz >= 0]]
        N = np.zeros((A.shape[0], Q))
        for j, (ci, tt) in enumerate(design.nuis):
            if tt == t:
                N[:, j] = (camp[ok] == ci) & (dz < 0)
        A = np.concatenate([A, N], axis=1) * w[t]
        b = design.W[ok, t] * w[t]
        systems.append((t, A, b))
        AtA += A.T @ A
        Atb += A.T @ b
        before += float(np.sum((b - A @ c0) ** 2))
    return NormalEquations(AtA, Atb, systems, before)


def _constant_priors(
    sample: Sample, design: JointDesign, models: Mapping[tuple[str, str], ElementModel], AtA: np.ndarray
) -> list[str]:
    """Add the constants' priors to ``AtA`` (in place); return the constants held at zero.

    A machine constant that only zeroed sessions see is not identified: the sessions' offsets absorb
    any value of it. A weak prior (CONSTANT_PRIOR, far wider than any constant the data pin) sends
    such constants to zero instead of to an arbitrary split between elements that cancels at the
    measured poses and not at others.
    The thermal model is relative to the cold start (eq. 3.1: dT from the first readings): a constant
    is a geometric error, which only an absolute reading taken cold can tell from the slow structures
    (column growth, base lag, arm gradient are nearly constant through a warm stage). Where no such
    reading exists for a work-space component, its constants are held at zero (COLD_PRIOR) and the
    fit says so, rather than registering a constant that trades off with those structures.
    """
    cold = _cold_absolute(sample, design.D, design.train)
    held: list[str] = []
    for i, (key, j) in enumerate(design.cols):
        if models[key].features[j].kind == "intercept":  # the prior's row: coefficient / spread (noise units above)
            k = PARAMS.index(key[1])
            free = bool(cold[k]) or not design.mask[design.train, k].any()
            spread = CONSTANT_PRIOR[key[1].startswith("d")] * (1.0 if free else COLD_PRIOR)
            if not free:
                held.append(f"{key[0]}.{key[1]}")
            AtA[i, i] += spread**-2
    return held


def _physical_priors(
    design: JointDesign,
    models: Mapping[tuple[str, str], ElementModel],
    priors: Mapping[tuple[str, str, Feature], PhysicalPrior],
    normal: NormalEquations,
) -> None:
    """Add the physics-informed priors (``_physical_terms``) to the normal equations (in place).

    a' c ~ N(physical value, spread^2), in the noise-weighted units of the rows; a picks the term and
    the single sites of its structure (``PhysicalPrior``).
    """
    cols = design.cols
    for i, (key, j) in enumerate(cols):
        prior = priors.get((key[0], key[1], models[key].features[j]))
        if prior is None or prior.spread <= 0:
            continue
        a = np.zeros(normal.AtA.shape[0])
        for i2, (key2, j2) in enumerate(cols):
            g = models[key2].features[j2]
            if i2 == i or (key2 == key and g.kind in ("dT", "lag") and g.channels[0] in prior.sites):
                a[i2] = 1.0
        normal.AtA[...] += np.outer(a, a) / prior.spread**2
        normal.Atb[...] += a * prior.value / prior.spread**2


@dataclass(frozen=True)
class JointSolution:
    """The joint adjustment's estimates: coefficients (models, then nuisances), covariance and residuals."""

    c: np.ndarray
    cov: np.ndarray
    residual_variance: dict[str, float]
    rho: dict[str, float]
    inflation: float
    m_obs: int
    after: float


def _solve(normal: NormalEquations, w: np.ndarray, P: int, ridge: float) -> JointSolution:
    """Solve the scaled normal equations; a second pass gives the residuals and the covariance."""
    AtA, Atb = normal.AtA, normal.Atb
    scale = np.sqrt(np.maximum(np.diag(AtA), 1e-300))
    M = AtA / np.outer(scale, scale) + ridge * np.eye(AtA.shape[0])
    c = np.linalg.solve(M, Atb / scale) / scale
    sse, m_obs = 0.0, 0
    residual_variance: dict[str, float] = {}
    rho: dict[str, float] = {}
    inflation_sum = 0.0
    for t, A, b in normal.systems:
        r = b - A @ c
        sse += float(r @ r)
        m_obs += len(b)
        residual_variance[PARAMS[t]] = float(np.mean(r * r)) / w[t] ** 2
        rho[PARAMS[t]], infl = ar1_inflation(r)
        inflation_sum += infl * len(b)
    s2 = sse / max(m_obs - P, 1)
    # serial correlation of the laser residuals (AR(1): the HAC long-run variance, module uncertainty)
    inflation = inflation_sum / max(m_obs, 1)
    cov = np.linalg.inv(M) / np.outer(scale, scale) * s2 * inflation
    cov = 0.5 * (cov + cov.T)
    return JointSolution(c, cov, residual_variance, rho, inflation, m_obs, sse)


def _store_estimates(
    models: Mapping[tuple[str, str], ElementModel], design: JointDesign, sol: JointSolution
) -> list[tuple[str, str, Feature]]:
    """Write the joint estimates into the element models (in place); return the solve's columns."""
    cov_diag = np.diag(sol.cov)
    i = 0
    columns: list[tuple[str, str, Feature]] = []
    for key, F in design.blocks:
        k = F.shape[1]
        models[key].coef = [float(v) for v in sol.c[i : i + k]]
        models[key].std_errors = [float(np.sqrt(max(v, 0.0))) for v in cov_diag[i : i + k]]
        models[key].cov = sol.cov[i : i + k, i : i + k]
        models[key].residual_variance = sol.residual_variance.get(key[1])
        columns += [(key[0], key[1], f) for f in models[key].features]
        i += k
    columns += [("campaign", PARAMS[t], Feature("session", label=f"campaign {ci}")) for ci, t in design.nuis]
    return columns


def _campaign_offsets(design: JointDesign, sol: JointSolution) -> list[CampaignOffsetRecord]:
    """Return each later campaign's offset per term with its standard error."""
    P, cov_diag = design.n_coefficients, np.diag(sol.cov)
    return [
        {
            "campaign": ci,
            "term": PARAMS[t],
            "offset": float(sol.c[P + j]),
            "std_error": float(np.sqrt(max(cov_diag[P + j], 0))),
        }
        for j, (ci, t) in enumerate(design.nuis)
    ]


class CampaignOffsetRecord(TypedDict):
    """A later campaign's offset of one term, with its standard error (the campaign by its index)."""

    campaign: int
    term: str
    offset: float
    std_error: float


class JointSummary(TypedDict, total=False):
    """The joint adjustment's summary (the document's ``joint_adjustment``); empty when it did not run."""

    coefficients: int
    session_offsets_replaced_by_datums: int
    campaign_offsets: list[CampaignOffsetRecord]
    constants_held_at_zero: list[str]
    constants_held_why: str
    points: int
    weighted_rms_before: float
    weighted_rms_after: float


class JointResult(TypedDict, total=False):
    """What :func:`joint_adjust` puts in its ``result``: the offsets, the estimates, the pinning."""

    campaign_offsets: list[CampaignOffsetRecord]
    joint: JointFit
    pinning: list[Pinning]


class AllocationRecord(TypedDict, total=False):
    """One entry of the document's ``allocation`` log: a stage's element, the lengths' re-selection,
    the physical terms added, or the joint adjustment."""

    element: str
    axes: list[str]
    n: int
    n_cumulative: int
    n_train: int
    stages: list[int]
    channels: str  # "model_channels" or "screened"
    terms: int  # the lengths' re-selection: how many terms it chose
    physical_terms: list[str]
    joint_adjustment: JointSummary


@dataclass(frozen=True)
class JointOutcome:
    """What the joint adjustment produced: its summary (the document's ``joint_adjustment``) and estimates."""

    summary: JointSummary
    campaign_offsets: list[CampaignOffsetRecord] = field(default_factory=list)
    #: the estimates with their covariance (None when there was nothing to adjust)
    joint: JointFit | None = None
    #: how well each element model was pinned
    pinning: list[Pinning] = field(default_factory=list)


def adjust_jointly(
    sample: Sample,
    models: dict[tuple[str, str], ElementModel],
    dims: Dims = TABLE_A1,
    noise: Mapping[str, float] | None = None,
    ridge: float = 1e-9,
    priors: Mapping[tuple[str, str, Feature], PhysicalPrior] | None = None,
) -> JointOutcome:
    """Re-estimate every coefficient of the allocated models together, on all training points (in place).

    The terms and the elements they belong to stay as the staged allocation chose them; their
    coefficients are refined by one weighted least-squares solve through the linearised chain
    (W = sum_e Ad_e(q) p_e, eq. 4.12 to first order), each measured term weighted by its noise.
    """
    # a zeroed reading is the model less the model at its datum: no free offset per session
    D = datum_rows(sample)
    offsets = _strip_sessions(models)
    keys = [k for k, m in models.items() if m.features]
    if not keys:
        return JointOutcome({"coefficients": 0})
    design = joint_design(sample, models, keys, dims, noise, D)
    normal = normal_equations(design, models)
    held = _constant_priors(sample, design, models, normal.AtA)
    _physical_priors(design, models, priors or {}, normal)
    P = design.n_coefficients
    sol = _solve(normal, design.w, P, ridge)
    columns = _store_estimates(models, design, sol)
    campaign_offsets = _campaign_offsets(design, sol)
    systems = normal.systems
    joint = JointFit(
        columns,
        sol.c,
        sol.cov,
        sol.residual_variance,
        sol.rho,
        float(sol.inflation),
        sol.m_obs,
        design={PARAMS[t]: A for t, A, _ in systems},
        weights={PARAMS[t]: float(design.w[t]) for t, _, _ in systems},
    )
    pinning = joint.pinning({key: F[design.train] for key, F in design.blocks})
    m_obs = sol.m_obs
    summary: JointSummary = {
        "coefficients": P,
        "session_offsets_replaced_by_datums": offsets,
        "campaign_offsets": campaign_offsets,
        "constants_held_at_zero": held,
        "constants_held_why": (
            "no absolute reading of the term at the cold start: a constant there trades off with the slow structures"
            if held
            else ""
        ),
        "points": m_obs,
        "weighted_rms_before": float(np.sqrt(normal.before / max(m_obs, 1))),
        "weighted_rms_after": float(np.sqrt(sol.after / max(m_obs, 1))),
    }
    return JointOutcome(summary, campaign_offsets, joint, pinning)


def joint_adjust(
    sample: Sample,
    models: dict[tuple[str, str], ElementModel],
    dims: Dims = TABLE_A1,
    noise: Mapping[str, float] | None = None,
    ridge: float = 1e-9,
    result: JointResult | None = None,
    priors: Mapping[tuple[str, str, Feature], PhysicalPrior] | None = None,
) -> JointSummary:
    """Re-estimate every coefficient of the allocated models together (``adjust_jointly``); return its summary.

    With ``result`` (a dict), the estimates with their covariance (``uncertainty.JointFit``, key
    ``joint``), how well each element model was pinned (``pinning``) and the campaigns' offsets
    (``campaign_offsets``) are put there. Returns a summary (number of coefficients, weighted rms
    before and after).
    """
    out = adjust_jointly(sample, models, dims, noise, ridge, priors)
    if result is not None and out.joint is not None:
        result["campaign_offsets"] = out.campaign_offsets
        result["joint"] = out.joint
        result["pinning"] = out.pinning
    return out.summary


# ----------------------------------------------------------------------------- validation tables


def _measurement_name(axis: str, term: str) -> str:
    """Return the thesis' name of an error measurement (Position, X Straightness, Roll, ...)."""
    if term in ANGLES:
        if axis in ROTARY:  # a rotary axis' own rotation is its positioning; the other two tilt it (ISO 230-7)
            return "Positioning" if term == ROTATION_ABOUT[axis] else f"{term.capitalize()} Tilt"
        if term == ROTATION_ABOUT[axis]:
            return "Roll"
        return "Pitch" if term == PITCH_YAW[axis][0] else "Yaw"
    t_axis = term[1].upper()
    if axis in ROTARY:
        return f"{t_axis} Deflection"
    return "Position" if t_axis == axis else f"{t_axis} Straightness"


def composed_errors(composed: Composed, sample: Sample) -> np.ndarray:
    """Return the (N, 6) error of the lines' element (T1) that the composed line corrections add."""
    out = np.zeros((sample.q.shape[0], len(PARAMS)))
    d = _directions(sample)
    for param, rows in composed.terms.items():
        feats = [f for f, *_ in rows]
        out[:, PARAMS.index(param)] = design_matrix(feats, sample.inputs, sample.q, d).to_numpy(float) @ np.array(
            [c for _, c, *_ in rows]
        )
    return out


def validation_table(
    sample: Sample,
    models: Mapping[tuple[str, str], ElementModel],
    dims: Dims,
    composed: Composed | None = None,
    campaign_offsets: Sequence[Mapping[str, Any]] = (),
) -> tuple[pd.DataFrame, np.ndarray]:
    """Return tables 6.1/6.2: per (axis, term) the work-space RMSE on training and held-out data, R^2 and F.

    ``link`` names the elements whose models carry that term (largest contribution first); R^2 and
    F are those of the full chain's prediction on the training points (F with as many regressors
    as the contributing terms). With ``composed`` line corrections, the prediction is the model
    document's (corrections on T1) plus each point's own line's home deviation
    (``models.lines``); ``line`` names the correction in the link column.
    """
    el = predict_models(models, sample)
    W_link = workspace_error(sample.q, el, dims)
    if composed is not None and composed.terms:
        el = {k: v.copy() for k, v in el.items()}
        el[LINE_ELEMENT] = el.get(LINE_ELEMENT, np.zeros((sample.q.shape[0], 6))) + composed_errors(composed, sample)
        W_hat = workspace_error(sample.q, el, dims)
    else:
        W_hat = W_link
    # zeroed readings: the link models less their value at the datum (the lines carry their own session offsets)
    D = datum_rows(sample)
    W_hat = W_hat - (W_link - at_datum(W_link, D))
    camp = sample.frame["campaign"].to_numpy()
    for o in campaign_offsets:  # a later campaign's absolute readings carry its own offset (joint_adjust)
        k = PARAMS.index(str(o["term"]))
        on = (camp == o["campaign"]) & (D[:, k] < 0)
        W_hat[on, k] += float(o["offset"])
    if composed is not None and composed.home_deviation:
        W_hat = W_hat + home_deviation(composed, sample.frame, sample.inputs, sample.q, _directions(sample))
    W = sample.frame[list(PARAMS)].to_numpy(float)
    H = sample.frame[list(HELD)].to_numpy(float) if all(h in sample.frame.columns for h in HELD) else None
    role = sample.frame["role"].to_numpy(object)
    axis_col = sample.frame["axis"].to_numpy(str)
    rows = []
    for axis in AXES:
        on = axis_col == axis
        if not on.any():
            continue
        for k, term in enumerate(PARAMS):
            col = W[:, k]
            ok = on & np.isfinite(col)
            tr, ho, va = ok & (role == "train"), ok & (role == "holdout"), ok & (role == "validation")
            if H is not None and np.isfinite(H[:, k]).any():  # the time split: the held-out values apart
                ho = on & np.isfinite(H[:, k])
                col = np.where(ho, H[:, k], col)
            if tr.sum() < 3:
                continue
            contrib = {e: float(np.std(v[tr, k])) for e, v in el.items()}
            top = max(contrib.values(), default=0.0)
            links = [e for e, c in sorted(contrib.items(), key=lambda kv: -kv[1]) if top > 0 and c >= 0.05 * top]
            n_terms = sum(len(models[(e, term)].features) for e in links if (e, term) in models)
            if composed is not None and LINE_ELEMENT in links:
                n_terms += len(composed.terms.get(term, []))
            r2 = r_squared(col[tr], W_hat[tr, k])
            n = int(tr.sum())
            dof = n - n_terms - 1
            f = (r2 / max(n_terms, 1)) / ((1 - r2) / dof) if dof > 0 and n_terms and r2 < 1 else float("nan")
            rows.append(
                {
                    "axis": axis,
                    "term": term,
                    "link": "+".join(links) or "-",
                    "measurement": _measurement_name(axis, term),
                    "unit": term_unit(term),
                    "rmse_train": rmse(col[tr] - W_hat[tr, k]),
                    "rmse_holdout": rmse(col[ho] - W_hat[ho, k]),
                    "rmse_validation": rmse(col[va] - W_hat[va, k]),
                    "r2": r2,
                    "f": f,
                    "r2_holdout": r_squared(col[ho], W_hat[ho, k]) if ho.sum() > 2 else float("nan"),
                    "n_train": n,
                    "n_holdout": int(ho.sum()),
                    "n_validation": int(va.sum()),
                }
            )
    return pd.DataFrame(rows), W_hat


def predict_without(steps: FitSteps, drop: Callable[[Feature], bool]) -> pd.DataFrame:
    """Return ``prediction_frame`` of the fitted model with the terms ``drop`` selects left out (not refitted).

    Every other coefficient stays as fitted: the difference to the whole model's prediction is what
    those terms contribute to each reading (diagnosis: the effects the fitted model carries).
    """
    models = {
        k: replace(m, coef=[0.0 if drop(f) else c for f, c in zip(m.features, m.coef)])
        for k, m in steps.allocation.models.items()
    }
    comp = steps.corrections.composed
    composed = Composed(
        {t: [(f, 0.0 if drop(f) else c, se, p) for f, c, se, p in rows] for t, rows in comp.terms.items()},
        comp.home_deviation,
    )
    sample = steps.samples.sample
    _, W_hat = validation_table(sample, models, steps.allocation.dims, composed, steps.joint.campaign_offsets)
    return prediction_frame(sample, W_hat)


def prediction_frame(sample: Sample, W_hat: np.ndarray) -> pd.DataFrame:
    """Return one row per reading: where and when, its value, the model's prediction of it and its part.

    ``part`` is ``train`` for a reading the fit trained on, ``holdout`` for one it held out (never
    read before the scoring), ``validation``/``skip`` for the rows of stages it does not train on.
    The prediction is what the instrument reads (zeroed sessions less their datum), as tables 6.1/6.2
    score it: the figures diagnosis, the demo and the API state are computed from this frame.
    """
    f = sample.frame
    W = f[list(PARAMS)].to_numpy(float)
    H = f[list(HELD)].to_numpy(float) if all(h in f.columns for h in HELD) else np.full_like(W, np.nan)
    role = f["role"].to_numpy(object)
    out = []
    for k, term in enumerate(PARAMS):
        tr, ho = np.isfinite(W[:, k]), np.isfinite(H[:, k])
        on = tr | ho
        if not on.any():
            continue
        part = np.where(ho[on], "holdout", role[on])
        out.append(
            pd.DataFrame(
                {
                    "campaign": f["campaign"].to_numpy()[on],
                    "time_s": f["time_s"].to_numpy(float)[on],
                    "axis": f["axis"].to_numpy(str)[on],
                    "term": term,
                    "position": f["position"].to_numpy(float)[on],
                    "direction": f["direction"].to_numpy(float)[on],
                    "value": np.where(ho, H[:, k], W[:, k])[on],
                    "predicted": W_hat[on, k],
                    "part": part,
                }
            )
        )
    cols = ["campaign", "time_s", "axis", "term", "position", "direction", "value", "predicted", "part"]
    return pd.concat(out, ignore_index=True) if out else pd.DataFrame(columns=cols)


# ----------------------------------------------------------------------------- the pipeline


def _reference(bundles: Sequence[BundleLike], channels: Sequence[str]) -> dict[str, float]:
    """Return the reference temperatures: each channel's first reading of the first campaign (eq. 3.1)."""
    ref = {}
    for c in channels:
        for b in bundles:
            if c in b.temperatures.columns:
                v = b.temperatures[c].to_numpy(float)
                ok = np.isfinite(v)
                if ok.any():
                    ref[c] = float(v[ok][0])
                    break
    return ref


def campaign_travel(bundles: Sequence[BundleLike]) -> dict[str, list[float]]:
    """Return the axis travel the campaigns state (``machine.travel``, from their plans), per axis.

    Campaigns of one machine state one travel; where they differ the narrowest holds (the
    intersection: a limit any campaign states is never widened). Axes no campaign states are absent.
    """
    out: dict[str, list[float]] = {}
    for b in bundles:
        for axis, (lo, hi) in (getattr(b.meta.machine, "travel", None) or {}).items():
            have = out.get(str(axis))
            out[str(axis)] = [float(lo), float(hi)] if have is None else [max(have[0], lo), min(have[1], hi)]
    for axis, (lo, hi) in out.items():
        if not lo < hi:
            raise ValidationError(f"the campaigns state travels of {axis} that do not overlap (machine.travel)")
    return out


def fit_bundles(
    bundles: Sequence[BundleLike],
    options: FitOptions | None = None,
    *,
    source_campaigns: Sequence[int | str] = (),
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Return the fitted model of one machine from one or more campaign bundles."""
    # the products here are tall and thin: one BLAS thread does them as fast, and on a shared
    # 2-core machine several threads per process only queue behind each other
    with threadpool_limits(limits=1):
        return _fit_bundles(bundles, options or FitOptions(), Timer(progress), source_campaigns)


class Timer:
    """The pipeline's stage timings: each lap's seconds since the last one, reported to ``progress``."""

    def __init__(self, progress: Callable[[str], None] | None = None) -> None:
        self.timings: dict[str, float] = {}
        self._tick = time.perf_counter()
        self._progress = progress

    def restart(self) -> None:
        """Start the next lap now (what came before is not timed)."""
        self._tick = time.perf_counter()

    def lap(self, name: str) -> None:
        """Record the seconds since the last lap under ``name`` and report the stage done."""
        now = time.perf_counter()
        self.timings[name] = round(now - self._tick, 3)
        self._tick = now
        if self._progress is not None:
            self._progress(name)


@dataclass(frozen=True)
class Campaigns:
    """The campaigns of one machine to fit, with the findings' substitutions applied (``plan_findings``)."""

    machine: str
    bundles: list[BundleLike]
    #: the diagnosis findings folded in (None without findings)
    plan: FindingsPlan | None
    #: the earliest campaign start: time zero of the drift terms
    origin: datetime


def prepare_campaigns(bundles: Sequence[BundleLike], opts: FitOptions) -> Campaigns:
    """Return the campaigns to fit; refuse none and campaigns of different machines."""
    if not bundles:
        raise ValidationError("no campaigns to fit")
    machines = {b.meta.machine.id for b in bundles}
    if len(machines) != 1:
        raise ValidationError(f"campaigns of different machines: {', '.join(sorted(machines))}")
    machine = machines.pop()
    plan = None
    if opts.findings is not None and opts.findings.effects:
        # faulty channels are replaced by their virtual-sensor estimates before anything reads them
        plan = plan_findings(opts.findings, bundles, force=opts.force_findings)
        bundles = plan.bundles
    origin = min(b.meta.started_at for b in bundles)
    return Campaigns(machine, list(bundles), plan, origin)


@dataclass(frozen=True)
class ChannelMeta:
    """What the campaigns say of their thermocouples: where each sits, the room's, the user's selections."""

    #: per channel its location and structure (the first campaign stating it wins)
    chan_meta: dict[str, dict[str, str]]
    room: list[str]
    #: per axis the channels the user chose for its model (bundle ``model_channels``)
    model_channels: dict[str, list[str]]

    @property
    def structures(self) -> dict[str, str]:
        """Return the structure of each channel."""
        return {c: m["structure"] for c, m in self.chan_meta.items()}

    @property
    def locations(self) -> dict[str, str]:
        """Return the location of each channel."""
        return {c: m["location"] for c, m in self.chan_meta.items()}


def channel_metadata(bundles: Sequence[BundleLike]) -> ChannelMeta:
    """Return the campaigns' channel metadata merged (first statement of a channel wins, lists united)."""
    chan_meta: dict[str, dict[str, str]] = {}
    room: list[str] = []
    model_channels: dict[str, list[str]] = {}
    for b in bundles:
        for c, ch in b.meta.channels.items():
            chan_meta.setdefault(c, {"location": ch.location, "structure": ch.structure})
        room += [c for c in b.meta.room_channels if c not in room]
        for ax, cs in (b.meta.model_channels or {}).items():
            model_channels.setdefault(ax, [])
            model_channels[ax] += [c for c in cs if c not in model_channels[ax]]
    return ChannelMeta(chan_meta, room, model_channels)


@dataclass(frozen=True)
class Screened:
    """The screening of ch. 5.4 and the temperatures it read."""

    #: the channels every campaign reads, and their readings (gaps filled) over all campaigns
    common: list[str]
    temps: pd.DataFrame
    screening: ScreeningResult

    @property
    def kept(self) -> list[str]:
        """Return the channels the screening kept."""
        return self.screening.kept


def screen(
    bundles: Sequence[BundleLike], meta: ChannelMeta, holdout_fraction: float, split: str = STAGE_SPLIT
) -> Screened:
    """Return the screening (ch. 5.4): every campaign trains the model (the neural comparison is beside it)."""
    common = [c for c in channel_columns(bundles[0].temperatures) if all(c in b.temperatures for b in bundles)]
    temps = pd.concat([fill_gaps(b.temperatures[["time_s", *common]]) for b in bundles], ignore_index=True)
    # the training errors choose among near-duplicate sites (held-out points never steer the choice)
    errs = [_training_errors(b.errors, b.meta.stages, holdout_fraction, split) for b in bundles]
    screening = screen_channels(temps, meta.chan_meta, meta.room, errors=errs)
    _keep_gradient_corners(screening, screen_channels(temps, meta.chan_meta, meta.room), meta.chan_meta)
    return Screened(common, temps, screening)


def candidates(meta: ChannelMeta, screened: Screened, plan: FindingsPlan | None, opts: FitOptions) -> Candidates:
    """Return what the stage fits may choose from: kept channels, structure members, screws, findings' terms."""
    kept, structures, room = screened.kept, meta.structures, meta.room
    # a structure's mean (eq. 3.3) is over all its sites that read, kept or not
    members: dict[str, list[str]] = {}
    dropped = screened.screening.dropped
    dead = {c for c, why in dropped.items() if why == "no readings" or why.startswith("constant")}
    for c in screened.common:
        st = structures.get(c, "")
        if st and st != "unspecified" and c not in room and c not in dead:
            members.setdefault(st, []).append(c)
    members = {st: cs for st, cs in members.items() if len(cs) >= 2 and any(c in kept for c in cs)}
    screws = {ax: [c for c in kept if structures.get(c, "") in SCREW_STRUCTURES.get(AXIS_JOINT[ax], ())] for ax in AXES}
    extras = list(plan.extras) if plan else []
    return Candidates(
        list(kept), structures, meta.locations, members, screws, list(room), tuple(opts.lag_taus_s), extras
    )


@dataclass(frozen=True)
class Samples:
    """The error points with dT and lags of every channel a model may read, and the candidates."""

    cands: Candidates
    #: the channels read, with their reference temperatures (eq. 3.1)
    channels: list[str]
    reference: dict[str, float]
    sample: Sample


def build_fit_samples(campaigns: Campaigns, meta: ChannelMeta, screened: Screened, opts: FitOptions) -> Samples:
    """Return the samples at the error points with the candidates' channels and lags."""
    plan, kept = campaigns.plan, screened.kept
    cands = candidates(meta, screened, plan, opts)
    chosen = [c for cs in meta.model_channels.values() for c in cs if c in screened.common]
    extra_chans = list(plan.channels) if plan else []
    members = (c for cs in cands.members.values() for c in cs)
    channels = list(dict.fromkeys([*kept, *chosen, *members, *extra_chans]))
    reference = _reference(campaigns.bundles, channels)
    # a channel that never read anything has no reference (eq. 3.1): no term can read it
    channels = [c for c in channels if c in reference]
    lag_chans = [c for c in dict.fromkeys([*kept, *chosen]) if c not in meta.room and c in reference]
    lags = [(c, t) for t in opts.lag_taus_s for c in lag_chans]
    lags += [lag for lag in (plan.lags if plan else []) if lag not in lags]
    sample = build_samples(
        campaigns.bundles, channels, None, lags, opts.holdout_fraction, campaigns.origin, split=opts.split
    )
    return Samples(cands, channels, reference, sample)


@dataclass(frozen=True)
class Allocation:
    """The per-link models of the staged allocation through the chain (eq. 4.20), and its log."""

    #: the chain's fixed links (eq. 4.13): the lengths the campaigns state, else Table A.1's
    dims: dict[str, tuple[float, float, float]]
    models: dict[tuple[str, str], ElementModel]
    #: the document's ``allocation``: one row per stage, the physical terms, the joint adjustment
    log: list[AllocationRecord]


def allocate_models(bundles: Sequence[BundleLike], samples: Samples, meta: ChannelMeta, opts: FitOptions) -> Allocation:
    """Return the per-link stepwise models, allocated stage by stage (``fit_elements``)."""
    dims = chain_dims(bundles)
    models, log = fit_elements(samples.sample, samples.cands, meta.model_channels, opts, dims)
    if not models:
        raise ValidationError("no error term had enough training samples to fit")
    return Allocation(dims, models, log)


def _noise(bundles: Sequence[BundleLike]) -> dict[str, float]:
    """Return the first campaign's stated noise ("len" mm, "ang" rad), where it states it."""
    noise_meta = bundles[0].meta.noise
    noise = {}
    if noise_meta is not None and noise_meta.length_mm:
        noise["len"] = float(noise_meta.length_mm)
    if noise_meta is not None and noise_meta.angle_rad:
        noise["ang"] = float(noise_meta.angle_rad)
    return noise


def physical_and_joint(
    bundles: Sequence[BundleLike], samples: Samples, allocation: Allocation, opts: FitOptions
) -> JointOutcome:
    """Add the physical terms and re-estimate every coefficient together (in place on the models and log)."""
    priors: dict[tuple[str, str, Feature], PhysicalPrior] = {}
    models = allocation.models
    physics_terms = (
        _physical_terms(models, samples.cands, bundles, priors) if opts.joint_adjust and opts.physical_terms else []
    )
    if physics_terms:
        allocation.log.append({"physical_terms": physics_terms})
    if not opts.joint_adjust:
        return JointOutcome({})
    return adjust_jointly(samples.sample, models, allocation.dims, _noise(bundles), priors=priors)


@dataclass(frozen=True)
class LinePools:
    """The terms each measured line's correction may read (``models.lines``).

    A link shared by several axes reads the channels of all of them: a line must be able to undo what
    the links put on it, so its pool holds those channels as well as its own. The user's selection of
    the line's channels is honoured (bundle ``model_channels``), with the links'.
    """

    sample: Sample
    models: Mapping[tuple[str, str], ElementModel]
    cands: Candidates
    model_channels: Mapping[str, Sequence[str]]
    kept: Sequence[str]

    def _link_read(self) -> list[str]:
        return [c for m in self.models.values() for f in m.features for c in f.channels]

    def _link_lags(self) -> list[Feature]:
        return [f for m in self.models.values() for f in m.features if f.kind == "lag"]

    def channels(self, axis: str) -> list[str]:
        """Return the line's channels: its own (the user's selection, else the kept ones) and the links'."""
        have = self.sample.inputs.dT.columns
        own = [c for c in (self.model_channels.get(axis) or self.kept) if c in have]
        return list(dict.fromkeys([*own, *(c for c in self._link_read() if c in have)]))

    def pool(self, axis: str) -> list[Feature]:
        """Return the line's candidate terms."""
        extra = [*self.cands.for_axes([axis], self.model_channels.get(axis)), *self._link_lags()]
        return line_pool(axis, self.channels(axis), extra)

    def full(self, axis: str) -> list[Feature]:
        """Return the standard model (spec section 2) plus what the links put on the line: their
        channels, position x dT of them (an angle acting through the line's lever) and lags."""
        out = line_pool(axis, self.channels(axis), ())
        out += list(dict.fromkeys(self._link_lags()))
        # what the chain's lever arm makes of them along the line (eq. 4.12): position x lag, position^2 x dT
        out += levered(axis, [f for m in self.models.values() for f in m.features])
        if any(f.kind == "direction" and f.label == axis for m in self.models.values() for f in m.features):
            out.append(Feature("direction", label=axis))
        return out

    def standard(self, axis: str) -> list[Feature]:
        """Return the standard model of the bundle spec (section 2): position^1..3 and dT of the line's
        model_channels (the screened channels where the bundle names none), nothing else."""
        have = self.sample.inputs.dT.columns
        chans = [c for c in (self.model_channels.get(axis) or self.kept) if c in have]
        return [Feature("position", power=p, label=axis) for p in (1, 2, 3)] + [Feature("dT", (c,)) for c in chans]


@dataclass(frozen=True)
class LineCorrections:
    """What the link models leave along each measured line, kept by validation, and the composed corrections."""

    lines: list[LineFit] = field(default_factory=list)
    composed: Composed = field(default_factory=lambda: Composed({}, {}))


def link_prediction(
    sample: Sample, allocation: Allocation, campaign_offsets: Sequence[Mapping[str, Any]]
) -> np.ndarray:
    """Return the work space error the link models predict as the instruments read it (datums, campaigns' offsets)."""
    D_rows = datum_rows(sample)
    W_link = at_datum(workspace_error(sample.q, predict_models(allocation.models, sample), allocation.dims), D_rows)
    for o in campaign_offsets:
        k = PARAMS.index(str(o["term"]))
        W_link[(sample.frame["campaign"].to_numpy() == o["campaign"]) & (D_rows[:, k] < 0), k] += o["offset"]
    return W_link


def line_corrections(
    samples: Samples,
    allocation: Allocation,
    joint: JointOutcome,
    meta: ChannelMeta,
    screened: Screened,
    opts: FitOptions,
) -> LineCorrections:
    """Return each measured line's correction over the standard terms (the standard form), kept by validation."""
    if not opts.lines:
        return LineCorrections()
    sample = samples.sample
    W_link = link_prediction(sample, allocation, joint.campaign_offsets)
    pools = LinePools(sample, allocation.models, samples.cands, meta.model_channels, screened.kept)
    lines = fit_lines(
        sample.frame,
        sample.q,
        _directions(sample),
        sample.inputs,
        sample.frame[list(PARAMS)].to_numpy(float),
        W_link,
        pools.pool,
        opts,
        full_of=pools.full,
        standard_of=pools.standard,
    )
    return LineCorrections(lines, compose(lines, allocation.dims))


@dataclass(frozen=True)
class Checked:
    """Tables 6.1/6.2 (validation) and 6.3 (the physical check) of the fit."""

    validation: pd.DataFrame
    W_hat: np.ndarray
    check: PhysicalCheck


def validate(
    bundles: Sequence[BundleLike],
    samples: Samples,
    allocation: Allocation,
    joint: JointOutcome,
    corrections: LineCorrections,
    meta: ChannelMeta,
) -> Checked:
    """Return the validation tables, and table 6.3 with the lengths the campaigns state (or "no geometry")."""
    offsets = list(joint.campaign_offsets)
    validation, W_hat = validation_table(
        samples.sample, allocation.models, allocation.dims, corrections.composed, offsets
    )
    check = physical_check(allocation.models, meta.structures, bundles, locations=meta.locations, room=meta.room)
    return Checked(validation, W_hat, check)


def compare_neural(
    bundles: Sequence[BundleLike], meta: ChannelMeta, screened: Screened, opts: FitOptions
) -> list[NeuralComparison]:
    """Return the neural comparison (ch. 6.6): the same inputs to both models, the targets fixed in advance
    (options), both extrapolation directions, absolute readings only (models/neural.py)."""
    neural: list[NeuralComparison] = []
    targets = list(opts.network_targets)
    if targets == ["all"]:
        seen = pd.concat([b.errors[["axis", "term"]] for b in bundles]).drop_duplicates()
        targets = [f"{a}/{t}" for a, t in sorted(map(tuple, seen.to_numpy().tolist()))]
    for target in targets:
        # the user's sensor selection for the axis, else the screening's: the same for both models
        chosen = meta.model_channels.get(str(target).partition("/")[0], [])
        net_channels = [c for c in chosen if c in screened.common] or screened.kept
        neural += neural_comparisons(
            bundles,
            [target],
            net_channels,
            split=opts.network_split,
            hidden=opts.network_hidden,
            max_samples=opts.network_max_samples,
            max_iter=opts.network_max_iter,
            seed=opts.seed,
        )
    return neural


def virtual_sensors(screened: Screened, opts: FitOptions) -> list[VirtualSensorRecord]:
    """Return the virtual sensors of the kept channels (ch. 6.6, fig. 6.9), as the document holds them."""
    kept = screened.kept
    if not (opts.virtual_sensors and len(kept) >= 2):
        return []
    return [s.to_dict() for s in fit_virtual_sensors(screened.temps[["time_s", *kept]], kept).values()]


@dataclass(frozen=True)
class FitSteps:
    """The results of every step of the pipeline, in order (what the document is built from)."""

    campaigns: Campaigns
    meta: ChannelMeta
    screened: Screened
    samples: Samples
    allocation: Allocation
    joint: JointOutcome
    corrections: LineCorrections
    checked: Checked
    neural: list[NeuralComparison]
    virtual_sensors: list[VirtualSensorRecord]


def _document_terms(steps: FitSteps) -> list[dict[str, Any]]:
    """Return the document's ``terms`` (``registry.TermDoc``): the link models, then the lines' corrections."""
    terms: list[dict[str, Any]] = []
    points = int(steps.joint.summary.get("points", 0))
    for (element, param), m in steps.allocation.models.items():
        term = _term_doc(element, param, m, points)
        if term is not None:
            terms.append(term)
    _merge_lines(terms, steps.corrections.composed, steps.checked.validation)
    return terms


def _document_inputs(steps: FitSteps, terms: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Return the document's ``inputs``: each channel read with its reference and the range seen in training."""
    channels, kept, plan = steps.samples.channels, steps.screened.kept, steps.campaigns.plan
    temps = steps.screened.temps
    lo = temps[channels].min()
    hi = temps[channels].max()
    used = sorted({c for t in terms for f in t["features"] for c in f.get("channels", [])})
    substituted = {c for sub in (plan.substitutions if plan else []) for c in (sub.channel, *sub.neighbours)}
    reference = steps.samples.reference
    return {
        c: {"reference": reference[c], "min": float(lo[c]), "max": float(hi[c])}
        for c in channels
        if c in used or c in kept or c in substituted
    }


def _findings_records(
    plan: FindingsPlan | None, models: Mapping[tuple[str, str], ElementModel]
) -> list[FindingOutcomeRecord]:
    """Return the document's ``findings``: each finding folded in and the models its terms entered."""
    if plan is None:
        return []
    entered: dict[str, list[str]] = {}
    for (element, param), m in models.items():
        for f in m.features:
            entered.setdefault(f.name, []).append(f"{element}.{param}")
    return plan.records(entered)


def build_document(steps: FitSteps, source_campaigns: Sequence[int | str] = ()) -> ModelDocument:
    """Return the model document of a fit, validated (``document.validate_document``)."""
    camp, alloc, checked, plan = steps.campaigns, steps.allocation, steps.checked, steps.campaigns.plan
    terms = _document_terms(steps)
    adjustment = steps.joint.summary
    doc: dict[str, Any] = {
        "format": MODEL_FORMAT,
        "machine": camp.machine,
        "created_at": now_iso(),
        "source_campaigns": list(source_campaigns) or [b.name for b in camp.bundles],
        "kept_channels": list(steps.screened.kept),
        "inputs": _document_inputs(steps, terms),
        "dims": {k: list(v) for k, v in alloc.dims.items()},
        "alpha_c_per_degC": ALPHA_C,
        "terms": terms,
        "screening": steps.screened.screening.to_dict(),
        "validation": checked.validation.to_dict("records"),
        "physical": checked.check.table.to_dict("records"),
        "physical_check": checked.check.to_dict(),
        "virtual_sensors": steps.virtual_sensors,
        "neural_comparison": [c.to_dict() for c in steps.neural] or None,
        "allocation": alloc.log + ([{"joint_adjustment": adjustment}] if adjustment else []),
        "time_origin": camp.origin.isoformat(),
        "substitutions": [sub.to_dict() for sub in (plan.substitutions if plan else [])],
        "findings": _findings_records(plan, alloc.models),
        "lines": [_line_record(fit, steps.corrections.composed) for fit in steps.corrections.lines],
    }
    if steps.joint.joint is not None:  # the coefficients' covariance across terms, for the prediction interval
        doc["joint_covariance"] = _joint_covariance(steps.joint.joint, terms)  # (issue 21.4)
    travel = campaign_travel(camp.bundles)
    if travel:  # the machine's travel the campaigns state: the compensator's envelope (docs/compensate.md)
        doc["envelope"] = {"travel": travel, "source": "campaigns"}
    return validate_document(strict_json(doc))


def _fit_bundles(
    bundles: Sequence[BundleLike], opts: FitOptions, timer: Timer, sources: Sequence[int | str]
) -> FitResult:
    """Return the fitted model (the pipeline itself; see ``fit_bundles``): each step a typed result."""
    campaigns = prepare_campaigns(bundles, opts)
    timer.restart()
    meta = channel_metadata(campaigns.bundles)
    screened = screen(campaigns.bundles, meta, opts.holdout_fraction, opts.split)
    timer.lap("screening")
    samples = build_fit_samples(campaigns, meta, screened, opts)
    timer.lap("samples")
    allocation = allocate_models(campaigns.bundles, samples, meta, opts)
    timer.lap("allocation_and_regression")
    joint = physical_and_joint(campaigns.bundles, samples, allocation, opts)
    if opts.joint_adjust:
        timer.lap("joint_adjustment")
    corrections = line_corrections(samples, allocation, joint, meta, screened, opts)
    if opts.lines:
        timer.lap("lines")
    checked = validate(campaigns.bundles, samples, allocation, joint, corrections, meta)
    timer.lap("validation")
    neural = compare_neural(campaigns.bundles, meta, screened, opts) if opts.network else []
    if opts.network:
        timer.lap("network")
    sensors = virtual_sensors(screened, opts)
    timer.lap("virtual_sensors")
    steps = FitSteps(campaigns, meta, screened, samples, allocation, joint, corrections, checked, neural, sensors)
    document = build_document(steps, sources)
    timer.lap("document")
    return replace(FitResult.of(steps, document, timer.timings), split=opts.split)


def _merge_lines(terms: list[dict[str, Any]], composed: Composed, validation: pd.DataFrame) -> None:
    """Add the lines' composed corrections to the T1 terms of a document (in place; ``models.lines``)."""
    for param, rows in composed.terms.items():
        entry = next((t for t in terms if t["element"] == LINE_ELEMENT and t["param"] == param), None)
        if entry is None:
            on = validation[validation["term"] == param] if not validation.empty else validation
            entry = {
                "element": LINE_ELEMENT,
                "param": param,
                "axis": None,
                "term": param,
                "features": [],
                "coefficients": [],
                "std_errors": [],
                "p_values": [],
                "statistics": {
                    # a parameter no measured line shows (an angle's lever on a length): n_train 0 says so
                    "rmse_train": float(on["rmse_train"].max()) if len(on) else 0.0,
                    "rmse_holdout": float(on["rmse_holdout"].max()) if len(on) else None,
                    "n_train": int(on["n_train"].sum()) if len(on) else 0,
                    "n_holdout": int(on["n_holdout"].sum()) if len(on) else 0,
                },
                "steps": [],
            }
            terms.append(entry)
        taken = {f["name"]: Feature.from_dict(f) for f in entry["features"]}
        names = [f["name"] for f in entry["features"]]
        # the lines' corrections are fitted apart from the link models: their variances add, no covariance
        cov = entry.get("covariance")
        C = np.asarray(cov, float) if cov is not None else np.diag(np.square(entry["std_errors"]))
        for f, c, se, p in rows:
            f = distinct(f, taken)
            if f.name in names:
                i = names.index(f.name)
                entry["coefficients"][i] += c
                entry["std_errors"][i] = float(np.hypot(entry["std_errors"][i], se))
                entry["p_values"][i] = min(entry["p_values"][i], p)
                C[i, i] += se**2
            else:
                names.append(f.name)
                entry["features"].append(f.to_dict())
                entry["coefficients"].append(c)
                entry["std_errors"].append(se)
                entry["p_values"].append(p)
                C = np.pad(C.reshape(len(names) - 1, len(names) - 1), ((0, 1), (0, 1)))
                C[-1, -1] = se**2
        entry["covariance"] = [[float(v) for v in r] for r in C]


def _joint_covariance(joint: JointFit, terms: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Return the document's ``joint_covariance``: the joint adjustment's covariance of the terms' coefficients.

    The link models are estimated together (``joint_adjust``), and where the campaign pins only a sum
    (the column's growth against the carriage's, an angle constant against another) their coefficients
    are strongly anti-correlated: taken independent, the prediction's spread would be many times the
    real one. Columns are (element, param, feature name) of the document's terms, in the joint's order.
    """
    in_doc = {(t["element"], t["param"], f["name"]) for t in terms for f in t["features"]}
    idx = [i for i, (e, p, f) in enumerate(joint.columns) if (e, p, f.name) in in_doc]
    C = joint.cov[np.ix_(idx, idx)]
    return {
        "columns": [[joint.columns[i][0], joint.columns[i][1], joint.columns[i][2].name] for i in idx],
        "matrix": [[float(v) for v in row] for row in C],
    }


def _line_record(fit: LineFit, composed: Composed) -> LineRecord:
    """Return a line's entry of the document: which form won, why, and its home deviation."""
    out = fit.to_dict()
    dev = composed.home_deviation.get((fit.axis, fit.term))
    out["home_deviation"] = (
        None if dev is None else {"features": [f.to_dict() for f in dev[0]], "coefficients": [float(c) for c in dev[1]]}
    )
    return out


def chain_dims(bundles: Sequence[BundleLike]) -> dict[str, tuple[float, float, float]]:
    """Return the fixed link lengths (a, b, c) of the chain: Table A.1 with the machine's stated links over it.

    Campaigns that disagree on the links are refused (one machine has one geometry).
    """

    def xyz(v: Any) -> tuple[float, float, float]:
        x, y, z = v  # a link is (a, b, c): Table A.1, Geometry.links_mm
        return float(x), float(y), float(z)

    dims = {k: xyz(v) for k, v in TABLE_A1.items()}
    stated: dict[str, tuple[float, float, float]] | None = None
    for g, _names in stated_geometries(bundles).values():
        links = g.get("links_mm")
        if not links:
            continue
        here = {GEOMETRY_LINKS[name]: xyz(v) for name, v in dict(links).items()}
        if stated is not None and here != stated:
            raise ValidationError("the campaigns state different link lengths for one machine (machine.geometry)")
        stated = here
    dims.update(stated or {})
    return dims


def _term_doc(element: str, param: str, m: ElementModel, joint_points: int) -> dict[str, Any] | None:
    """Return the document's term of one element model (``registry.TermDoc``), or None if it has no term.

    A zeroed instrument's session offsets belong to the campaign, not to the machine: they are left out.
    A model that only the stated geometry put there (``_physical_terms``: a link the staged allocation
    gave nothing) was estimated in the joint adjustment with the rest and goes into the document like
    them; leaving it out would apply a model other than the one fitted.
    """
    keep = [i for i, f in enumerate(m.features) if f.kind != "session"]
    if not keep:
        return None
    if m.fits:
        fit = m.primary
        res = fit.result
        axis = _axes_of(fit)
        statistics: dict[str, Any] = {
            "rmse_train": res.rmse,
            "rmse_holdout": fit.rmse_holdout,
            "r2": res.rsquared,
            "f": res.fvalue,
            "n_train": res.nobs,
            "n_holdout": fit.n_holdout,
            "condition_number": res.condition_number,
        }
    else:
        axis = JOINT_OF.get(element)
        rv = m.residual_variance
        statistics = {"rmse_train": float(np.sqrt(rv)) if rv is not None else 0.0, "n_train": joint_points}
    return {
        "element": element,
        "param": param,
        "axis": axis,
        "term": param,
        "features": [m.features[i].to_dict() for i in keep],
        "coefficients": [float(m.coef[i]) for i in keep],
        "std_errors": [float(m.std_errors[i]) for i in keep],
        "p_values": [float(m.p_values[i]) for i in keep],
        # what the compensator needs for a prediction interval: sqrt(x' C x + residual variance)
        "covariance": None if m.cov is None else [[float(m.cov[i, j]) for j in keep] for i in keep],
        "residual_variance": m.residual_variance,
        "statistics": statistics,
        "steps": [{"stage_element": f.element, **st.to_dict()} for f in m.fits for st in f.result.steps],
    }


def _axes_of(fit: TermFit) -> str | None:
    """Return the element's own axis for a joint (None for a link, measured through every axis)."""
    return JOINT_OF.get(fit.element)


# ----------------------------------------------------------------------------- documents as JSON


def result_document_json(result: FitResult) -> dict[str, Any]:
    """Return the model document of a fit as strict JSON."""
    return document_json(result.document)
