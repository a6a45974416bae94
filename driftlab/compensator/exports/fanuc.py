"""Fanuc bidirectional pitch error compensation, as a parameter tape (``N.... A1P....`` / ``N1nnnn P....``).

The control keeps one compensation point every ``No. 3624`` detection units along the axis; the
point at the reference position is ``No. 3620``. The value stored at point n is the change of
compensation over the interval from point n-1 to point n (an increment, in detection units times
the magnification ``No. 3623``), so the compensation at a position is the sum of the increments
from the reference position; with interpolation-type pitch error compensation (``No. 3605#1``) the
increment is spread linearly over its interval. The compensation at the reference position
itself is zero by construction: the model's correction there goes into the reference position
shift (``No. 1850``). Bidirectional compensation (``No. 3605#0 BDP = 1``) keeps a second set of
points for negative travel, numbered from ``No. 3626``, and ``No. 3627`` holds the difference of
the two directions at the reference position.

Increments are rounded so that their running sums stay within half a detection unit of the
correction (the rounding error never accumulates). Points are numbered from ``first_point``
(positive travel) and ``first_point + points`` (negative travel).
"""

from __future__ import annotations

import numpy as np

from driftlab.compensator.exports import Export
from driftlab.compensator.exports.grid import AxisTable
from driftlab.errors import ValidationError


def _counts(values: np.ndarray, unit: float) -> np.ndarray:
    return np.rint(values / unit).astype(np.int64)


def write(
    table: AxisTable,
    reference: float = 0.0,
    detection_unit: float = 0.0001,
    first_point: int | None = None,
    axis_number: int | None = None,
    magnification: int = 1,
) -> Export:
    """Return the parameter tape: the 36xx settings, No. 1850 and the pitch error data of both directions."""
    pos = table.positions
    k = "XYZAB".index(table.axis)
    if first_point is None:  # the axes share one point numbering: 256 points per axis, both directions
        first_point = 256 * k
        if 2 * pos.size > 256:
            raise ValidationError(f"fanuc: {pos.size} points per direction: at most 128 (use a coarser --step)")
    matches = np.flatnonzero(np.abs(pos - reference) < 1e-9 * max(1.0, abs(reference)))
    if matches.size == 0:
        raise ValidationError(
            f"fanuc: the reference position {reference:g} is not a grid point "
            f"({pos[0]:g}..{pos[-1]:g} by {table.step:g})"
        )
    ref = int(matches[0])
    unit = detection_unit * magnification
    m = pos.size
    a = f"A{axis_number or k + 1}"
    shift = _counts(np.array([table.forward[ref]]), detection_unit)[0]
    blocks = []
    for values in (table.forward, table.reverse):
        absolute = _counts(values - table.forward[ref], unit)  # counts relative to the reference position
        inc = np.zeros(m, dtype=np.int64)
        inc[1:] = np.diff(absolute)  # point n: change from point n-1 to n
        blocks.append((absolute, inc))
    if np.abs(np.concatenate([blocks[0][1], blocks[1][1]])).max(initial=0) > 32767:
        raise ValidationError("fanuc: a pitch error increment exceeds 32767 units: raise the magnification")
    neg_first = first_point + m
    rev_at_ref = int(blocks[1][0][ref])
    step_units = int(round(table.step / detection_unit))
    params = {
        "1850": int(shift),  # reference position shift: the correction at the reference position
        "3605": 3,  # bit 0 BDP: bidirectional; bit 1: interpolation type
        "3620": first_point + ref,
        "3621": first_point,
        "3622": first_point + m - 1,
        "3623": magnification,
        "3624": step_units,
        "3626": neg_first,
        "3627": rev_at_ref,
    }
    lines = ["%", f"(DRIFTLAB THERMAL COMPENSATION {table.axis} MODEL {table.model.upper()})"]
    lines += [f"N{no}{a}P{val}" for no, val in params.items()]
    lines += [f"N{10000 + first_point + i}P{int(v)}" for i, v in enumerate(blocks[0][1])]
    lines += [f"N{10000 + neg_first + i}P{int(v)}" for i, v in enumerate(blocks[1][1])]
    lines.append("%")
    settings = {
        "detection_unit": detection_unit,
        "first_point_position": float(pos[0]),
        **{f"No.{k}": v for k, v in params.items()},
    }
    return Export("fanuc", "\n".join(lines) + "\n", settings)
