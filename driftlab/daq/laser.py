"""Laser interferometer over GPIB via pyvisa (thesis ch. 5.5, table 5.3, ch. 5.6 beam breaks).

Physics
-------
* Air refractive index: Edlen's equation in the revised form of Birch & Downs,
  Metrologia 30 (1993) 155 and the correction Metrologia 31 (1994) 315 (eqs. in
  :func:`air_refractive_index`); water-vapour saturation pressure from Davis,
  Metrologia 29 (1992) 67 (CIPM-81/91).
* The head counts fringes of the vacuum wavelength; a double-pass optic changes the
  optical path by 2 n d, so d = N lambda_vac / (2 n).  Straightness optics divide
  the lateral motion by the optics factor, angle optics turn a path difference over
  the reflector spacing into an angle (asin).  Each point is the mean of ten readings
  taken after the axis has settled (ch. 5.5).
* A broken beam (low signal or an error reply) flags the sample and marks the
  reference lost: the head's count is no longer tied to the datum, so no later
  reading is returned until the reference is re-established (ch. 5.5, 5.6).

Legacy protocol of the thesis' HP-IB laser processor, driftlab's own (rig driver ``thesis-laser``;
no laser on the market speaks it; docs/instruments.md says which systems publish what). Instrument
protocol (ASCII over GPIB, ``\\n`` terminated, every command answered):

=====================  =========================================================
``*IDN?``              ``<maker>,<model>,<serial>,<firmware>``
``MODE LIN|STR|ANG``   select linear, straightness or angle optics -> ``OK``
``AXIS X|Y|Z|A|B``     axis whose motion is measured -> ``OK``
``TERM <term>``        error term the optics are set up for -> ``OK``
``REF``                zero the count at the present position -> ``OK``
``ENV?``               weather station: ``<air degC>,<pressure Pa>,<RH %>``
``MEAS?``              ``<fringes>,<signal %>``; ``ERR BEAM`` while the beam is broken (or a rotary axis
                       is beyond the angular optics' range); ``ERR OPTICS`` when the optics mounted
                       are not those of the configured mode, axis and term
``MEAS? <n>``          a burst of n readings taken by the head back to back:
                       ``<fringes>,<signal %>;...`` (n pairs); ``ERR BEAM`` as above
=====================  =========================================================

With ``burst=True`` the driver reads a point as one burst of two settle readings plus the
readings to average (``MEAS? 12``) instead of twelve exchanges, and falls back to polling
with pauses only when that burst shows the axis still moving.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_REFERENCE_LOST, ErrorSample, Reading
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.transport import LineChannel, VisaPort
from driftlab.errors import InstrumentError, ValidationError

HENE_VACUUM_WAVELENGTH_NM = 632.991  # stabilised He-Ne laser, vacuum wavelength

# Table 5.3: which error terms the laser measures for each axis, and with which optics.
# The rest (roll of linear axes, translations of rotary axes) use proximity sensors on
# reference surfaces (driftlab.daq.proximity).
LASER_TERMS: dict[str, dict[str, str]] = {
    "X": {"dx": "LIN", "dy": "STR", "dz": "STR", "beta": "ANG", "gamma": "ANG"},
    "Y": {"dx": "STR", "dy": "LIN", "dz": "STR", "alpha": "ANG", "gamma": "ANG"},
    "Z": {"dx": "STR", "dy": "STR", "dz": "LIN", "alpha": "ANG", "beta": "ANG"},
    "A": {"alpha": "ANG"},
    "B": {"beta": "ANG"},
}
MODES = ("LIN", "STR", "ANG")


def water_vapour_saturation_pa(t_c: float | np.ndarray) -> np.ndarray:
    """Return the saturation vapour pressure of water (Pa) at ``t_c`` degC (Davis 1992, CIPM-81/91)."""
    t_k = np.asarray(t_c, dtype=float) + 273.15
    a, b, c, d = 1.2378847e-5, -1.9121316e-2, 33.93711047, -6.3431645e3
    return np.exp(a * t_k**2 + b * t_k + c + d / t_k)


def air_refractive_index(
    t_c: float | np.ndarray,
    pressure_pa: float | np.ndarray,
    rh_percent: float | np.ndarray,
    wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM,
) -> np.ndarray:
    """Return n of moist air by Edlen's equation, revised by Birch & Downs (1993, 1994)."""
    t = np.asarray(t_c, dtype=float)
    p = np.asarray(pressure_pa, dtype=float)
    sigma2 = (1e3 / wavelength_nm) ** 2  # (vacuum wavenumber in um^-1)^2
    # Dispersion of standard air (15 degC, 101325 Pa, dry, 450 ppm CO2).
    n_s = (8342.54 + 2406147.0 / (130.0 - sigma2) + 15998.0 / (38.9 - sigma2)) * 1e-8
    # Density correction for temperature and pressure.
    n_tp = p * n_s / 96095.43 * (1.0 + 1e-8 * (0.601 - 0.00972 * t) * p) / (1.0 + 0.0036610 * t)
    # Water vapour, partial pressure f (Pa).
    f = np.asarray(rh_percent, dtype=float) / 100.0 * water_vapour_saturation_pa(t)
    return 1.0 + n_tp - f * (3.7345 - 0.0401 * sigma2) * 1e-10


@dataclass(frozen=True)
class Environment:
    """Air conditions along the beam."""

    t_c: float = 20.0
    pressure_pa: float = 101325.0
    rh_percent: float = 50.0

    def refractive_index(self, wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM) -> float:
        """Return n of air for these conditions."""
        return float(air_refractive_index(self.t_c, self.pressure_pa, self.rh_percent, wavelength_nm))


@dataclass(frozen=True)
class Optics:
    """Instrument constants of the optics in use."""

    wavelength_nm: float = HENE_VACUUM_WAVELENGTH_NM
    straightness_factor: float = 10.0  # lateral motion -> path change ratio of the straightness optics
    angle_spacing_mm: float = 32.0  # distance between the two retro-reflectors of the angle optics


def fringes_to_value(mode: str, fringes: ArrayLike, n_air: float, optics: Optics = Optics()) -> np.ndarray:
    """Return the measured quantity (mm for LIN/STR, rad for ANG) from fringe counts."""
    path_mm = np.asarray(fringes, dtype=float) * optics.wavelength_nm * 1e-6 / (2.0 * n_air)
    if mode == "LIN":
        return path_mm
    if mode == "STR":
        return path_mm / optics.straightness_factor
    if mode == "ANG":
        return np.arcsin(path_mm / optics.angle_spacing_mm)
    raise ValidationError(f"unknown laser mode {mode!r}")


def value_to_fringes(mode: str, value: float | np.ndarray, n_air: float, optics: Optics = Optics()) -> np.ndarray:
    """Return the fringe count the head shows for a measured quantity (inverse of fringes_to_value)."""
    v = np.asarray(value, dtype=float)
    if mode == "LIN":
        path_mm = v
    elif mode == "STR":
        path_mm = v * optics.straightness_factor
    elif mode == "ANG":
        path_mm = np.sin(v) * optics.angle_spacing_mm
    else:
        raise ValidationError(f"unknown laser mode {mode!r}")
    return path_mm * 2.0 * n_air / (optics.wavelength_nm * 1e-6)


def remove_linear_trend(positions: Sequence[float], values: Sequence[float]) -> np.ndarray:
    """Return straightness values with their least-squares line over the travel removed (ch. 5.5)."""
    x = np.asarray(positions, dtype=float)
    y = np.asarray(values, dtype=float)
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return y.copy()
    slope, intercept = np.polyfit(x[ok], y[ok], 1)
    return y - (slope * x + intercept)


def _parse_meas(text: str) -> tuple[float, float] | None:
    """Return (fringes, signal %) of a MEAS? reply, None for ``ERR BEAM``."""
    if text == "ERR BEAM":
        return None
    if text == "ERR OPTICS":
        raise ValueError("the head has no optics mounted for this axis and term")
    fringes_s, signal_s = text.split(",")
    fringes, signal = float(fringes_s), float(signal_s)
    if not (math.isfinite(fringes) and 0.0 <= signal <= 100.0):
        raise ValueError("reading out of range")
    return fringes, signal


def _parse_burst(text: str) -> list[tuple[float, float]] | None:
    """Return the (fringes, signal %) pairs of a ``MEAS? n`` reply, None for ``ERR BEAM``."""
    if text == "ERR BEAM":
        return None
    out = []
    for part in text.split(";"):
        pair = _parse_meas(part)
        if pair is None:
            raise ValueError("beam error inside a burst")
        out.append(pair)
    return out


def _parse_env(text: str) -> Environment:
    t_s, p_s, h_s = text.split(",")
    env = Environment(float(t_s), float(p_s), float(h_s))
    if not (-10 <= env.t_c <= 50 and 60e3 <= env.pressure_pa <= 115e3 and 0 <= env.rh_percent <= 100):
        raise ValueError("environment out of range")
    return env


@dataclass(frozen=True)
class SettleOptions:
    """How a laser driver reads one point: after the axis settles (consecutive readings within the
    tolerance, polled every ``settle_poll_s`` at most ``max_settle_polls`` times), the mean of
    ``readings_per_point`` readings (ch. 5.5: ten readings averaged); ``sleep`` waits between polls."""

    readings_per_point: int = 10
    settle_tolerance_mm: float = 0.0005
    settle_tolerance_rad: float = 5e-7
    settle_poll_s: float = 0.5
    max_settle_polls: int = 120
    sleep: Callable[[float], None] = time.sleep


class LaserMeasures:
    """What every laser driver offers on top of its own ``configure``, ``read`` and datum (table 5.3).

    A subclass sets ``mode`` (LIN, STR or ANG) in ``configure(axis, term)``, keeps the position of
    its last datum in ``reference_position`` and returns one averaged point from ``read()``; this
    gives it the DisplacementMeter / AngleMeter reads and the ErrorMeter's ``measure_error``.
    """

    mode: str | None
    reference_position: float

    def _settle_with(self, settle: SettleOptions) -> None:
        """Take the point-reading settings (kept as attributes: the rig sets ``readings_per_point`` per point)."""
        self.readings_per_point = settle.readings_per_point
        self.settle_tolerance_mm = settle.settle_tolerance_mm
        self.settle_tolerance_rad = settle.settle_tolerance_rad
        self.settle_poll_s = settle.settle_poll_s
        self.max_settle_polls = settle.max_settle_polls
        self.sleep = settle.sleep

    def configure(self, axis: str, term: str) -> str:
        """Set up the optics for (axis, term); return the mode."""
        raise NotImplementedError

    def read(self) -> Reading:
        """Return one averaged point in the current mode."""
        raise NotImplementedError

    def read_displacement(self) -> Reading:
        """Return the displacement (mm) in LIN or STR mode (DisplacementMeter)."""
        if self.mode not in ("LIN", "STR"):
            raise ValidationError("read_displacement needs linear or straightness optics")
        return self.read()

    def read_angle(self) -> Reading:
        """Return the angle (rad) in ANG mode (AngleMeter)."""
        if self.mode != "ANG":
            raise ValidationError("read_angle needs angle optics")
        return self.read()

    def measure_error(self, axis: str, term: str, position: float, direction: int) -> ErrorSample:
        """Return the error at a commanded position: measured minus commanded motion for LIN, else the reading."""
        mode = self.configure(axis, term)
        reading = self.read()
        value = reading.value
        if reading.ok and mode == "LIN":
            value -= position - self.reference_position
        return ErrorSample(axis, term, float(position), int(direction), value, reading.flag)


class LaserInterferometer(LaserMeasures):
    """The thesis' HP-IB laser (legacy protocol) on a line channel; an AngleMeter or DisplacementMeter by mode."""

    def __init__(
        self,
        channel: LineChannel,
        optics: Optics = Optics(),
        settle: SettleOptions = SettleOptions(),
        *,
        min_signal_percent: float = 25.0,
        environment: Environment | None = None,
        burst: bool = False,
    ) -> None:
        self._io = channel
        self.optics = optics
        self._settle_with(settle)
        self.min_signal_percent = min_signal_percent
        self.manual_environment = environment
        self.burst = burst
        self.mode: str | None = None
        self.axis: str | None = None
        self.term: str | None = None
        self.reference_lost = True  # no reference until reference() is called
        self.reference_epoch = 0
        self.reference_position: float = 0.0

    @classmethod
    def open(
        cls, address: str, timeout_s: float = 5.0, policy: RetryPolicy | None = None, **kwargs: Any
    ) -> LaserInterferometer:
        """Return a laser on a VISA resource (``GPIB0::3::INSTR``; ``TCPIP0::..::SOCKET`` for the simulator)."""
        return cls(LineChannel(VisaPort.open(address, timeout_s), "laser", policy), **kwargs)

    def close(self) -> None:
        """Release the GPIB session."""
        self._io.close()

    def identify(self) -> str:
        """Return the instrument's identification string."""
        return self._io.query("*IDN?", _parse_idn)

    def configure(self, axis: str, term: str) -> str:
        """Set optics, axis and term for a table 5.3 measurement; return the optics mode used."""
        mode = LASER_TERMS.get(axis, {}).get(term)
        if mode is None:
            raise ValidationError(f"the laser does not measure {term} of the {axis} axis (table 5.3)")
        if mode != self.mode:
            self._io.command(f"MODE {mode}")
            self.mode = mode
            self.reference_lost = True
        if axis != self.axis:
            self._io.command(f"AXIS {axis}")
            self.axis = axis
            self.reference_lost = True
        if term != self.term:
            self._io.command(f"TERM {term}")
            self.term = term
            # New optics set-up: the count no longer refers to the old datum.
            self.reference_lost = True
        return mode

    def environment(self) -> Environment:
        """Return the air conditions used for compensation (manual, or the head's weather station)."""
        if self.manual_environment is not None:
            return self.manual_environment
        return self._io.query("ENV?", _parse_env)

    def reference(self, position: float = 0.0) -> None:
        """Zero the head at the present axis ``position``; a new reference epoch starts."""
        self._io.command("REF")
        self.reference_position = float(position)
        self.reference_lost = False
        self.reference_epoch += 1

    def _fringes(self) -> float | None:
        """Return one fringe count, or None when the beam is broken or too weak to trust."""
        raw = self._io.query("MEAS?", _parse_meas)
        if raw is None or raw[1] < self.min_signal_percent:
            return None
        return raw[0]

    def _lose_reference(self) -> Reading:
        self.reference_lost = True
        return Reading.missing(FLAG_BEAM_BREAK)

    def read(self) -> Reading:
        """Return the settled mean of ten readings in mm or rad; flagged missing on a beam break."""
        if self.mode is None:
            raise ValidationError("laser not configured: call configure(axis, term) first")
        if self.reference_lost:
            return Reading.missing(FLAG_REFERENCE_LOST)
        n_air = self.environment().refractive_index(self.optics.wavelength_nm)
        tol = self.settle_tolerance_rad if self.mode == "ANG" else self.settle_tolerance_mm
        if self.burst:
            n = self.readings_per_point
            burst = self._io.query(f"MEAS? {2 + n}", self._burst_parser(2 + n))
            if burst is None or any(signal < self.min_signal_percent for _, signal in burst):
                return self._lose_reference()
            first, second = (float(fringes_to_value(self.mode, f, n_air, self.optics)) for f, _ in burst[:2])
            if abs(second - first) <= tol:
                counts = [f for f, _ in burst[2:]]
                return Reading(float(fringes_to_value(self.mode, np.mean(counts), n_air, self.optics)))
            self.sleep(self.settle_poll_s)  # still moving: poll until it settles, as without bursts
        previous: float | None = None
        for _ in range(self.max_settle_polls):
            fringes = self._fringes()
            if fringes is None:
                return self._lose_reference()
            value = float(fringes_to_value(self.mode, fringes, n_air, self.optics))
            if previous is not None and abs(value - previous) <= tol:
                break
            previous = value
            self.sleep(self.settle_poll_s)
        else:
            raise InstrumentError(f"laser: axis did not settle within {self.max_settle_polls} polls")
        counts = []
        for _ in range(self.readings_per_point):
            fringes = self._fringes()
            if fringes is None:
                return self._lose_reference()
            counts.append(fringes)
        return Reading(float(fringes_to_value(self.mode, np.mean(counts), n_air, self.optics)))

    @staticmethod
    def _burst_parser(n: int) -> Callable[[str], list[tuple[float, float]] | None]:
        def parse(text: str) -> list[tuple[float, float]] | None:
            out = _parse_burst(text)
            if out is not None and len(out) != n:
                raise ValueError(f"expected {n} readings, got {len(out)}")
            return out

        return parse


def _parse_idn(text: str) -> str:
    """Return an identification string of four comma-separated fields."""
    if text.count(",") != 3:
        raise ValueError("bad *IDN? reply")
    return text
