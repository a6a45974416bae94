"""Bundle v2 (spec "Bundle v2"): the full commanded pose and the instrument setup of every reading."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import BundleError, load_bundle, write_bundle
from driftlab.campaigns.store import connect

from .conftest import make_bundle, small_frames, small_meta

SETUPS = {
    "z-pos": {"instrument": "laser", "optics": "linear", "axis": "Z", "terms": ["Z/dz"], "datum": "session"},
    "z-str": {"instrument": "laser", "optics": "straightness", "axis": "Z", "terms": ["Z/dx"]},
    "z-roll": {
        "instrument": "proximity",
        "fixture": "reference_edge",
        "axis": "Z",
        "terms": ["Z/gamma"],
        "datum": "absolute",
        "reference": {"artefact": "parallel reference lines", "u_rad": 1e-7},
    },
}


def _v2(tmp_path: Path, edit_errors=None, edit_meta=None) -> Path:
    temps, cond, errors = small_frames()
    errors = errors.copy()
    errors["x"], errors["y"], errors["z"], errors["a"], errors["b"] = 127.0, 63.5, errors["position"], 0.0, -10.0
    errors["setup"] = errors["term"].map({"dz": "z-pos", "dx": "z-str", "gamma": "z-roll"})
    meta = {**small_meta(), "format": "driftlab-bundle/2", "setups": json.loads(json.dumps(SETUPS))}
    if edit_errors:
        errors = edit_errors(errors)
    if edit_meta:
        edit_meta(meta)
    return write_bundle(tmp_path / "v2", meta, temps, cond, errors)


def test_v2_round_trips_through_the_file_with_pose_and_setup(tmp_path):
    b = load_bundle(_v2(tmp_path))
    assert b.meta.v2 and set(b.meta.setups) == set(SETUPS)
    head = (tmp_path / "v2" / "errors.csv").read_text().splitlines()[0]
    assert head == "time_s,axis,term,position,direction,x,y,z,a,b,setup,value"
    assert (b.errors["z"] == b.errors["position"]).all() and (b.errors["x"] == 127.0).all()
    assert set(b.errors["setup"]) == {"z-pos", "z-str", "z-roll"}
    again = load_bundle(write_bundle(tmp_path / "again", b.meta, b.temperatures, b.conditions, b.errors))
    pd.testing.assert_frame_equal(b.errors, again.errors, check_exact=True)
    assert b.content_hash() == again.content_hash()


def test_v2_imports_and_exports_exactly_on_both_databases(store_url, tmp_path):
    original = load_bundle(_v2(tmp_path))
    store = connect(store_url)
    try:
        stored = store.campaigns.load(store.campaigns.import_bundle(original))
    finally:
        store.close()
    pd.testing.assert_frame_equal(original.errors, stored.errors, check_exact=True)
    assert stored.meta == original.meta and stored.content_hash() == original.content_hash()


def test_v1_bundles_still_import_and_keep_their_hash(store_url, tmp_path):
    b = load_bundle(make_bundle(tmp_path / "v1"))
    assert not b.meta.v2 and list(b.errors.columns) == ["time_s", "axis", "term", "position", "direction", "value"]
    store = connect(store_url)
    try:
        stored = store.campaigns.load(store.campaigns.import_bundle(b))
    finally:
        store.close()
    assert stored.content_hash() == b.content_hash() and not stored.meta.v2


def _row_of(errors: pd.DataFrame, mask) -> int:
    return int(np.flatnonzero(mask)[0]) + 2  # header is line 1


@pytest.mark.parametrize(
    "name,edit_errors,edit_meta,message",
    [
        (
            "unknown-setup",
            lambda e: e.assign(setup=e["setup"].where(e.index != 5, "nope")),
            None,
            "column setup: 'nope' is not among campaign.json setups",
        ),
        ("term-not-in-setup", lambda e: e.assign(setup="z-pos"), None, "setup 'z-pos' does not deliver Z/dx"),
        (
            "pose-mismatch",
            lambda e: e.assign(z=e["z"].where(e.index != 7, e["z"] + 1.0)),
            None,
            "differs from position",
        ),
        ("missing-pose", lambda e: e.assign(b=e["b"].where(e.index != 3, np.nan)), None, "column b: missing value"),
        ("bad-setup-term", None, lambda m: m["setups"]["z-pos"].update(terms=["Z/dw"]), "is not AXIS/term"),
        ("setup-other-axis", None, lambda m: m["setups"]["z-pos"].update(terms=["X/dx"]), "lists terms of another"),
    ],
)
def test_v2_refusals_are_one_line(tmp_path, name, edit_errors, edit_meta, message):
    path = _v2(tmp_path, edit_errors=edit_errors, edit_meta=None)
    if edit_meta:
        doc = json.loads((path / "campaign.json").read_text())
        edit_meta(doc)
        (path / "campaign.json").write_text(json.dumps(doc))
    with pytest.raises(BundleError) as exc:
        load_bundle(path)
    msg = str(exc.value)
    assert message in msg and "\n" not in msg
    assert msg.startswith("errors.csv:" if edit_errors else "campaign.json:")


def test_the_row_of_a_refused_reading_is_named(tmp_path):
    path = _v2(tmp_path, edit_errors=lambda e: e.assign(setup=e["setup"].where(e.index != 5, "nope")))
    with pytest.raises(BundleError, match=r"^errors.csv:7: column setup"):
        load_bundle(path)


def test_a_daemon_campaign_exports_as_v2_with_every_setup(tmp_path):
    from driftlab.campaigns.plan import parse_plan
    from driftlab.daemon.run import run_daemon

    plan = parse_plan(
        {
            "format": "driftlab-plan/1",
            "name": "v2-daemon",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 120,
            "setups": {
                "b-run": {
                    "instrument": "proximity",
                    "fixture": "cylinder",
                    "axis": "B",
                    "terms": ["dx", "dy", "dz", "alpha", "gamma"],
                },
                "x-pos": {"instrument": "laser", "optics": "linear", "axis": "X", "terms": ["dx"]},
            },
            "stages": [
                {
                    "name": "b",
                    "axis": "B",
                    "setup": "b-run",
                    "duration_s": 1800,
                    "sweep": {"positions": [-20, 20], "interval_s": 900, "point_s": 6},
                },
                {
                    "name": "x",
                    "axis": "X",
                    "setup": "x-pos",
                    "duration_s": 1800,
                    "sweep": {"positions": [0, 254], "interval_s": 900, "point_s": 6},
                },
            ],
        },
        "p.yaml",
    )
    db = f"sqlite:///{tmp_path / 'd.sqlite'}"
    root = Path(__file__).resolve().parents[2]
    res = run_daemon(plan, db_url=db, scenario_path=root / "examples" / "scenarios" / "clean.yaml", speed=math.inf)
    store = connect(db)
    try:
        b = store.campaigns.load(res.campaign_id)
    finally:
        store.close()
    out = load_bundle(write_bundle(tmp_path / "exp", b.meta, b.temperatures, b.conditions, b.errors))
    assert out.meta.v2 and out.meta.setups["b-run"].terms == ["B/dx", "B/dy", "B/dz", "B/alpha", "B/gamma"]
    assert out.meta.setups["x-pos"].datum == "session" and out.meta.setups["b-run"].datum == "absolute"
    e = out.errors
    assert set(e.loc[e.axis == "B", "term"]) == {"dx", "dy", "dz", "alpha", "gamma"}
    assert (e.loc[e.axis == "B", "b"] == e.loc[e.axis == "B", "position"]).all()
    assert (e.loc[e.axis == "X", ["y", "z", "a", "b"]] == 0.0).all().all()
    assert set(e.loc[e.axis == "X", "setup"]) == {"x-pos"}
