"""Helpers of the API tests: a small bundle, a model document, seeding a database."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.campaigns.store import connect
from driftlab.jobs import registry as model_registry
from driftlab.testing import smallbundle

TOKEN = "test-token-0123456789"
MACHINE = "vmc-api-01"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def small_meta(machine: str = MACHINE, started_at: str = "2026-03-02T08:00:00Z") -> dict[str, Any]:
    """Return a campaign.json with four channels (two room) and two Z-axis stages of 20 minutes each."""
    return smallbundle.small_meta(machine, started_at, name="API test VMC", scans=80, noise=False)


def small_frames(seed: int = 0, scans: int = 80, sweeps: int = 8) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Return temperatures (one missing cell), conditions and Z-axis errors of a short campaign."""
    return smallbundle.small_frames(seed, scans, sweeps)


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
        campaign_id = store.campaigns.import_bundle(load_bundle(path))
        doc = model_registry.register_model(store, model_document(), source_campaigns=[campaign_id])
    return Seeded(url, campaign_id, int(doc.version or 0))
