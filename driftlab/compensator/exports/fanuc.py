"""FANUC Series 0i / 30i bidirectional, interpolation-type pitch error compensation as a parameter tape.

The control keeps one compensation point every ``No. 3624`` detection units along the axis; the
point at the reference position is ``No. 3620``. The value stored at point n is the change of
compensation over the interval from point n-1 to point n (an increment, in detection units times
the magnification ``No. 3623``), so the compensation at a position is the sum of the increments
from the reference position; with interpolation-type compensation (``No. 3605#1``) each increment
is spread linearly over its interval. Bidirectional compensation (``No. 3605#0 BDP``) keeps a
second set of points for negative travel from ``No. 3626``. At the reference position the
compensation in the direction of reference position return is zero by construction, and
``No. 3627`` holds the value there for movement in the opposite direction. The model's correction
at the reference position goes into the reference position shift ``No. 1850`` (enabled by
``No. 1002#2 SFD``, effective after the next reference position return).

Tape format: ``%``, one ``N<no>A<axis>P<value>`` per axis parameter, bit parameters as eight binary
digits (bit 7 first), pitch error data as ``N1<point>P<value>``, ``%``. Increments are rounded so
that their running sums stay within half a detection unit of the correction. Point numbers run
0..1023 for all axes and both directions together; by default axis k (X=0 ... B=4) uses 204 of
them from 204 k.

Sources: FANUC Series 0i-MODEL F Parameter Manual (B-64610EN) and Series 30i/31i/32i-MODEL B
Parameter Manual (B-64490EN), parameters 1002, 1850, 1851, 1852, 3605, 3620-3627 and the tape
format of section 3 (edition and page not checked here: docs/exports.md lists this as unverified).
"""

from __future__ import annotations

import numpy as np

from driftlab.compensator.exports.controllers import Controller, Export
from driftlab.compensator.exports.grid import AxisTable
from driftlab.errors import ValidationError

POINTS_PER_AXIS = 204  # 1024 point numbers over five axes
LAST_POINT = 1023
MAX_INCREMENT = 32767


def _counts(values: np.ndarray, unit: float) -> np.ndarray:
    return np.rint(values / unit).astype(np.int64)


def write(
    table: AxisTable,
    ctl: Controller,
    reference: float = 0.0,
    detection_unit: float = 0.0001,
    first_point: int | None = None,
    axis_number: int | None = None,
    magnification: int = 1,
    reference_return: int = 1,
) -> Export:
    """Return the parameter tape: No. 1850, the 36xx settings and the pitch error data of both directions."""
    pos = table.positions
    k = "XYZAB".index(table.axis)
    m = pos.size
    if first_point is None:
        first_point = POINTS_PER_AXIS * k
        if 2 * m > POINTS_PER_AXIS:
            raise ValidationError(
                f"{ctl.name}: {m} points per direction; with the default numbering an axis has "
                f"{POINTS_PER_AXIS // 2} per direction (use a coarser --step)"
            )
    if first_point < 0 or first_point + 2 * m - 1 > LAST_POINT:
        raise ValidationError(
            f"{ctl.name}: points {first_point}..{first_point + 2 * m - 1} exceed the numbers 0..{LAST_POINT}"
        )
    if reference_return not in (1, -1):
        raise ValidationError("the reference position return direction is +1 or -1")
    matches = np.flatnonzero(np.abs(pos - reference) < 1e-9 * max(1.0, abs(reference)))
    if matches.size == 0:
        raise ValidationError(
            f"{ctl.name}: the reference position {reference:g} is not a grid point ({pos[0]:g}..{pos[-1]:g})"
        )
    ref = int(matches[0])
    unit = detection_unit * magnification
    a = f"A{axis_number or k + 1}"
    base = table.forward if reference_return > 0 else table.reverse  # zero at the reference by construction
    shift = int(_counts(np.array([base[ref]]), detection_unit)[0])
    sets = []
    for values in (table.forward, table.reverse):
        absolute = _counts(values - base[ref], unit)  # relative to the reference position
        inc = np.zeros(m, dtype=np.int64)
        inc[1:] = np.diff(absolute)  # point n: change from point n-1 to n
        sets.append((absolute, inc))
    if np.abs(np.concatenate([sets[0][1], sets[1][1]])).max(initial=0) > MAX_INCREMENT:
        raise ValidationError(
            f"{ctl.name}: a pitch error increment exceeds {MAX_INCREMENT} units: raise the magnification"
        )
    neg_first = first_point + m
    opposite = sets[1] if reference_return > 0 else sets[0]
    lines = ["%", f"N1850{a}P{shift}"]
    lines.append(f"N3605{a}P{0b11:08b}")  # bit 0 BDP bidirectional, bit 1 interpolation type
    params = {
        "3620": first_point + ref,
        "3621": first_point,
        "3622": first_point + m - 1,
        "3623": magnification,
        "3624": int(round(table.step / detection_unit)),
        "3626": neg_first,
        "3627": int(opposite[0][ref]),
    }
    lines += [f"N{no}{a}P{val}" for no, val in params.items()]
    lines += [f"N{10000 + first_point + i}P{int(v)}" for i, v in enumerate(sets[0][1])]
    lines += [f"N{10000 + neg_first + i}P{int(v)}" for i, v in enumerate(sets[1][1])]
    lines.append("%")
    settings = {
        "No.1002#2 SFD": "1 (reference position shift used; takes effect after a reference position return)",
        "No.1850": shift,
        "No.3605": f"{0b11:08b}",
        **{f"No.{no}": v for no, v in params.items()},
        "No.1851/1852": "unchanged: the two direction sets hold the model's reversal",
        "reference position return": "+" if reference_return > 0 else "-",
        "detection unit": detection_unit,
    }
    return Export(ctl.name, {"": "\n".join(lines) + "\n"}, settings)
