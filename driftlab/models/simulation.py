"""Appendix A time-driven error laws and the ch. 4.5 compensation study.

Reading of the (partly garbled) appendix, decided here once:

* A1 (fixed links): ``p(t) = [0.3 + 0.7 (1 - exp(-t/tau_L))] K_L``: 0.3 of the steady value at
  t = 0, 1.0 as t -> inf. Table A.2: K_L da, db, dc in 1e-3 mm, K_L alpha, beta, gamma in 1e-6 rad.
* A2 (translational axes): ``p(x, t) = [0.3 x + 0.7 x_max (1 - exp(-t/tau_T))] K_T``: a kinematic
  part linear in the position and a thermal part that grows with time to the value at full
  travel, so at ``x = x_max`` the law goes from 0.3 to 1.0 of ``K_T x_max`` like A1. Table A.3
  (rows X, Y, Z; travels 254, 254, -254 mm, Z moves down): K_T dx in 1e-6 mm/mm, K_T alpha,
  beta, gamma in 1e-6 rad/mm. The straightness slots of eqs. 4.14-4.16 are the integrals of the
  angles over the travel (eq. 4.10), done in closed form: for X ``dy = int gamma``,
  ``dz = -int beta``; for Y ``dx = -int gamma``, ``dz = int alpha``; for Z ``dx = int beta``,
  ``dy = -int alpha``.
* A3 (rotary axes): ``p(theta, t) = [0.3 theta + 0.7 theta_max (1 - exp(-t/tau_R))] K_R``,
  table A.4 (rows theta_x, theta_y; theta_max = pi/4): K_R dx, dy, dz in 1e-3 mm/rad,
  K_R alpha, beta, gamma in 1e-6 rad/rad.
* Backlash (ch. 4.5 names it, gives no value): a reversal error of ``BACKLASH_MM`` on X, Y, Z and
  ``BACKLASH_RAD`` on A, B, half of it against the direction of motion, in the axis's own
  positioning slot. 0.005 mm is two resolution steps of a preloaded ballscrew nut; 0.005 deg for
  the gear-driven rotary table, whose backlash ch. 6 found to be its largest error.
* Resolution (ch. 4.6): commands are quantised to 0.0025 mm and 0.001 deg.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import TypedDict

import numpy as np

from driftlab.errors import ValidationError
from driftlab.metrics import rmse
from driftlab.physics import kinematics as kin
from driftlab.physics.kinematics import TABLE_A1, ElementErrors

HOUR_S = 3600.0

#: Table A.2, per link: (K alpha, K beta, K gamma) rad, (K da, K db, K dc) mm, tau_L s
TABLE_A2: Mapping[str, tuple[np.ndarray, float]] = MappingProxyType(
    {
        name: (np.array([a * 1e-6, b * 1e-6, g * 1e-6, da * 1e-3, db * 1e-3, dc * 1e-3]), tau_h * HOUR_S)
        for name, (da, db, dc, a, b, g, tau_h) in {
            "T1": (12.7, -50.8, 25.4, -10.0, -15.0, 4.9, 1.5),  # spindle head
            "T2": (-12.7, 25.4, -76.2, -24.0, -15.0, 10.0, 2.5),  # vertical column
            "T3": (-50.8, -25.4, 25.4, 4.9, 10.0, 15.0, 2.7),  # Y-X carriage
            "T4": (50.8, -38.1, 25.4, 10.0, -15.0, 20.0, 1.9),  # main table
            "T5": (-12.7, 9.6, -6.4, -10.0, -15.0, -20.0, 1.2),  # theta_x - theta_z support
            "T6": (-1.6, 1.2, -0.8, -2.5, -3.3, -5.0, 0.5),  # part table
        }.items()
    }
)

#: Table A.3, per translational joint: axis column of q, x_max mm,
#: (K alpha, K beta, K gamma) rad/mm, K dx mm/mm, tau_T s
TABLE_A3: Mapping[str, tuple[int, float, np.ndarray, float, float]] = MappingProxyType(
    {
        "phi_x": (0, 254.0, np.array([0.142e-6, 0.094e-6, 0.189e-6]), 40.0e-6, 2.8 * HOUR_S),
        "phi_y": (1, 254.0, np.array([0.213e-6, 0.220e-6, -0.252e-6]), -60.0e-6, 3.0 * HOUR_S),
        "phi_z": (2, -254.0, np.array([-0.194e-6, 0.238e-6, -0.083e-6]), -5.0e-6, 3.0 * HOUR_S),
    }
)

#: Table A.4, per rotary joint: axis column of q, theta_max rad,
#: (K alpha, K beta, K gamma) rad/rad then (K dx, K dy, K dz) mm/rad, tau_R s
TABLE_A4: Mapping[str, tuple[int, float, np.ndarray, float]] = MappingProxyType(
    {
        "theta_x": (3, np.pi / 4, np.array([12.7e-6, 19.1e-6, 25.5e-6, 32.3e-3, -24.3e-3, 16.2e-3]), 1.4 * HOUR_S),
        "theta_y": (4, np.pi / 4, np.array([13.0e-6, 19.0e-6, 25.0e-6, 8.1e-3, -6.1e-3, 4.1e-3]), 2.0 * HOUR_S),
    }
)

#: machine resolution (ch. 4.6): 0.0025 mm and 0.001 deg
RESOLUTION_MM: float = 0.0025
RESOLUTION_DEG: float = 0.001
RESOLUTION_RAD: float = float(np.deg2rad(RESOLUTION_DEG))

#: reversal errors (full width) of the linear and rotary axes; see the module docstring
BACKLASH_MM: float = 0.005
BACKLASH_RAD: float = float(np.deg2rad(0.005))

#: joint -> slot of PARAMS holding its own positioning error (eqs. 4.14-4.18)
_POSITIONING_SLOT = {"phi_x": 3, "phi_y": 4, "phi_z": 5, "theta_x": 0, "theta_y": 1}

LAWS: Mapping[str, str] = MappingProxyType(
    {**{name: "A1" for name in kin.LINKS}, **{name: "A2" for name in TABLE_A3}, **{name: "A3" for name in TABLE_A4}}
)

Factor = float | Mapping[str, float]


def warmup(t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Return the thermal growth fraction 1 - exp(-t/tau) of laws A1-A3 (0 at t = 0, 1 as t -> inf)."""
    return -np.expm1(-np.asarray(t_s, dtype=float) / tau_s)


def _factor(value: Factor, element: str) -> float:
    if isinstance(value, Mapping):
        unknown = set(value) - set(kin.ELEMENTS) - {"A1", "A2", "A3"}
        if unknown:
            raise ValidationError(f"unknown law or element {sorted(unknown)}: use A1, A2, A3 or {kin.ELEMENTS}")
        return float(value.get(element, value.get(LAWS[element], 1.0)))
    return float(value)


def _direction(direction: np.ndarray | None, n: int) -> np.ndarray:
    if direction is None:
        return np.zeros((n, 5))
    d = np.asarray(direction, dtype=float)
    try:
        d = np.broadcast_to(d, (n, 5))
    except ValueError:
        raise ValidationError(f"direction must broadcast to (N, 5) for {n} poses, got shape {d.shape}") from None
    return np.sign(d)


def appendix_a_errors(
    t_s: np.ndarray | float,
    q: np.ndarray,
    direction: np.ndarray | None = None,
    *,
    dims: Mapping[str, tuple[float, float, float]] = TABLE_A1,
    gain: Factor = 1.0,
    tau_scale: Factor = 1.0,
    backlash: bool = True,
) -> dict[str, np.ndarray]:
    """Return the (N, 6) errors of all 11 elements at times ``t_s`` and joints ``q`` (laws A1-A3).

    The arrays are column-major (each parameter contiguous), which the kinematics kernels read
    without copying.

    ``direction`` (N, 5) holds the sign of each axis's motion (0 = at rest, no backlash term).
    ``gain`` and ``tau_scale`` scale the K constants and the time constants, either one number for
    all or a mapping keyed by law ("A1", "A2", "A3") or by element name (element wins); the
    diagnosis module calibrates these against data. ``dims`` is accepted for the contract's
    signature and validated; the appendix laws give absolute values, so link lengths do not enter.
    """
    if isinstance(direction, Mapping):  # the contract's third positional argument was dims
        dims, direction = direction, None
    kin._dims_array(dims)
    q = kin._as_q(q)
    n = q.shape[0]
    t = np.broadcast_to(np.asarray(t_s, dtype=float), (n,))
    if not np.all(np.isfinite(t)) or np.any(t < 0):
        raise ValidationError("times t_s must be finite and >= 0 (s since the start of the warm-up)")
    sgn = _direction(direction, n)
    if any(_factor(tau_scale, name) <= 0 for name in kin.ELEMENTS):
        raise ValidationError("tau_scale must be > 0 (it scales the time constants of laws A1-A3)")
    out: dict[str, np.ndarray] = {}
    for name, (k, tau) in TABLE_A2.items():
        level = 0.3 + 0.7 * warmup(t, tau * _factor(tau_scale, name))  # eq. A1
        out[name] = (_factor(gain, name) * k[:, None] * level[None, :]).T
    for name, (col, x_max, k_ang, k_dx, tau) in TABLE_A3.items():
        x = q[:, col]
        w = warmup(t, tau * _factor(tau_scale, name))
        g_lin = 0.3 * x + 0.7 * x_max * w  # eq. A2
        g_int = 0.15 * x * x + 0.7 * x_max * w * x  # integral of eq. A2 over the travel 0..x
        ka, kb, kg = k_ang
        p = np.empty((n, 6), order="F")
        p[:, 0], p[:, 1], p[:, 2] = ka * g_lin, kb * g_lin, kg * g_lin
        if name == "phi_x":  # eq. 4.14: dy = int gamma dx, dz = -int beta dx
            p[:, 3], p[:, 4], p[:, 5] = k_dx * g_lin, kg * g_int, -kb * g_int
        elif name == "phi_y":  # eq. 4.15: dx = -int gamma dy, dz = int alpha dy
            p[:, 3], p[:, 4], p[:, 5] = -kg * g_int, k_dx * g_lin, ka * g_int
        else:  # eq. 4.16: dx = int beta dz, dy = -int alpha dz
            p[:, 3], p[:, 4], p[:, 5] = kb * g_int, -ka * g_int, k_dx * g_lin
        out[name] = _factor(gain, name) * p
    for name, (col, th_max, k, tau) in TABLE_A4.items():
        g = 0.3 * q[:, col] + 0.7 * th_max * warmup(t, tau * _factor(tau_scale, name))  # eq. A3
        out[name] = (_factor(gain, name) * k[:, None] * g[None, :]).T
    if backlash:
        for name, slot in _POSITIONING_SLOT.items():
            col = kin.JOINT_AXIS[name]
            b = BACKLASH_MM if col < 3 else BACKLASH_RAD
            out[name][:, slot] -= 0.5 * b * sgn[:, col]  # lost motion: the axis lags its command
    return out


def sinusoidal_program(t_s: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return (q (N, 5), direction (N, 5)) of the ch. 4.5 program: a sinusoid on every axis.

    Each axis sweeps its appendix A travel (0..x_max, 0..theta_max) with its own period (25 to
    55 min) and a seeded phase, so the five motions keep changing their combination.
    """
    rng = np.random.default_rng(seed)
    t = np.asarray(t_s, dtype=float)
    travel = np.array(
        [
            TABLE_A3["phi_x"][1],
            TABLE_A3["phi_y"][1],
            TABLE_A3["phi_z"][1],
            TABLE_A4["theta_x"][1],
            TABLE_A4["theta_y"][1],
        ]
    )
    period_s = np.array([25.0, 32.0, 39.0, 47.0, 55.0]) * 60.0
    phase = rng.uniform(0, 2 * np.pi, 5)
    arg = 2 * np.pi * t[:, None] / period_s[None, :] + phase[None, :]
    q = 0.5 * travel * (1.0 - np.cos(arg))
    direction = np.sign(travel * np.sin(arg))  # sign of dq/dt
    return q, direction


def _quantise(q: np.ndarray) -> np.ndarray:
    step = np.array([RESOLUTION_MM] * 3 + [RESOLUTION_RAD] * 2)
    return np.round(q / step) * step


class MaxAbsFigures(TypedDict):
    """The largest absolute work-space error of each component over the run."""

    dx_mm: float
    dy_mm: float
    dz_mm: float
    alpha_deg: float
    beta_deg: float


class WorkspaceFigures(TypedDict):
    """The ch. 4.5 figures of one run: maximum and RMS position, angle and roll errors."""

    max_mm: float
    rms_mm: float
    max_deg: float
    rms_deg: float
    max_roll_deg: float
    rms_roll_deg: float
    max_abs: MaxAbsFigures


class ThesisStudy(TypedDict):
    """The JSON of :func:`thesis_study`: the figures without and with compensation, and the run's settings."""

    uncompensated: WorkspaceFigures
    compensated: WorkspaceFigures
    resolution: dict[str, float]  # mm, deg
    hours: float
    samples: int
    singular_poses: int
    backlash: dict[str, float]  # mm, deg


def _figures(w: np.ndarray) -> WorkspaceFigures:
    pos = np.linalg.norm(w[:, 3:], axis=1)
    ang = np.rad2deg(np.linalg.norm(w[:, :2], axis=1))  # the reachable rotations alpha, beta
    roll = np.rad2deg(np.abs(w[:, 2]))
    absmax = np.abs(w).max(axis=0)
    return {
        "max_mm": float(pos.max()),
        "rms_mm": rmse(pos),
        "max_deg": float(ang.max()),
        "rms_deg": rmse(ang),
        "max_roll_deg": float(roll.max()),
        "rms_roll_deg": rmse(roll),
        "max_abs": {
            "dx_mm": float(absmax[3]),
            "dy_mm": float(absmax[4]),
            "dz_mm": float(absmax[5]),
            "alpha_deg": float(np.rad2deg(absmax[0])),
            "beta_deg": float(np.rad2deg(absmax[1])),
        },
    }


def _workspace(q_nominal: np.ndarray, q_cmd: np.ndarray, errors: ElementErrors) -> np.ndarray:
    """Parameters of T_real(q_cmd) @ inv(T_ideal(q_nominal)): the tool versus the part."""
    t_real = kin.machine_chain(q_cmd, errors)
    return kin.htm_to_params(t_real @ kin.htm_inverse(kin.ideal_chain(q_nominal)))


def thesis_study(hours: float = 8.0, dt_s: float = 10.0, seed: int = 0) -> ThesisStudy:
    """Return the ch. 4.5 figures (work-space error without and with compensation) as a JSON dict.

    The program is ``sinusoidal_program``; errors follow ``appendix_a_errors``. Position figures
    are the norm of W's translation (tool tip versus part), angle figures the norm of the
    reachable rotations alpha, beta; the roll about the spindle is reported on its own.
    """
    if not (np.isfinite(hours) and hours > 0):
        raise ValidationError(f"hours must be > 0, got {hours}")
    if not (np.isfinite(dt_s) and 0 < dt_s <= hours * HOUR_S):
        raise ValidationError(f"dt_s must be > 0 and no longer than the run, got {dt_s}")
    t = np.arange(0.0, hours * HOUR_S + 0.5 * dt_s, dt_s)
    q, direction = sinusoidal_program(t, seed)

    # without compensation: the nominal program at the machine's resolution
    q_plain = _quantise(q)
    w_plain = _workspace(q, q_plain, appendix_a_errors(t, q_plain, direction))

    # with compensation: the model (same laws, backlash from the known motion direction) is solved
    # for the five axis commands, angles quantised first, then translations solved and quantised
    model = appendix_a_errors(t, q, direction)
    comp = kin.compensate(q, model, resolution_mm=RESOLUTION_MM, resolution_rad=RESOLUTION_RAD)
    w_comp = _workspace(q, comp.q_cmd, appendix_a_errors(t, comp.q_cmd, direction))

    return {
        "uncompensated": _figures(w_plain),
        "compensated": _figures(w_comp),
        "resolution": {"mm": RESOLUTION_MM, "deg": RESOLUTION_DEG},
        "hours": float(hours),
        "samples": int(len(t)),
        "singular_poses": int(comp.singular.sum()),
        "backlash": {"mm": BACKLASH_MM, "deg": float(np.rad2deg(BACKLASH_RAD))},
    }
