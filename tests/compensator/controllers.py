"""Test-side loaders of the controller tables, each written from its controller's manual or source.

They share nothing with the writers: each parses the file text as the controller's loader does,
refuses what the controller refuses (too many points, a malformed header, an uneven spacing), and
returns the correction (mm or deg) the controller adds to the commanded position at positions ``p``
travelled in direction ``d`` (+1/-1). Sources: docs/exports.md.
"""

from __future__ import annotations

import re

import numpy as np


class Refused(Exception):
    """The controller would not load this file."""


def _linear(x: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Linear between points, the end values held beyond them (every manual here says so)."""
    i = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, xs.size - 2)
    t = np.clip((x - xs[i]) / (xs[i + 1] - xs[i]), 0.0, 1.0)
    return ys[i] + t * (ys[i + 1] - ys[i])


# --- LinuxCNC: src/emc/motion/usrmotintf.cc usrmotLoadComp, command.c EMCMOT_SET_JOINT_COMP, control.c


def linuxcnc(text: str, p: np.ndarray, d: int) -> np.ndarray:
    """COMP_FILE_TYPE 1: sscanf "%lf %lf %lf" per line until one fails; at most 256 ascending entries."""
    rows: list[tuple[float, float, float]] = []
    for line in text.splitlines():
        m = re.match(r"^\s*([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+([-+0-9.eE]+)", line)
        if not m:
            break
        try:
            rows.append((float(m.group(1)), float(m.group(2)), float(m.group(3))))
        except ValueError:
            break
        if len(rows) > 256:  # EMCMOT_COMP_SIZE: "too many compensation entries"
            raise Refused("linuxcnc: more than 256 entries")
        if len(rows) > 1 and rows[-1][0] <= rows[-2][0]:
            raise Refused("linuxcnc: compensation values must increase")
    t = np.array(rows)
    return _linear(p, t[:, 0], t[:, 1] if d > 0 else t[:, 2])


# --- SINUMERIK: Function Manual Extended Functions 03/2013 K3 4.4; 808D FM 01/2017 p. 106


def _siemens_vars(text: str, header: str) -> dict[str, str]:
    lines = [ln.split(";", 1)[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if lines[0] != header or lines[1] != "CHANDATA(1)" or lines[-1] != "M17":
        raise Refused(f"siemens: not a {header} program with CHANDATA(1) ... M17")
    out: dict[str, str] = {}
    for ln in lines[2:-1]:
        m = re.match(r"^\$([A-Z_]+)\[([^\]]+)\]=(\S+)$", ln)
        if not m:
            raise Refused(f"siemens: cannot read {ln!r}")
        out[f"{m.group(1)}[{m.group(2)}]"] = m.group(3)
    return out


def _siemens_table(var: dict[str, str], prefix: str, key: str, value_key, limit: int, p: np.ndarray) -> np.ndarray:
    step = float(var[f"{prefix}_STEP[{key}]"])
    lo, hi = float(var[f"{prefix}_MIN[{key}]"]), float(var[f"{prefix}_MAX[{key}]"])
    k = (hi - lo) / step
    if abs(k - round(k)) > 1e-6:
        raise Refused("siemens: MAX - MIN is not a whole number of STEPs")
    n = int(round(k)) + 1
    if n > limit:
        raise Refused(f"siemens: {n} interpolation points, at most {limit}")
    values = np.array([float(var[value_key(i)]) for i in range(n)])
    return _linear(p, lo + step * np.arange(n), values)


def siemens(files: dict[str, str], settings: dict, axis: str, generation: str, p: np.ndarray, d: int) -> np.ndarray:
    """LEC of the axis, plus the CEC tables of the axis whose direction matches; the axis moves by -sum."""
    limit = {"808d": 200, "828d": 200}.get(generation, 10**6)
    lec = _siemens_vars(files[""], "%_N_AX_EEC_INI")
    total = _siemens_table(lec, "AA_ENC_COMP", f"0,{axis}", lambda i: f"AA_ENC_COMP[0,{i},{axis}]", limit, p)
    if "_CEC" in files:
        if generation == "808d":
            raise Refused("808d: no CEC")
        cec = _siemens_vars(files["_CEC"], "%_N_NC_CEC_INI")
        tables = sorted({int(k.split("[")[1].rstrip("]")) for k in cec if k.startswith("AN_CEC_INPUT_AXIS[")})
        for t in tables:
            if cec[f"AN_CEC_INPUT_AXIS[{t}]"] != f"({axis})" or cec[f"AN_CEC_OUTPUT_AXIS[{t}]"] != f"({axis})":
                continue
            direction = int(cec[f"AN_CEC_DIRECTION[{t}]"])
            if direction not in (0, d):
                continue
            total = total + _siemens_table(cec, "AN_CEC", str(t), lambda i, t=t: f"AN_CEC[{t},{i}]", limit, p)
    correction = -total  # "a positive compensation value causes the axis to move in the negative direction"
    if generation == "808d" and d < 0:
        correction = correction + float(settings[f"MD32450 $MA_BACKLASH[0,{axis}]"])
    return correction


# --- HEIDENHAIN: MANUALplus 620 TM 01/2012 6.10.3; TNC 426/430 TM 6.4.1; TNC 407/415/425 TM 01.98 1.6.4


def heidenhain(text: str, settings: dict, generation: str, p: np.ndarray, d: int) -> np.ndarray:
    """A .COM table between BEGIN and [END], its columns read by name; tnc426 plus MP710 after a reversal."""
    lines = text.splitlines()
    head = lines[0].split()
    if head[0] != "BEGIN" or not head[1].endswith(".COM") or head[2] not in ("MM", "DEG") or lines[-1] != "[END]":
        raise Refused("heidenhain: not a BEGIN <name>.COM MM|DEG ... [END] table")
    cols = lines[1].split()
    rows = np.array([[float(x) for x in ln.split()] for ln in lines[2:-1]])
    col = {c: rows[:, i] for i, c in enumerate(cols)}
    if not np.array_equal(col["NR"], np.arange(rows.shape[0])):
        raise Refused("heidenhain: NR must count from 0")
    if generation == "tnc640":
        axis = [c for c in cols if c not in ("NR", "AXISPOS", "BACKLASH")]
        if cols[:2] != ["NR", "AXISPOS"] or len(axis) != 1:
            raise Refused("heidenhain 620: columns NR, AXISPOS, <axis>[, BACKLASH]")
        values = col["BACKLASH"] if d < 0 and "BACKLASH" in col else col[axis[0]]
        return _linear(p, col["AXISPOS"], values)
    axis = cols[1]
    if cols != ["NR", axis, "D" + axis]:
        raise Refused("heidenhain 426: columns NR, <axis>, D<axis>")
    pos = col[axis]
    if pos.size > 256:
        raise Refused("heidenhain 426: more than 256 entries (module 9095 error 3)")
    spacing = np.diff(pos) / 1e-4  # in 0.1 um: 2^16 = 6.5536 mm
    k = np.log2(spacing[0])
    if abs(k - round(k)) > 1e-6 or np.abs(spacing - spacing[0]).max() > 1e-3:
        raise Refused("heidenhain 426: the points must be a power of two apart")
    values = _linear(p, pos, col["D" + axis])
    index = "XYZAB".index(axis)
    # positive backlash (MP710): the table travels too short after a reversal, the control adds it
    return values - (settings[f"MP710.{index}"] if d < 0 else 0.0)


# --- FANUC: 0i-F / 30i-B parameter manuals, 1850, 3605, 3620-3627; tape format


def fanuc(
    text: str, reference: float, detection_unit: float, p: np.ndarray, d: int, axis_no: int, ref_return: int = 1
) -> np.ndarray:
    """Parameter tape: increments summed from the reference point per direction set; the direction of
    reference position return is zero there, the other starts at No. 3627; plus the No. 1850 shift."""
    lines = text.splitlines()
    if lines[0] != "%" or lines[-1] != "%":
        raise Refused("fanuc: a tape begins and ends with %")
    par: dict[int, str] = {}
    data: dict[int, int] = {}
    for line in lines[1:-1]:
        m = re.match(rf"^N(\d{{4}})A{axis_no}P(-?\d+)$", line)
        if m:
            par[int(m.group(1))] = m.group(2)
            continue
        m = re.match(r"^N1(\d{4})P(-?\d+)$", line)
        if not m:
            raise Refused(f"fanuc: cannot read {line!r}")
        if int(m.group(1)) > 1023:
            raise Refused("fanuc: compensation point numbers run 0..1023")
        data[int(m.group(1))] = int(m.group(2))
    bits = par[3605]
    if not re.fullmatch(r"[01]{8}", bits):
        raise Refused("fanuc: a bit parameter is eight binary digits")
    if bits[-1] != "1" or bits[-2] != "1":  # bit 0 BDP, bit 1 interpolation type (bit 7 written first)
        raise Refused("fanuc: bidirectional interpolation-type compensation is not enabled")
    n_ref, n_lo, n_hi = (int(par[k]) for k in (3620, 3621, 3622))
    mag, interval, n_neg, opposite = (int(par[k]) for k in (3623, 3624, 3626, 3627))
    m = n_hi - n_lo + 1
    first = n_lo if d > 0 else n_neg
    inc = np.array([data[first + i] for i in range(m)], dtype=float)
    i_ref = n_ref - n_lo
    absolute = np.zeros(m)
    absolute[i_ref + 1 :] = np.cumsum(inc[i_ref + 1 :])  # point n holds the change from n-1 to n
    absolute[:i_ref] = -np.cumsum(inc[1 : i_ref + 1][::-1])[::-1]
    if d != ref_return:
        absolute = absolute + opposite
    positions = reference + interval * detection_unit * (np.arange(m) - i_ref)
    return _linear(p, positions, absolute * detection_unit * mag) + int(par[1850]) * detection_unit
