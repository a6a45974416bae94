"""Helpers of the API tests: a small bundle, a model document, seeding a database."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.campaigns.store import connect
from driftlab.jobs import registry as model_registry

TOKEN = "test-token-0123456789"
MACHINE = "vmc-api-01"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def small_meta(machine: str = MACHINE, started_at: str = "2026-03-02T08:00:00Z") -> dict[str, Any]:
    """Return a campaign.json with four channels (two room) and two Z-axis stages."""
    return {
        "format": "driftlab-bundle/1",
        "machine": {"id": machine, "name": "API test VMC", "resolution_mm": 0.0025, "resolution_deg": 0.001},
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
            {
                "name": "spindle-8k",
                "start_s": 0,
                "end_s": 1200,
                "heat_source": "spindle",
                "axis": "Z",
                "spindle_rpm": 8000,
                "feed_mm_min": 0,
            },
            {
                "name": "cool",
                "start_s": 1200,
                "end_s": 2400,
                "heat_source": "none",
                "axis": "Z",
                "spindle_rpm": 0,
                "feed_mm_min": 0,
            },
        ],
    }


def small_frames(seed: int = 0, scans: int = 80, sweeps: int = 8) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Return temperatures (one missing cell), conditions and Z-axis errors of a short campaign."""
    rng = np.random.default_rng(seed)
    t = np.arange(scans) * 30.0
    temps = pd.DataFrame({"time_s": t})
    for k, ch in enumerate(["T1", "T2", "T49", "T50"]):
        temps[ch] = 20.0 + k + 0.01 * t / 30 + rng.normal(0, 0.05, scans)
    temps.loc[3, "T2"] = np.nan
    cond = pd.DataFrame(
        {
            "time_s": t,
            "spindle_rpm": np.where(t < 1200, 8000.0, 0.0),
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


def model_document(machine: str = MACHINE, coefficient: float = 0.002) -> dict[str, Any]:
    """Return a small valid model document reading T1 and T2 (dz of the spindle link, dx of the Z joint)."""
    return {
        "machine": machine,
        "inputs": {
            "T1": {"reference": 20.0, "min": 19.0, "max": 30.0},
            "T2": {"reference": 21.0, "min": 19.0, "max": 30.0},
        },
        "kept_channels": ["T1", "T2"],
        "terms": [
            {
                "element": "T1",
                "param": "dz",
                "axis": "Z",
                "term": "dz",
                "features": [
                    {"kind": "intercept", "name": "const"},
                    {"kind": "dT", "name": "dT[T1]", "channels": ["T1"]},
                ],
                "coefficients": [0.001, coefficient],
                "statistics": {"rmse_train": 0.0005, "n_train": 80},
            },
            {
                "element": "phi_z",
                "param": "dx",
                "axis": "Z",
                "term": "dx",
                "features": [{"kind": "dT", "name": "dT[T2]", "channels": ["T2"]}],
                "coefficients": [0.0005],
                "statistics": {"rmse_train": 0.0004, "n_train": 80},
            },
        ],
    }


@dataclass
class Seeded:
    """A seeded database: its URL, the campaign id and the registered model version."""

    url: str
    campaign_id: int
    model_version: int


def seed(url: str, tmp_path: Path) -> Seeded:
    """Import a small bundle (written with write_bundle) and register one model document."""
    temps, cond, errors = small_frames()
    path = write_bundle(tmp_path / "bundle", small_meta(), temps, cond, errors)
    with connect(url) as store:
        campaign_id = store.import_bundle(load_bundle(path))
        doc = model_registry.register_model(store, model_document(), source_campaigns=[campaign_id])
    return Seeded(url, campaign_id, int(doc.version or 0))
