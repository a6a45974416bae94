"""Heidenhain TNC nonlinear axis error compensation table (``*.COM``) and the backlash value.

The compensation value table lists, for datum points of the axis at equal spacing, the
compensation value the control adds to the nominal position of the axis (``NR`` the line
number, then the axis position, then ``D<axis>``); between datum points the control interpolates
linearly. The table has no direction: the difference between the approach directions (the
model's reversal, a constant along the axis for driftlab's models) goes into the axis' backlash
compensation (``CfgAxisComp/backLash``, MP710 on older TNCs), which the control splits half and
half on either side of the table value when the direction reverses. The file is activated through
the compensation assignment table (``*.CMA``) of the axis.
"""

from __future__ import annotations

import numpy as np

from driftlab.compensator.exports import Export
from driftlab.compensator.exports.grid import AxisTable


def write(table: AxisTable, name: str | None = None) -> Export:
    """Return the ``.COM`` table (bidirectional mean) and the backlash setting (mean reversal)."""
    ax = table.axis
    unit = "MM" if table.unit == "mm" else "DEG"
    fname = (name or f"{ax}.COM").upper()
    mean = (table.forward + table.reverse) / 2.0
    backlash = float(np.mean(table.forward - table.reverse))
    rows = [f"BEGIN {fname} {unit}", f"{'NR':<6}{ax:<14}D{ax}"]
    rows += [f"{i:<6}{p:<+14.4f}{v:+.6f}" for i, (p, v) in enumerate(zip(table.positions, mean))]
    rows.append("[END]")
    settings = {f"CfgAxisComp/{ax}/backLash": round(backlash, 6), "compensation assignment (*.CMA)": f"{ax}: {fname}"}
    return Export("heidenhain", "\n".join(rows) + "\n", settings)
