"""A laser's capture software followed through its live Renishaw CSV export, read by driftlab's own importer.

The capture software is played by the test appending rows to the file between the follower's polls
(its sleep), so nothing waits on the wall clock.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from driftlab.commands.rig import export_readers
from driftlab.daemon.rigfile import InstrumentSpec, open_instrument
from driftlab.daq.export_follower import ExportFollower
from driftlab.errors import InstrumentError, ValidationError

PREAMBLE = "Axis,X\nMachine,vmc-01\nDate,2026-03-02T08:00:00Z\nTest,linear\n\nRun,Direction,Target (mm),Error (um)\n"


class CaptureSoftware:
    """Appends the export's rows one poll at a time, the last one in two halves (a row being written)."""

    def __init__(self, path: Path, rows: list[str]) -> None:
        self.path, self.rows = path, list(rows)
        path.write_text(PREAMBLE)
        self.polls = 0
        self.now = 0.0

    def sleep(self, dt: float) -> None:
        self.polls += 1
        self.now += dt
        if self.rows:
            row = self.rows.pop(0)
            with self.path.open("a") as f:
                f.write(row)


def follower(tmp_path: Path, rows: list[str], **kw) -> tuple[ExportFollower, CaptureSoftware]:
    cap = CaptureSoftware(tmp_path / "live.csv", rows)
    reader = export_readers()["renishaw-csv"]
    f = ExportFollower(
        cap.path, lambda p: reader(p, None), "renishaw-csv", sleep=cap.sleep, clock=lambda: cap.now, **kw
    )
    return f, cap


def test_each_point_waits_for_its_row_and_passes_over_others(tmp_path):
    rows = ["1,+,0,0.5000\n", "1,+,100,3.2500\n", "1,+,20", "0,6.0000\n", "1,-,200,5.1000\n"]
    f, cap = follower(tmp_path, rows, poll_s=1.0, timeout_s=60.0)
    first = f.measure_error("X", "dx", 100.0, 1)
    assert first.value == pytest.approx(3.25e-3) and first.ok  # um in the export, mm in driftlab
    # the row for 200 + arrives in two writes: the half-written row is waited out, not misread
    assert f.measure_error("X", "dx", 200.0, 1).value == pytest.approx(6.0e-3)
    assert f.measure_error("X", "dx", 200.0, -1).value == pytest.approx(5.1e-3)
    assert f.status()["rows"] == 4.0


def test_a_row_that_never_comes_is_one_line_after_the_timeout(tmp_path):
    f, cap = follower(tmp_path, ["1,+,0,0.5\n"], poll_s=10.0, timeout_s=30.0)
    with pytest.raises(InstrumentError, match=r"no row for X dx at 300 \+ after 30 s"):
        f.measure_error("X", "dx", 300.0, 1)
    assert cap.polls == 3


def test_the_rig_driver_needs_the_file_and_a_known_format(tmp_path):
    spec = InstrumentSpec(driver="laser-export", resource=str(tmp_path / "none.csv"))
    with pytest.raises(InstrumentError, match="none.csv"):
        open_instrument("laser", spec, lambda: None, lambda: 0.0, readers=export_readers())
    bad = InstrumentSpec(driver="laser-export", resource="x.csv", options={"format": "carto-rtx"})
    with pytest.raises(ValidationError, match="one of renishaw-csv"):
        open_instrument("laser", bad, lambda: None, lambda: 0.0, readers=export_readers())
    (tmp_path / "live.csv").write_text(PREAMBLE + "1,+,0,0.5\n")
    ok = InstrumentSpec(driver="laser-export", resource=str(tmp_path / "live.csv"))
    laser, close = open_instrument("laser", ok, lambda: None, lambda: 0.0, readers=export_readers())
    assert laser.identify().startswith("renishaw-csv live export") and laser.status() == {
        "rows": 1.0,
        "last_value": 0.0005,
    }
    close()
