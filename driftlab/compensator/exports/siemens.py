"""SINUMERIK 840D sl, 828D and 808D: leadscrew error compensation (LEC) and direction-dependent CEC tables.

Written as the initialisation programs the function manual shows (load them with the enabling
machine data at 0, set the machine data, power on again):

* LEC, file ``%_N_AX_EEC_INI`` (``CHANDATA(1)``, ``$AA_ENC_COMP[0,N,AXn]``, ``$AA_ENC_COMP_STEP``,
  ``_MIN``, ``_MAX``, ``_IS_MODULO``, ``M17``): one compensation value per interpolation point from
  ``_MIN`` to ``_MAX`` at ``_STEP``, linear between points, the end values held beyond them;
  enabled by MD32700 ``$MA_ENC_COMP_ENABLE[0] = 1`` once the axis is referenced.
* CEC, file ``%_N_NC_CEC_INI`` (840D sl, 828D): two tables ``$AN_CEC[t,N]`` with the axis as its own
  base and compensation axis (``$AN_CEC_INPUT_AXIS[t]=(AXn)``, ``$AN_CEC_OUTPUT_AXIS[t]=(AXn)``),
  ``$AN_CEC_DIRECTION[t] = 1`` (positive travel only) and ``-1`` (negative only), holding what differs
  between the directions; enabled by MD32710 ``$MA_CEC_ENABLE = 1`` and SD41300
  ``$SN_CEC_TABLE_ENABLE[t] = 1``, sized on the 840D sl by MD18342 ``$MN_MM_CEC_MAX_POINTS[t]``
  (the 828D has eight fixed tables of 200 points).
* 808D: no CEC; the LEC holds the positive direction and the reversal, constant along the axis for
  driftlab's models, is the backlash MD32450 ``$MA_BACKLASH[0]``.

Sign: "a positive compensation value causes the corresponding machine axis to move in the negative
direction" (LEC): the value is the axis error, so driftlab's correction c (added to the command) is
written as -c. The CEC tables are written the same way (unverified, docs/exports.md).

Sources: SINUMERIK Function Manual Extended Functions, 03/2013, 6FC5397-1BP40-3BA1, K3 section 4.4
(p. 237 interpolation, loading; p. 242 LEC example; pp. 248-249 CEC table parameters, direction;
p. 264 direction-dependent example, MD18342[0]/[1], the 828D's tables); SINUMERIK 808D Function
Manual 01/2017 p. 106 (200 points, the sign); SINUMERIK 802D sl Function Manual 11/2012,
6FC5397-1CP10-5BA0, p. 222 (``%_N_NC_CEC_INI``, ``CHANDATA(1)``, ``=(AX2)``).
"""

from __future__ import annotations

import numpy as np

from driftlab.compensator.exports.controllers import Controller, Export
from driftlab.compensator.exports.grid import AxisTable

DECIMALS = 7


def _num(v: float) -> str:
    return f"{v:.{DECIMALS}f}"


def _head(program: str, table: AxisTable, ax: str, what: str) -> list[str]:
    """Return the first lines of an initialisation program: its name, the channel, what it holds."""
    about = f"; driftlab thermal compensation of {table.axis} ({ax}), model {table.model}"
    return [program, "CHANDATA(1)", about, f"; {what}"]


def _grid(table: AxisTable, name: str, index: str) -> list[str]:
    """Return the lines that place a table on its axis: ``NAME_STEP[INDEX]``, ``_MIN``, ``_MAX``."""
    lo, hi = float(table.positions[0]), float(table.positions[-1])
    step = _num(table.step)
    return [f"{name}_STEP[{index}]={step}", f"{name}_MIN[{index}]={_num(lo)}", f"{name}_MAX[{index}]={_num(hi)}"]


def _lec(table: AxisTable, ax: str, values: np.ndarray, what: str) -> str:
    out = _head("%_N_AX_EEC_INI", table, ax, f"LEC: {what}; values = axis error (-correction), {table.unit}")
    out += [f"$AA_ENC_COMP[0,{i},{ax}]={_num(-v)}" for i, v in enumerate(values)]
    out += _grid(table, "$AA_ENC_COMP", f"0,{ax}")
    out += [f"$AA_ENC_COMP_IS_MODULO[0,{ax}]=0", "M17"]
    return "\n".join(out) + "\n"


def _cec(table: AxisTable, ax: str, parts: list[tuple[np.ndarray, int]], first_table: int) -> str:
    what = "CEC: the direction-dependent rest of the correction; values = axis error (-correction)"
    out = _head("%_N_NC_CEC_INI", table, ax, what)
    for k, (values, direction) in enumerate(parts):
        t = first_table + k
        out += [f"$AN_CEC[{t},{i}]={_num(-v)}" for i, v in enumerate(values)]
        out += [f"$AN_CEC_INPUT_AXIS[{t}]=({ax})", f"$AN_CEC_OUTPUT_AXIS[{t}]=({ax})", *_grid(table, "$AN_CEC", str(t))]
        out += [
            f"$AN_CEC_DIRECTION[{t}]={direction}",
            f"$AN_CEC_MULT_BY_TABLE[{t}]=0",
            f"$AN_CEC_IS_MODULO[{t}]=0",
        ]
    out.append("M17")
    return "\n".join(out) + "\n"


def write(table: AxisTable, ctl: Controller, machine_axis: str | None = None, first_table: int = 0) -> Export:
    """Return the LEC program (and the CEC program where the directions differ) and the machine data to set."""
    ax = machine_axis or f"AX{'XYZAB'.index(table.axis) + 1}"
    n = int(table.positions.size)
    reversal = table.reverse - table.forward
    notes: list[str] = ["load with MD32700 (and MD32710) at 0, then set them and power on again"]
    if ctl.name == "808d":
        r = table.uniform_reversal("808d", "the 808D has no direction-dependent table (use 828d or 840d-sl)")
        files = {"": _lec(table, ax, table.forward, "positive direction")}
        backlash = {
            f"MD32700 $MA_ENC_COMP_ENABLE[0,{ax}]": 1,
            f"MD32450 $MA_BACKLASH[0,{ax}]": round(r, DECIMALS),
        }
        return Export(ctl.name, files, backlash, tuple(notes))
    mean = (table.forward + table.reverse) / 2.0
    files = {"": _lec(table, ax, mean, "the mean of both directions")}
    settings: dict[str, object] = {f"MD32700 $MA_ENC_COMP_ENABLE[0,{ax}]": 1}
    if ctl.name == "840d-sl":
        settings[f"MD38000 $MA_MM_ENC_COMP_MAX_POINTS[0,{ax}]"] = n
    if np.abs(reversal).max() > 1e-9:
        files["_CEC"] = _cec(table, ax, [(table.forward - mean, 1), (table.reverse - mean, -1)], first_table)
        settings[f"MD32710 $MA_CEC_ENABLE[{ax}]"] = 1
        for t in (first_table, first_table + 1):
            if ctl.name == "840d-sl":
                settings[f"MD18342 $MN_MM_CEC_MAX_POINTS[{t}]"] = n
            settings[f"SD41300 $SN_CEC_TABLE_ENABLE[{t}]"] = 1
    else:
        notes.append("the directions do not differ: no CEC table")
    return Export(ctl.name, files, settings, tuple(notes))
