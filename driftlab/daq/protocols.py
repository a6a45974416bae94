"""Typed capability protocols for driftlab's instruments.

Upstream code (the scheduler, the compensator) depends on what a device can do, never on
its class: a real driver on a GPIB bus and its simulated twin both satisfy the same
protocol, and ``isinstance(x, TemperatureScanner)`` works on either (the protocols are
runtime-checkable; the check looks at method names only, the type hints carry the rest).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Protocol, runtime_checkable

from driftlab.readings import (  # noqa: F401 - the drivers' values, re-exported with their protocols
    FLAG_BEAM_BREAK,
    FLAG_OPEN,
    FLAG_REFERENCE_LOST,
    ErrorSample,
    Reading,
    ScanBlock,
    SphereMeasurement,
    StreamReport,
    TemperatureScan,
)


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
