"""The HTML reports a person reads: the campaign overview, findings in words, µm/µrad, one colour scale for the maps,
no JSON."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path

import numpy as np
import pytest

from driftlab.campaigns.bundle import write_bundle
from driftlab.cli import main
from driftlab.commands import demo_report
from tests import effects_generator as gen

RAW_NAME = re.compile(r"\b(lag_T\d+|time_days|dT_T\d+|tau_s|start_s)\b")


@pytest.fixture(scope="module")
def lag_bundle(tmp_path_factory) -> Path:
    """A bundle from the virtual machine with a thermal lag hidden on Z/dz (not in the model's form)."""
    case = gen.vm_case([gen.Planted("thermal_lag", "Z", "dz", ["T34"], {"tau_s": 2400.0})], seed=11, hours=30)
    b = case.bundle
    return write_bundle(tmp_path_factory.mktemp("bundles") / "lag-z", b.meta, b.temperatures, b.conditions, b.errors)


def test_diagnosis_page_reads_as_words(lag_bundle: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    monkeypatch.setenv("COLUMNS", "120")  # a wide terminal keeps each effect's name on one line (80: it wraps)
    js, page = tmp_path / "r.json", tmp_path / "r.html"
    assert main(["diagnose", str(lag_bundle), "--json", str(js), "--html", str(page)]) == 0
    out = capsys.readouterr().out
    doc = json.loads(js.read_text())
    html = page.read_text()
    [eff] = doc["effects"]
    tau_min = round(eff["params"]["tau_s"] / 60)
    # the terminal lists the finding, its cause and its held-out gain in um
    assert f"thermal lag of T34, tau {tau_min} min" in out and " µm " in out
    assert "1 effect accepted" in out
    # the page: an overview of the campaign first (stage table, one figure), then the finding in words
    assert html.index("<h2>The campaign</h2>") < html.index("<h2>Findings (1)</h2>")
    assert all(st["name"] in html for st in json.loads((lag_bundle / "campaign.json").read_text())["stages"])
    assert 'alt="campaign overview: stages, temperatures and errors over time"' in html
    assert f"thermal lag of T34, tau {tau_min} min, on Z/dz" in html and f"time constant {tau_min} min" in html
    assert "Lengths are in micrometres (µm), angles in microradians (µrad)" in html
    text = re.sub(r'src="data:image/png;base64,[^"]+"', "", html)
    assert not RAW_NAME.search(text), RAW_NAME.search(text)
    assert "{&quot;" not in text and '{"' not in text  # no raw JSON
    assert "(mm)" not in text.replace("feed (mm/min)", "")


def test_demo_page_has_one_scale_for_its_maps_in_um_and_no_json() -> None:
    rng = np.random.default_rng(0)
    dev = {
        "uncompensated": rng.normal(0, 0.06, (99, 15)),
        "offline": rng.normal(0, 0.005, (99, 15)),
        "online": rng.normal(0, 0.003, (99, 15)),
    }
    table = {k: {"rmse_mm": float(np.sqrt(np.mean(v**2))), "max_mm": float(np.max(np.abs(v)))} for k, v in dev.items()}
    diag = demo_report.diagnosis_summary(
        {
            "effects": [
                {
                    "kind": "thermal_lag",
                    "axis": "Z",
                    "term": "dz",
                    "channels": ["T34"],
                    "params": {"tau_s": 3000.0},
                    "p_value": 1e-9,
                    "cause": "the arm lags its thermocouple",
                    "rmse_holdout_before": 0.004,
                    "rmse_holdout_after": 0.001,
                }
            ]
        }
    )
    report = demo_report.build_report(
        table=table,
        diagnosis=diag,
        steps=[{"name": "fit", "command": "driftlab fit --campaign 1", "wall_s": 12.0}],
        extra={
            "planted": [
                {"kind": "thermal_lag", "axis": "Z", "term": "dz", "channels": ["T34"], "params": {"tau_s": 3000}}
            ],
            "wall_s": 95.0,
        },
    )
    png = demo_report.surface_figure(dev)
    html = demo_report.to_html(report, png)
    text = re.sub(r'src="data:image/png;base64,[^"]+"', "", html)
    assert "RMSE (µm)" in text and f"{table['offline']['rmse_mm'] * 1e3:.1f}" in text and " um" not in text
    # verdicts like with like: the uncompensated run is a baseline, a compensated one is judged by its reduction
    assert "<td>as in the thesis" not in text and "baseline (the thesis&#x27; machine: 60 µm)" in text
    ours = 1 - table["offline"]["rmse_mm"] / table["uncompensated"]["rmse_mm"]
    assert f"removes {ours:.0%} of the error" in text and "(92%)" in text
    assert "thermal lag of T34, tau 50 min on Z/dz" in text  # the planted effect, in words
    assert "{" not in text.split("<body>")[1] and "tau_s" not in text
    assert base64.b64decode(png).startswith(b"\x89PNG")
    fig = demo_report.surface_axes(dev)
    maps = [ax for ax in fig.axes if ax.images]
    assert len(maps) == 3 and len(fig.axes) == 4  # three maps, one colour bar
    top = max(np.max(np.abs(v)) for v in dev.values()) * 1e3
    for ax, (_k, v) in zip(maps, dev.items()):
        lo, hi = ax.images[0].get_clim()
        assert hi == pytest.approx(top) and lo == -hi  # one symmetric scale for all, in µm
        assert f"range {v.min() * 1e3:+.1f} .. {v.max() * 1e3:+.1f} µm" in ax.get_title()
    # the JSON document keeps its keys
    assert {
        "format",
        "uncompensated",
        "offline",
        "online",
        "diagnosis",
        "thesis",
        "ordering_holds",
        "steps",
        "planted",
        "wall_s",
    } <= set(report)


def test_the_demo_report_judges_the_order_at_the_compensators_resolution():
    from driftlab.commands import demo_report
    from driftlab.compensator.compensate import RESOLUTION_MM

    assert demo_report.RESOLUTION_MM == RESOLUTION_MM
    runs = {"uncompensated": {"rmse_mm": 0.005}, "offline": {"rmse_mm": 0.0009}, "online": {"rmse_mm": 0.0019}}
    assert "within the machine's 2.5 µm step" in demo_report.ordering_text(runs)
    runs["online"]["rmse_mm"] = 0.0004
    assert demo_report.ordering_text(runs) == "holds"
    runs["online"]["rmse_mm"] = 0.003  # beyond the step: no excuse given
    assert demo_report.ordering_text(runs) == "does not hold"
