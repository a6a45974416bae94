"""A small valid campaign (four channels, two Z-axis stages, Z-axis errors) for the store and API tests."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from driftlab.campaigns.bundle import CampaignJson

SCAN_S = 30.0  # one thermocouple scan every 30 s


def small_meta(
    machine: str = "vmc-test-01",
    started_at: str = "2026-03-02T08:00:00Z",
    *,
    name: str = "test VMC",
    scans: int = 40,
    noise: bool = True,
) -> CampaignJson:
    """Return a campaign.json with four channels (two room) and two Z-axis stages splitting ``scans`` in half."""
    half = int(scans * SCAN_S) // 2
    stage = {"axis": "Z", "feed_mm_min": 0}
    meta: CampaignJson = {
        "format": "driftlab-bundle/1",
        "machine": {"id": machine, "name": name, "resolution_mm": 0.0025, "resolution_deg": 0.001},
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
            {"name": "spindle-8k", "start_s": 0, "end_s": half, "heat_source": "spindle", "spindle_rpm": 8000, **stage},
            {"name": "cool", "start_s": half, "end_s": 2 * half, "heat_source": "none", "spindle_rpm": 0, **stage},
        ],
    }
    if noise:
        meta["noise"] = {"length_mm": 0.0005, "angle_rad": 5e-7}
    return meta


def small_frames(seed: int = 0, scans: int = 40, sweeps: int = 4) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Return temperatures (one missing cell), conditions and Z-axis errors (dx, dz, gamma) of a small campaign."""
    rng = np.random.default_rng(seed)
    t = np.arange(scans) * SCAN_S
    temps = pd.DataFrame({"time_s": t})
    for k, ch in enumerate(["T1", "T2", "T49", "T50"]):
        temps[ch] = 20.0 + k + 0.01 * t / SCAN_S + rng.normal(0, 0.05, scans)
    temps.loc[3, "T2"] = np.nan
    cond = pd.DataFrame(
        {
            "time_s": t,
            "spindle_rpm": np.where(t < scans * SCAN_S / 2, 8000.0, 0.0),
            "feed_mm_min": 0.0,
            "x": 0.0,
            "y": 0.0,
            "z": np.nan,
            "a": 0.0,
            "b": 0.0,
        }
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
    return temps, cond, errors.sort_values("time_s", kind="stable").reset_index(drop=True)
