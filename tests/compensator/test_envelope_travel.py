"""The machine's travel travels from the plan to the campaign to the fitted model (issue 24).

A plan's ``machine.travel`` is written into the campaign (campaign.json ``machine.travel``, stored
with the campaign on either database); a model fitted on campaigns carries their travel in its
envelope (the narrowest where campaigns differ), a fit's machine file wins axis by axis, and the
compensator then refuses targets beyond it without any ``--machine-file``.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from driftlab.campaigns.bundle import Bundle, BundleError, load_bundle, write_bundle
from driftlab.campaigns.plan import load_plan
from driftlab.campaigns.store import connect
from driftlab.compensator.compensate import ErrorModel, FirstPass, scan_program
from driftlab.compensator.guard import Guard
from driftlab.daemon.run import run_daemon
from driftlab.errors import ValidationError
from driftlab.jobs.tasks import fit_campaigns
from driftlab.models.fitting import FitOptions
from tests.campaigns.test_live import PLAN, SCENARIO
from tests.models.test_fitting import synthetic_bundle

TRAVEL = {"X": [0.0, 254.0], "Y": [0.0, 254.0], "Z": [-260.0, 10.0]}


def test_a_campaign_carries_its_plans_travel(db_url: str, tmp_path: Path) -> None:
    """The daemon writes the plan's travel into the campaign; the store gives it back with the campaign."""
    plan = tmp_path / "plan.yaml"
    plan.write_text(PLAN.replace("channels: from scenario}", "channels: from scenario, travel: {Z: [-260, 10]}}"))
    scen = tmp_path / "scen.yaml"
    scen.write_text(SCENARIO)
    r = run_daemon(load_plan(plan), db_url=db_url, scenario_path=scen, speed=math.inf, stop_after_commits=2)
    with connect(db_url) as store:
        bundle = store.campaigns.load(r.campaign_id)
    assert bundle.meta.machine.travel == {"Z": (-260.0, 10.0)}
    # and a bundle written from it keeps it (campaign.json machine.travel)
    path = write_bundle(tmp_path / "b", bundle.meta, bundle.temperatures, bundle.conditions, bundle.errors)
    assert load_bundle(path).meta.machine.travel == {"Z": (-260.0, 10.0)}


def test_a_simulated_campaign_on_a_plan_without_travel_carries_the_virtual_machines(tmp_path: Path) -> None:
    """`daemon --sim` on a plan stating no travel writes the virtual machine's (Tables A.3, A.4)."""
    from driftlab.daq.sim.truth import AXIS_RANGE

    db_url = f"sqlite:///{tmp_path / 's.sqlite'}"
    plan = tmp_path / "plan.yaml"
    plan.write_text(PLAN)
    scen = tmp_path / "scen.yaml"
    scen.write_text(SCENARIO)
    r = run_daemon(load_plan(plan), db_url=db_url, scenario_path=scen, speed=math.inf, stop_after_commits=2)
    with connect(db_url) as store:
        bundle = store.campaigns.load(r.campaign_id)
    assert bundle.meta.machine.travel == dict(AXIS_RANGE)
    assert bundle.meta.machine.travel["Z"] == (-254.0, 0.0)


@pytest.mark.parametrize(
    "travel, expected",
    [
        ({"X": [10.0, 0.0]}, "travel of X must be two finite numbers, low < high"),
        ({"X": ["0", 254.0]}, "travel.X.0"),
        ({"X": [True, 254.0]}, "travel.X.0"),
        ({"C": [0.0, 1.0]}, "travel.C"),
    ],
)
def test_a_bad_travel_in_campaign_json_is_refused(tmp_path: Path, travel: dict, expected: str) -> None:
    b = synthetic_bundle(0)
    path = write_bundle(tmp_path / "b", b.meta, b.temperatures, b.conditions, b.errors)
    import json

    doc = json.loads((path / "campaign.json").read_text())
    doc["machine"]["travel"] = travel
    (path / "campaign.json").write_text(json.dumps(doc))
    with pytest.raises(BundleError, match=expected):
        load_bundle(path)


def _with_travel(b: Bundle, travel: dict) -> Bundle:
    machine = b.meta.machine.model_copy(update={"travel": {a: tuple(v) for a, v in travel.items()}})
    return Bundle(b.name, b.meta.model_copy(update={"machine": machine}), b.temperatures, b.conditions, b.errors)


def test_a_fitted_model_carries_the_campaigns_travel_and_the_compensator_holds_to_it(tmp_path: Path) -> None:
    narrower = {**TRAVEL, "X": [5.0, 250.0]}
    with connect(f"sqlite:///{tmp_path / 's.sqlite'}") as store:
        ids = [
            store.campaigns.import_bundle(_with_travel(synthetic_bundle(0), TRAVEL)),
            store.campaigns.import_bundle(_with_travel(synthetic_bundle(1), narrower)),
        ]
        _, doc = fit_campaigns(store, ids, FitOptions(network=False), envelope={"travel": {"Z": [-100.0, 0.0]}})
    assert doc.envelope is not None
    travel = {str(a): list(v) for a, v in doc.envelope.travel.items()}
    # X: the narrowest the campaigns state; Y: theirs; Z: the fit's machine file wins
    assert travel == {"X": [5.0, 250.0], "Y": [0.0, 254.0], "Z": [-100.0, 0.0]}
    model = ErrorModel.from_document(doc.model_dump(mode="json"))
    guard = Guard.for_model(model)  # no machine file: the document's own travel
    prog = tmp_path / "p.nc"
    prog.write_text("G90 G1 F1000\nX100 Y100 Z-50\nX252\n")
    temps = {c: (lo + hi) / 2 for c, (lo, hi) in model.ranges.items()}
    with pytest.raises(ValidationError, match=r"p.nc:3: target X 252 mm is outside the travel 5..250 mm"):
        scan_program(prog, "p.nc", (4, 3), check=FirstPass(guard, model, temps))


def test_campaigns_whose_travels_do_not_overlap_are_refused() -> None:
    from driftlab.models.fitting import campaign_travel

    a = _with_travel(synthetic_bundle(0), {"X": [0.0, 100.0]})
    b = _with_travel(synthetic_bundle(1), {"X": [150.0, 254.0]})
    assert campaign_travel([a]) == {"X": [0.0, 100.0]}
    assert campaign_travel([synthetic_bundle(0)]) == {}
    with pytest.raises(ValidationError, match="travels of X that do not overlap"):
        campaign_travel([a, b])
