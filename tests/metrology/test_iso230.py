"""ISO 230-2 against a plain loop of the standard's definitions; ISO 230-3 on a staged virtual campaign; the CLI."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import Bundle, CampaignMeta, write_bundle
from driftlab.cli import main
from driftlab.daq.sim.campaign import simulate_campaign
from driftlab.daq.sim.scenario import Scenario
from driftlab.metrology import iso230_2, iso230_3
from driftlab.metrology.iso230_2 import PositioningRunError


def reference_iso230_2(readings: list[tuple[float, int, float]]) -> dict:
    """Return the axis figures by a plain loop over the definitions (no numpy), for readings in measuring order."""
    runs: list[tuple[int, dict[float, float]]] = []
    for pos, d, x in readings:
        if not runs or runs[-1][0] != d:
            runs.append((d, {}))
        runs[-1][1][round(pos, 6)] = x
    up = [r for d, r in runs if d > 0]
    down = [r for d, r in runs if d < 0]
    targets = sorted(up[0])
    n = len(up)

    def mean(vals):
        return sum(vals) / len(vals)

    def sd(vals):
        m = mean(vals)
        return math.sqrt(sum((v - m) ** 2 for v in vals) / (len(vals) - 1))

    xu = {t: mean([r[t] for r in up]) for t in targets}
    xd = {t: mean([r[t] for r in down]) for t in targets}
    su = {t: sd([r[t] for r in up]) for t in targets}
    sdn = {t: sd([r[t] for r in down]) for t in targets}
    assert n == len(down)
    B = {t: xu[t] - xd[t] for t in targets}
    xb = {t: (xu[t] + xd[t]) / 2 for t in targets}
    Ru = {t: 4 * su[t] for t in targets}
    Rd = {t: 4 * sdn[t] for t in targets}
    Rj = {t: max(2 * su[t] + 2 * sdn[t] + abs(B[t]), Ru[t], Rd[t]) for t in targets}
    out = {
        "A_up": max(xu[t] + 2 * su[t] for t in targets) - min(xu[t] - 2 * su[t] for t in targets),
        "A_down": max(xd[t] + 2 * sdn[t] for t in targets) - min(xd[t] - 2 * sdn[t] for t in targets),
        "B": max(abs(B[t]) for t in targets),
        # ISO 230-2:2014 mean reversal value of an axis: the mean of the signed B_j over the targets
        "B_mean": sum(B[t] for t in targets) / len(targets),
        "E_up": max(xu.values()) - min(xu.values()),
        "E_down": max(xd.values()) - min(xd.values()),
        "M": max(xb.values()) - min(xb.values()),
        "R_up": max(Ru.values()),
        "R_down": max(Rd.values()),
        "R": max(Rj.values()),
    }
    out["A"] = max(max(xu[t] + 2 * su[t], xd[t] + 2 * sdn[t]) for t in targets) - min(
        min(xu[t] - 2 * su[t], xd[t] - 2 * sdn[t]) for t in targets
    )
    out["E"] = max(list(xu.values()) + list(xd.values())) - min(list(xu.values()) + list(xd.values()))
    out["targets"] = {t: (xu[t], xd[t], su[t], sdn[t], B[t], Rj[t]) for t in targets}
    return out


def synthetic_runs(seed: int, n_runs: int = 5, targets=None, shuffle_down=False) -> list[tuple[float, int, float]]:
    """Return readings of n_runs bidirectional runs: scale error, backlash, noise (mm)."""
    rng = np.random.default_rng(seed)
    targets = np.array([0.0, 97.3, 203.1, 298.8, 401.2, 502.5, 598.9]) if targets is None else targets
    out = []
    for _ in range(n_runs):
        for t in targets:
            out.append((float(t), 1, 2e-5 * t + 0.003 + rng.normal(0, 0.0015)))
        down = targets[::-1] if not shuffle_down else rng.permutation(targets)
        for t in down:
            out.append((float(t), -1, 2e-5 * t - 0.004 + rng.normal(0, 0.002)))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_iso230_2_figures_equal_a_plain_loop_of_the_definitions(seed):
    readings = synthetic_runs(seed, n_runs=3 + seed, shuffle_down=seed % 2 == 1)
    pos, d, x = (np.array(c) for c in zip(*readings))
    res = iso230_2.evaluate(pos, d, x)
    ref = reference_iso230_2(readings)
    worst = max(abs(res.figures[k] - ref[k]) for k in iso230_2.FIGURES)
    assert worst < 1e-9, worst
    for j, t in enumerate(res.targets):
        xu, xd, su, sdn, b, rj = ref["targets"][t]
        got = (res.xbar_up[j], res.xbar_down[j], res.s_up[j], res.s_down[j], res.reversal[j], res.R_j[j])
        assert np.allclose(got, (xu, xd, su, sdn, b, rj), rtol=0, atol=1e-12)
    doc = res.to_json_dict()
    assert set(doc) == set(iso230_2.FIGURES) | {"targets"}
    assert len(doc["targets"]) == 7
    # the planted backlash: reversal about 7 um everywhere; A covers E and the repeatability
    assert 0.004 < res.figures["B"] < 0.012
    assert res.figures["A"] >= res.figures["E"] and res.figures["A"] >= res.figures["A_up"]


def test_iso230_2_rotary_axis_in_arcsec():
    rows = []
    rng = np.random.default_rng(5)
    for _ in range(3):
        for d, order in ((1, [0.0, 90.0, 180.0, 270.0]), (-1, [270.0, 180.0, 90.0, 0.0])):
            for p in order:
                rows.append(
                    {
                        "time_s": float(len(rows)),
                        "axis": "A",
                        "term": "alpha",
                        "position": p,
                        "direction": d,
                        "value": 1e-5 * d + rng.normal(0, 1e-6),
                    }
                )
    res = iso230_2.from_bundle_errors(pd.DataFrame(rows), "A")
    assert res.unit == "arcsec"
    assert res.figures["B"] == pytest.approx(2e-5 * iso230_2.ARCSEC_PER_RAD, rel=0.2)  # about 4.1 arcsec


@pytest.mark.parametrize(
    "mutate,needle",
    [
        (lambda r: r[:-7], "5 up runs but 4 down runs"),
        (lambda r: [x for i, x in enumerate(r) if i != 3], "up run 1 misses target 298.8"),
        (lambda r: [x for x in r if x[1] > 0], "needs runs in both directions"),
        (lambda r: r[:14], "one run per direction"),
    ],
)
def test_iso230_2_refuses_readings_that_are_not_paired_runs(mutate, needle):
    readings = mutate(synthetic_runs(0))
    pos, d, x = (np.array(c) for c in zip(*readings))
    with pytest.raises(PositioningRunError, match=needle):
        iso230_2.evaluate(pos, d, x)


@pytest.fixture(scope="module")
def vm_bundle(tmp_path_factory):
    """A 24 h staged campaign on the virtual machine, sweeps every 30 min, written as a bundle."""
    sim = simulate_campaign(Scenario(name="iso", hours=24, seed=2, sweep_interval_s=1800))
    path = tmp_path_factory.mktemp("iso") / "bundle"
    write_bundle(path, sim.meta, sim.temperatures, sim.conditions, sim.errors)
    return path, Bundle("iso", CampaignMeta.model_validate(sim.meta), sim.temperatures, sim.conditions, sim.errors)


def test_cli_iso230_part2_json_and_html(vm_bundle, tmp_path, capsys):
    path, bundle = vm_bundle
    out, page = tmp_path / "x.json", tmp_path / "x.html"
    assert main(["iso230", str(path), "--part", "2", "--axis", "X", "--json", str(out), "--html", str(page)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc) == set(iso230_2.FIGURES) | {"targets", "drift_between_runs", "warning", "conditions"}
    rows = bundle.errors[(bundle.errors["axis"] == "X") & (bundle.errors["term"] == "dx")]
    ref = reference_iso230_2(list(zip(rows["position"], rows["direction"], rows["value"])))
    assert max(abs(doc[k] - ref[k]) for k in iso230_2.FIGURES) < 1e-9
    assert len(doc["targets"]) == 11  # points_per_axis
    text = page.read_text()
    assert "data:image/png;base64," in text
    # a metrologist's page: the conditions, values in µm without e-notation, the warning about thermal drift
    assert "Test conditions" in text and "air temperature" in text and "B̄ (mean reversal value)" in text
    assert "µm" in text and not re.search(r"\d[eE][-+]\d", text.split("data:image")[0] + text.split('">')[-1])
    assert doc["warning"] and "thermal drift" in doc["warning"]
    out_text = capsys.readouterr().out
    assert "ISO 230-2" in out_text and "µm" in out_text and "warning: the runs span thermal drift" in out_text


def _drifting(readings, drift_per_run: float):
    """The same runs with a deviation that grows by ``drift_per_run`` from one pair of runs to the next."""
    out, pair, last = [], -1, None
    for pos, d, x in readings:
        if d > 0 and last != d:
            pair += 1
        last = d
        out.append((pos, d, x + drift_per_run * pair))
    return out


def test_iso230_2_warns_when_the_runs_span_thermal_drift():
    readings = synthetic_runs(0, n_runs=8)
    pos, d, x = (np.array(c) for c in zip(*readings))
    steady = iso230_2.evaluate(pos, d, x)
    assert steady.drift_warning is None
    pos, d, x = (np.array(c) for c in zip(*_drifting(readings, 0.002)))
    drifting = iso230_2.evaluate(pos, d, x)
    # 2 um per pair of runs over 8 pairs: the runs' means wander by 14 um, and R carries it
    assert drifting.drift == pytest.approx(steady.drift + 0.014, abs=0.002)
    assert drifting.drift_warning and "thermal drift" in drifting.drift_warning
    assert drifting.figures["R"] > steady.figures["R"]
    # B-bar, the mean reversal value: the signed mean of B_j, not max |B_j|
    assert drifting.figures["B_mean"] == pytest.approx(np.mean(drifting.reversal), abs=1e-15)


def test_iso230_2_per_stage_and_per_window(vm_bundle, tmp_path, capsys):
    path, bundle = vm_bundle
    whole = iso230_2.from_bundle_errors(bundle.errors, "X")
    per_stage = iso230_2.windows(bundle.errors, "X", stages=list(bundle.meta.stages))
    assert len(per_stage) >= 2 and all(w.result.runs < whole.runs for w in per_stage)
    # a stage's runs drift less than the whole campaign's
    assert min(w.result.drift for w in per_stage) < whole.drift
    hourly = iso230_2.windows(bundle.errors, "X", window_s=3 * 3600.0)
    assert all(w.end_s - w.start_s == pytest.approx(3 * 3600.0) for w in hourly)
    assert sum(w.result.runs for w in hourly) <= whole.runs
    out, page = tmp_path / "w.json", tmp_path / "w.html"
    argv = ["iso230", str(path), "--part", "2", "--axis", "X", "--per-stage", "--json", str(out), "--html", str(page)]
    assert main(argv) == 0
    doc = json.loads(out.read_text())
    assert [w["label"] for w in doc["windows"]] == [w.label for w in per_stage]
    assert page.read_text().count("Test conditions") == len(per_stage)
    capsys.readouterr()


def test_iso230_3_stages_of_a_staged_campaign(vm_bundle, tmp_path):
    _, bundle = vm_bundle
    res = iso230_3.evaluate_bundle(bundle)
    assert res.etve and res.spindle and res.linear
    assert {t.extra["axis"] for t in res.linear} == {"X", "Y", "Z"}
    sp = res.spindle[0]
    # the spindle heats the head: Z grows by tens of um over a 3 h spindle stage (thesis ch. 5.2)
    z = max(v for k, v in sp.figures.items() if k.endswith("/dz"))
    assert z > 0.005
    # an independent check of one figure: the largest range of X/dz drift at any point in the stage
    e = bundle.errors
    sel = e[(e["time_s"] >= sp.start_s) & (e["time_s"] <= sp.end_s) & (e["axis"] == "X") & (e["term"] == "dz")]
    want = max(g["value"].max() - g["value"].min() for _, g in sel.groupby(["position", "direction"]))
    assert sp.figures["X/dz"] == pytest.approx(want, abs=1e-12)
    for t in res.linear:
        assert t.figures["drift_max"] >= max(t.figures["drift_P1"], t.figures["drift_P2"])
    assert res.etve[0].room_range_degC is not None
    doc = res.to_json_dict()
    assert set(doc) == {"etve", "spindle", "linear"}


@pytest.mark.parametrize(
    "spelling",
    [
        {"idle": "none", "feed": "axis", "combined": "spindle+axis"},  # campaigns stored before
        {},  # the one vocabulary
    ],
)
def test_iso230_3_reads_the_daemons_heat_words_and_the_old_spelling(vm_bundle, spelling):
    """The daemon's stages (``Stage.heat_label``) and stored campaigns that spelt them none/axis/spindle+axis give
    the same ETVE, spindle and linear tests as the simulator's words."""
    _, bundle = vm_bundle
    meta = bundle.meta.model_dump(mode="json")
    for st in meta["stages"]:
        st["heat_source"] = spelling.get(st["heat_source"], st["heat_source"])
    relabelled = Bundle("old", CampaignMeta.model_validate(meta), bundle.temperatures, bundle.conditions, bundle.errors)
    got = iso230_3.evaluate_bundle(relabelled)
    want = iso230_3.evaluate_bundle(bundle)
    assert [len(got.etve), len(got.spindle), len(got.linear)] == [len(want.etve), len(want.spindle), len(want.linear)]
    assert got.etve and got.spindle and got.linear
    assert got.linear[0].figures == want.linear[0].figures


def test_the_daemons_plan_stages_use_the_one_vocabulary():
    """The demo's plan gives its stages the words ISO 230-3 looks for: idle, spindle and feed stages."""
    from driftlab.campaigns.plan import load_plan
    from driftlab.resources import examples_dir
    from driftlab.vocabulary import HEAT_SOURCES

    plan = load_plan(examples_dir() / "plans" / "demo-full.yaml")
    words = {r["heat_source"] for r in plan.bundle_stages()}
    assert words <= set(HEAT_SOURCES) and {"idle", "spindle", "feed"} <= words


def test_iso230_3_plots_one_unit_per_axis(vm_bundle):
    """Lengths (µm) and angles (arcsec) never share an axis; the legend sits outside the data."""
    _, bundle = vm_bundle
    res = iso230_3.evaluate_bundle(bundle)
    fig = iso230_3.plot(res.spindle[0])
    labels = [ax.get_ylabel() for ax in fig.axes if ax.get_ylabel()]
    assert labels == ["drift (µm)", "drift (arcsec)"]
    for ax in fig.axes:
        legend = ax.get_legend()
        assert legend is not None and legend.get_bbox_to_anchor().x0 >= ax.get_window_extent().x1 - 1
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_cli_iso230_part3_and_one_line_errors(vm_bundle, tmp_path):
    path, _ = vm_bundle
    out, page = tmp_path / "t.json", tmp_path / "t.html"
    assert main(["iso230", str(path), "--part", "3", "--json", str(out), "--html", str(page)]) == 0
    assert json.loads(out.read_text())["spindle"]
    assert page.read_text().count("data:image/png") >= 3
    bad = tmp_path / "bad.json"
    proc = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "iso230", str(path), "--part", "2", "--json", str(bad)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and proc.stderr.strip() == "driftlab: error: --part 2 needs --axis (X Y Z A B)"
    assert not bad.exists()
    proc = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "iso230", str(tmp_path / "nope"), "--part", "2", "--axis", "X"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1
