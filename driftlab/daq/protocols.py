"""Typed capability protocols for driftlab's instruments.

Upstream code (the scheduler, the compensator) depends on what a device can do, never on
its class: a real driver on a GPIB bus and its simulated twin both satisfy the same
protocol, and ``isinstance(x, TemperatureScanner)`` works on either (the protocols are
runtime-checkable; the check looks at method names only, the type hints carry the rest).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

# Flags carried by a reading that is missing (value NaN). A reading with a flag is
# never a measurement: stores keep the NaN and the flag, models skip it.
FLAG_OPEN = "open_thermocouple"
FLAG_BEAM_BREAK = "beam_break"
FLAG_REFERENCE_LOST = "reference_lost"


@dataclass(frozen=True)
class Reading:
    """One scalar reading: a value in driftlab units, or NaN with a flag saying why it is missing."""

    value: float
    flag: str | None = None

    @property
    def ok(self) -> bool:
        """Return True when the reading is a valid measurement."""
        return self.flag is None and math.isfinite(self.value)

    @classmethod
    def missing(cls, flag: str) -> Reading:
        """Return a flagged missing reading."""
        return cls(float("nan"), flag)


@dataclass(frozen=True)
class TemperatureScan:
    """One scan of the thermocouple card: degC per channel, NaN plus a flag where missing."""

    t_s: float
    values: Mapping[str, float]
    flags: Mapping[str, str] = field(default_factory=dict)

    def ok(self, channel: str) -> bool:
        """Return True when ``channel`` holds a valid temperature in this scan."""
        return channel not in self.flags and math.isfinite(self.values[channel])


@dataclass(frozen=True)
class ScanBlock:
    """Consecutive buffered scans k..k+n-1 of the card: degC per scan and channel, NaN where open.

    Arrays, not per-scan mappings: a block carries thousands of readings and nothing between the
    card and the store needs them one at a time.
    """

    first_index: int
    t_s: np.ndarray  # (n,) scan times, s
    channels: tuple[str, ...]
    values: np.ndarray  # (n, c) degC, NaN where the junction is open
    open: np.ndarray  # (n, c) True where the junction read open (over-range)

    def __len__(self) -> int:
        """Return the number of scans in the block."""
        return len(self.t_s)

    def scan(self, i: int) -> TemperatureScan:
        """Return scan i of the block as a TemperatureScan."""
        row, opened = self.values[i].tolist(), self.open[i].tolist()
        return TemperatureScan(
            t_s=float(self.t_s[i]),
            values=dict(zip(self.channels, row)),
            flags={c: FLAG_OPEN for c, o in zip(self.channels, opened) if o},
        )


@dataclass(frozen=True)
class ErrorSample:
    """One measured point of an error sweep (a row of errors.csv); NaN plus a flag when missing."""

    axis: str
    term: str
    position: float
    direction: int
    value: float
    flag: str | None = None

    @property
    def ok(self) -> bool:
        """Return True when the sample is a valid measurement."""
        return self.flag is None and math.isfinite(self.value)


@dataclass(frozen=True)
class SphereMeasurement:
    """A probed sphere: centre (mm, machine coordinates), fitted radius and fit residual."""

    name: str
    centre: np.ndarray
    radius_mm: float
    rms_residual_mm: float
    points: np.ndarray


@dataclass(frozen=True)
class StreamReport:
    """What happened while streaming a program to the controller."""

    blocks_sent: int
    polls: int
    min_free_seen: int
    starved: int


@runtime_checkable
class TemperatureScanner(Protocol):
    """Scans a set of named thermocouple channels."""

    @property
    def channels(self) -> Sequence[str]:
        """Return the channel names, in scan order."""

    def scan(self) -> TemperatureScan:
        """Return one scan of every channel."""


@runtime_checkable
class BlockScanner(TemperatureScanner, Protocol):
    """A scanner with a hardware pacer and a scan buffer: scan k is taken at k * interval, read in blocks."""

    def pace(self, interval_s: float) -> None:
        """Set the pacer's scan interval (s); scan k is taken at k * interval_s."""

    def scan_block(self, first_index: int, n: int) -> ScanBlock:
        """Return the buffered scans first_index .. first_index + n - 1 (already taken by the pacer)."""


@runtime_checkable
class DisplacementMeter(Protocol):
    """Reads a displacement (mm) along its measuring direction."""

    def read_displacement(self) -> Reading:
        """Return the displacement in mm (NaN plus flag when it could not be measured)."""


@runtime_checkable
class AngleMeter(Protocol):
    """Reads a small angle (rad)."""

    def read_angle(self) -> Reading:
        """Return the angle in rad (NaN plus flag when it could not be measured)."""


@runtime_checkable
class ErrorMeter(Protocol):
    """Measures one work-space error term of an axis at a commanded position (the laser, table 5.3)."""

    def measure_error(self, axis: str, term: str, position: float, direction: int) -> ErrorSample:
        """Return the error (mm or rad) at ``position`` approached from ``direction``."""


@runtime_checkable
class Prober(Protocol):
    """Locates reference spheres in the work space with a touch-trigger probe."""

    def probe_sphere(self, name: str, nominal_centre: Sequence[float], radius_mm: float) -> SphereMeasurement:
        """Return the fitted centre of the sphere near ``nominal_centre``."""


@runtime_checkable
class MachineLink(Protocol):
    """The serial link to the machine controller: stream motion code, read positions."""

    def send_program(self, lines: Iterable[str], low_water: int = ..., wait: bool = ...) -> StreamReport:
        """Stream ``lines`` to the controller's buffer and return what happened."""

    def position(self) -> dict[str, float]:
        """Return the current axis positions (X, Y, Z mm; A, B deg)."""

    def buffer_free(self) -> int:
        """Return the number of free blocks in the controller's buffer."""

    def close(self) -> None:
        """Release the link."""
