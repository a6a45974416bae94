"""The fitting pipeline: screening -> allocation through the HTM chain -> per-link stepwise models
-> validation (tables 6.1-6.3) -> neural comparison -> virtual sensors -> a model document.

Pure over bundles (``fit_bundles``); the store and job wrappers live at the bottom.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.models.features import (
    INTERCEPT,
    Feature,
    Inputs,
    build_inputs,
    candidate_features,
    channel_columns,
    design_matrix,
    fill_gaps,
)
from driftlab.models.kinematics import ELEMENTS, JOINT_AXIS, JOINTS, PARAMS, TABLE_A1, allocate, workspace_error
from driftlab.models.neural import ExtrapolationResult, extrapolation_errors, fit_network
from driftlab.models.regression import TermFit, r_squared, rmse, stepwise
from driftlab.models.registry import ALPHA_C_PER_DEGC, MODEL_FORMAT, ModelDocument, document_json, now_iso, validate_document
from driftlab.models.selection import ScreeningResult, screen_channels
from driftlab.models.virtual_sensor import fit_virtual_sensors

log = logging.getLogger(__name__)

AXES: tuple[str, ...] = ("X", "Y", "Z", "A", "B")
ROTARY = ("A", "B")
#: the joint each axis drives
AXIS_JOINT: Mapping[str, str] = {"X": "phi_x", "Y": "phi_y", "Z": "phi_z", "A": "theta_x", "B": "theta_y"}
#: names of the error measurements of tables 6.1/6.2, by (axis, term)
MEASUREMENT_NAMES: Mapping[str, str] = {"alpha": "Roll", "beta": "Pitch", "gamma": "Yaw"}
#: structures whose thermocouples may explain each element (ch. 4.3: only thermocouples close to
#: the source of the error); room and base channels are candidates everywhere
ELEMENT_STRUCTURES: Mapping[str, tuple[str, ...]] = {
    "T1": ("spindle", "spindle_arm"),
    "phi_z": ("z_screw", "z_motor", "spindle_arm", "z_column"),
    "T2": ("z_column",),
    "phi_y": ("y_screw", "y_motor", "z_column"),
    "T3": ("xy_carriage",),
    "phi_x": ("x_screw", "x_motor", "x_table", "xy_carriage"),
    "T4": ("x_table", "xy_carriage"),
    "theta_x": ("a_drive", "rotary_base"),
    "T5": ("rotary_base",),
    "theta_y": ("b_drive", "b_table"),
    "T6": ("b_table",),
}
EVERYWHERE = ("room", "base")
#: feature kinds that belong to a joint (position shape, reversal, ballscrew)
SEED_KINDS = frozenset({"position", "direction", "pos_dT"})
#: ballscrew sites of each translational joint (eq. 3.2: error ~ position x dT of the screw)
SCREW_STRUCTURES: Mapping[str, tuple[str, ...]] = {
    "phi_x": ("x_screw", "x_motor"), "phi_y": ("y_screw", "y_motor"), "phi_z": ("z_screw", "z_motor"),
}


@dataclass
class FitOptions:
    """Knobs of the pipeline (defaults follow the thesis' practice)."""

    holdout_fraction: float = 0.25
    lag_taus_s: tuple[float, ...] = (1800.0, 5400.0)
    p_enter: float = 1e-4
    p_remove: float = 1e-3
    min_gain: float = 0.01
    max_terms: int = 10
    vif_max: float = 30.0
    network: bool = True
    network_hidden: tuple[int, ...] = (30, 15, 7)
    network_max_samples: int = 5000
    virtual_sensors: bool = True
    seed: int = 0


@dataclass
class Sample:
    """The error samples of the campaigns as poses: one row per (campaign, time, axis, position, direction)."""

    frame: pd.DataFrame  # campaign, time_s, axis, position, direction, stage, element, role + one column per term
    q: np.ndarray  # (N, 5) joint coordinates (mm, rad)
    inputs: Inputs  # dT and lags at each sample

    def take(self, mask: np.ndarray) -> "Sample":
        """Return the rows selected by a boolean mask."""
        return Sample(self.frame[mask].reset_index(drop=True), self.q[mask], self.inputs.take(mask))


@dataclass
class FitResult:
    """Everything a fit produced: the document plus the tables a metrologist reads."""

    document: ModelDocument
    screening: ScreeningResult
    term_fits: dict[tuple[str, str], TermFit]
    validation: pd.DataFrame  # tables 6.1/6.2 layout
    physical: pd.DataFrame  # table 6.3 layout
    extrapolation: ExtrapolationResult | None
    timings_s: dict[str, float] = field(default_factory=dict)

    def report(self) -> dict[str, Any]:
        """Return the JSON report of ``driftlab fit --json``."""
        rows = []
        for r in self.validation.to_dict("records"):
            rows.append({k: r[k] for k in ("axis", "term", "link", "rmse_train", "rmse_holdout", "r2", "f")})
        out: dict[str, Any] = {
            "model_version": self.document.version,
            "machine": self.document.machine,
            "kept_channels": list(self.document.kept_channels),
            "dropped_channels": dict(self.screening.dropped),
            "terms": rows,
            "physical": self.physical.to_dict("records"),
            "timings_s": self.timings_s,
        }
        if self.extrapolation is not None:
            out["extrapolation"] = self.extrapolation.to_dict()
        return _strict_json(out)


def _strict_json(obj: Any) -> Any:
    """Return ``obj`` with numpy scalars made plain and non-finite floats made None."""
    if isinstance(obj, dict):
        return {k: _strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict_json(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


# ----------------------------------------------------------------------------- stages -> elements


def stage_elements(stages: Sequence[Any]) -> list[tuple[Any, str | None, str]]:
    """Return (stage, element, role) in plan order: the element the stage's errors are allocated to (ch. 4.3).

    A single heat source names the element: the spindle its support structure (T1), an axis feed
    or motor hold that axis' joint. Cool-downs belong to the heat source before them (a baseline
    to the first one); combined sources are kept for validation; power-off stages are skipped.
    """
    out: list[tuple[Any, str | None, str]] = []
    last: str | None = None
    pending: list[Any] = []
    for st in stages:
        hs = str(getattr(st, "heat_source", "")).lower()
        axis = getattr(st, "axis", None)
        if hs == "off":
            out.append((st, None, "skip"))
            continue
        if "+" in hs or hs == "combined":
            out.append((st, None, "validation"))
            continue
        element = None
        if hs == "spindle":
            element = "T1"
        elif hs in ("feed", "axis", "motor_hold") and axis in AXIS_JOINT:
            element = AXIS_JOINT[axis]
        if element is None:  # idle / none / cool-down
            if last is None:
                pending.append(st)
                out.append((st, None, "pending"))
            else:
                out.append((st, last, "train"))
            continue
        last = element
        out.append((st, element, "train"))
        if pending:
            out = [(s, element, "train") if r == "pending" else (s, e, r) for s, e, r in out]
            pending = []
    return [(s, e, "skip" if r == "pending" else r) for s, e, r in out]


# ----------------------------------------------------------------------------- samples


def _points(errors: pd.DataFrame) -> pd.DataFrame:
    """Return one row per measured point with one column per term (NaN where not measured)."""
    if errors.empty:
        return pd.DataFrame(columns=["time_s", "axis", "position", "direction", *PARAMS])
    wide = errors.pivot_table(
        index=["time_s", "axis", "position", "direction"], columns="term", values="value", aggfunc="mean"
    ).reset_index()
    wide.columns.name = None
    for p in PARAMS:
        if p not in wide.columns:
            wide[p] = np.nan
    return wide


def _q(axis: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Return (N, 5) joint coordinates: the moved axis at its position (deg -> rad for A/B), others home."""
    q = np.zeros((axis.size, 5))
    for k, ax in enumerate(AXES):
        m = axis == ax
        q[m, k] = np.deg2rad(position[m]) if ax in ROTARY else position[m]
    return q


def build_samples(
    bundles: Sequence[Any],
    channels: Sequence[str],
    reference: Mapping[str, float],
    lags: Sequence[tuple[str, float]],
    holdout_fraction: float,
) -> Sample:
    """Return the error points of all campaigns with their stage, element, role and inputs."""
    frames, qs, dts, lagged = [], [], [], []
    for ci, b in enumerate(bundles):
        pts = _points(b.errors)
        if pts.empty:
            continue
        pts.insert(0, "campaign", ci)
        t = pts["time_s"].to_numpy(float)
        pts["stage"] = -1
        pts["element"] = None
        pts["role"] = "skip"
        for si, (st, element, role) in enumerate(stage_elements(b.meta.stages)):
            m = (t >= st.start_s) & (t <= st.end_s) & (pts["stage"].to_numpy() < 0)
            pts.loc[m, "stage"] = si
            pts.loc[m, "element"] = element
            pts.loc[m, "role"] = role
            if role == "train" and m.any():
                ts = np.sort(t[m])
                cut = ts[int(np.floor((1 - holdout_fraction) * ts.size))] if ts.size >= 8 else np.inf
                pts.loc[m & (t >= cut), "role"] = "holdout"
        if not b.meta.stages:
            # no plan: everything is one stage allocated to the measured axis' joint
            pts["element"] = pts["axis"].map(AXIS_JOINT)
            ts = np.sort(t)
            cut = ts[int(np.floor((1 - holdout_fraction) * ts.size))]
            pts["role"] = np.where(t >= cut, "holdout", "train")
        inp = build_inputs(b.temperatures, t, reference, channels, lags)
        frames.append(pts)
        qs.append(_q(pts["axis"].to_numpy(str), pts["position"].to_numpy(float)))
        dts.append(inp.dT)
        lagged.append(inp.lagged)
    if not frames:
        raise ValidationError("the campaigns hold no error measurements")
    frame = pd.concat(frames, ignore_index=True)
    lag_all = {k: np.concatenate([lg[k] for lg in lagged]) for k in lagged[0]}
    return Sample(frame, np.vstack(qs), Inputs(pd.concat(dts, ignore_index=True), lag_all))


# ----------------------------------------------------------------------------- per-element fits


def _element_candidates(
    element: str,
    kept: Sequence[str],
    structures: Mapping[str, str],
    locations: Mapping[str, str],
    room: Sequence[str],
    lag_taus: Sequence[float],
    override: Sequence[str] | None,
) -> list[Feature]:
    """Return the candidate terms of one element: near-by channels, recast physically (ch. 6.4.2)."""
    if override:
        chans = list(override)
    else:
        near = set(ELEMENT_STRUCTURES.get(element, ())) | set(EVERYWHERE)
        chans = [c for c in kept if structures.get(c, "") in near or c in room]
        if len([c for c in chans if c not in room]) == 0:
            chans = list(kept)  # unknown structure names (a real machine): let stepwise choose
    joint = element in JOINTS
    screw: list[str] = []
    if joint:
        ss = SCREW_STRUCTURES.get(element, ())
        screw = [c for c in chans if structures.get(c, "") in ss or "ballscrew" in locations.get(c, "").lower()]
        if element in SCREW_STRUCTURES and not screw and not any(structures.get(c) in ss for c in kept):
            screw = [c for c in chans if c not in room]
    lag_chans = [c for c in chans if c not in room]
    return candidate_features(
        chans, structures, joint=joint, screw_channels=screw, lag_taus_s=lag_taus, lag_channels=lag_chans,
        room_channels=[c for c in room if c in chans],
    )


def _joint_position(element: str, q: np.ndarray) -> np.ndarray:
    """Return the coordinate that drives a joint (zeros for a link)."""
    return q[:, JOINT_AXIS[element]] if element in JOINT_AXIS else np.zeros(q.shape[0])


def predict_fits(
    fits: Mapping[tuple[str, str], TermFit], sample: Sample, direction: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Return element errors (N, 6) predicted by the fitted term models at the sample poses."""
    n = sample.q.shape[0]
    d = sample.frame["direction"].to_numpy(float) if direction is None else direction
    out: dict[str, np.ndarray] = {}
    for (element, param), fit in fits.items():
        pos = _joint_position(element, sample.q)
        dd = d * (sample.frame["axis"].map(AXIS_JOINT).to_numpy(object) == element)
        arr = out.setdefault(element, np.zeros((n, 6)))
        arr[:, PARAMS.index(param)] += fit.predict(sample.inputs, pos, dd)
    return out


def _measured_w(sample: Sample, known: Mapping[str, np.ndarray], dims: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Return W (N, 6) with unmeasured terms filled by the known model, and the measured mask."""
    W = sample.frame[list(PARAMS)].to_numpy(float)
    mask = np.isfinite(W)
    if not mask.all():
        W_known = workspace_error(sample.q, known, dims) if known else np.zeros_like(W)
        W = np.where(mask, W, W_known)
    return W, mask


def fit_elements(
    sample: Sample,
    kept: Sequence[str],
    structures: Mapping[str, str],
    locations: Mapping[str, str],
    room: Sequence[str],
    model_channels: Mapping[str, Sequence[str]],
    options: FitOptions,
    dims: Mapping[str, Any] = TABLE_A1,
    on_element: Callable[[str], None] | None = None,
) -> tuple[dict[tuple[str, str], TermFit], list[dict[str, Any]]]:
    """Return the term models of every element, allocated in chain order from the spindle (eq. 4.20)."""
    fits: dict[tuple[str, str], TermFit] = {}
    allocation_log: list[dict[str, Any]] = []
    elements = [e for e in ELEMENTS if (sample.frame["element"] == e).any()]
    for element in elements:
        rows = (sample.frame["element"] == element).to_numpy()
        sub = sample.take(rows)
        known = {k: v for k, v in predict_fits(fits, sub).items() if k != element}
        W, mask = _measured_w(sub, known, dims)
        E = allocate(W, sub.q, known, element, dims)  # eq. 4.20
        train = (sub.frame["role"] == "train").to_numpy()
        axes = sorted(set(sub.frame["axis"]))
        override = None
        for ax in axes:
            if AXIS_JOINT.get(ax) == element and model_channels.get(ax):
                override = list(model_channels[ax])
        if override is None and len(axes) == 1 and model_channels.get(axes[0]):
            override = list(model_channels[axes[0]])
        cands = _element_candidates(element, kept, structures, locations, room, options.lag_taus_s, override)
        pos = _joint_position(element, sub.q)
        d = sub.frame["direction"].to_numpy(float)
        seed_joint = None
        if element not in JOINTS:
            # a link is measured through a moving axis: that joint's shape (position, reversal,
            # ballscrew) is fitted alongside and handed to the joint, not left in the link's residual
            main_axis = sub.frame["axis"].mode().iloc[0]
            seed_joint = AXIS_JOINT[main_axis]
            pos = _joint_position(seed_joint, sub.q)
            d = d * (sub.frame["axis"] == main_axis).to_numpy()
            joint_cands = _element_candidates(seed_joint, kept, structures, locations, room, (), None)
            cands = cands + [f for f in joint_cands if f.kind in SEED_KINDS and f not in cands]
        X = design_matrix([INTERCEPT, *cands], sub.inputs, pos, d)
        for k, param in enumerate(PARAMS):
            m_train = train & mask[:, k]
            if m_train.sum() < 12:
                continue
            y = E[:, k]
            res = stepwise(
                X[m_train].reset_index(drop=True), y[m_train], cands, forced=[INTERCEPT],
                p_enter=options.p_enter, p_remove=options.p_remove, min_gain=options.min_gain,
                max_terms=options.max_terms, vif_max=options.vif_max,
            )
            fit = TermFit(element, param, res)
            m_hold = (~train) & mask[:, k] & (sub.frame["role"] == "holdout").to_numpy()
            if m_hold.any():
                fit.rmse_holdout = rmse(y[m_hold] - res.predict(X[m_hold]))
                fit.n_holdout = int(m_hold.sum())
            if seed_joint is not None:
                fit, seed = fit.split(lambda f: f.kind in SEED_KINDS, seed_joint)
                if seed is not None and (seed_joint, param) not in fits:
                    fits[(seed_joint, param)] = seed  # replaced when the joint's own stage is fitted
            fits[(element, param)] = fit
        allocation_log.append(
            {"element": element, "axes": axes, "stages": sorted({int(s) for s in sub.frame["stage"]}),
             "n": int(rows.sum()), "channels": override or "screened"}
        )
        if on_element is not None:
            on_element(element)
    return fits, allocation_log


# ----------------------------------------------------------------------------- validation tables


def _measurement_name(axis: str, term: str) -> str:
    """Return the thesis' name of an error measurement (Position, X Straightness, Roll, ...)."""
    if term in MEASUREMENT_NAMES:
        return MEASUREMENT_NAMES[term]
    t_axis = term[1].upper()
    if axis in ROTARY:
        return f"{t_axis} Deflection"
    return "Position" if t_axis == axis else f"{t_axis} Straightness"


def validation_table(
    sample: Sample, fits: Mapping[tuple[str, str], TermFit], dims: Mapping[str, Any]
) -> tuple[pd.DataFrame, np.ndarray]:
    """Return tables 6.1/6.2: per (axis, term, link) the work-space RMSE on training and held-out data, R^2, F."""
    W_hat = workspace_error(sample.q, predict_fits(fits, sample), dims)
    W = sample.frame[list(PARAMS)].to_numpy(float)
    rows = []
    role = sample.frame["role"].to_numpy(object)
    for (axis, element), idx in sample.frame.groupby(["axis", "element"]).groups.items():
        idx = np.asarray(list(idx))
        for k, term in enumerate(PARAMS):
            col = W[idx, k]
            ok = np.isfinite(col)
            if not ok.any() or (element, term) not in fits:
                continue
            fit = fits[(element, term)]
            r = col - W_hat[idx, k]
            tr = ok & (role[idx] == "train")
            ho = ok & (role[idx] == "holdout")
            rows.append({
                "axis": axis, "term": term, "link": element, "measurement": _measurement_name(axis, term),
                "unit": "rad" if term in MEASUREMENT_NAMES else "mm",
                "rmse_train": rmse(r[tr]), "rmse_holdout": rmse(r[ho]),
                "r2": fit.result.rsquared, "f": fit.result.fvalue,
                "r2_holdout": r_squared(col[ho], W_hat[idx, k][ho]) if ho.sum() > 2 else float("nan"),
                "n_train": int(tr.sum()), "n_holdout": int(ho.sum()),
                "terms": ", ".join(f.name for f in fit.terms if f.kind != "intercept"),
            })
    # combined-source stages: never trained on, the sternest hold-out
    val = role == "validation"
    for axis in sorted(set(sample.frame.loc[val, "axis"])):
        m = val & (sample.frame["axis"] == axis).to_numpy()
        for k, term in enumerate(PARAMS):
            col = W[m, k]
            ok = np.isfinite(col)
            if ok.sum() > 2:
                rows.append({
                    "axis": axis, "term": term, "link": "combined", "measurement": _measurement_name(axis, term),
                    "unit": "rad" if term in MEASUREMENT_NAMES else "mm", "rmse_train": float("nan"),
                    "rmse_holdout": rmse(col[ok] - W_hat[m, k][ok]), "r2": float("nan"), "f": float("nan"),
                    "r2_holdout": r_squared(col[ok], W_hat[m, k][ok]), "n_train": 0, "n_holdout": int(ok.sum()),
                    "terms": "",
                })
    table = pd.DataFrame(rows)
    if not table.empty:
        table["_a"] = table["axis"].map({a: i for i, a in enumerate(AXES)})
        table = table.sort_values(["_a", "term", "link"]).drop(columns="_a").reset_index(drop=True)
    return table, W_hat


def physical_table(
    fits: Mapping[tuple[str, str], TermFit],
    dims: Mapping[str, Any],
    geometry: Mapping[str, float] | None = None,
    alpha_c: float = ALPHA_C_PER_DEGC,
) -> pd.DataFrame:
    """Return table 6.3: each physically recast coefficient beside its physical value (ch. 3.5).

    position x dT of a ballscrew: alpha_c per mm of travel (eq. 3.1/3.2, L = position);
    dT or a structure mean on a link's length term: alpha_c L (eq. 3.1/3.3, L from the link dims);
    a gradient on a translation: alpha_c L^2 / 2H (eq. 3.5); on an angle: alpha_c L / H (eq. 3.4).
    """
    g = {"arm_length_mm": 400.0, "arm_height_mm": 200.0}
    g.update(geometry or {})
    rows = []
    for (element, param), fit in fits.items():
        for f, coef, se in zip(fit.terms, fit.coefficients, fit.std_errors):
            phys = rel = None
            if f.kind == "pos_dT" and param in ("dx", "dy", "dz"):
                phys, rel = alpha_c, "alpha_c dT L, L = position (eq. 3.2), per mm of travel"
            elif f.kind in ("dT", "mean") and element in dims and param in ("dx", "dy", "dz"):
                L = abs(float(tuple(dims[element])[("dx", "dy", "dz").index(param)]))
                if L > 0:
                    phys, rel = alpha_c * L, f"alpha_c dT L, L = {L:.0f} mm (eq. 3.1/3.3)"
            elif f.kind == "gradient" and not _room_pair(f):
                L, H = g["arm_length_mm"], g["arm_height_mm"]
                if param in ("dx", "dy", "dz"):
                    phys, rel = alpha_c * L**2 / (2 * H), f"alpha_c dT L^2/2H, L = {L:.0f}, H = {H:.0f} mm (eq. 3.5)"
                else:
                    phys, rel = alpha_c * L / H, f"alpha_c dT L/H, L = {L:.0f}, H = {H:.0f} mm (eq. 3.4), rad"
            if phys is None:
                continue
            rows.append({
                "term": f"{element}.{param} {f.name}", "element": element, "param": param, "feature": f.name,
                "regression": float(coef), "std_error": float(se), "physical": float(phys), "relationship": rel,
                "ratio": float(coef / phys) if phys else float("nan"),
            })
    return pd.DataFrame(rows, columns=["term", "element", "param", "feature", "regression", "std_error",
                                       "physical", "relationship", "ratio"])


def _room_pair(f: Feature, room: Sequence[str] = ("T49", "T50")) -> bool:
    """Return True for the ceiling-floor room gradient (not a structural bending term)."""
    return any(c in room for c in f.channels)


# ----------------------------------------------------------------------------- the pipeline


def _reference(bundles: Sequence[Any], channels: Sequence[str]) -> dict[str, float]:
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


def _extrapolation_split(bundles: Sequence[Any], room: Sequence[str], min_shift_degC: float = 1.0) -> int | None:
    """Return the index of a campaign whose room air lies beyond all the others' (ch. 6.6), or None."""
    if len(bundles) < 2 or not room:
        return None
    means = []
    for b in bundles:
        cols = [c for c in room if c in b.temperatures.columns]
        means.append(float(np.nanmean(b.temperatures[cols].to_numpy(float))) if cols else np.nan)
    i = int(np.nanargmax(means))
    others = [j for j in range(len(bundles)) if j != i]
    hi_others = max(
        float(np.nanmax(bundles[j].temperatures[[c for c in room if c in bundles[j].temperatures.columns]].to_numpy(float)))
        for j in others
    )
    cols = [c for c in room if c in bundles[i].temperatures.columns]
    if float(np.nanmean(bundles[i].temperatures[cols].to_numpy(float))) - hi_others >= min_shift_degC:
        return i
    return None


def _room_shift(bundles: Sequence[Any], ext_i: int | None, room: Sequence[str]) -> float:
    """Return how far (degC) the extrapolation campaign's mean room air lies above the training maximum."""
    if ext_i is None:
        return float("nan")

    def vals(b: Any) -> np.ndarray:
        return b.temperatures[[c for c in room if c in b.temperatures.columns]].to_numpy(float)

    hi = max(float(np.nanmax(vals(b))) for i, b in enumerate(bundles) if i != ext_i)
    return float(np.nanmean(vals(bundles[ext_i]))) - hi


def fit_bundles(
    bundles: Sequence[Any],
    options: FitOptions | None = None,
    *,
    source_campaigns: Sequence[Any] = (),
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Return the fitted model of one machine from one or more campaign bundles."""
    opts = options or FitOptions()
    if not bundles:
        raise ValidationError("no campaigns to fit")
    machines = {b.meta.machine.id for b in bundles}
    if len(machines) != 1:
        raise ValidationError(f"campaigns of different machines: {', '.join(sorted(machines))}")
    machine = machines.pop()
    timings: dict[str, float] = {}
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        timings[name] = round(now - tick, 3)
        tick = now
        if progress is not None:
            progress(name)

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
    structures = {c: m["structure"] for c, m in chan_meta.items()}
    locations = {c: m["location"] for c, m in chan_meta.items()}

    ext_i = _extrapolation_split(bundles, room) if opts.network else None
    train_bundles = [b for i, b in enumerate(bundles) if i != ext_i]

    # 1. screening (ch. 5.4)
    common = [c for c in channel_columns(train_bundles[0].temperatures) if all(c in b.temperatures for b in train_bundles)]
    temps = pd.concat([fill_gaps(b.temperatures[["time_s", *common]]) for b in train_bundles], ignore_index=True)
    forced = sorted({c for cs in model_channels.values() for c in cs})
    screening = screen_channels(temps, chan_meta, room, always_keep=forced)
    kept = screening.kept
    lap("screening")

    # 2. samples at the error points, with dT and lags of every channel a model may read
    channels = list(dict.fromkeys([*kept, *forced]))
    reference = _reference(bundles, channels)
    lag_chans = [c for c in channels if c not in room]
    lags = [(c, t) for t in opts.lag_taus_s for c in lag_chans]
    sample = build_samples(train_bundles, channels, reference, lags, opts.holdout_fraction)
    lap("samples")

    # 3-4. allocation through the chain and per-link stepwise models
    dims = TABLE_A1
    fits, alloc = fit_elements(sample, kept, structures, locations, room, model_channels, opts, dims)
    if not fits:
        raise ValidationError("no error term had enough training samples to fit")
    lap("allocation_and_regression")

    # 5. validation tables
    validation, W_hat = validation_table(sample, fits, dims)
    physical = physical_table(fits, dims)
    lap("validation")

    # 6. neural comparison and extrapolation (ch. 6.6)
    extrapolation = None
    net_summary: dict[str, Any] | None = None
    if opts.network:
        extrapolation, net_summary = _network_comparison(
            sample, W_hat, fits, bundles[ext_i] if ext_i is not None else None, channels, reference, lags, dims, opts,
            _room_shift(bundles, ext_i, room),
        )
        lap("network")

    # 7. virtual sensors (ch. 6.6, fig. 6.9)
    vs = []
    if opts.virtual_sensors and len(kept) >= 2:
        train_t = temps[["time_s", *kept]]
        vs = [s.to_dict() for s in fit_virtual_sensors(train_t, kept).values()]
    lap("virtual_sensors")

    # 8. the document
    lo = temps[channels].min()
    hi = temps[channels].max()
    terms = []
    for (element, param), fit in fits.items():
        sub = validation[(validation["link"] == element) & (validation["term"] == param)] if not validation.empty else validation
        axis = str(sub["axis"].iloc[0]) if len(sub) else None
        res = fit.result
        terms.append({
            "element": element, "param": param, "axis": axis, "term": param,
            "features": [f.to_dict() for f in fit.terms],
            "coefficients": [float(v) for v in fit.coefficients],
            "std_errors": [float(v) for v in fit.std_errors],
            "p_values": [float(v) for v in fit.p_values],
            "statistics": {
                "rmse_train": res.rmse, "rmse_holdout": fit.rmse_holdout, "r2": res.rsquared, "f": res.fvalue,
                "n_train": res.nobs, "n_holdout": fit.n_holdout, "condition_number": res.condition_number,
            },
            "steps": [s.to_dict() for s in res.steps],
        })
    used = sorted({c for t in terms for f in t["features"] for c in f.get("channels", [])})
    inputs = {c: {"reference": reference[c], "min": float(lo[c]), "max": float(hi[c])} for c in channels if c in used or c in kept}
    doc = {
        "format": MODEL_FORMAT,
        "machine": machine,
        "created_at": now_iso(),
        "source_campaigns": list(source_campaigns) or [b.name for b in bundles],
        "kept_channels": list(kept),
        "inputs": inputs,
        "dims": {k: list(v) for k, v in dims.items()},
        "alpha_c_per_degC": ALPHA_C_PER_DEGC,
        "terms": terms,
        "screening": screening.to_dict(),
        "validation": validation.to_dict("records"),
        "physical": physical.to_dict("records"),
        "virtual_sensors": vs,
        "extrapolation": None if extrapolation is None else {**extrapolation.to_dict(), **(net_summary or {})},
        "allocation": alloc,
    }
    document = validate_document(_strict_json(doc))
    lap("document")
    return FitResult(document, screening, fits, validation, physical, extrapolation, timings)


def _network_comparison(
    sample: Sample,
    W_hat: np.ndarray,
    fits: Mapping[tuple[str, str], TermFit],
    ext_bundle: Any | None,
    channels: Sequence[str],
    reference: Mapping[str, float],
    lags: Sequence[tuple[str, float]],
    dims: Mapping[str, Any],
    opts: FitOptions,
    shift_degC: float = float("nan"),
) -> tuple[ExtrapolationResult | None, dict[str, Any]]:
    """Return the ch. 6.6 comparison on the largest position error: in range, and beyond it when data allow."""
    W = sample.frame[list(PARAMS)].to_numpy(float)
    best, target = -1.0, None
    for ax in ("Z", "X", "Y"):
        k = PARAMS.index("d" + ax.lower())
        m = (sample.frame["axis"] == ax).to_numpy() & np.isfinite(W[:, k])
        if m.sum() > 50 and float(np.nanstd(W[m, k])) > best:
            best, target = float(np.nanstd(W[m, k])), (ax, k)
    if target is None:
        return None, {}
    ax, k = target
    raw = [c for c in channels]

    def net_inputs(s: Sample) -> pd.DataFrame:
        X = s.inputs.dT[raw].copy()
        X["position"] = s.q[:, AXES.index(ax)]
        X["direction"] = s.frame["direction"].to_numpy(float)
        return X

    m_ax = (sample.frame["axis"] == ax).to_numpy() & np.isfinite(W[:, k])
    role = sample.frame["role"].to_numpy(object)
    tr = m_ax & (role == "train")
    ho = m_ax & (role == "holdout")
    X_all = net_inputs(sample)
    net = fit_network(X_all[tr].reset_index(drop=True), W[tr, k], hidden=opts.network_hidden,
                      max_samples=opts.network_max_samples, seed=opts.seed)
    summary = {"target": f"{ax} {'d' + ax.lower()}", "network_hidden": list(opts.network_hidden)}
    net_ho = net.predict(X_all[ho].reset_index(drop=True))
    summary["network_holdout_mm"] = rmse(W[ho, k] - net_ho)
    summary["regression_holdout_mm"] = rmse(W[ho, k] - W_hat[ho, k])
    if ext_bundle is None:
        return None, summary
    ext = build_samples([ext_bundle], channels, reference, lags, 0.0)
    We = ext.frame[list(PARAMS)].to_numpy(float)
    me = (ext.frame["axis"] == ax).to_numpy() & np.isfinite(We[:, k])
    if me.sum() < 5:
        return None, summary
    ext = ext.take(me)
    reg_out = workspace_error(ext.q, predict_fits(fits, ext), dims)[:, k]
    net_out = net.predict(net_inputs(ext))
    res = extrapolation_errors(W[ho, k], W_hat[ho, k], net_ho, We[me, k], reg_out, net_out, shift_degC)
    return res, summary


# ----------------------------------------------------------------------------- documents as JSON


def result_document_json(result: FitResult) -> dict[str, Any]:
    """Return the model document of a fit as strict JSON."""
    return document_json(result.document)
