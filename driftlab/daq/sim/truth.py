"""The true error field of the virtual machine: link/joint errors from positions and temperatures.

Base truth (what the bundle's standard model, spec section 2, can explain exactly):

* geometric errors of each joint as small polynomials in its own coordinate (ch. 3.3), plus
  constant assembly errors of the links (squareness, offsets);
* thermal errors linear in the temperature changes of the driver channels, with the physical
  relationships of ch. 3.5 and the magnitudes of Table 6.3: column and table growth
  ``alpha_c dT L`` (eqs. 3.1, 3.3), the fixed (non-travelled) part of each ballscrew (eq. 3.2),
  spindle-arm bending from the upper/lower gradient ``alpha_c dT L / H`` and
  ``alpha_c dT L^2 / (2H)`` (eqs. 3.4, 3.5).

The work-space error is ``kinematics.workspace_error`` of the chain (eq. 4.12). To first order it is
``sum_i Ad(prefix_i) p_i``, so an angle error of an element acts through the lever of every joint to
its left, and an error right of a rotary joint is rotated by it. The base field is placed so that
no such lever turns it into a product the standard model lacks: thermal angles only in T1 (whose
prefix is constant), thermal errors right of the rotary A joint only along X (unchanged by a
rotation about X), and a linear joint's own tilts (perpendicular to its axis) at most quadratic in
its position (the lever q makes them cubic). Hence every (axis, term) is, to within ~1e-6 of the
laser noise, a cubic in position plus a linear combination of dT of ``MODEL_CHANNELS``.

Hidden effects (the spec's effect catalogue) are added on top, per (axis, term), by
``hidden_delta``; ``sensor_fault`` changes the readings only (``machine.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import lru_cache
from types import MappingProxyType
from typing import TypedDict

import numpy as np

from driftlab.daq.sim.scenario import ANGLE_TERMS, HiddenEffect
from driftlab.daq.sim.sites import CHANNELS, SITE_INDEX, structure_channels
from driftlab.daq.sim.sites import MODEL_CHANNELS as MODEL_CHANNELS  # the model channels are part of the truth's story
from driftlab.daq.sim.sites import THESIS_SELECTION as THESIS_SELECTION
from driftlab.errors import ValidationError
from driftlab.physics import kinematics as kin
from driftlab.physics.thermal import ALPHA_C
from driftlab.vocabulary import AXES, TERMS

#: travel of each axis (Table A.3: 254 mm for X, Y, Z; Table A.4: pi/4 for the rotary axes), in
#: bundle units (mm, degrees); home (0) is where the other axes sit while one is measured
AXIS_RANGE: Mapping[str, tuple[float, float]] = MappingProxyType(
    {"X": (0.0, 254.0), "Y": (0.0, 254.0), "Z": (-254.0, 0.0), "A": (-45.0, 45.0), "B": (-45.0, 45.0)}
)
ROTARY: frozenset[str] = frozenset({"A", "B"})
_JOINT_OF_AXIS = {"X": "phi_x", "Y": "phi_y", "Z": "phi_z", "A": "theta_x", "B": "theta_y"}
_SCALE = {"phi_x": 254.0, "phi_y": 254.0, "phi_z": 254.0, "theta_x": math.pi / 4, "theta_y": math.pi / 4}
_U, _M = 1e-6, 1e-3  # rad, mm


# Geometric shapes: per joint, per parameter (alpha, beta, gamma, dx, dy, dz), amplitudes of
# s, s^2, s^3 with s = q / travel (s in [-1, 1]); magnitudes of Tables A.3/A.4 (a few um, urad).
# The tilts of a linear joint perpendicular to its axis have no s^3: they act through the lever q.
def _shape(angles_urad: list[list[float]], lengths_um: list[list[float]]) -> np.ndarray:
    return np.vstack([np.array(angles_urad) * _U, np.array(lengths_um) * _M * 1e-3])


GEOMETRY: Mapping[str, np.ndarray] = MappingProxyType(
    {
        "phi_x": _shape(
            [[3.0, -2.0, 1.5], [4.0, 2.5, 0.0], [-5.0, 2.0, 0.0]],
            [[9.0, -4.0, 2.5], [1.5, 3.0, -2.0], [-2.0, 2.5, 1.2]],
        ),
        "phi_y": _shape(
            [[3.5, -1.5, 0.0], [2.0, 1.5, -1.0], [-3.0, 2.5, 0.0]],
            [[2.0, -2.5, 1.5], [7.0, 3.0, -2.0], [-1.5, 2.0, 1.0]],
        ),
        "phi_z": _shape(
            [[-4.0, 2.0, 0.0], [3.0, -1.5, 0.0], [2.0, 1.0, -1.5]],
            [[2.5, 1.5, -1.0], [-2.0, 2.5, 1.5], [-8.0, 3.5, 2.0]],
        ),
        "theta_x": _shape(
            [[12.0, -3.0, 4.0], [3.0, 2.0, -1.5], [-2.5, 1.5, 1.0]],
            [[1.5, -1.0, 0.8], [2.5, 1.5, -1.0], [-2.0, 1.0, 1.2]],
        ),
        "theta_y": _shape(
            [[2.5, -1.5, 1.0], [10.0, 3.0, -3.0], [-2.0, 1.0, 1.5]],
            [[2.0, 1.0, -1.0], [-1.5, 1.2, 0.8], [1.8, -1.0, 0.9]],
        ),
    }
)
#: constant assembly errors of the links (squareness, offsets): (alpha, beta, gamma, dx, dy, dz)
LINK_CONSTANTS: Mapping[str, np.ndarray] = MappingProxyType(
    {
        "T2": np.array([-4.0 * _U, 6.0 * _U, 0.0, 0.0, 0.0, 0.0]),
        "T3": np.array([0.0, 0.0, 3.0 * _U, 0.0, 0.0, 0.0]),
        "T4": np.array([2.0 * _U, 0.0, 0.0, 0.0, 0.0, 0.0]),
        "T5": np.array([1.0 * _U, -1.0 * _U, 0.5 * _U, 1.0 * _M, -1.0 * _M, 0.5 * _M]),
        "T6": np.array([0.5 * _U, 1.0 * _U, -0.5 * _U, 0.5 * _M, 1.0 * _M, 2.0 * _M]),
    }
)

# Dimensions for the thermal relationships (mm): the spindle head of Table A.1 (arm length L = 400,
# height H = 200: eq. 3.4 then gives Table 6.3's 0.0014 deg/degC; eq. 3.5's tip deflection plus the
# same angle acting over the 400 mm head - ch. 3.5's "additional positional error" - gives
# 0.0145 mm/degC of Z position per degC of the T34-T32 gradient, Table 6.3: 0.0103 fitted, 0.0121
# physical); column 1200 (Table A.1); ballscrew non-travelled length l of eq. 3.2; slab thicknesses.
L_ARM, H_ARM = 400.0, 200.0
L_HEAD = 400.0
L_COLUMN = 1200.0
L_BASE_Y = 600.0
L_SCREW_FIXED = 150.0
L_SPINDLE = 150.0
H_CARRIAGE = H_TABLE = H_ROTARY = 200.0
L_GEAR = 100.0
L_B_TABLE = 300.0

#: the virtual machine's geometry as a campaign states it (``machine.geometry``, docs/bundle.md): the
#: thesis machine's links (Table A.1), the arm that bends under its upper-lower gradient (eqs. 3.4-3.5,
#: alpha about X and dz at the tip) and the ballscrews' non-travelled length (eq. 3.2). The shipped
#: scenarios and plans state the same (tests/daq/sim/test_geometry_stated.py).
STATED_GEOMETRY: Mapping[str, object] = MappingProxyType(
    {
        "source": "thesis appendix A, Table A.1; ch. 3.5 (spindle arm L 400 mm, H 200 mm; ballscrews l 150 mm)",
        "alpha_c_per_degC": ALPHA_C,
        "links_mm": {
            "spindle_head": list(kin.TABLE_A1["T1"]),
            "column": list(kin.TABLE_A1["T2"]),
            "carriage": list(kin.TABLE_A1["T3"]),
            "table": list(kin.TABLE_A1["T4"]),
            "rotary_support": list(kin.TABLE_A1["T5"]),
            "part_table": list(kin.TABLE_A1["T6"]),
        },
        "screw_fixed_mm": {"X": L_SCREW_FIXED, "Y": L_SCREW_FIXED, "Z": L_SCREW_FIXED},
        "bending": {
            "spindle_arm": {
                "length_mm": L_ARM,
                "height_mm": H_ARM,
                "across": "upper-lower",
                "angle": "alpha",
                "deflection": "dz",
            }
        },
    }
)


def _mean(structure: str) -> dict[str, float]:
    chans = structure_channels(structure)
    return {c: 1.0 / len(chans) for c in chans}


_ARM_GRADIENT = {"T33": 0.5, "T34": 0.5, "T32": -0.5, "T35": -0.5}  # upper minus lower mean (T34-T32 of Table 6.3)

#: (element, parameter, coefficient, channel weights, relationship): element error += coef * sum_k w_k dT_k
#: A link that warms grows along its own vector in the chain (Table A.1, T_i = Trans(d_i) E(p_i)): its error
#: is alpha_c dT d_i (eq. 3.1), so the arm (d_y = -400), the carriage and the table (d_z = -200) grow with
#: the sign of their link vectors, as the column (d_z = +1200) does.
THERMAL_TERMS: tuple[tuple[str, str, float, Mapping[str, float], str], ...] = (
    ("T1", "alpha", ALPHA_C * L_ARM / H_ARM, _ARM_GRADIENT, "eq. 3.4: arm bending angle from its gradient"),
    ("T1", "dz", ALPHA_C * L_ARM**2 / (2 * H_ARM), _ARM_GRADIENT, "eq. 3.5: arm tip deflection"),
    ("T1", "dy", -ALPHA_C * L_HEAD, _mean("spindle_arm"), "eq. 3.1: arm growth along its length"),
    ("T1", "dz", -ALPHA_C * L_SPINDLE, {"T37": 1.0}, "eq. 3.1: spindle housing growth"),
    ("phi_z", "dz", ALPHA_C * L_SCREW_FIXED, {"T30": 1.0}, "eq. 3.2: fixed part of the Z ballscrew"),
    (
        "T2",
        "dz",
        ALPHA_C * L_COLUMN,
        {"T24": 0.5, "T26": 0.5},
        "eq. 3.3: column growth, mean of its upper-front and lower-back corners (ch. 5.4)",
    ),
    ("T2", "dy", ALPHA_C * L_BASE_Y, {"T13": 0.5, "T19": 0.5}, "eq. 3.1: base growth column-to-table, base extremes"),
    ("phi_y", "dy", ALPHA_C * L_SCREW_FIXED, {"T20": 1.0}, "eq. 3.2: fixed part of the Y ballscrew"),
    ("T3", "dz", -ALPHA_C * H_CARRIAGE, {"T7": 1.0}, "eq. 3.1: carriage thickness (T7 stands for T1-T8, ch. 5.4)"),
    (
        "phi_x",
        "dx",
        ALPHA_C * L_SCREW_FIXED,
        {"T9": 0.6, "T10": 0.4},
        "eq. 3.2: fixed part of the X ballscrew; screw temperature from nut and motor (ch. 5.4)",
    ),
    ("T4", "dz", -ALPHA_C * H_TABLE, {"T7": 1.0}, "eq. 3.1: table thickness"),
    ("theta_x", "dz", ALPHA_C * H_ROTARY, {"T42": 1.0}, "eq. 3.1: rotary base height, seen by the A drive (ch. 5.4)"),
    ("theta_x", "dy", ALPHA_C * L_GEAR, {"T42": 1.0}, "eq. 3.1: A gear housing growth"),
    ("theta_y", "dx", ALPHA_C * L_B_TABLE, {"T45": 1.0}, "eq. 3.1: B table growth along X"),
)

#: channels that drive the base truth (the thesis' selection of ch. 5.4, with all four arm corners)
DRIVERS: tuple[str, ...] = tuple(c for c in CHANNELS if any(c in w for _, _, _, w, _ in THERMAL_TERMS))
assert all(set(DRIVERS) <= set(chs) for chs in MODEL_CHANNELS.values())
_PARAM = {p: i for i, p in enumerate(kin.PARAMS)}


def _sensitivity() -> dict[str, np.ndarray]:
    """Return element -> (n_sites, 6) element error per degC of each site."""
    out: dict[str, np.ndarray] = {}
    for element, param, coef, weights, _ in THERMAL_TERMS:
        s = out.setdefault(element, np.zeros((len(CHANNELS), 6)))
        for ch, w in weights.items():
            s[SITE_INDEX[ch], _PARAM[param]] += coef * w
    return out


SENSITIVITY: Mapping[str, np.ndarray] = MappingProxyType(_sensitivity())


def axis_pose(axis: str, position: np.ndarray) -> np.ndarray:
    """Return (N, 5) joint coordinates q with ``axis`` at ``position`` (bundle units) and the others at home."""
    pos = np.asarray(position, dtype=float).ravel()
    q = np.zeros((pos.size, 5))
    k = AXES.index(axis)
    q[:, k] = np.radians(pos) if axis in ROTARY else pos
    return q


def geometric_errors(q: np.ndarray) -> dict[str, np.ndarray]:
    """Return ElementErrors of the joints' polynomial shapes at q (N, 5) plus the links' constants."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    out: dict[str, np.ndarray] = {}
    for joint, amp in GEOMETRY.items():
        s = q[:, kin.JOINT_AXIS[joint]] / _SCALE[joint]
        basis = np.stack([s, s * s, s * s * s], axis=1)  # (N, 3)
        out[joint] = basis @ amp.T  # (N, 6)
    for link, const in LINK_CONSTANTS.items():
        out[link] = np.broadcast_to(const, (len(q), 6))
    return out


def thermal_errors(dT: np.ndarray) -> dict[str, np.ndarray]:
    """Return ElementErrors driven by true temperature changes dT (N, 50) (THERMAL_TERMS)."""
    dT = np.atleast_2d(np.asarray(dT, dtype=float))
    return {element: dT @ s for element, s in SENSITIVITY.items()}


def element_errors(q: np.ndarray, dT: np.ndarray) -> dict[str, np.ndarray]:
    """Return the true ElementErrors (geometric + thermal) at poses q (N, 5) and temperature changes dT (N, 50)."""
    out = geometric_errors(q)
    for element, e in thermal_errors(dT).items():
        out[element] = out[element] + e if element in out else e
    return out


def base_workspace(axis: str, position: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """Return the (N, 6) true work-space error (no hidden effect) moving ``axis``, others at home."""
    q = axis_pose(axis, position)
    dT = np.broadcast_to(np.atleast_2d(dT), (len(q), len(CHANNELS)))
    return kin.workspace_error(q, element_errors(q, dT))


class BaseTerm(TypedDict):
    """The base truth of one (axis, term): see ``base_coefficients``."""

    poly: list[float]
    channels: dict[str, float]
    cubic_residual: float


@lru_cache(maxsize=1)
def base_coefficients() -> dict[str, dict[str, BaseTerm]]:
    """Return axis -> term -> {"poly": [c0, c1, c2, c3] in bundle units, "channels": {ch: coef per degC},
    "cubic_residual"}."""
    out: dict[str, dict[str, BaseTerm]] = {}
    n = len(CHANNELS)
    drivers = [SITE_INDEX[c] for c in DRIVERS]
    for axis in AXES:
        lo, hi = AXIS_RANGE[axis]
        pos = np.linspace(lo, hi, 61)
        geo = base_workspace(axis, pos, np.zeros(n))
        V = np.vander(pos, 4, increasing=True)
        poly, *_ = np.linalg.lstsq(V, geo, rcond=None)
        resid = np.abs(geo - V @ poly).max(axis=0)
        # per-degC work-space sensitivity of each driver, at home (the levers make it position-free)
        home = axis_pose(axis, np.zeros(len(drivers)))
        unit = np.zeros((len(drivers), n))
        unit[np.arange(len(drivers)), drivers] = 1.0
        w_unit = kin.workspace_error(home, thermal_errors(unit))
        out[axis] = {}
        for j, term in enumerate(kin.PARAMS):
            chans = {DRIVERS[i]: float(w_unit[i, j]) for i in range(len(drivers)) if w_unit[i, j] != 0.0}
            out[axis][term] = {
                "poly": [float(c) for c in poly[:, j]],
                "channels": chans,
                "cubic_residual": float(resid[j]),
            }
    return out


def lag_coefficient(effect: HiddenEffect) -> float:
    """Return the coefficient c of a thermal_lag effect: its coef_per_degC or the channel's base coefficient."""
    if "coef_per_degC" in effect.params:
        return float(effect.params["coef_per_degC"])
    ch = effect.channels[0]
    assert effect.axis is not None and effect.term is not None  # HiddenEffect: only sensor_fault has neither
    c = base_coefficients()[effect.axis][effect.term]["channels"].get(ch, 0.0)
    scale = 1e-9 if effect.term in ANGLE_TERMS else 1e-6
    if abs(c) < scale:
        raise ValidationError(
            f"hidden thermal_lag on {effect.axis}/{effect.term}: {ch} has no base coefficient on this term; "
            f"give params.coef_per_degC or choose a driving channel"
        )
    return float(c)


def hidden_delta(
    effect: HiddenEffect,
    t_s: np.ndarray,
    position: np.ndarray,
    direction: np.ndarray,
    dT: np.ndarray | None,
    lag_dT: np.ndarray | None = None,
) -> np.ndarray:
    """Return the planted work-space error of one effect on its (axis, term) (spec section 3).

    ``position`` in bundle units (mm; degrees for A/B), ``dT`` the true temperature change of the
    effect's channel since t = 0, ``lag_dT`` its first-order lag (thermal_lag only).
    """
    p = effect.params
    k = effect.kind
    t = np.asarray(t_s, dtype=float)
    if k == "reversal":  # full span between the two approach directions (3.3, 5.5)
        mag = float(p.get("magnitude_mm", p.get("magnitude_rad", 0.0)))
        return 0.5 * mag * np.asarray(direction, dtype=float)
    if k == "drift":  # slow change not explained by temperature (3.2, 6.4.3)
        return float(p["rate_per_day"]) * t / 86400.0
    if k == "sensor_fault":  # readings only: the structure keeps deforming with its true temperature
        return np.zeros_like(t)
    assert dT is not None
    if k == "screw_expansion":  # eq. 3.2: alpha * position * dT of the screw
        return float(p["coef_per_mm_degC"]) * np.asarray(position, dtype=float) * dT
    if k == "unmapped_channel":
        return float(p["coef_per_degC"]) * dT
    if k == "quadratic":
        return float(p["coef_per_degC2"]) * dT * dT
    if k == "thermal_lag":  # the body follows a lag of its thermocouple: c (lag(dT) - dT)
        assert lag_dT is not None
        return lag_coefficient(effect) * (lag_dT - dT)
    raise ValueError(f"unknown effect kind {k!r}")


def term_index(term: str) -> int:
    """Return the column of ``term`` in a (N, 6) parameter array."""
    return TERMS.index(term)
