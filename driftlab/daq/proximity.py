"""Proximity sensors on an A/D card (thesis ch. 5.5 figs. 5.11-5.13, appendix C tables C.1-C.2).

Calibration model (appendix C): each sensor's output voltage is a straight line in
the motion, ``V_i = constant_i + slope_i,k * d_k`` (V, V/mm) with one slope per motion
direction k; the off-primary slopes are the cross-axis terms caused by reference
surfaces that are not perfectly flat or square.  Stacking the sensors gives a
calibration matrix ``V = c + S d``.  Angles come from two sensors a known distance
apart on reference surfaces: a rotation theta moves their gaps by +-lever * theta, so
the unknowns (translations and angles) are found together by least squares on
``V - c = [S | A] [d; theta]`` where ``A[i, j] = slope_i,primary * lever_i,j``.

A/D card protocol (ASCII, ``\\n`` terminated):

=========================  ======================================================
``*IDN?``                  ``<maker>,<model>,<serial>,<firmware>``
``VOLT? <first>,<last>``   voltages of channels first..last, comma separated (V)
=========================  ======================================================
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from driftlab.daq.protocols import Reading
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.transport import LineChannel, open_port
from driftlab.errors import ValidationError

FLAG_OUT_OF_RANGE = "sensor_out_of_range"
AD_RANGE_V = (0.0, 10.0)  # unipolar 0-10 V input range of the A/D card
MOTIONS = ("dx", "dy", "dz")

# Appendix C, table C.1: A-axis reference-surface sensors. (constant V, slope V/mm) per motion.
TABLE_C1: dict[str, dict[str, tuple[float, float]]] = {
    "dx": {"P1": (5.1292, 0.0104), "P2": (5.2750, 0.0481), "P3": (4.9305, 0.1306),
           "P4": (5.3869, 0.0185), "P5": (4.1980, 8.5811)},
    "dy": {"P1": (5.1095, 8.4225), "P2": (5.2712, 8.5398), "P3": (5.1215, 0.0040),
           "P4": (5.5147, 0.0062), "P5": (4.2214, -0.0496)},
    "dz": {"P1": (5.1609, -0.0044), "P2": (5.3165, -0.0269), "P3": (5.1204, 8.4622),
           "P4": (5.5392, 8.7469), "P5": (4.2362, 0.0027)},
}  # fmt: skip
# Appendix C, table C.2: B-axis reference-surface sensors.
TABLE_C2: dict[str, dict[str, tuple[float, float]]] = {
    "dx": {"P1": (5.7087, 0.3243), "P2": (5.7002, 0.3658), "P3": (5.6850, 8.7099),
           "P4": (4.8001, 8.6156), "P5": (5.2896, 0.0443)},
    "dy": {"P1": (5.7150, -0.0321), "P2": (5.6976, -0.0361), "P3": (5.6643, -0.0065),
           "P4": (4.7992, -0.0113), "P5": (5.2609, -8.3337)},
    "dz": {"P1": (5.6861, 8.6192), "P2": (5.6810, 8.6111), "P3": (5.6915, -0.0529),
           "P4": (4.8268, -0.2458), "P5": (5.2590, -0.0104)},
}  # fmt: skip


def voltage_to_displacement(volts: float | np.ndarray, constant: float, slope: float) -> np.ndarray:
    """Return displacement (mm) of one sensor from its voltage: (V - constant) / slope (appendix C)."""
    if slope == 0:
        raise ValidationError("proximity sensor slope must be non-zero")
    return (np.asarray(volts, dtype=float) - constant) / slope


def angle_from_pair(d_a: float | np.ndarray, d_b: float | np.ndarray, separation_mm: float) -> np.ndarray:
    """Return the angle (rad) of a reference surface from two gap changes ``separation_mm`` apart (fig. 5.11)."""
    if separation_mm <= 0:
        raise ValidationError("sensor separation must be positive")
    return np.arctan2(np.asarray(d_a, dtype=float) - np.asarray(d_b, dtype=float), separation_mm)


@dataclass(frozen=True)
class CalibrationMatrix:
    """V = constants + slopes @ d for a set of sensors (rows) and motions (columns)."""

    sensors: tuple[str, ...]
    motions: tuple[str, ...]
    constants: np.ndarray  # (n_sensors,) V
    slopes: np.ndarray  # (n_sensors, n_motions) V/mm

    @classmethod
    def from_table(cls, table: Mapping[str, Mapping[str, tuple[float, float]]]) -> CalibrationMatrix:
        """Return the matrix of an appendix C style table; each sensor's constant is the mean of its runs."""
        motions = tuple(table)
        sensors = tuple(next(iter(table.values())))
        if any(tuple(table[m]) != sensors for m in motions):
            raise ValidationError("every motion of a calibration table must list the same sensors")
        constants = np.array([np.mean([table[m][s][0] for m in motions]) for s in sensors])
        slopes = np.array([[table[m][s][1] for m in motions] for s in sensors])
        return cls(sensors, motions, constants, slopes)

    def primary(self) -> np.ndarray:
        """Return, per sensor, the index of the motion it is most sensitive to."""
        return np.argmax(np.abs(self.slopes), axis=1)

    def voltages(self, d: np.ndarray) -> np.ndarray:
        """Return the sensor voltages for motions ``d`` of shape (..., n_motions)."""
        return self.constants + np.asarray(d, dtype=float) @ self.slopes.T


@dataclass(frozen=True)
class ReferenceSurfaceArray:
    """Sensors on reference surfaces: translations and angles from a calibration matrix and levers."""

    calibration: CalibrationMatrix
    # lever_mm[sensor][angle term]: the gap change per rad of that angle, along the sensor's primary motion.
    lever_mm: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    @property
    def angles(self) -> tuple[str, ...]:
        """Return the angle terms this array resolves."""
        return tuple(sorted({t for levers in self.lever_mm.values() for t in levers}))

    def design_matrix(self) -> np.ndarray:
        """Return [S | A]: sensitivities of every voltage to (motions..., angles...)."""
        cal = self.calibration
        prim = cal.primary()
        a = np.zeros((len(cal.sensors), len(self.angles)))
        for i, sensor in enumerate(cal.sensors):
            for j, term in enumerate(self.angles):
                a[i, j] = cal.slopes[i, prim[i]] * self.lever_mm.get(sensor, {}).get(term, 0.0)
        m = np.hstack([cal.slopes, a])
        if np.linalg.matrix_rank(m) < m.shape[1]:
            raise ValidationError("proximity array cannot resolve its terms: calibration matrix is singular")
        return m

    def terms(self) -> tuple[str, ...]:
        """Return the names of the solved quantities, in column order."""
        return self.calibration.motions + self.angles

    def solve(self, volts: np.ndarray) -> np.ndarray:
        """Return (..., n_terms) translations (mm) and angles (rad) from voltages (..., n_sensors)."""
        v = np.asarray(volts, dtype=float) - self.calibration.constants
        sol, *_ = np.linalg.lstsq(self.design_matrix(), v.reshape(-1, v.shape[-1]).T, rcond=None)
        return sol.T.reshape(v.shape[:-1] + (len(self.terms()),))

    def forward(self, values: np.ndarray) -> np.ndarray:
        """Return the voltages produced by (..., n_terms) translations and angles (for simulation)."""
        return self.calibration.constants + np.asarray(values, dtype=float) @ self.design_matrix().T


def a_axis_array(separation_mm: float = 150.0) -> ReferenceSurfaceArray:
    """Return the A-axis array of table C.1 (fig. 5.12): P1/P2 read Y and P3/P4 read Z, each pair split along X."""
    half = separation_mm / 2.0
    return ReferenceSurfaceArray(
        CalibrationMatrix.from_table(TABLE_C1),
        # rotation gamma about Z moves a point at x by +gamma*x in Y; beta about Y moves it by -beta*x in Z
        {"P1": {"gamma": half}, "P2": {"gamma": -half}, "P3": {"beta": -half}, "P4": {"beta": half}},
    )


def b_axis_array(separation_mm: float = 150.0) -> ReferenceSurfaceArray:
    """Return the B-axis array of table C.2 (fig. 5.13): P1/P2 read Z and P3/P4 read X, each pair split along Y."""
    half = separation_mm / 2.0
    return ReferenceSurfaceArray(
        CalibrationMatrix.from_table(TABLE_C2),
        # alpha about X moves a point at y by +alpha*y in Z; gamma about Z moves it by -gamma*y in X
        {"P1": {"alpha": half}, "P2": {"alpha": -half}, "P3": {"gamma": -half}, "P4": {"gamma": half}},
    )


def _in_range(volts: np.ndarray) -> np.ndarray:
    lo, hi = AD_RANGE_V
    return np.isfinite(volts) & (volts > lo) & (volts < hi)


class ADCard:
    """The thesis' DT2801 A/D card (legacy protocol ``VOLT?``, rig driver thesis-ad-card): voltages of channels."""

    def __init__(self, channel: LineChannel, n_channels: int = 16) -> None:
        self._io = channel
        self.n_channels = n_channels

    @classmethod
    def open(
        cls, address: str, n_channels: int = 16, timeout_s: float = 2.0, policy: RetryPolicy | None = None
    ) -> ADCard:
        """Return a card on a VISA resource name or a serial device/URL."""
        return cls(LineChannel(open_port(address, timeout_s), "A/D card", policy), n_channels)

    def close(self) -> None:
        """Release the card's port."""
        self._io.close()

    def read_volts(self, channels: Sequence[int]) -> np.ndarray:
        """Return the voltages (V) of ``channels`` in the order given."""
        chans = list(channels)
        if not chans or min(chans) < 0 or max(chans) >= self.n_channels:
            raise ValidationError(f"A/D channels must be 0..{self.n_channels - 1}")
        first, last = min(chans), max(chans)
        n = last - first + 1

        def parse(text: str) -> np.ndarray:
            fields = text.split(",")
            if len(fields) != n:
                raise ValueError(f"expected {n} values, got {len(fields)}")
            return np.array([float(f) for f in fields])

        volts = self._io.query(f"VOLT? {first},{last}", parse)
        return volts[np.array(chans) - first]


class ProximitySensor:
    """One calibrated proximity sensor: a DisplacementMeter."""

    def __init__(self, card: ADCard, channel: int, constant: float, slope: float) -> None:
        self.card, self.channel, self.constant, self.slope = card, channel, constant, slope

    def read_displacement(self) -> Reading:
        """Return the displacement (mm); flagged missing when the voltage is at the A/D rails."""
        v = self.card.read_volts([self.channel])
        if not _in_range(v)[0]:
            return Reading.missing(FLAG_OUT_OF_RANGE)
        return Reading(float(voltage_to_displacement(v[0], self.constant, self.slope)))


class RollPair:
    """Two sensors on parallel reference lines a known distance apart (fig. 5.11): an AngleMeter."""

    def __init__(self, sensor_a: ProximitySensor, sensor_b: ProximitySensor, separation_mm: float) -> None:
        self.sensor_a, self.sensor_b, self.separation_mm = sensor_a, sensor_b, separation_mm

    def read_angle(self) -> Reading:
        """Return the roll angle (rad) from the two gap changes."""
        a, b = self.sensor_a.read_displacement(), self.sensor_b.read_displacement()
        if not (a.ok and b.ok):
            return Reading.missing(FLAG_OUT_OF_RANGE)
        return Reading(float(angle_from_pair(a.value, b.value, self.separation_mm)))


class ReferenceSurfaceMeter:
    """A reference-surface sensor array read through an A/D card."""

    def __init__(self, card: ADCard, channels: Sequence[int], array: ReferenceSurfaceArray) -> None:
        if len(channels) != len(array.calibration.sensors):
            raise ValidationError("one A/D channel per calibrated sensor is required")
        self.card, self.channels, self.array = card, list(channels), array

    def read(self) -> dict[str, Reading]:
        """Return every resolved term (mm or rad); all flagged missing if any sensor is out of range."""
        v = self.card.read_volts(self.channels)
        if not np.all(_in_range(v)):
            return {t: Reading.missing(FLAG_OUT_OF_RANGE) for t in self.array.terms()}
        sol = self.array.solve(v)
        return {t: Reading(float(x)) for t, x in zip(self.array.terms(), sol, strict=True) if math.isfinite(x)}
