"""HEIDENHAIN TNC nonlinear axis error compensation tables (``*.COM``), per generation.

* ``tnc640`` (the 620 generation: TNC 640/620, MANUALplus 620): columns ``NR``, ``AXISPOS`` (the
  compensation points, from the machine datum), a column named after the axis (the compensation
  value of the positive direction) and ``BACKLASH`` ("the compensation values measured in the
  negative direction of traverse"): both directions live in the table; the control interpolates
  linearly between points. The axis' ``backLash`` machine parameter is left as it is.
* ``tnc426`` (TNC 426/430 and the 407/415/425 before them): columns ``NR``, the axis (the points)
  and ``D<axis>``; at most 256 entries, the points a power of two apart; activated through MP730.
  The table holds the positive direction, and the reversal, constant along the axis for driftlab's
  models, goes into the backlash MP710, which "the TNC adds to or subtracts from the encoder signal
  after a reversal": the full value at every reversal, not half on either side.

Each table is assigned to its axis in the compensation assignment table (``*.CMA``). The value is
what the control adds to the nominal position, i.e. driftlab's correction (sign: docs/exports.md).

Sources: HEIDENHAIN Technical Manual MANUALplus 620, January 2012, section 6.10.3 (pp. 713-718:
the columns, the CMA table) and p. 708 (backlash added at every reversal); Technical Manual TNC
426/430, section 6.4.1 (p. 6-36, MP710); Technical Manual TNC 407/415/425, 01.98, section 1.6.4
(p. 4-28: power-of-two spacing, 2^16 = 6.5536 mm) and module 9095 (error 3: more than 256 entries).
"""

from __future__ import annotations

from driftlab.compensator.exports.controllers import Controller, Export
from driftlab.compensator.exports.grid import AxisTable


def write(table: AxisTable, ctl: Controller, name: str | None = None) -> Export:
    """Return the ``.COM`` table of the generation and the settings that go with it."""
    ax = table.axis
    unit = "MM" if table.unit == "mm" else "DEG"
    fname = (name or f"{ax}.COM").upper()
    cma = {"compensation assignment (*.CMA)": f"column {ax}: {fname}, ACTIVE *"}
    if ctl.name == "tnc640":
        rows = [f"BEGIN {fname} {unit}", f"{'NR':<6}{'AXISPOS':<14}{ax:<14}BACKLASH"]
        rows += [
            f"{i:<6}{p:<+14.4f}{f:<+14.6f}{r:+.6f}"
            for i, (p, f, r) in enumerate(zip(table.positions, table.forward, table.reverse))
        ]
        rows.append("[END]")
        return Export(ctl.name, {"": "\n".join(rows) + "\n"}, cma)
    r = table.uniform_reversal(ctl.name, "one backlash value cannot hold it (use tnc640)")
    rows = [f"BEGIN {fname} {unit}", f"{'NR':<6}{ax:<14}D{ax}"]
    rows += [f"{i:<6}{p:<+14.4f}{v:+.6f}" for i, (p, v) in enumerate(zip(table.positions, table.forward))]
    rows.append("[END]")
    k = "XYZAB".index(ax)
    # positive backlash: the encoder leads the table, which travels too short after a reversal; the
    # negative direction's correction is the positive one minus the backlash
    settings = {f"MP710.{k}": round(-r, 6), f"MP730 bit {k}": 1, **cma}
    return Export(ctl.name, {"": "\n".join(rows) + "\n"}, settings)
