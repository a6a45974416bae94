"""What instruments measure: readings, scans, error samples; the values every layer passes on.

The drivers (``daq``) produce them, the store (``campaigns``) keeps them, the daemon moves them
from one to the other. They are plain frozen dataclasses with no behaviour beyond checks, so
both sides can depend on them without depending on each other.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

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
