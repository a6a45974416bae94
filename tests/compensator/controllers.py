"""Test-side readers of the controller tables: each applies a table the way its controller does.

They share nothing with the writers: each parses the file text as the controller's loader would
and returns the correction (mm or deg) the controller adds to the commanded position at positions
``p`` approached in direction ``d`` (+1/-1), interpolating linearly between the table's points.
"""

from __future__ import annotations

import re

import numpy as np


def linuxcnc(text: str, p: np.ndarray, d: int) -> np.ndarray:
    """COMP_FILE_TYPE 1: 'nominal forward reverse' lines, read until the first line that is not three numbers."""
    rows = []
    for line in text.splitlines():
        parts = line.split()
        try:
            rows.append([float(x) for x in parts[:3]]) if len(parts) >= 3 else None
        except ValueError:
            break
        if len(parts) < 3:
            break
    t = np.array(rows)
    assert np.all(np.diff(t[:, 0]) > 0), "nominal positions must ascend"
    return np.interp(p, t[:, 0], t[:, 1] if d > 0 else t[:, 2])  # np.interp holds the end values


def siemens(text: str, axis: str, p: np.ndarray, d: int) -> np.ndarray:
    """LEC of the axis plus every CEC table whose input and output is the axis and whose direction matches; -sum."""
    var: dict[str, str] = {}
    for line in text.splitlines():
        m = re.match(r"^(\$[A-Z_]+)\[([^\]]*)\]=(\S+)$", line.strip())
        if m:
            var[f"{m.group(1)}[{m.group(2)}]"] = m.group(3)

    def table(prefix: str, key: str, n_key: str) -> np.ndarray:
        step = float(var[f"{prefix}_STEP[{key}]"])
        lo, hi = float(var[f"{prefix}_MIN[{key}]"]), float(var[f"{prefix}_MAX[{key}]"])
        n = int(round((hi - lo) / step)) + 1
        values = np.array([float(var[n_key.format(i=i)]) for i in range(n)])
        return np.interp(p, lo + step * np.arange(n), values)

    total = table("$AA_ENC_COMP", f"0,{axis}", "$AA_ENC_COMP[0,{i}," + axis + "]")
    tables = sorted({int(k.split("[")[1].rstrip("]")) for k in var if k.startswith("$AN_CEC_INPUT_AXIS[")})
    for t in tables:
        if var[f"$AN_CEC_INPUT_AXIS[{t}]"] != axis or var[f"$AN_CEC_OUTPUT_AXIS[{t}]"] != axis:
            continue
        direction = int(var[f"$AN_CEC_DIRECTION[{t}]"])
        if direction != 0 and direction != d:
            continue
        total = total + table("$AN_CEC", str(t), "$AN_CEC[" + str(t) + ",{i}]")
    return -total  # the values are the error the control cancels


def heidenhain(text: str, backlash: float, p: np.ndarray, d: int) -> np.ndarray:
    """A .COM table between BEGIN and [END]: position column, D<axis> column; plus half the backlash per direction."""
    lines = text.splitlines()
    assert lines[0].startswith("BEGIN ") and lines[-1] == "[END]"
    head = lines[1].split()
    assert head[0] == "NR" and head[2] == "D" + head[1]
    rows = np.array([[float(x) for x in ln.split()[1:3]] for ln in lines[2:-1]])
    return np.interp(p, rows[:, 0], rows[:, 1]) + d * backlash / 2.0


def fanuc(text: str, reference: float, detection_unit: float, p: np.ndarray, d: int, axis_no: int = 1) -> np.ndarray:
    """Parameter tape: 36xx settings and pitch error increments summed from the reference point, interpolated."""
    par: dict[int, int] = {}
    data: dict[int, int] = {}
    for line in text.splitlines():
        m = re.match(rf"^N(\d{{4}})A{axis_no}P(-?\d+)$", line)
        if m:
            par[int(m.group(1))] = int(m.group(2))
            continue
        m = re.match(r"^N(1\d{4})P(-?\d+)$", line)
        if m:
            data[int(m.group(1)) - 10000] = int(m.group(2))
    ref_no, lo_no, hi_no = par[3620], par[3621], par[3622]
    unit = detection_unit * par[3623]
    step = par[3624] * detection_unit
    first = lo_no if d > 0 else par[3626]
    m = hi_no - lo_no + 1
    inc = np.array([data[first + i] for i in range(m)], dtype=float)
    ref = ref_no - lo_no
    absolute = np.zeros(m)
    absolute[ref + 1 :] = np.cumsum(inc[ref + 1 :])  # point n holds the change from n-1 to n
    absolute[:ref] = -np.cumsum(inc[1 : ref + 1][::-1])[::-1]
    if d < 0:
        absolute = absolute + par[3627]
    positions = reference + step * (np.arange(m) - ref)
    return (np.interp(p, positions, absolute) * unit) + par[1850] * detection_unit
