"""The model's correction of one axis on a grid of that axis' positions: what every controller table holds.

A controller's axis compensation (LinuxCNC axis comp, Siemens LEC/CEC, Heidenhain nonlinear axis
error compensation, Fanuc pitch error compensation) adds to the commanded position of one axis a
value read from a table over that axis' own position, per approach direction where the format has
them. The model's correction of that axis is the axis component of the compensation solve of
eqs. 4.23-4.26 (``physics.kinematics.compensate``, the same solve the streaming compensator uses)
with the other axes at a fixed pose and the temperatures of one scan.

Units: linear axes in mm, rotary axes in degrees (the controllers' units); the correction is what
the controller adds to the command (``q_cmd - q``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from driftlab.compensator.compensate import ErrorModel
from driftlab.errors import ValidationError
from driftlab.physics import kinematics
from driftlab.vocabulary import AXES

#: the largest variation of the reversal along the axis one backlash value may stand for (mm, deg)
REVERSAL_SPREAD = 0.25e-3

ROTARY = ("A", "B")
MAX_POINTS = 4096  # no controller here holds more


@dataclass(frozen=True)
class AxisTable:
    """Correction of one axis on an equally spaced grid: forward (approached +) and reverse (approached -)."""

    axis: str
    positions: np.ndarray  # (m,) ascending, equally spaced, mm or deg
    forward: np.ndarray  # (m,) correction added to the command when moving + (mm or deg)
    reverse: np.ndarray  # (m,) ... when moving -
    model: str = "model"
    pose: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    temperatures: Mapping[str, float] = field(default_factory=dict)

    @property
    def unit(self) -> str:
        """Return "deg" for a rotary axis, else "mm"."""
        return "deg" if self.axis in ROTARY else "mm"

    @property
    def step(self) -> float:
        """Return the grid spacing (mm or deg)."""
        return float(self.positions[1] - self.positions[0])

    def uniform_reversal(self, controller: str, why: str) -> float:
        """Return the mean reversal (reverse less forward) for a controller that takes one backlash value.

        ValidationError ``CONTROLLER: ...`` (``why``: what that controller lacks, what to use) when the
        reversal varies along the axis by more than REVERSAL_SPREAD.
        """
        reversal = self.reverse - self.forward
        r = float(np.mean(reversal))
        spread = float(np.abs(reversal - r).max())
        if spread > REVERSAL_SPREAD:
            raise ValidationError(f"{controller}: the reversal varies by {spread * 1e3:.2f} um along the axis; {why}")
        return r


def axis_correction(
    model: ErrorModel,
    temperatures: Mapping[str, float],
    axis: str,
    positions: np.ndarray,
    direction: int,
    pose: tuple[float, ...] = (0.0,) * 5,
) -> np.ndarray:
    """Return the model's correction (mm or deg) of ``axis`` at ``positions`` approached in ``direction`` (+1/-1)."""
    k = AXES.index(axis)
    p = np.asarray(positions, dtype=float)
    q = np.tile(np.asarray(pose, dtype=float), (p.size, 1))
    q[:, 3:] = np.deg2rad(q[:, 3:])
    q[:, k] = np.deg2rad(p) if axis in ROTARY else p
    d = np.ones((p.size, 5))
    d[:, k] = direction
    errors = model.predict(q, temperatures, d)
    res = kinematics.compensate(q, errors, model.dims)  # eqs. 4.23-4.26: angles first, then translations
    corr = res.q_cmd[:, k] - q[:, k]
    if not np.all(np.isfinite(corr)):
        raise ValidationError("the model predicts non-finite errors for these temperatures")
    return np.rad2deg(corr) if axis in ROTARY else corr


@dataclass(frozen=True)
class Grid:
    """The table's points for one controller, and what was changed to meet its rules (said to the user)."""

    positions: np.ndarray
    notes: tuple[str, ...] = ()


def _check_range(lo: float, hi: float, step: float) -> None:
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValidationError(f"the axis range {lo:g}..{hi:g} is empty")
    if not (np.isfinite(step) and step > 0):
        raise ValidationError(f"the grid step must be positive, got {step:g}")


def grid_positions(lo: float, hi: float, step: float, max_points: int = MAX_POINTS) -> Grid:
    """Return equal intervals from exactly ``lo`` to exactly ``hi``, none longer than ``step``."""
    _check_range(lo, hi, step)
    n = max(1, int(np.ceil((hi - lo) / step - 1e-9)))
    if n + 1 > max_points:
        raise ValidationError(
            f"{n + 1} points: a table holds at most {max_points}; use --step {(hi - lo) / (max_points - 1):.6g} or more"
        )
    actual = (hi - lo) / n
    pos = lo + actual * np.arange(n + 1)
    pos[-1] = hi
    notes: tuple[str, ...] = ()
    if abs(actual - step) > 1e-9 * max(1.0, step):
        notes = (f"the step {step:g} does not divide {lo:g}..{hi:g}: {n} intervals of {actual:.6g} instead",)
    return Grid(np.round(pos, 9), notes)


def unit_grid(lo: float, hi: float, step: float, unit: float, reference: float, max_points: int = MAX_POINTS) -> Grid:
    """Return points from ``lo`` to ``hi`` an integer number of ``unit`` apart, one of them at ``reference``."""
    _check_range(lo, hi, step)
    counts = [(v - lo) / unit for v in (hi, reference)]
    if any(abs(c - round(c)) > 1e-6 for c in counts) or abs(lo / unit - round(lo / unit)) > 1e-6:
        raise ValidationError(
            f"the range {lo:g}..{hi:g} and the reference {reference:g} must be whole units of {unit:g}"
        )
    length, ref = (int(round(c)) for c in counts)
    if not 0 <= ref <= length:
        raise ValidationError(f"the reference position {reference:g} is outside {lo:g}..{hi:g}")
    g = math.gcd(length, ref)  # the interval must divide both the range and the reference's offset
    want = max(1, int(np.floor(step / unit + 1e-9)))
    d = max((k for k in _divisors(g) if k <= want), default=1)
    n = length // d + 1
    if n > max_points:
        raise ValidationError(
            f"{n} points: a table holds at most {max_points}, and the largest interval that divides "
            f"{lo:g}..{hi:g} with a point at {reference:g} and is at most {step:g} is {d * unit:g}; "
            "choose another --range or --reference"
        )
    notes: tuple[str, ...] = ()
    if d != want or abs(want * unit - step) > 1e-9 * max(1.0, step):
        notes = (f"the interval is {d * unit:g} (whole detection units, a point at the reference {reference:g})",)
    return Grid(np.round(lo + d * unit * np.arange(n), 9), notes)


def power_of_two_grid(lo: float, hi: float, step: float, unit: float = 1e-4, max_points: int = MAX_POINTS) -> Grid:
    """Return points from ``lo`` spaced by the largest 2^k x ``unit`` not above ``step``, reaching ``hi``."""
    _check_range(lo, hi, step)
    if step < unit:
        raise ValidationError(f"the grid step {step:g} is below the smallest spacing {unit:g}")
    k = int(np.floor(np.log2(step / unit) + 1e-12))
    s = unit * 2.0**k
    n = int(np.ceil((hi - lo) / s - 1e-9)) + 1
    if n > max_points:
        raise ValidationError(
            f"{n} points: a table holds at most {max_points} at a spacing of 2^{k} x {unit:g} = {s:g}; "
            "use a larger --step"
        )
    pos = np.round(lo + s * np.arange(n), 9)
    notes = [f"the spacing is 2^{k} x {unit:g} = {s:g} (the control needs a power of two)"]
    if pos[-1] > hi + 1e-9:
        notes.append(
            f"the last point lies at {pos[-1]:g}, {pos[-1] - hi:.6g} beyond the range: the axis never gets there"
        )
    return Grid(pos, tuple(notes))


def _divisors(n: int) -> list[int]:
    if n == 0:
        return []
    small = [k for k in range(1, int(math.isqrt(n)) + 1) if n % k == 0]
    return sorted(set(small + [n // k for k in small]))


def correction_table(
    model: ErrorModel,
    temperatures: Mapping[str, float],
    axis: str,
    positions: np.ndarray,
    *,
    pose: tuple[float, ...] = (0.0,) * 5,
) -> AxisTable:
    """Return the model's correction of ``axis`` at ``positions`` in both approach directions."""
    axis = axis.upper()
    if axis not in AXES:
        raise ValidationError(f"axis {axis!r} is not one of {' '.join(AXES)}")
    if len(pose) != 5:
        raise ValidationError("the pose of the other axes needs five values X,Y,Z,A,B")
    pos = np.asarray(positions, dtype=float)
    temps = {c: float(temperatures[c]) for c in model.channels if c in temperatures} or dict(temperatures)
    missing = [c for c in model.channels if c not in temperatures]
    if missing:
        raise ValidationError(f"temperatures lack the model's channel(s) {', '.join(missing)}")
    fwd = axis_correction(model, temperatures, axis, pos, +1, pose)
    rev = axis_correction(model, temperatures, axis, pos, -1, pose)
    return AxisTable(axis, pos, fwd, rev, model.label, tuple(float(v) for v in pose), temps)


#: the JSON summary of an axis table (``from`` is a keyword: the functional form)
TableSummary = TypedDict(
    "TableSummary",
    {
        "axis": str,
        "unit": str,
        "points": int,
        "step": float,
        "from": float,
        "to": float,
        "model": str,
        "max_forward": float,
        "max_reverse": float,
    },
)


def describe(table: AxisTable) -> TableSummary:
    """Return a JSON-ready summary of a table (grid, largest corrections)."""
    return {
        "axis": table.axis,
        "unit": table.unit,
        "points": int(table.positions.size),
        "step": table.step,
        "from": float(table.positions[0]),
        "to": float(table.positions[-1]),
        "model": table.model,
        "max_forward": float(np.abs(table.forward).max()),
        "max_reverse": float(np.abs(table.reverse).max()),
    }


def controller_grid(
    spacing: str,
    max_points: int,
    lo: float,
    hi: float,
    step: float,
    *,
    reference: float = 0.0,
    unit: float = 1e-4,
) -> Grid:
    """Return the points of a table over [lo, hi] that meet a controller's spacing rule and point limit."""
    if spacing == "detection-unit":
        return unit_grid(lo, hi, step, unit, reference, max_points)
    if spacing == "power-of-two":
        return power_of_two_grid(lo, hi, step, 1e-4, max_points)
    return grid_positions(lo, hi, step, max_points)
