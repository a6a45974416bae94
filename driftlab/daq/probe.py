"""Touch-trigger probe through the controller link, sphere centres, lobing (thesis ch. 5.6).

The probe rides in the spindle; on contact the controller latches the axis positions
and reports them over the RS-232 link (ch. 5.7), so the probe talks through the
machine link's ``PRB`` command (see :mod:`driftlab.daq.machine_link`).

* Sphere centre: each reference sphere is probed five times (ch. 5.6): once from
  above and four times around it at 45 degrees elevation.  The stylus-centre points
  lie on a sphere of radius R + r; the centre is the linear least-squares solution of
  ``|p|^2 = 2 c.p + (rho^2 - |c|^2)`` refined by geometric least squares (scipy).
* Lobing: the probe triggers after a pre-travel that depends on the approach angle
  (three-point lobing of the kinematic seat, ch. 5.6).  Probing a calibrated sphere
  round its equator measures the pre-travel delta(theta) = (R + r) - |p - c|,
  fitted as a0 + sum_k (a_k cos k theta + b_k sin k theta) over the lobing harmonics
  (3 and 6 by default); a point is compensated by stepping back delta(u) along its
  approach direction u, the harmonic part weighted by the horizontal share of u.
* Spindle angles (fig. 5.18): four proximity sensors read a reference bar in the
  spindle, two in X and two in Y at heights a known distance L apart.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from driftlab.daq.protocols import Reading, SphereMeasurement
from driftlab.daq.proximity import FLAG_OUT_OF_RANGE, ProximitySensor
from driftlab.daq.transport import LineChannel
from driftlab.errors import InstrumentError, ValidationError
from driftlab.metrics import rmse


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Return (centre, radius, rms residual) of the least-squares sphere through >= 4 points."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise ValidationError("a sphere fit needs at least four 3-D points")
    a = np.hstack([2.0 * p, np.ones((len(p), 1))])
    b = np.sum(p * p, axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    if np.linalg.matrix_rank(a) < 4:
        raise ValidationError("sphere fit is degenerate: the points are coplanar")
    c0 = sol[:3]
    r0 = math.sqrt(max(sol[3] + c0 @ c0, 0.0))

    def residual(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    res = least_squares(residual, np.append(c0, r0), method="lm")
    centre, radius = res.x[:3], float(res.x[3])
    rms = rmse(residual(res.x))
    return centre, radius, rms


def fit_circle_xy(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Return ((xc, yc), radius) of the least-squares circle through points' X, Y."""
    p = np.asarray(points, dtype=float)[:, :2]
    a = np.hstack([2.0 * p, np.ones((len(p), 1))])
    sol, *_ = np.linalg.lstsq(a, np.sum(p * p, axis=1), rcond=None)
    c = sol[:2]
    return c, math.sqrt(sol[2] + c @ c)


@dataclass(frozen=True)
class LobingMap:
    """Probe pre-travel (mm) as a function of approach direction."""

    a0: float = 0.0
    harmonics: tuple[int, ...] = ()
    cos: tuple[float, ...] = ()
    sin: tuple[float, ...] = ()

    def pretravel(self, directions: np.ndarray) -> np.ndarray:
        """Return the pre-travel (mm) for approach unit vectors of shape (N, 3)."""
        u = np.atleast_2d(np.asarray(directions, dtype=float))
        theta = np.arctan2(u[:, 1], u[:, 0])
        rho = np.hypot(u[:, 0], u[:, 1])
        h = np.zeros(len(u))
        for k, a, b in zip(self.harmonics, self.cos, self.sin, strict=True):
            h += a * np.cos(k * theta) + b * np.sin(k * theta)
        return self.a0 + rho * h

    def compensate(self, points: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Return stylus-centre points moved back along their approach by the pre-travel."""
        u = np.atleast_2d(np.asarray(directions, dtype=float))
        return np.asarray(points, dtype=float) - self.pretravel(u)[:, None] * u

    @classmethod
    def fit(cls, directions: np.ndarray, pretravel: np.ndarray, harmonics: Sequence[int] = (3, 6)) -> LobingMap:
        """Return the map fitted by least squares to measured pre-travel at horizontal approaches."""
        u = np.atleast_2d(np.asarray(directions, dtype=float))
        theta = np.arctan2(u[:, 1], u[:, 0])
        cols = [np.ones(len(u))]
        for k in harmonics:
            cols += [np.cos(k * theta), np.sin(k * theta)]
        m = np.column_stack(cols)
        if len(u) < m.shape[1]:
            raise ValidationError(f"lobing fit needs at least {m.shape[1]} approach angles")
        coef, *_ = np.linalg.lstsq(m, np.asarray(pretravel, dtype=float), rcond=None)
        return cls(float(coef[0]), tuple(harmonics), tuple(coef[1::2]), tuple(coef[2::2]))


def sphere_pattern(centre: Sequence[float], reach_mm: float, elevation_deg: float = 45.0) -> np.ndarray:
    """Return the five outward unit normals probed on a sphere: the top and four at ``elevation_deg``."""
    e = math.radians(elevation_deg)
    normals = [(0.0, 0.0, 1.0)]
    for az in (0.0, 90.0, 180.0, 270.0):
        a = math.radians(az)
        normals.append((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))
    return np.array(normals)


def _parse_hit(text: str) -> np.ndarray | None:
    if text == "MISS":
        return None
    word, rest = text.split(" ", 1)
    if word != "HIT":
        raise ValueError("not a HIT reply")
    xyz = np.array([float(v) for v in rest.split(",")])
    if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
        raise ValueError("bad HIT coordinates")
    return xyz


class TouchProbe:
    """A touch-trigger probe reporting through the controller link: a Prober."""

    def __init__(
        self,
        channel: LineChannel,
        stylus_radius_mm: float = 1.0,
        lobing: LobingMap | None = None,
        clearance_mm: float = 3.0,
        overtravel_mm: float = 3.0,
        link: Any | None = None,
    ) -> None:
        self._io = channel
        self.link = link  # when set, probing waits for the programmed motion to finish
        self.stylus_radius_mm = stylus_radius_mm
        self.lobing = lobing or LobingMap()
        self.clearance_mm = clearance_mm
        self.overtravel_mm = overtravel_mm

    @classmethod
    def on_link(cls, link: Any, **kwargs: Any) -> TouchProbe:
        """Return a probe reporting through a SerialMachineLink's channel (the controller latches the hits)."""
        return cls(link.channel, link=link, **kwargs)

    def close(self) -> None:
        """Release the channel (only when the probe owns it)."""
        self._io.close()

    def probe_point(self, start: Sequence[float], direction: Sequence[float], distance_mm: float) -> np.ndarray:
        """Return the stylus centre (mm) latched at trigger; InstrumentError if nothing is touched."""
        u = np.asarray(direction, dtype=float)
        u = u / np.linalg.norm(u)
        s = np.asarray(start, dtype=float)
        hit = self._probe_move(s, u, distance_mm)
        if hit is None:
            raise InstrumentError(
                f"probe: no trigger within {distance_mm:.3f} mm from {s[0]:.3f},{s[1]:.3f},{s[2]:.3f}"
            )
        return hit

    def _probe_move(self, start: np.ndarray, u: np.ndarray, distance_mm: float) -> np.ndarray | None:
        """Return the stylus centre latched on a probing move from ``start`` along ``u``, None without contact."""
        args = ",".join(f"{v + 0.0:.6f}" for v in (*start, *u, distance_mm))  # + 0.0: no "-0.000000"
        return self._io.query(f"PRB {args}", _parse_hit)

    def probe_points(
        self, nominal_centre: Sequence[float] | np.ndarray, radius_mm: float, normals: np.ndarray
    ) -> np.ndarray:
        """Return lobing-compensated stylus centres probed along the given outward normals."""
        c = np.asarray(nominal_centre, dtype=float)
        reach = radius_mm + self.stylus_radius_mm
        if self.link is not None:
            self.link.wait_done()
        hits, dirs = [], []
        for n in np.atleast_2d(normals):
            start = c + (reach + self.clearance_mm) * n
            hits.append(self.probe_point(start, -n, self.clearance_mm + self.overtravel_mm))
            dirs.append(-n)
        return self.lobing.compensate(np.array(hits), np.array(dirs))

    def probe_sphere(self, name: str, nominal_centre: Sequence[float], radius_mm: float) -> SphereMeasurement:
        """Return the sphere's centre from five probed points (ch. 5.6)."""
        pts = self.probe_points(nominal_centre, radius_mm, sphere_pattern(nominal_centre, radius_mm))
        centre, rho, rms = fit_sphere(pts)
        return SphereMeasurement(name, centre, rho - self.stylus_radius_mm, rms, pts)

    def calibrate_lobing(
        self,
        centre_z_mm: float,
        nominal_centre: Sequence[float],
        radius_mm: float,
        n_angles: int = 24,
        harmonics: Sequence[int] = (3, 6),
    ) -> LobingMap:
        """Probe a calibrated sphere round its equator, fit and install the lobing map; return it."""
        c = np.array([nominal_centre[0], nominal_centre[1], centre_z_mm], dtype=float)
        az = np.linspace(0.0, 2.0 * math.pi, n_angles, endpoint=False)
        normals = np.column_stack([np.cos(az), np.sin(az), np.zeros(n_angles)])
        saved, self.lobing = self.lobing, LobingMap()
        try:
            pts = self.probe_points(c, radius_mm, normals)
        finally:
            self.lobing = saved
        centre_xy, _ = fit_circle_xy(pts)
        reach = radius_mm + self.stylus_radius_mm
        pretravel = reach - np.hypot(pts[:, 0] - centre_xy[0], pts[:, 1] - centre_xy[1])
        self.lobing = LobingMap.fit(-normals, pretravel, harmonics)
        return self.lobing


def spindle_angles(gaps_mm: np.ndarray, spacing_mm: float) -> dict[str, np.ndarray]:
    """Return alpha, beta (rad) and dx, dy (mm) of the spindle bar from four sensors (fig. 5.18).

    ``gaps_mm`` is (..., 4): bar displacement seen by the X sensors at the lower and upper
    height, then the Y sensors at the lower and upper height; ``spacing_mm`` is the height
    between the two levels.  A rotation beta about Y moves the upper level by +beta*L in X,
    a rotation alpha about X moves it by -alpha*L in Y.
    """
    if spacing_mm <= 0:
        raise ValidationError("sensor spacing must be positive")
    g = np.asarray(gaps_mm, dtype=float)
    x1, x2, y1, y2 = g[..., 0], g[..., 1], g[..., 2], g[..., 3]
    return {
        "alpha": -np.arctan2(y2 - y1, spacing_mm),
        "beta": np.arctan2(x2 - x1, spacing_mm),
        "dx": x1,
        "dy": y1,
    }


def table_tilt(
    centre_a: Sequence[float], centre_b: Sequence[float], ref_a: Sequence[float], ref_b: Sequence[float]
) -> float:
    """Return the change (rad) of the table's tilt along the line of two spheres from their centres' Z drift."""
    a, b = np.asarray(centre_a, float), np.asarray(centre_b, float)
    ra, rb = np.asarray(ref_a, float), np.asarray(ref_b, float)
    run = float(np.hypot(*(rb - ra)[:2]))
    if run <= 0:
        raise ValidationError("the two spheres must be apart in X-Y")
    return math.atan2((b[2] - rb[2]) - (a[2] - ra[2]), run)


class SpindleBarMeter:
    """Four proximity sensors on a reference bar in the spindle (fig. 5.18)."""

    def __init__(self, sensors: Sequence[ProximitySensor], spacing_mm: float) -> None:
        if len(sensors) != 4:
            raise ValidationError("the spindle bar array has four sensors: X lower, X upper, Y lower, Y upper")
        self.sensors = list(sensors)
        self.spacing_mm = spacing_mm

    def read(self) -> dict[str, Reading]:
        """Return alpha, beta (rad) and dx, dy (mm); all flagged missing if a sensor is out of range."""
        readings = [s.read_displacement() for s in self.sensors]
        if not all(r.ok for r in readings):
            return {k: Reading.missing(FLAG_OUT_OF_RANGE) for k in ("alpha", "beta", "dx", "dy")}
        out = spindle_angles(np.array([r.value for r in readings]), self.spacing_mm)
        return {k: Reading(float(v)) for k, v in out.items()}
