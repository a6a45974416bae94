"""Siemens SINUMERIK 840D: leadscrew error compensation (LEC) and direction-dependent CEC tables.

Written as a part program that sets the compensation system variables (load it, run it once, then
set the enabling machine data and power on again, as the function manual prescribes):

* LEC (``$AA_ENC_COMP[0,N,AXn]``, ``$AA_ENC_COMP_STEP``, ``_MIN``, ``_MAX``, ``_IS_MODULO``): the
  compensation values of the first measuring system, one per interpolation point from ``_MIN`` to
  ``_MAX`` at ``_STEP``; enabled with MD32700 ``$MA_ENC_COMP_ENABLE[0] = 1``.
* CEC tables (``$AN_CEC[t,N]``, ``$AN_CEC_INPUT_AXIS``, ``$AN_CEC_OUTPUT_AXIS``, ``_STEP``, ``_MIN``,
  ``_MAX``, ``$AN_CEC_DIRECTION``, ``$AN_CEC_MULT_BY_TABLE``, ``$AN_CEC_IS_MODULO``): the axis is its own
  base (input) and compensation (output) axis; table t holds the part of the correction that
  differs between the directions, ``$AN_CEC_DIRECTION[t] = 1`` (positive travel only) and ``-1``
  (negative only); enabled with MD32710 ``$MA_CEC_ENABLE = 1`` and MD18342 ``$MN_MM_CEC_MAX_POINTS``.

Values are the axis error to cancel, as the function manual has the measured error entered: the
control corrects the actual value by them, so the machine moves by minus the value. driftlab's
correction c (added to the command) is therefore written as -c. Between points the control
interpolates linearly; beyond ``_MIN``/``_MAX`` the end value holds.
"""

from __future__ import annotations

import numpy as np

from driftlab.compensator.exports import Export
from driftlab.compensator.exports.grid import AxisTable

DECIMALS = 7


def _num(v: float) -> str:
    return f"{v:.{DECIMALS}f}"


def write(table: AxisTable, machine_axis: str | None = None, first_table: int = 0) -> Export:
    """Return the part program (LEC with the bidirectional mean, CEC tables with the direction-dependent rest)."""
    ax = machine_axis or f"AX{'XYZAB'.index(table.axis) + 1}"
    mean = (table.forward + table.reverse) / 2.0
    lo, hi, step = float(table.positions[0]), float(table.positions[-1]), table.step
    modulo = 0
    out = [
        f"; driftlab thermal compensation of {table.axis} ({ax}), model {table.model}",
        "; LEC: bidirectional mean; CEC: direction-dependent rest; values = axis error (-correction)",
    ]
    out += [f"$AA_ENC_COMP[0,{i},{ax}]={_num(-v)}" for i, v in enumerate(mean)]
    out += [
        f"$AA_ENC_COMP_STEP[0,{ax}]={_num(step)}",
        f"$AA_ENC_COMP_MIN[0,{ax}]={_num(lo)}",
        f"$AA_ENC_COMP_MAX[0,{ax}]={_num(hi)}",
        f"$AA_ENC_COMP_IS_MODULO[0,{ax}]={modulo}",
    ]
    for k, (values, direction) in enumerate(((table.forward - mean, 1), (table.reverse - mean, -1))):
        t = first_table + k
        out += [f"$AN_CEC[{t},{i}]={_num(-v)}" for i, v in enumerate(values)]
        out += [
            f"$AN_CEC_INPUT_AXIS[{t}]={ax}",
            f"$AN_CEC_OUTPUT_AXIS[{t}]={ax}",
            f"$AN_CEC_STEP[{t}]={_num(step)}",
            f"$AN_CEC_MIN[{t}]={_num(lo)}",
            f"$AN_CEC_MAX[{t}]={_num(hi)}",
            f"$AN_CEC_DIRECTION[{t}]={direction}",
            f"$AN_CEC_MULT_BY_TABLE[{t}]=0",
            f"$AN_CEC_IS_MODULO[{t}]={modulo}",
        ]
    out.append("M17")
    settings = {
        f"$MA_ENC_COMP_ENABLE[0,{ax}]": 1,
        f"$MA_CEC_ENABLE[{ax}]": 1,
        "$MN_MM_CEC_MAX_POINTS": int(np.asarray(table.positions).size),
        f"$MA_MM_ENC_COMP_MAX_POINTS[0,{ax}]": int(np.asarray(table.positions).size),
    }
    return Export("siemens-cec", "\n".join(out) + "\n", settings)
