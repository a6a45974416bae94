"""ISO 230-2:2014 evaluation of bidirectional positioning runs: per-target statistics and the axis figures.

Input is a sequence of readings of one axis (target position, approach direction, deviation
``x_ij = measured - target``) in measuring order. A *run* is a maximal sequence of readings
approached from one direction; up runs (direction +1) and down runs (-1) pair in time order, and
every run must visit the same targets once each. Everything else is the standard's arithmetic,
vectorised over targets: means, estimators of the standard uncertainty (n - 1), reversal values,
repeatabilities (coverage factor 2), systematic deviations and accuracies.

Units: linear axes in mm (targets in mm); rotary axes in arcsec (targets in degrees). A bundle's
rotations are in rad; :func:`from_bundle_errors` converts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
import pandas as pd

from driftlab.errors import ValidationError
from driftlab.labels import UM

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: the axis figures of ISO 230-2:2014, in the order the report lists them
FIGURES = ("A", "A_up", "A_down", "B", "B_mean", "E", "E_up", "E_down", "M", "R", "R_up", "R_down")
#: how far the runs' mean deviations may wander, in pooled standard uncertainties, before the report warns that
#: the runs span thermal drift (noise alone moves a run's mean by about s / sqrt(targets))
DRIFT_WARNING_S = 2.0
#: the term giving each axis' positioning deviation in a bundle (eq. 4.5: the axis' own translation/rotation)
POSITIONING_TERM = {"X": "dx", "Y": "dy", "Z": "dz", "A": "alpha", "B": "beta"}
ROTARY = ("A", "B")
ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0
_TARGET_DECIMALS = 6  # targets equal to 1e-6 mm (deg) are the same target


class PositioningRunError(ValidationError):
    """Readings that do not form ISO 230-2 bidirectional runs (unpaired runs, a target missing from a run)."""


class TargetRow(TypedDict):
    """One target of the ISO 230-2 report: the mean deviations, spreads, reversal and ranges there."""

    position: float
    xbar_up: float
    xbar_down: float
    s_up: float
    s_down: float
    B: float
    xbar: float
    R_up: float
    R_down: float
    R: float


@dataclass(frozen=True)
class Iso230_2Result:
    """The ISO 230-2 statistics of one axis: per target (arrays over ``targets``) and the axis figures."""

    axis: str
    unit: str  # "mm" or "arcsec"
    targets: np.ndarray  # (m,) target positions P_j, ascending
    runs: int  # n: runs per direction
    deviations_up: np.ndarray  # (n, m) x_ij approached in +
    deviations_down: np.ndarray  # (n, m) x_ij approached in -
    xbar_up: np.ndarray
    xbar_down: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    reversal: np.ndarray  # B_j
    xbar: np.ndarray  # mean bidirectional deviation
    R_up_j: np.ndarray
    R_down_j: np.ndarray
    R_j: np.ndarray
    figures: dict[str, float]
    run_means: np.ndarray  # (n,) mean deviation of each pair of runs (up and down), in measuring order

    @property
    def drift(self) -> float:
        """Return how far the pairs of runs' mean deviations wander (max - min): thermal drift between runs."""
        return float(self.run_means.max() - self.run_means.min())

    @property
    def pooled_s(self) -> float:
        """Return the pooled unidirectional standard uncertainty over targets and directions."""
        return float(np.sqrt(np.mean(np.concatenate([self.s_up, self.s_down]) ** 2)))

    @property
    def drift_warning(self) -> str | None:
        """Return a warning when the runs wander by more than DRIFT_WARNING_S pooled uncertainties, else None."""
        if self.drift <= DRIFT_WARNING_S * self.pooled_s:
            return None
        value, unit = display(self.drift, self.unit)
        return (
            f"the runs span thermal drift: their mean deviations wander by {value} {unit}, "
            f"{self.drift / max(self.pooled_s, 1e-300):.1f} times the standard uncertainty; R and A then hold the "
            "drift, not the axis' repeatability: evaluate runs taken while the machine was thermally stable "
            "(--stage, --per-stage or --window)"
        )

    def to_json_dict(self) -> dict[str, float | list[TargetRow]]:
        """Return the report document: exactly the axis figures plus ``targets`` (one row per target)."""
        rows: list[TargetRow] = [
            {
                "position": float(p),
                "xbar_up": float(self.xbar_up[j]),
                "xbar_down": float(self.xbar_down[j]),
                "s_up": float(self.s_up[j]),
                "s_down": float(self.s_down[j]),
                "B": float(self.reversal[j]),
                "xbar": float(self.xbar[j]),
                "R_up": float(self.R_up_j[j]),
                "R_down": float(self.R_down_j[j]),
                "R": float(self.R_j[j]),
            }
            for j, p in enumerate(self.targets)
        ]
        return {**{k: float(self.figures[k]) for k in FIGURES}, "targets": rows}


def split_runs(position: np.ndarray, direction: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Return the runs of readings in measuring order: (direction, row indices) of each maximal one-direction
    sequence."""
    d = np.asarray(direction)
    if d.size == 0:
        return []
    starts = np.flatnonzero(np.r_[True, d[1:] != d[:-1]])
    ends = np.r_[starts[1:], d.size]
    return [(int(d[s]), np.arange(s, e)) for s, e in zip(starts, ends)]


def evaluate(
    position: np.ndarray, direction: np.ndarray, deviation: np.ndarray, *, axis: str = "X", unit: str = "mm"
) -> Iso230_2Result:
    """Return the ISO 230-2 result of readings in measuring order (position, direction +1/-1, deviation)."""
    pos = np.round(np.asarray(position, dtype=float), _TARGET_DECIMALS)
    dev = np.asarray(deviation, dtype=float)
    runs = split_runs(pos, np.asarray(direction))
    up = [idx for d, idx in runs if d > 0]
    down = [idx for d, idx in runs if d < 0]
    if not up or not down:
        raise PositioningRunError(f"{axis}: ISO 230-2 needs runs in both directions ({len(up)} up, {len(down)} down)")
    if len(up) != len(down):
        raise PositioningRunError(
            f"{axis}: {len(up)} up runs but {len(down)} down runs: up and down runs pair in time order"
        )
    if len(up) < 2:
        raise PositioningRunError(f"{axis}: one run per direction: the standard uncertainty needs at least two")
    targets = np.unique(pos)  # every target any run visits
    if targets.size < 2:
        raise PositioningRunError(f"{axis}: the runs visit {targets.size} target: at least two are needed")

    def table(idx_runs: list[np.ndarray], label: str) -> np.ndarray:
        out = np.empty((len(idx_runs), targets.size))
        for i, idx in enumerate(idx_runs):
            p = pos[idx]
            if p.size != targets.size or not np.array_equal(np.sort(p), targets):
                missing = sorted(set(targets.tolist()) - set(p.tolist()))
                what = f"misses target {missing[0]:g}" if missing else "visits a target twice"
                raise PositioningRunError(f"{axis}: {label} run {i + 1} {what}: every run visits the same targets once")
            out[i, np.searchsorted(targets, p)] = dev[idx]
        return out

    x_up = table(up, "up")
    x_down = table(down, "down")
    return _statistics(axis, unit, targets, x_up, x_down)


def _statistics(axis: str, unit: str, targets: np.ndarray, x_up: np.ndarray, x_down: np.ndarray) -> Iso230_2Result:
    """Return the per-target statistics and the axis figures of deviation tables (runs x targets)."""
    # ISO 230-2:2014 'mean unidirectional positional deviation at a position': xbar_j = (1/n) sum_i x_ij
    xbar_up, xbar_down = x_up.mean(axis=0), x_down.mean(axis=0)
    # 'estimator for the unidirectional standard uncertainty of positioning at a position' (n - 1 in the denominator)
    s_up, s_down = x_up.std(axis=0, ddof=1), x_down.std(axis=0, ddof=1)
    # 'reversal value at a position': B_j = xbar_j(up) - xbar_j(down)
    b_j = xbar_up - xbar_down
    # 'mean bidirectional positional deviation at a position': xbar_j = (xbar_j(up) + xbar_j(down)) / 2
    xbar = (xbar_up + xbar_down) / 2.0
    # 'unidirectional repeatability of positioning at a position': R_j = 4 s_j (coverage factor 2)
    r_up_j, r_down_j = 4.0 * s_up, 4.0 * s_down
    # 'bidirectional repeatability at a position': R_j = max(2 s_j(up) + 2 s_j(down) + |B_j|; R_j(up); R_j(down))
    r_j = np.maximum.reduce([2.0 * s_up + 2.0 * s_down + np.abs(b_j), r_up_j, r_down_j])
    both = np.concatenate([xbar_up, xbar_down])
    hi = np.concatenate([xbar_up + 2.0 * s_up, xbar_down + 2.0 * s_down])
    lo = np.concatenate([xbar_up - 2.0 * s_up, xbar_down - 2.0 * s_down])
    figures = {
        # 'bidirectional accuracy of positioning of an axis': max(xbar + 2s) - min(xbar - 2s) over both directions
        "A": float(hi.max() - lo.min()),
        # 'unidirectional accuracy of positioning of an axis'
        "A_up": float((xbar_up + 2.0 * s_up).max() - (xbar_up - 2.0 * s_up).min()),
        "A_down": float((xbar_down + 2.0 * s_down).max() - (xbar_down - 2.0 * s_down).min()),
        # 'reversal value of an axis': B = max |B_j|
        "B": float(np.abs(b_j).max()),
        # 'mean reversal value of an axis': B-bar = (1/m) sum_j B_j (signed)
        "B_mean": float(b_j.mean()),
        # 'bidirectional systematic positional deviation of an axis': max - min of both directions' means
        "E": float(both.max() - both.min()),
        # 'unidirectional systematic positional deviation of an axis'
        "E_up": float(xbar_up.max() - xbar_up.min()),
        "E_down": float(xbar_down.max() - xbar_down.min()),
        # 'mean bidirectional positional deviation of an axis': M = max xbar_j - min xbar_j
        "M": float(xbar.max() - xbar.min()),
        # 'bidirectional repeatability of positioning of an axis': R = max R_j
        "R": float(r_j.max()),
        # 'unidirectional repeatability of positioning of an axis': R = max R_j (one direction)
        "R_up": float(r_up_j.max()),
        "R_down": float(r_down_j.max()),
    }
    return Iso230_2Result(
        axis=axis,
        unit=unit,
        targets=targets,
        runs=x_up.shape[0],
        deviations_up=x_up,
        deviations_down=x_down,
        xbar_up=xbar_up,
        xbar_down=xbar_down,
        s_up=s_up,
        s_down=s_down,
        reversal=b_j,
        xbar=xbar,
        R_up_j=r_up_j,
        R_down_j=r_down_j,
        R_j=r_j,
        figures=figures,
        run_means=(x_up.mean(axis=1) + x_down.mean(axis=1)) / 2.0,
    )


def from_bundle_errors(errors: pd.DataFrame, axis: str, term: str | None = None) -> Iso230_2Result:
    """Return the ISO 230-2 result of one axis from a bundle's errors (the axis' positioning term by default)."""
    rows, scale, unit = _rows(errors, axis, term)  # measuring order; rows at one time keep the file's order
    return evaluate(
        rows["position"].to_numpy(float),
        rows["direction"].to_numpy(),
        rows["value"].to_numpy(float) * scale,
        axis=axis.upper(),
        unit=unit,
    )


@dataclass(frozen=True)
class Window:
    """The runs of one stage or time window and their ISO 230-2 result."""

    label: str
    start_s: float
    end_s: float
    result: Iso230_2Result


def _rows(errors: pd.DataFrame, axis: str, term: str | None) -> tuple[pd.DataFrame, float, str]:
    axis = axis.upper()
    if axis not in POSITIONING_TERM:
        raise ValidationError(f"axis {axis!r} is not one of {' '.join(POSITIONING_TERM)}")
    term = term or POSITIONING_TERM[axis]
    rows = errors[(errors["axis"] == axis) & (errors["term"] == term)]
    if rows.empty:
        raise ValidationError(f"the campaign has no {axis}/{term} readings")
    rows = rows.sort_values("time_s", kind="stable")
    is_rotation = term in ("alpha", "beta", "gamma")
    return rows, (ARCSEC_PER_RAD if is_rotation else 1.0), ("arcsec" if is_rotation else "mm")


def windows(
    errors: pd.DataFrame,
    axis: str,
    term: str | None = None,
    *,
    window_s: float | None = None,
    stages: list[Any] | None = None,
) -> list[Window]:
    """Return the ISO 230-2 result of the runs in each stage (``stages``) or each time window of ``window_s``.

    Whole runs are grouped by the time of their first reading; a group with fewer than two pairs of
    runs is left out. ValidationError when no group holds an evaluation."""
    rows, scale, unit = _rows(errors, axis, term)
    t = rows["time_s"].to_numpy(float)
    runs = split_runs(rows["position"].to_numpy(float), rows["direction"].to_numpy())
    groups: dict[tuple[float, float, str], list[np.ndarray]] = {}
    for _d, idx in runs:
        t0 = t[idx[0]]
        if stages is not None:
            st = next((s for s in stages if s.start_s <= t0 < s.end_s), None)
            if st is None:
                continue
            key = (float(st.start_s), float(st.end_s), str(st.name))
        else:
            assert window_s is not None and window_s > 0
            k = int((t0 - t[0]) // window_s)
            lo = t[0] + k * window_s
            key = (lo, lo + window_s, f"{(lo - t[0]) / 3600:.1f}-{(lo + window_s - t[0]) / 3600:.1f} h")
        groups.setdefault(key, []).append(idx)
    out: list[Window] = []
    for (lo, hi, label), idx_runs in sorted(groups.items()):
        idx = np.concatenate(idx_runs)
        try:
            res = evaluate(
                rows["position"].to_numpy(float)[idx],
                rows["direction"].to_numpy()[idx],
                rows["value"].to_numpy(float)[idx] * scale,
                axis=axis.upper(),
                unit=unit,
            )
        except PositioningRunError:
            continue  # fewer than two pairs of complete runs in this stage or window
        out.append(Window(label, lo, hi, res))
    if not out:
        raise ValidationError(f"no stage or window holds two pairs of complete {axis.upper()} runs")
    return out


def display(value: float, unit: str) -> tuple[str, str]:
    """Return a figure as people read it: mm shown in µm with 1 or 2 decimals, arcsec with 2; never e-notation."""
    v, u = (value * 1e3, UM) if unit == "mm" else (value, unit)
    text = f"{v:.2f}" if abs(v) < 100 else f"{v:.1f}"
    return ("0.00" if text in ("-0.00", "-0.0") else text), u


def plot(result: Iso230_2Result) -> Figure:
    """Return the standard's plot (matplotlib Figure): each run's deviations, the means and the mean +- 2s
    per direction, the figures beneath; the legend beside the plot, clear of the data."""
    # lazy: matplotlib adds 0.46 s to `import driftlab.metrology.iso230_2` (measured); only plots need it
    import matplotlib

    matplotlib.use("Agg")
    # lazy: matplotlib adds 0.46 s to `import driftlab.metrology.iso230_2` (measured); only plots need it
    import matplotlib.pyplot as plt

    scale = 1e3 if result.unit == "mm" else 1.0
    _, unit = display(0.0, result.unit)
    fig, ax = plt.subplots(figsize=(10, 5.6), layout="constrained")
    p = result.targets
    for i in range(result.runs):
        for dev, c, name in ((result.deviations_up, "tab:blue", "+"), (result.deviations_down, "tab:red", "-")):
            ax.plot(
                p, dev[i] * scale, color=c, lw=0.5, alpha=0.35, marker=".", ms=3,
                label=f"runs approached {name}" if i == 0 else None,
            )  # fmt: skip
    for mean, s, c, name in (
        (result.xbar_up, result.s_up, "tab:blue", "+"),
        (result.xbar_down, result.s_down, "tab:red", "-"),
    ):
        ax.plot(p, mean * scale, color=c, lw=2, label=f"mean {name}")
        ax.plot(p, (mean + 2 * s) * scale, color=c, lw=1, ls="--", label=f"mean {name} ± 2s")
        ax.plot(p, (mean - 2 * s) * scale, color=c, lw=1, ls="--")
    ax.plot(p, result.xbar * scale, color="black", lw=1.2, ls=":", label="mean bidirectional")
    ax.axhline(0.0, color="grey", lw=0.5)
    unit_p = "deg" if result.axis in ROTARY else "mm"
    ax.set_xlabel(f"target position {result.axis} ({unit_p})")
    ax.set_ylabel(f"positional deviation ({unit})")
    ax.set_title(f"ISO 230-2: axis {result.axis}, {result.runs} runs per direction, {p.size} targets", fontsize=11)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    f = result.figures
    names = {"B_mean": "B̄"}
    cells = [f"{names.get(k, k)} = {display(f[k], result.unit)[0]}" for k in FIGURES]
    text = "   ".join(cells[:6]) + "\n" + "   ".join(cells[6:]) + f"   ({unit})"
    ax.text(0.0, -0.16, text, transform=ax.transAxes, fontsize=9.5, family="monospace", va="top")
    return fig
