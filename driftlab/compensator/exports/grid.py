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

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from driftlab.compensator.compensate import ErrorModel
from driftlab.errors import ValidationError
from driftlab.physics import kinematics
from driftlab.vocabulary import AXES

ROTARY = ("A", "B")


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


def grid_positions(lo: float, hi: float, step: float, reference: float | None = None) -> np.ndarray:
    """Return equally spaced positions covering [lo, hi] by ``step``, one of them at ``reference`` if given."""
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValidationError(f"the axis range {lo:g}..{hi:g} is empty")
    if not (np.isfinite(step) and step > 0):
        raise ValidationError(f"the grid step must be positive, got {step:g}")
    origin = lo if reference is None else reference
    first = origin - np.floor((origin - lo) / step + 1e-9) * step
    n = int(np.ceil((hi - first) / step - 1e-9)) + 1
    if n < 2:
        raise ValidationError(f"a step of {step:g} leaves fewer than two grid points on {lo:g}..{hi:g}")
    if n > 4096:
        raise ValidationError(f"{n} grid points: use a coarser --step (controllers hold a few hundred)")
    return np.round(first + step * np.arange(n), 9)


def correction_table(
    model: ErrorModel,
    temperatures: Mapping[str, float],
    axis: str,
    lo: float,
    hi: float,
    step: float,
    *,
    pose: tuple[float, ...] = (0.0,) * 5,
    reference: float | None = None,
) -> AxisTable:
    """Return the model's correction of ``axis`` on a grid over [lo, hi] in both approach directions."""
    axis = axis.upper()
    if axis not in AXES:
        raise ValidationError(f"axis {axis!r} is not one of {' '.join(AXES)}")
    if len(pose) != 5:
        raise ValidationError("the pose of the other axes needs five values X,Y,Z,A,B")
    pos = grid_positions(lo, hi, step, reference)
    temps = {c: float(temperatures[c]) for c in model.channels if c in temperatures} or dict(temperatures)
    missing = [c for c in model.channels if c not in temperatures]
    if missing:
        raise ValidationError(f"temperatures lack the model's channel(s) {', '.join(missing)}")
    fwd = axis_correction(model, temperatures, axis, pos, +1, pose)
    rev = axis_correction(model, temperatures, axis, pos, -1, pose)
    return AxisTable(axis, pos, fwd, rev, model.label, tuple(float(v) for v in pose), temps)


def describe(table: AxisTable) -> dict[str, Any]:
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
