"""Instrument setups in plans (Table 5.3, figs. 5.7-5.13) and `driftlab plan check`."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from driftlab.campaigns.plan import load_plan, parse_plan
from driftlab.campaigns.setups import Setup, all_cells, deliverable
from driftlab.cli import main
from driftlab.errors import ValidationError

ROOT = Path(__file__).resolve().parents[2]
FULL = ROOT / "examples" / "plans" / "thesis-full.yaml"
DEMO_FULL = ROOT / "examples" / "plans" / "demo-full.yaml"


def _plan(setup: dict, positions=(0.0, 100.0), travel=None, **stage) -> dict:
    doc = {
        "format": "driftlab-plan/1",
        "name": "p",
        "machine": {"id": "m", "channels": {"T1": {"location": "a"}}},
        "scan_interval_s": 60,
        "setups": {"s1": setup},
        "stages": [
            {
                "name": "one",
                "axis": setup["axis"],
                "setup": "s1",
                "duration_s": 3600,
                "sweep": {"positions": list(positions), "interval_s": 600},
                **stage,
            }
        ],
    }
    if travel:
        doc["machine"]["travel"] = travel
    return doc


def test_table_5_3_thirty_terms_each_have_a_setup():
    """Every cell of the five-axis model is delivered by some instrument and fixture (Table 5.3)."""
    kinds = {"laser": ("linear", "straightness", "angular"), "proximity": ("reference_edge", "cylinder", "sphere")}
    got = {f"{ax}/{t}" for inst, ks in kinds.items() for k in ks for ax in "XYZAB" for t in deliverable(inst, k, ax)}
    assert got == set(all_cells())
    # the roll of a linear axis is what the laser cannot see (ch. 5.5): the reference edge gives it
    assert deliverable("laser", "angular", "X") == ("beta", "gamma")
    assert deliverable("proximity", "reference_edge", "X") == ("alpha",)
    assert deliverable("proximity", "cylinder", "A") == ("dx", "dy", "dz", "beta", "gamma")


@pytest.mark.parametrize(
    "setup,message",
    [
        ({"instrument": "laser", "optics": "linear", "axis": "X", "terms": ["alpha"]}, "cannot deliver X/alpha"),
        (
            {"instrument": "laser", "optics": "angular", "axis": "X", "terms": ["beta", "gamma"]},
            "one term per alignment",
        ),
        ({"instrument": "proximity", "fixture": "cylinder", "axis": "X", "terms": ["dx"]}, "measures nothing on the X"),
        ({"instrument": "laser", "fixture": "cylinder", "axis": "X", "terms": ["dx"]}, "names its optics"),
    ],
)
def test_a_setup_that_cannot_deliver_its_terms_is_refused(setup, message):
    with pytest.raises(ValidationError, match=message):
        parse_plan(_plan(setup), "p.yaml")


def test_rotary_sweep_beyond_the_angular_optics_range_is_refused_in_one_line_naming_the_stage():
    setup = {"instrument": "laser", "optics": "angular", "axis": "A", "terms": ["alpha"]}
    with pytest.raises(ValidationError) as exc:
        parse_plan(_plan(setup, positions=(-40.0, 0.0, 40.0)), "p.yaml")
    msg = str(exc.value)
    assert "\n" not in msg and "stages[0] (one)" in msg and "+-10 deg" in msg and "-40, 40" in msg
    # with the counter-rotating table (fig. 5.10) the full travel is measured
    ok = parse_plan(_plan({**setup, "counter_rotating": True}, positions=(-40.0, 0.0, 40.0)), "p.yaml")
    assert [p.position for p in ok.sweep_points()][:3] == [-40.0, 0.0, 40.0]


def test_moves_outside_the_travel_are_refused():
    setup = {"instrument": "laser", "optics": "linear", "axis": "X", "terms": ["dx"]}
    with pytest.raises(ValidationError, match=r"stages\[0\] \(one\): sweep positions 300 outside the X travel 0..254"):
        parse_plan(_plan(setup, positions=(0.0, 300.0), travel={"X": [0, 254]}), "p.yaml")
    posed = {**setup, "pose": {"Z": -400.0}}
    with pytest.raises(ValidationError, match="stands Z at -400, outside its travel"):
        parse_plan(_plan(posed, travel={"X": [0, 254], "Z": [-254, 0]}), "p.yaml")


def test_unknown_setup_and_setup_on_another_axis_are_refused():
    setup = {"instrument": "laser", "optics": "linear", "axis": "X", "terms": ["dx"]}
    doc = _plan(setup)
    doc["stages"][0]["setup"] = "nope"
    with pytest.raises(ValidationError, match="setup 'nope' is not among the plan's setups"):
        parse_plan(doc, "p.yaml")
    doc = _plan(setup)
    doc["stages"][0]["axis"] = "Y"
    with pytest.raises(ValidationError, match="measures the X axis, the stage moves Y"):
        parse_plan(doc, "p.yaml")


def test_sweep_points_carry_their_setup_and_terms():
    plan = parse_plan(
        _plan(
            {
                "instrument": "proximity",
                "fixture": "cylinder",
                "axis": "B",
                "terms": ["dx", "dy", "dz", "alpha", "gamma"],
            },
            positions=(-20.0, 20.0),
        ),
        "p.yaml",
    )
    pts = plan.sweep_points()
    assert {p.setup for p in pts} == {"s1"} and pts[0].terms == ("dx", "dy", "dz", "alpha", "gamma")
    assert plan.missing_terms() == [c for c in all_cells() if c not in {"B/dx", "B/dy", "B/dz", "B/alpha", "B/gamma"}]


def test_legacy_plans_keep_their_laser_term_and_fingerprint():
    plan = load_plan(ROOT / "examples" / "plans" / "z-axis-demo.yaml")
    assert plan.coverage()["Z/dz"] and len(plan.missing_terms()) == 29
    assert {p.setup for p in plan.sweep_points()} == {"laser-Z-dz"}
    # the timeline hash of a plan without setups is what it was before setups existed (resume)
    assert plan.fingerprint() == "ae9d3b8873909f00"


@pytest.mark.parametrize("path", [FULL, DEMO_FULL])
def test_shipped_full_plans_cover_all_thirty_terms(path):
    plan = load_plan(path)
    assert plan.missing_terms() == []
    assert all(s.setup for s in plan.stages)


def test_thesis_full_is_about_a_week_and_in_staged_order():
    plan = load_plan(FULL)
    assert 6 * 86400 <= plan.total_s <= 8 * 86400
    assert plan.staged_order


def test_shipped_plans_are_what_the_generator_writes(tmp_path, monkeypatch):
    import importlib.util

    spec = importlib.util.spec_from_file_location("gen", ROOT / "examples" / "plans" / "generate_full.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    monkeypatch.setattr(gen, "HERE", tmp_path)
    gen.main()
    for name in ("thesis-full.yaml", "demo-full.yaml"):
        assert (tmp_path / name).read_text() == (ROOT / "examples" / "plans" / name).read_text()


def test_plan_check_prints_the_coverage_table(capsys):
    assert main(["plan", "check", str(FULL)]) == 0
    out = capsys.readouterr().out
    assert "30/30 motion-error terms measured" in out
    assert out.splitlines()[2].split()[0] == "X" and "x-roll.base" in out


def test_plan_check_json_and_what_the_model_lacks(capsys):
    assert main(["plan", "check", "--json", str(ROOT / "examples" / "plans" / "demo-z.yaml")]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["measured"] == ["Z/dz"] and len(rep["missing"]) == 29
    assert rep["setups"]["laser-Z-dz"]["optics"] == "linear"


def test_plan_check_error_is_one_line_and_exit_1(tmp_path, capsys):
    doc = _plan({"instrument": "laser", "optics": "angular", "axis": "B", "terms": ["beta"]}, positions=(-30.0, 0.0))
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(doc))
    assert main(["plan", "check", str(p)]) == 2  # ValidationError: bad input
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "stages[0] (one)" in err and "-30" in err


def test_setup_entry_for_bundle_v2():
    s = Setup(instrument="proximity", fixture="reference_edge", axis="Z", terms=["gamma"], pose={"X": 127.0})
    e = s.bundle_entry()
    assert e == {
        "instrument": "proximity",
        "axis": "Z",
        "terms": ["Z/gamma"],
        "datum": "absolute",
        "fixture": "reference_edge",
        "reference": {"pose": {"X": 127.0}},
    }
    assert s.full_pose(-50.0) == {"x": 127.0, "y": 0.0, "z": -50.0, "a": 0.0, "b": 0.0}
