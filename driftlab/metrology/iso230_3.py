"""ISO 230-3:2020 thermal tests evaluated from the stages of a campaign.

The three tests of the standard map onto the staged plan (thesis ch. 5.2, Fig. 5.1):

* environmental temperature variation error (ETVE, ISO 230-3 clause 5): stages with no heat source
  that do not follow a heated stage (else ``off``, else ``idle`` ones, marked ``follows_heat``); the
  machine stands still while the room temperature varies. For every
  measured point (axis, term, position, direction) the drift is the reading minus its first reading
  in the stage; the ETVE of a term is the largest range (max - min) of that drift, beside the range
  of the room temperature over the same period.
* thermal distortion caused by spindle rotation (clause 6): ``spindle`` stages; the thermal drift of
  each term over the stage, its range and its value at the end of the stage (from the stage start).
* thermal distortion caused by moving linear axes (clause 7): ``feed`` stages of a linear axis; the
  positioning deviation of the moved axis at each target over the stage: change at the two end targets
  (P1, P2) and the largest change anywhere on the axis (the thermal expansion of the axis).

Translations in mm, rotations reported in arcsec (a bundle's rad converted), times in hours.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.labels import ARCSEC, UM
from driftlab.vocabulary import LINEAR_AXES, ROTATIONS, heat_source

if TYPE_CHECKING:
    from matplotlib.figure import Figure

ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
POSITIONING_TERM = {"X": "dx", "Y": "dy", "Z": "dz"}


def _unit(term: str) -> tuple[float, str]:
    return (ARCSEC_PER_RAD, "arcsec") if term in ROTATIONS else (1.0, "mm")


@dataclass(frozen=True)
class DriftSeries:
    """The drift of one measured point over a stage: times (h from the stage start) and drift (mm or arcsec)."""

    axis: str
    term: str
    position: float
    direction: int
    unit: str
    t_h: np.ndarray
    drift: np.ndarray

    @property
    def range(self) -> float:
        """Return max - min of the drift over the stage."""
        return float(self.drift.max() - self.drift.min()) if self.drift.size else 0.0


#: the JSON form of a :class:`StageTest` (no series): stage, start_s, end_s, duration_h, figures, units,
#: room_range_degC when known, then the test's own keys (``spindle_rpm``, ``end_drift``; ``axis``,
#: ``feed_mm_min``, ``P1``, ``P2``)
StageTestRecord: TypeAlias = dict[str, object]


@dataclass(frozen=True)
class StageTest:
    """One ISO 230-3 test over one stage: the figures per term and the series behind them."""

    kind: str  # "etve", "spindle" or "linear"
    stage: str
    start_s: float
    end_s: float
    figures: dict[str, float]  # per "AXIS/term" (etve, spindle) or named figures (linear)
    units: dict[str, str]
    series: list[DriftSeries] = field(default_factory=list)
    room_range_degC: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json_dict(self) -> StageTestRecord:
        """Return the test as a JSON-ready dict (no series)."""
        out: StageTestRecord = {
            "stage": self.stage,
            "start_s": self.start_s,
            "end_s": self.end_s,
            "duration_h": (self.end_s - self.start_s) / 3600.0,
            "figures": self.figures,
            "units": self.units,
        }
        if self.room_range_degC is not None:
            out["room_range_degC"] = self.room_range_degC
        out.update(self.extra)
        return out


@dataclass(frozen=True)
class Iso230_3Result:
    """All ISO 230-3 tests found in a campaign's stages."""

    etve: list[StageTest]
    spindle: list[StageTest]
    linear: list[StageTest]

    def to_json_dict(self) -> dict[str, list[StageTestRecord]]:
        """Return ``{"etve": [...], "spindle": [...], "linear": [...]}`` (one entry per stage)."""
        return {k: [t.to_json_dict() for t in getattr(self, k)] for k in ("etve", "spindle", "linear")}


def drift_series(errors: pd.DataFrame, start_s: float, end_s: float) -> list[DriftSeries]:
    """Return the drift of every measured point (axis, term, position, direction) read within [start_s, end_s]."""
    sel = errors[(errors["time_s"] >= start_s) & (errors["time_s"] <= end_s)]
    out: list[DriftSeries] = []
    for (axis, term, pos, d), g in sel.groupby(["axis", "term", "position", "direction"], sort=True):
        if len(g) < 2:
            continue
        g = g.sort_values("time_s", kind="stable")
        scale, unit = _unit(str(term))
        v = g["value"].to_numpy(float) * scale
        # ISO 230-3 clauses 5 and 6: drift is relative to the reading at the start of the test
        out.append(
            DriftSeries(
                str(axis),
                str(term),
                float(pos),
                int(d),
                unit,
                (g["time_s"].to_numpy(float) - start_s) / 3600.0,
                v - v[0],
            )
        )
    return out


def _per_term(series: list[DriftSeries], stat: str) -> tuple[dict[str, float], dict[str, str]]:
    """Return the largest ``range`` (or |end drift|) per AXIS/term over its measured points, and the units."""
    figures: dict[str, float] = {}
    units: dict[str, str] = {}
    for s in series:
        key = f"{s.axis}/{s.term}"
        value = s.range if stat == "range" else float(abs(s.drift[-1]))
        figures[key] = max(figures.get(key, 0.0), value)
        units[key] = s.unit
    return figures, units


def etve_test(
    errors: pd.DataFrame,
    temperatures: pd.DataFrame | None,
    room_channels: list[str],
    stage: Any,
    follows_heat: bool = False,
) -> StageTest:
    """Return the ETVE of one stage without heat source: per AXIS/term the largest drift range (ISO 230-3 clause 5)."""
    series = drift_series(errors, stage.start_s, stage.end_s)
    figures, units = _per_term(series, "range")
    room = None
    if temperatures is not None and room_channels:
        t = temperatures["time_s"].to_numpy(float)
        rows = temperatures[(t >= stage.start_s) & (t <= stage.end_s)]
        if len(rows):
            mean_room = rows[room_channels].mean(axis=1, skipna=True).to_numpy(float)  # air temperature (clause 5)
            if np.isfinite(mean_room).any():
                room = float(np.nanmax(mean_room) - np.nanmin(mean_room))
    return StageTest(
        "etve", stage.name, stage.start_s, stage.end_s, figures, units, series, room, {"follows_heat": follows_heat}
    )


def spindle_test(errors: pd.DataFrame, stage: Any) -> StageTest:
    """Return the thermal distortion of one spindle stage: per AXIS/term max drift range and end drift
    (ISO 230-3 clause 6)."""
    series = drift_series(errors, stage.start_s, stage.end_s)
    figures, units = _per_term(series, "range")
    end, _ = _per_term(series, "end")
    return StageTest(
        "spindle",
        stage.name,
        stage.start_s,
        stage.end_s,
        figures,
        units,
        series,
        extra={"spindle_rpm": stage.spindle_rpm, "end_drift": end},
    )


def linear_test(errors: pd.DataFrame, stage: Any) -> StageTest | None:
    """Return the thermal distortion of one feed stage of a linear axis (ISO 230-3 clause 7), None if it was
    not measured."""
    axis = stage.axis
    term = POSITIONING_TERM[axis]
    series = [
        s for s in drift_series(errors[(errors["axis"] == axis) & (errors["term"] == term)], stage.start_s, stage.end_s)
    ]
    if not series:
        return None
    positions = sorted({s.position for s in series})
    p1, p2 = positions[0], positions[-1]

    def at(p: float) -> float:
        return max(s.range for s in series if s.position == p)

    figures = {
        # change of the positioning deviation at the two end targets over the test (ISO 230-3 clause 7, P1 and P2)
        "drift_P1": at(p1),
        "drift_P2": at(p2),
        # the largest change anywhere on the measured length: the axis' thermal expansion and drift together
        "drift_max": max(s.range for s in series),
    }
    return StageTest(
        "linear",
        stage.name,
        stage.start_s,
        stage.end_s,
        figures,
        {k: "mm" for k in figures},
        series,
        extra={"axis": axis, "feed_mm_min": stage.feed_mm_min, "P1": p1, "P2": p2},
    )


def evaluate_bundle(bundle: Any) -> Iso230_3Result:
    """Return every ISO 230-3 test the campaign's stages hold (ValidationError when there is none)."""
    stages = list(bundle.meta.stages)
    if not stages:
        raise ValidationError(f"{bundle.name}: campaign.json has no stages: ISO 230-3 tests are evaluated per stage")
    errors = bundle.errors
    # the daemon's and the simulator's words, and both spellings of stored campaigns (vocabulary.heat_source)
    heat = {id(s): heat_source(s.heat_source) for s in stages}
    # ETVE (clause 5): stages without heat source, preferably not right after a heated one (a cool-down's
    # drift is the machine's own heat leaving); else the power-off stages, else the idle ones, marked so
    ordered = sorted(stages, key=lambda s: s.start_s)
    after_heat = {id(s): i > 0 and heat[id(ordered[i - 1])] not in ("off", "idle") for i, s in enumerate(ordered)}
    rest = [s for s in ordered if heat[id(s)] in ("off", "idle")]
    off = (
        [s for s in rest if not after_heat[id(s)]]
        or [s for s in rest if heat[id(s)] == "off"]
        or [s for s in rest if heat[id(s)] == "idle"]
    )
    etve = [etve_test(errors, bundle.temperatures, list(bundle.meta.room_channels), s, after_heat[id(s)]) for s in off]
    spindle = [spindle_test(errors, s) for s in stages if heat[id(s)] == "spindle"]
    linear = [
        t
        for s in stages
        if heat[id(s)] == "feed" and s.axis in LINEAR_AXES
        for t in [linear_test(errors, s)]
        if t is not None
    ]
    etve = [t for t in etve if t.series]
    spindle = [t for t in spindle if t.series]
    if not (etve or spindle or linear):
        raise ValidationError(
            f"{bundle.name}: no stage with readings is an ISO 230-3 test (no heat source, "
            "spindle, or feed of a linear axis)"
        )
    return Iso230_3Result(etve, spindle, linear)


def plot(test: StageTest) -> Figure:
    """Return the test's plot (matplotlib Figure): drift against time per term (ETVE, spindle) or per target
    (linear); lengths in µm and angles in arcsec on panels of their own, one unit per axis."""
    # lazy: matplotlib adds 0.40 s to `import driftlab.metrology.iso230_3` (measured); only plots need it
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib adds 0.40 s to `import driftlab.metrology.iso230_3` (measured); only plots need it
    import matplotlib.pyplot as plt

    if test.kind == "linear":
        fig, ax = plt.subplots(figsize=(9, 4.6), layout="constrained")
        p1, p2 = test.extra["P1"], test.extra["P2"]
        for s in test.series:
            if s.position in (p1, p2):
                ax.plot(
                    s.t_h, s.drift * 1e3, label=f"{s.axis} at {s.position:g} mm ({'+' if s.direction > 0 else '-'})"
                )
        ax.set_ylabel(f"change of positioning deviation ({UM})")
        ax.set_title(
            f"ISO 230-3 linear motion: {test.stage}, axis {test.extra['axis']} at {test.extra['feed_mm_min']:g} mm/min",
            fontsize=10,
        )
        axes = [ax]
    else:
        lengths = sorted((k for k in test.figures if test.units[k] == "mm"), key=lambda k: -test.figures[k])[:6]
        angles = sorted((k for k in test.figures if test.units[k] != "mm"), key=lambda k: -test.figures[k])[:6]
        panels = [(keys, unit) for keys, unit in ((lengths, UM), (angles, ARCSEC)) if keys]
        fig, axs = plt.subplots(len(panels), 1, figsize=(9, 3.0 + 2.4 * len(panels)), sharex=True, layout="constrained")
        axes = list(np.atleast_1d(axs))
        for ax, (keys, unit) in zip(axes, panels):
            for key in keys:
                axis, term = key.split("/")
                best = max((s for s in test.series if s.axis == axis and s.term == term), key=lambda s: s.range)
                scale = 1e3 if best.unit == "mm" else 1.0
                ax.plot(best.t_h, best.drift * scale, label=f"{key} at {best.position:g}")
            ax.set_ylabel(f"drift ({unit})")
        what = "ETVE" if test.kind == "etve" else "spindle rotation"
        axes[0].set_title(
            f"ISO 230-3 {what}: {test.stage}"
            + (f", room range {test.room_range_degC:.2f} °C" if test.room_range_degC is not None else ""),
            fontsize=10,
        )
    for ax in axes:
        ax.axhline(0.0, color="grey", lw=0.5)
        # the legend beside the plot, never over the data
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    axes[-1].set_xlabel("time from the stage start (h)")
    return fig
