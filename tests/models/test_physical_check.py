"""Table 6.3: fitted coefficients against physical ones, with the geometry stated for the machine (ch. 3.5).

The physical coefficient is alpha_c times a length of *this* machine: from ``machine.geometry`` of its
campaigns, never the virtual machine's lengths; with none stated the check says "no geometry".
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from driftlab.campaigns.bundle import Bundle, BundleError, CampaignMeta, load_bundle, write_bundle
from driftlab.daq.sim import truth
from driftlab.models.features import Feature
from driftlab.models.fitting import ElementModel
from driftlab.models.physical_check import (
    STATUS_COMPARED,
    STATUS_CONFLICT,
    STATUS_NO_GEOMETRY,
    machine_geometry,
    physical_check,
)
from driftlab.physics.geometry import Geometry

ROOT = Path(__file__).resolve().parents[2]
ALPHA_C = 12.1e-6  # ch. 3.5: "a typical value for alpha_c is 12.1e-6 /degC"
THESIS = dict(truth.STATED_GEOMETRY)

STRUCTURES = {
    "T32": "spindle_arm",
    "T33": "spindle_arm",
    "T34": "spindle_arm",
    "T35": "spindle_arm",
    "T9": "x_screw",
    "T10": "x_motor",
    "T24": "z_column",
    "T26": "z_column",
    "T49": "room",
    "T50": "room",
}
LOCATIONS = {
    "T32": "spindle arm lower front",
    "T33": "spindle arm upper back",
    "T34": "spindle arm upper front",
    "T35": "spindle arm lower back",
    "T24": "Z column upper front",
    "T26": "Z column lower back",
}
ARM_UL = Feature("gradient", ("T33", "T34", "T32", "T35"), power=2, label="spindle_arm upper-lower")
ARM_FB = Feature("gradient", ("T32", "T34", "T33", "T35"), power=2, label="spindle_arm front-back")


def _model(element, param, *terms):
    """An element model with the given (feature, coefficient) terms (standard errors 1 % of each)."""
    m = ElementModel(element, param)
    for f, c in terms:
        m.features.append(f)
        m.coef.append(c)
        m.std_errors.append(abs(c) / 100)
        m.p_values.append(0.0)
    return m


def _models():
    return {
        ("T1", "alpha"): _model("T1", "alpha", (ARM_UL, 2.3e-5), (ARM_FB, 4e-6)),
        ("T1", "dz"): _model("T1", "dz", (ARM_UL, 0.0045)),
        ("phi_x", "dx"): _model(
            "phi_x",
            "dx",
            (Feature("dT", ("T9",)), 0.0011),
            (Feature("dT", ("T10",)), 0.0007),
            (Feature("pos_dT", ("T9",), label="X"), 1.25e-5),
        ),
        # eq. 3.2 acts along the screw: the X screw's temperature in a straightness term is no ballscrew growth
        ("phi_x", "dy"): _model("phi_x", "dy", (Feature("dT", ("T9",)), 0.0004)),
        ("T2", "dz"): _model("T2", "dz", (Feature("mean", ("T24", "T26"), label="z_column"), 0.0140)),
        # the room's ceiling-floor difference is not a structure bending
        ("T2", "alpha"): _model("T2", "alpha", (Feature("gradient", ("T49", "T50")), 1e-6)),
    }


def _by_term(table):
    return {r["term"]: r for r in table.to_dict("records")}


def test_with_the_thesis_geometry_every_ratio_is_the_hand_calculation():
    check = physical_check(_models(), STRUCTURES, geometry=THESIS, locations=LOCATIONS)
    assert check.status == STATUS_COMPARED
    rows = _by_term(check.table)
    assert set(rows) == {
        "T1.alpha grad[spindle_arm upper-lower]",
        "T1.dz grad[spindle_arm upper-lower]",
        "phi_x.dx dT[T9]+dT[T10]",
        "phi_x.dx pos[X]*dT[T9]",
        "T2.dz mean[z_column]",
    }
    # eq. 3.4: d(theta)/dT = alpha_c L / H = 12.1e-6 * 400 / 200 = 2.42e-5 rad/degC (0.0014 deg/degC, table 6.3)
    r = rows["T1.alpha grad[spindle_arm upper-lower]"]
    assert r["physical"] == pytest.approx(2.42e-5) and r["ratio"] == pytest.approx(2.3e-5 / 2.42e-5)
    assert math.degrees(r["physical"]) == pytest.approx(0.0014, abs=5e-5) and "eq. 3.4" in r["relationship"]
    # eq. 3.5: d(d)/dT = alpha_c L^2 / 2H = 12.1e-6 * 400^2 / 400 = 4.84e-3 mm/degC
    r = rows["T1.dz grad[spindle_arm upper-lower]"]
    assert r["physical"] == pytest.approx(4.84e-3) and r["ratio"] == pytest.approx(0.0045 / 4.84e-3)
    assert "eq. 3.5" in r["relationship"]
    # eq. 3.2: the screw sites' dT together: alpha_c l = 12.1e-6 * 150 = 1.815e-3 mm/degC; per mm of travel: alpha_c
    r = rows["phi_x.dx dT[T9]+dT[T10]"]
    assert r["physical"] == pytest.approx(1.815e-3) and r["ratio"] == pytest.approx(0.0018 / 1.815e-3)
    assert r["std_error"] == pytest.approx(np.hypot(1.1e-5, 0.7e-5))
    assert rows["phi_x.dx pos[X]*dT[T9]"]["ratio"] == pytest.approx(1.25e-5 / ALPHA_C)
    # eqs. 3.1/3.3: the column's mean temperature over its height: alpha_c L = 12.1e-6 * 1200 = 0.01452 mm/degC
    r = rows["T2.dz mean[z_column]"]
    assert r["physical"] == pytest.approx(0.01452) and r["ratio"] == pytest.approx(0.0140 / 0.01452)
    assert set(check.table["status"]) == {STATUS_COMPARED}
    summary = check.to_dict()
    assert summary["compared"] == 5 and summary["geometry"]["bending"]["spindle_arm"]["height_mm"] == 200


def test_the_thesis_worked_example_of_ch_3_5_on_a_machine_with_other_lengths():
    """Ch. 3.5: a 1 degC gradient across 0.5 m over a 1 m length gives 0.0014 deg and 12.1 um."""
    other = {
        **THESIS,
        "bending": {"spindle_arm": {"length_mm": 1000.0, "height_mm": 500.0, "angle": "alpha", "deflection": "dz"}},
        "screw_fixed_mm": {"X": 300.0},
        "links_mm": {"column": [0.0, 400.0, 800.0]},
    }
    mine = _by_term(physical_check(_models(), STRUCTURES, geometry=THESIS, locations=LOCATIONS).table)
    theirs = _by_term(physical_check(_models(), STRUCTURES, geometry=other, locations=LOCATIONS).table)
    assert set(mine) == set(theirs)
    assert math.degrees(theirs["T1.alpha grad[spindle_arm upper-lower]"]["physical"]) == pytest.approx(0.0014, abs=2e-5)
    assert theirs["T1.dz grad[spindle_arm upper-lower]"]["physical"] == pytest.approx(0.0121)
    assert theirs["phi_x.dx dT[T9]+dT[T10]"]["physical"] == pytest.approx(ALPHA_C * 300)
    assert theirs["T2.dz mean[z_column]"]["physical"] == pytest.approx(ALPHA_C * 800)
    # the same fitted coefficients, other physical ones: every length-bearing relationship moves (the
    # angle of eq. 3.4 depends on L/H only, 2 on both machines; the per-mm screw term has no length)
    for term in set(mine) - {"phi_x.dx pos[X]*dT[T9]", "T1.alpha grad[spindle_arm upper-lower]"}:
        assert theirs[term]["physical"] != pytest.approx(mine[term]["physical"], rel=0.05), term
        assert theirs[term]["regression"] == mine[term]["regression"]
    assert theirs["T1.alpha grad[spindle_arm upper-lower]"]["physical"] == pytest.approx(
        mine["T1.alpha grad[spindle_arm upper-lower]"]["physical"]
    )
    stubby = {"bending": {"spindle_arm": {"length_mm": 400.0, "height_mm": 100.0, "angle": "alpha"}}}
    t = _by_term(physical_check(_models(), STRUCTURES, geometry=stubby, locations=LOCATIONS).table)
    assert t["T1.alpha grad[spindle_arm upper-lower]"]["physical"] == pytest.approx(ALPHA_C * 4)  # eq. 3.4, L/H = 4
    assert "T1.dz grad[spindle_arm upper-lower]" not in t  # no deflection stated for this arm


def test_without_a_stated_geometry_the_check_says_so_and_compares_nothing():
    class B:
        def __init__(self, name, geometry=None):
            self.name = name
            self.meta = CampaignMeta.model_validate(
                {
                    "format": "driftlab-bundle/1",
                    "machine": {"id": "mill-7", **({"geometry": geometry} if geometry else {})},
                    "started_at": "2026-03-02T08:00:00Z",
                    "channels": {"T9": {}},
                }
            )

    check = physical_check(_models(), STRUCTURES, [B("a"), B("b")], locations=LOCATIONS)
    assert check.status == STATUS_NO_GEOMETRY == "no geometry"
    assert check.table.empty and check.geometry is None
    assert "mill-7" in check.note and "machine.geometry" in check.note
    assert check.to_dict() == {"status": "no geometry", "note": check.note, "geometry": None, "rows": 0, "compared": 0}
    # one campaign stating it is enough; two stating different lengths is a conflict, not a guess
    assert machine_geometry([B("a"), B("b", THESIS)])[0] == STATUS_COMPARED
    other = {**THESIS, "screw_fixed_mm": {"X": 200.0}}
    status, g, note = machine_geometry([B("a", THESIS), B("b", other)])
    assert status == STATUS_CONFLICT and g is None and "different geometries" in note
    assert physical_check(_models(), STRUCTURES, [B("a", THESIS), B("b", other)]).table.empty


def test_a_relationship_whose_length_is_not_stated_is_listed_but_not_compared():
    partial = {"bending": THESIS["bending"]}
    t = _by_term(physical_check(_models(), STRUCTURES, geometry=partial, locations=LOCATIONS).table)
    assert t["phi_x.dx dT[T9]+dT[T10]"]["status"] == "not stated: screw_fixed_mm.X"
    assert t["T2.dz mean[z_column]"]["status"] == "not stated: links_mm.column"
    assert math.isnan(t["T2.dz mean[z_column]"]["physical"]) and math.isnan(t["T2.dz mean[z_column]"]["ratio"])
    assert t["T1.alpha grad[spindle_arm upper-lower]"]["status"] == STATUS_COMPARED


# ----------------------------------------------------------------------------- where the geometry is stated


def test_geometry_is_validated_in_campaign_json(tmp_path):
    from tests.models.test_fitting import synthetic_bundle

    b = synthetic_bundle(0)
    doc = b.meta.document()
    write_bundle(tmp_path / "none", b.meta, b.temperatures, None, b.errors)
    assert load_bundle(tmp_path / "none").meta.machine.geometry is None
    doc["machine"]["geometry"] = THESIS
    meta = CampaignMeta.model_validate(doc)
    write_bundle(tmp_path / "geo", meta, b.temperatures, None, b.errors)
    back = load_bundle(tmp_path / "geo")
    assert back.meta.machine.geometry == Geometry.model_validate(THESIS)
    assert back.content_hash() != load_bundle(tmp_path / "none").content_hash()
    # a wrong length is refused as one line naming the file, the line and the field
    raw = json.loads((tmp_path / "geo" / "campaign.json").read_text())
    raw["machine"]["geometry"]["bending"]["spindle_arm"]["height_mm"] = -200
    (tmp_path / "geo" / "campaign.json").write_text(json.dumps(raw, indent=1))
    with pytest.raises(BundleError, match=r"^campaign\.json:\d+: machine\.geometry\.bending\.spindle_arm\.height_mm"):
        load_bundle(tmp_path / "geo")
    raw["machine"]["geometry"] = {"source": "nothing stated"}
    (tmp_path / "geo" / "campaign.json").write_text(json.dumps(raw))
    with pytest.raises(BundleError, match="states at least one of"):
        load_bundle(tmp_path / "geo")


def test_geometry_round_trips_through_the_store(tmp_path):
    from driftlab.campaigns.store import connect
    from tests.models.test_fitting import synthetic_bundle

    b = synthetic_bundle(0)
    doc = b.meta.document()
    doc["machine"]["geometry"] = THESIS
    b = Bundle(b.name, CampaignMeta.model_validate(doc), b.temperatures, None, b.errors)
    store = connect(f"sqlite:///{tmp_path / 's.sqlite'}")
    cid = store.campaigns.import_bundle(b)
    assert store.campaigns.load(cid).meta.machine.geometry == Geometry.model_validate(THESIS)
    store.close()


@pytest.mark.parametrize(
    "path",
    [
        "scenarios/thesis.yaml",
        "scenarios/demo-full.yaml",
        "scenarios/reference.yaml",
        "scenarios/clean.yaml",
        "plans/thesis-full.yaml",
        "plans/demo-full.yaml",
    ],
)
def test_the_shipped_thesis_machine_states_the_virtual_machines_geometry(path):
    """The demo and the thesis comparisons show table 6.3: their scenarios and plans state the lengths."""
    doc = yaml.safe_load((ROOT / "examples" / path).read_text())
    assert Geometry.model_validate(doc["machine"]["geometry"]) == Geometry.model_validate(THESIS)
    # the lengths are the ones the virtual machine's truth is built with (eqs. 3.2, 3.4, 3.5; Table A.1)
    assert THESIS["bending"]["spindle_arm"]["length_mm"] == truth.L_ARM
    assert THESIS["bending"]["spindle_arm"]["height_mm"] == truth.H_ARM
    assert set(THESIS["screw_fixed_mm"].values()) == {truth.L_SCREW_FIXED}


def test_plan_and_scenario_stating_different_geometries_are_refused(tmp_path):
    from driftlab.campaigns.plan import load_plan
    from driftlab.daemon.run import run_daemon
    from driftlab.errors import ValidationError

    doc = yaml.safe_load((ROOT / "examples" / "plans" / "z-axis-demo.yaml").read_text())
    doc["machine"]["geometry"] = {**THESIS, "screw_fixed_mm": {"Z": 90.0}}
    p = tmp_path / "plan.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(ValidationError, match="different geometries"):
        run_daemon(
            load_plan(p),
            db_url=f"sqlite:///{tmp_path / 'd.sqlite'}",
            scenario_path=ROOT / "examples" / "scenarios" / "thesis.yaml",
            speed=math.inf,
        )
