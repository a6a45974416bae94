"""A laser system without a published remote command set, followed through its capture software's live export.

Renishaw's XL-80 (LaserXL / CARTO Capture) and API's XD systems are driven by their own software;
neither publishes a command set a third party can drive (their SDKs are licensed), and the
thesis' HP 5528A-era HP-IB processor and Keysight's 5530 (whose N1231B board is programmed
through Keysight's own library) have no command-set text available here to write a driver from.
What a shop can always do is let the capture software write its export file as the test runs
(a row per target, e.g. Renishaw's CSV: preamble, then ``Run, Direction, Target (mm),
Error (um)``) and let driftlab follow that file: the daemon moves the machine to a sweep point,
then waits for the software's row for that target and direction.

The file's format is read by a reader the caller supplies (the importers of
``driftlab.metrology.importers``, wired in by the commands: ``daq`` sits below them), returning
rows of (axis, term, position, direction, value) in bundle units (mm, rad). The follower re-reads
the file when it grew; a row being written (a parse error) is waited out; rows for other targets
are passed over. The capture software keeps the datum, so ``reference`` only records the position.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from driftlab.daq.protocols import ErrorSample
from driftlab.errors import DriftlabError, InstrumentError

#: (axis, term, position mm|deg, direction +1|-1, value mm|rad)
ExportRow = tuple[str, str, float, int, float]
ExportReader = Callable[[Path], Sequence[ExportRow]]


class ExportFollower:
    """An ErrorMeter reading a capture program's export file as it grows (one row per measured target)."""

    def __init__(
        self,
        path: Path | str,
        read_rows: ExportReader,
        fmt: str = "export",
        poll_s: float = 1.0,
        timeout_s: float = 600.0,
        position_tol: float = 1e-3,
        sleep: Callable[[float], None] = time.sleep,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self.read_rows = read_rows
        self.fmt = fmt
        self.poll_s, self.timeout_s, self.position_tol = poll_s, timeout_s, position_tol
        self.sleep, self.clock = sleep, clock
        self.reference_lost = False  # the capture software holds the datum
        self.reference_position = 0.0
        self.readings_per_point = 1
        self._consumed = 0  # rows already used or passed over
        self._stamp: tuple[int, int] | None = None
        self._rows: list[ExportRow] = []
        self._last_error: str | None = None

    def identify(self) -> str:
        """Return what is followed: the format and the file."""
        return f"{self.fmt} live export {self.path}"

    def configure(self, axis: str, term: str) -> str:
        """Nothing to set: the capture software is set up for the test by its operator."""
        return ""

    def reference(self, position: float = 0.0) -> None:
        """Record the datum position (the capture software zeroes itself at its first target)."""
        self.reference_position = float(position)

    def rows(self) -> list[ExportRow]:
        """Return the file's rows, re-read if it changed; InstrumentError if it cannot be opened at all."""
        try:
            st = self.path.stat()
        except OSError as exc:
            raise InstrumentError(f"{self.fmt} export {self.path}: {exc.strerror or exc}") from None
        stamp = (st.st_size, st.st_mtime_ns)
        if stamp != self._stamp:
            try:
                self._rows = list(self.read_rows(self.path))
                self._stamp = stamp
                self._last_error = None
            except DriftlabError as exc:  # a row half written: read again at the next poll
                self._last_error = exc.one_line()
        return self._rows

    def status(self) -> dict[str, float]:
        """Return how many rows the file holds and the last value (rig check's reading)."""
        rows = self.rows()
        out: dict[str, float] = {"rows": float(len(rows))}
        if rows:
            out["last_value"] = float(rows[-1][4])
        return out

    def measure_error(self, axis: str, term: str, position: float, direction: int) -> ErrorSample:
        """Return the export's next row for (axis, term, position, direction), waiting for it to be written."""
        deadline = self.clock() + self.timeout_s
        while True:
            rows = self.rows()
            for i in range(self._consumed, len(rows)):
                r_axis, r_term, r_pos, r_dir, value = rows[i]
                if (
                    r_axis == axis
                    and r_term == term
                    and r_dir == direction
                    and abs(r_pos - position) <= self.position_tol
                    and math.isfinite(value)
                ):
                    self._consumed = i + 1
                    return ErrorSample(axis, term, position, direction, float(value))
            if self.clock() >= deadline:
                why = f" (last read: {self._last_error})" if self._last_error else ""
                raise InstrumentError(
                    f"{self.fmt} export {self.path.name}: no row for {axis} {term} at {position:g} "
                    f"{'+' if direction > 0 else '-'} after {self.timeout_s:g} s{why}"
                )
            self.sleep(self.poll_s)

    def close(self) -> None:
        """Nothing to release."""
