"""`driftlab demo` end to end (a shorter cutting program): daemon, fit, diagnosis, API, streamed cutting test."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from driftlab.cli import main
from driftlab.daq.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Run the demo once into a temporary directory; return it."""
    out = tmp_path_factory.mktemp("demo") / "out"
    assert main(["demo", "--out", str(out), "--passes", "120"]) == 0
    return out


def test_demo_writes_its_reports(demo_out: Path) -> None:
    for name in (
        "demo-report.html",
        "demo-report.json",
        "diagnosis.html",
        "diagnosis.json",
        "fit-report.json",
        "driftlab.sqlite",
        "campaign-bundle/campaign.json",
    ):
        assert (demo_out / name).is_file(), name
    page = (demo_out / "demo-report.html").read_text()
    assert "Cutting test" in page and "data:image/png;base64," in page and 'href="diagnosis.html"' in page
    assert "off-line model predicted RMSE" in page and "of the CMM points inside their interval" in page


def test_demo_report_has_the_table_and_the_ordering(demo_out: Path) -> None:
    rep = json.loads((demo_out / "demo-report.json").read_text())
    for key in ("uncompensated", "offline", "online"):
        assert {"rmse_mm", "max_mm"} <= set(rep[key]), key
        assert 0 < rep[key]["rmse_mm"] <= rep[key]["max_mm"]
    assert rep["uncompensated"]["rmse_mm"] > rep["offline"]["rmse_mm"] > rep["online"]["rmse_mm"]
    assert rep["ordering_holds"] is True
    # the demo's plan measures all thirty terms, and the fitted model holds every one
    cells = {f"{a}/{t}" for a in "XYZAB" for t in ("dx", "dy", "dz", "alpha", "beta", "gamma")}
    assert set(rep["coverage"]["measured"]) == cells and set(rep["coverage"]["modelled"]) == cells
    assert rep["online"]["probe_cycles"] >= 1 and rep["online"]["updates"]
    # two cutting tests: the campaign's machine, and the same machine worn; the wear is what the on-line
    # model is for, so on the worn machine the off-line model alone falls behind the on-line one
    thermal, worn = rep["cutting_tests"]
    assert (thermal["case"], worn["case"]) == ("thermal", "thermal+wear")
    for c in (thermal, worn):
        assert c["uncompensated_mm"] > c["offline_mm"] > 0 and c["online_mm"] > 0
    assert worn["uncompensated_mm"] > thermal["uncompensated_mm"]
    assert worn["offline_mm"] > 2 * worn["online_mm"]
    assert worn["online_mm"] == rep["online"]["rmse_mm"]  # the top-level table is the thermal+wear case
    # beside each measured off-line cut, the model's own predicted spread of it (issue 21.4)
    for c in (thermal, worn):
        p = c["offline_predicted"]
        assert p["measured_rmse_mm"] == c["offline_mm"] and p["predicted_rmse_mm"] > 0 and 0 <= p["inside"] <= 1
    # every step is the real component, in order
    names = [s["name"] for s in rep["steps"]]
    assert names == [
        "daemon",
        "fit",
        "export",
        "diagnose",
        "serve",
        "cutting test (thermal)",
        "cutting test (thermal+wear)",
    ]
    assert rep["steps"][0]["command"].startswith("driftlab daemon --plan")
    assert rep["campaign"]["finished"] is True and rep["campaign"]["points"] > 0
    # the model came from the API with an ETag, and a repeated request was answered 304
    assert rep["model"]["version"] == 1 and rep["model"]["etag"]
    assert rep["model"]["if_none_match_status"] == 304
    assert rep["offline"]["stream"]["blocks_sent"] == rep["offline"]["blocks"] - 1


def test_demo_diagnosis_names_the_planted_effect(demo_out: Path) -> None:
    rep = json.loads((demo_out / "demo-report.json").read_text())
    planted = load_scenario(ROOT / "examples" / "scenarios" / "demo-full.yaml").hidden
    assert rep["planted"] == [e.model_dump() for e in planted]
    (eff,) = planted
    found = [
        f for f in rep["diagnosis"]["effects"] if (f["kind"], f["axis"], f["term"]) == (eff.kind, eff.axis, eff.term)
    ]
    assert found, rep["diagnosis"]
    mag = float(eff.params["magnitude_mm"])
    assert abs(found[0]["params"]["magnitude_mm"] - mag) < 0.25 * mag


@pytest.mark.parametrize(
    "bad",
    [
        ["--passes", "10"],
        ["--forgetting", "0.3"],
        ["--age-days", "-1"],
        ["--wear-um-per-day", "0"],
        ["--plan", "no-such-plan.yaml"],
    ],
)
def test_demo_refuses_bad_options_before_any_work(
    tmp_path: Path, bad: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["demo", "--out", str(out), *bad]) == 2
    err = capsys.readouterr().err
    assert err.startswith("driftlab: error: ") and err.count("\n") == 1
    assert not out.exists()
