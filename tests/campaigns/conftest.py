"""Fixtures of the campaign tests: small valid bundles made on the fly (never committed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import write_bundle

FL_THERMAL = Path(__file__).resolve().parents[3] / "shared" / "data" / "fl_thermal"


def small_meta(machine: str = "vmc-test-01", started_at: str = "2026-03-02T08:00:00Z") -> dict:
    """Return a campaign.json document with four channels, two of them room channels."""
    return {
        "format": "driftlab-bundle/1",
        "machine": {"id": machine, "name": "test VMC", "resolution_mm": 0.0025, "resolution_deg": 0.001},
        "started_at": started_at,
        "channels": {
            "T1": {"location": "spindle nose", "structure": "spindle"},
            "T2": {"location": "Z column", "structure": "column"},
            "T49": {"location": "ceiling", "structure": "room"},
            "T50": {"location": "floor", "structure": "room"},
        },
        "room_channels": ["T49", "T50"],
        "model_channels": {"Z": ["T1", "T2", "T49"]},
        "stages": [
            {"name": "spindle-8k", "start_s": 0, "end_s": 600, "heat_source": "spindle", "axis": "Z",
             "spindle_rpm": 8000, "feed_mm_min": 0},
            {"name": "cool", "start_s": 600, "end_s": 1200, "heat_source": "none", "axis": "Z",
             "spindle_rpm": 0, "feed_mm_min": 0},
        ],
        "noise": {"length_mm": 0.0005, "angle_rad": 5e-7},
    }


def small_frames(seed: int = 0, scans: int = 40, sweeps: int = 4) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Return temperatures (with a few missing cells), conditions and errors of a small campaign."""
    rng = np.random.default_rng(seed)
    t = np.arange(scans) * 30.0
    temps = pd.DataFrame({"time_s": t})
    for k, ch in enumerate(["T1", "T2", "T49", "T50"]):
        temps[ch] = 20.0 + k + 0.01 * t / 30 + rng.normal(0, 0.05, scans)
    temps.loc[3, "T2"] = np.nan
    cond = pd.DataFrame(
        {"time_s": t, "spindle_rpm": np.where(t < 600, 8000.0, 0.0), "feed_mm_min": 0.0,
         "x": 0.0, "y": 0.0, "z": np.nan, "a": 0.0, "b": 0.0}
    )
    rows = []
    positions = np.linspace(0.0, 400.0, 5)
    for s in range(sweeps):
        t0 = s * 300.0
        for d, order in ((1, positions), (-1, positions[::-1])):
            for i, p in enumerate(order):
                ts = t0 + (i + (5 if d < 0 else 0)) * 10.0
                for term in ("dx", "dz", "gamma"):
                    scale = 1e-6 if term == "gamma" else 1e-3
                    value = scale * (1 + s) * (p / 400.0 + 0.1 * d) + rng.normal(0, scale * 0.01)
                    rows.append((ts, "Z", term, p, d, value))
    errors = pd.DataFrame(rows, columns=["time_s", "axis", "term", "position", "direction", "value"])
    errors = errors.sort_values("time_s", kind="stable").reset_index(drop=True)
    return temps, cond, errors


def make_bundle(path: Path, seed: int = 0, machine: str = "vmc-test-01", started_at: str = "2026-03-02T08:00:00Z",
                scans: int = 40, sweeps: int = 4) -> Path:
    """Write a small valid bundle to ``path`` and return it."""
    temps, cond, errors = small_frames(seed, scans, sweeps)
    return write_bundle(path, small_meta(machine, started_at), temps, cond, errors)


@pytest.fixture
def bundle_dir(tmp_path: Path) -> Path:
    """A small valid bundle directory."""
    return make_bundle(tmp_path / "bundle")


@pytest.fixture
def fl_thermal() -> Path:
    """The real FL_THERMAL bundle shipped in shared/data."""
    if not FL_THERMAL.is_dir():
        pytest.skip("shared/data/fl_thermal not present")
    return FL_THERMAL


@pytest.fixture
def bundle_factory(tmp_path: Path):
    """Return a function writing small valid bundles (keyword arguments as make_bundle) under tmp_path."""
    counter = iter(range(10_000))

    def factory(**kwargs) -> Path:
        return make_bundle(tmp_path / f"bundle{next(counter)}", **kwargs)

    return factory


@pytest.fixture
def frames_factory():
    """Return small_frames (temperatures, conditions, errors of a small campaign)."""
    return small_frames


@pytest.fixture
def meta_factory():
    """Return small_meta (a campaign.json document)."""
    return small_meta


# ----------------------------------------------------------------------------- corrupted bundles
# Every test taking a ``corruption`` argument runs once per entry: (id, file, mutation, message).
# Line numbers are as an editor shows them (header = line 1).


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines(keepends=True)


def _set_line(path: Path, lineno: int, text: str) -> None:
    lines = _lines(path)
    lines[lineno - 1] = text
    path.write_text("".join(lines))


def _edit_cell(path: Path, lineno: int, column: str, value: str) -> None:
    lines = _lines(path)
    header = lines[0].rstrip("\n").split(",")
    fields = lines[lineno - 1].rstrip("\n").split(",")
    fields[header.index(column)] = value
    lines[lineno - 1] = ",".join(fields) + "\n"
    path.write_text("".join(lines))


def _edit_json(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc, indent=1) + "\n")


def _truncate_last(path: Path) -> None:
    text = path.read_text()
    path.write_text(text[: text.rstrip("\n").rfind(",") - 3])


def _duplicate_header(path: Path) -> None:
    lines = _lines(path)
    path.write_text("".join([lines[0], lines[0], *lines[1:]]))


def _duplicate_column(path: Path) -> None:
    lines = _lines(path)
    out = []
    for line in lines:
        fields = line.rstrip("\n").split(",")
        out.append(",".join([*fields, fields[1]]) + "\n")
    path.write_text("".join(out))


def _swap_rows(path: Path, a: int, b: int) -> None:
    lines = _lines(path)
    lines[a - 1], lines[b - 1] = lines[b - 1], lines[a - 1]
    path.write_text("".join(lines))


def _extra_channel_column(path: Path) -> None:
    lines = _lines(path)
    out = [lines[0].rstrip("\n") + ",T99\n"] + [line.rstrip("\n") + ",20.5\n" for line in lines[1:]]
    path.write_text("".join(out))


CORRUPTIONS = [
    ("missing-temperatures", "temperatures.csv", lambda p: p.unlink(), "temperatures.csv: file missing"),
    ("missing-campaign", "campaign.json", lambda p: p.unlink(), "campaign.json: file missing"),
    ("bad-json", "campaign.json", lambda p: _set_line(p, 3, ' "machine" {\n'), "campaign.json:3: invalid JSON"),
    ("wrong-format", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(format="driftlab-bundle/3")),
     "campaign.json:2: format: unsupported format 'driftlab-bundle/3'"),
    ("v2-without-setups", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(format="driftlab-bundle/2")),
     "campaign.json:2: format: a bundle v2 needs setups"),
    ("v1-with-setups", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(
        setups={"s": {"instrument": "laser", "terms": ["Z/dz"]}})), "setups: setups belong to 'driftlab-bundle/2'"),
    ("extra-field", "campaign.json", lambda p: _edit_json(p, lambda d: d.update(room_channel=["T49"])),
     "room_channel: Extra inputs are not permitted"),
    ("naive-started-at", "campaign.json",
     lambda p: _edit_json(p, lambda d: d.update(started_at="2026-03-02T08:00:00")),
     "started_at: Value error, started_at needs a time zone"),
    ("room-channel-unknown", "campaign.json",
     lambda p: _edit_json(p, lambda d: d.update(room_channels=["T49", "T77"])),
     "room_channels[1]: room channel 'T77' is not in channels"),
    ("model-channel-unknown", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["model_channels"].update(Z=["T1", "T8"])),
     "model_channels.Z[1]: model channel 'T8' is not in channels"),
    ("stage-ends-before-start", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][1].update(end_s=500)),
     "stages[1].end_s: stage 'cool' ends (500.0) before it starts (600.0)"),
    ("stages-overlap", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][1].update(start_s=300)),
     "stages[1].start_s: stage 'cool' starts at 300.0, before the previous stage ends"),
    ("stage-bad-axis", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["stages"][0].update(axis="W")), "stages[0].axis: Input should be"),
    ("unknown-term", "errors.csv", lambda p: _edit_cell(p, 7, "term", "dq"),
     "errors.csv:7: column term: 'dq' is not one of alpha beta gamma dx dy dz"),
    ("unknown-axis", "errors.csv", lambda p: _edit_cell(p, 4, "axis", "Q"),
     "errors.csv:4: column axis: 'Q' is not one of X Y Z A B"),
    ("direction-zero", "errors.csv", lambda p: _edit_cell(p, 9, "direction", "0"),
     "errors.csv:9: column direction: '0' is not +1 or -1"),
    ("errors-time-backwards", "errors.csv", lambda p: _swap_rows(p, 5, 30),
     "errors.csv:6: time_s 10.0 is before the previous row's 90.0"),
    ("temperatures-not-monotonic", "temperatures.csv", lambda p: _swap_rows(p, 10, 11),
     "temperatures.csv:11: time_s 240.0 is not after the previous row's 270.0"),
    ("temperatures-repeated-time", "temperatures.csv", lambda p: _edit_cell(p, 7, "time_s", "120.0"),
     "temperatures.csv:7: time_s 120.0 is not after"),
    ("text-in-number", "temperatures.csv", lambda p: _edit_cell(p, 12, "T2", "hot"),
     "temperatures.csv:12: column T2: 'hot' is not a number"),
    ("channel-not-in-map", "temperatures.csv", _extra_channel_column,
     "temperatures.csv:1: column 'T99' is not a channel of campaign.json"),
    ("channel-without-column", "campaign.json",
     lambda p: _edit_json(p, lambda d: d["channels"].update(T7={"location": "x", "structure": "y"})),
     "temperatures.csv:1: channel 'T7' of campaign.json has no column"),
    ("truncated-last-line", "temperatures.csv", _truncate_last,
     "temperatures.csv:41: expected 5 fields, found 4 (truncated line?)"),
    ("duplicate-header", "temperatures.csv", _duplicate_header, "temperatures.csv:2: repeated header line"),
    ("duplicate-column", "temperatures.csv", _duplicate_column, "temperatures.csv:1: duplicate column 'T1'"),
    ("empty-errors-file", "errors.csv", lambda p: p.write_text(""), "errors.csv:1: empty file"),
    ("errors-header-only", "errors.csv", lambda p: p.write_text("time_s,axis,term,position,direction,value\n"),
     "errors.csv:2: no error samples"),
    ("nan-temperature", "temperatures.csv", lambda p: _edit_cell(p, 8, "T49", "NaN"),
     "temperatures.csv:8: column T49: nan is not a finite number"),
    ("inf-error-value", "errors.csv", lambda p: _edit_cell(p, 12, "value", "inf"),
     "errors.csv:12: column value: inf is not a finite number"),
    ("missing-error-value", "errors.csv", lambda p: _edit_cell(p, 13, "value", ""),
     "errors.csv:13: column value: missing value"),
    ("kelvin", "temperatures.csv", lambda p: _edit_cell(p, 20, "T1", "295.4"),
     "temperatures.csv:20: column T1: 295.4 degC is outside"),
    ("micrometres", "errors.csv", lambda p: _edit_cell(p, 15, "value", "12.5"),
     "errors.csv:15: column value: 12.5 mm is implausibly large"),
    ("duplicate-reading", "errors.csv", lambda p: _set_line(p, 3, _lines(p)[1]),
     "errors.csv:3: duplicate reading"),
    ("blank-line", "temperatures.csv", lambda p: _set_line(p, 15, "\n"), "temperatures.csv:15: empty line"),
    ("conditions-unknown-column", "conditions.csv",
     lambda p: p.write_text(p.read_text().replace("feed_mm_min", "feed_ipm", 1)),
     "conditions.csv:1: unknown column 'feed_ipm'"),
    ("conditions-negative-rpm", "conditions.csv", lambda p: _edit_cell(p, 5, "spindle_rpm", "-100"),
     "conditions.csv:5: column spindle_rpm: -100.0 is negative"),
    ("errors-missing-column", "errors.csv",
     lambda p: p.write_text(p.read_text().replace("direction", "dir", 1)), "errors.csv:1: unknown column 'dir'"),
]




def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Parametrise tests that take ``corruption`` over every corrupted-bundle case."""
    if "corruption" in metafunc.fixturenames:
        metafunc.parametrize("corruption", CORRUPTIONS, ids=[c[0] for c in CORRUPTIONS])
