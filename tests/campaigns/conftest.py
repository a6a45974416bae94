"""Fixtures of the campaign tests: small valid bundles made on the fly (never committed)."""

from __future__ import annotations

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
