"""Simulated campaigns: bundle v1 frames, the standard model on clean data, every hidden effect planted."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import CampaignMeta, load_bundle, write_bundle
from driftlab.daq.sim.campaign import simulate_campaign
from driftlab.daq.sim.machine import VirtualMachine
from driftlab.daq.sim.scenario import ANGLE_TERMS, HiddenEffect, Scenario
from driftlab.daq.sim.sites import SITE_INDEX

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def clean():
    return simulate_campaign(Scenario(hours=12, seed=11))


def _standard_residuals(sim, axis, term):
    """Fit the spec's standard model (section 2) with numpy lstsq; return (residuals, stated sigma)."""
    T, E = sim.temperatures, sim.errors
    g = E[(E.axis == axis) & (E.term == term)]
    tt = T["time_s"].to_numpy()
    cols = [np.interp(g.time_s, tt, T[c]) - T[c].iloc[0] for c in sim.meta["model_channels"][axis]]
    p = g.position.to_numpy()
    X = np.column_stack([np.ones_like(p), p, p**2, p**3, *cols])
    scale = np.where(X.std(axis=0) > 0, X.std(axis=0), 1.0)
    y = g.value.to_numpy()
    coef, *_ = np.linalg.lstsq(X / scale, y, rcond=None)
    sigma = sim.meta["noise"]["angle_rad" if term in ANGLE_TERMS else "length_mm"]
    return y - (X / scale) @ coef, sigma


def test_frames_follow_bundle_v1(clean):
    meta = CampaignMeta.model_validate(clean.meta)
    assert meta.format == "driftlab-bundle/1"
    assert clean.meta["machine"]["resolution_mm"] == 0.0025 and clean.meta["machine"]["resolution_deg"] == 0.001
    assert list(clean.temperatures.columns) == ["time_s", *[f"T{i}" for i in range(1, 51)]]
    assert set(clean.meta["channels"]) == {f"T{i}" for i in range(1, 51)}
    assert clean.meta["channels"]["T34"]["location"] == "Upper right spindle support arm"
    assert clean.meta["room_channels"] == ["T49", "T50"]
    assert list(clean.conditions.columns) == ["time_s", "spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b"]
    assert list(clean.errors.columns) == ["time_s", "axis", "term", "position", "direction", "value"]
    assert np.all(np.diff(clean.temperatures.time_s) == 60.0) and len(clean.temperatures) == 12 * 60 + 1
    e = clean.errors
    assert np.all(np.diff(e.time_s) >= 0)
    assert set(np.unique(np.diff(np.unique(e.time_s)))) == {600.0}
    counts = e.groupby(["axis", "term", "direction"]).size()
    assert len(counts) == 5 * 6 * 2 and (counts == 73 * 11).all()
    assert e[e.axis == "Z"].position.between(-254, 0).all() and e[e.axis == "A"].position.between(-45, 45).all()
    assert e.direction.isin([1, -1]).all()
    assert clean.meta["noise"] == {"length_mm": 0.0005, "angle_rad": pytest.approx(4.848e-7, rel=1e-3)}
    assert len(clean.truth["base"]) == 5 and all(len(v) == 6 for v in clean.truth["base"].values())


def test_clean_scenario_is_explained_by_the_standard_model(clean):
    ratios = {}
    for axis in "XYZAB":
        for term in ("alpha", "beta", "gamma", "dx", "dy", "dz"):
            r, sigma = _standard_residuals(clean, axis, term)
            ratios[(axis, term)] = r.std() / sigma
    assert max(ratios.values()) < 1.3, max(ratios.items(), key=lambda kv: kv[1])
    assert min(ratios.values()) > 0.85  # the stated noise really is there
    # and the data carry a thermal signal far above the noise
    z = clean.errors[(clean.errors.axis == "Z") & (clean.errors.term == "dz")].value
    assert np.ptp(z) > 40 * 0.0005


EFFECTS = [
    HiddenEffect(kind="reversal", axis="X", term="dx", params={"magnitude_mm": 0.003}),
    HiddenEffect(kind="screw_expansion", axis="Y", term="dy", channels=["T20"], params={"coef_per_mm_degC": 1.21e-5}),
    HiddenEffect(kind="unmapped_channel", axis="Z", term="dz", channels=["T21"], params={"coef_per_degC": 0.006}),
    HiddenEffect(kind="thermal_lag", axis="Z", term="alpha", channels=["T34"], params={"tau_s": 2400}),
    HiddenEffect(kind="drift", axis="B", term="beta", params={"rate_per_day": 3e-5}),
    HiddenEffect(kind="quadratic", axis="A", term="dz", channels=["T42"], params={"coef_per_degC2": 0.002}),
    HiddenEffect(kind="sensor_fault", channels=["T9"], params={"start_s": 14400, "mode": "detached"}),
]


@pytest.fixture(scope="module")
def planted():
    base = Scenario(hours=8, seed=5)
    return simulate_campaign(base), simulate_campaign(base.model_copy(update={"hidden": EFFECTS})), base


def test_every_hidden_kind_is_planted_with_its_size(planted):
    off, on, base = planted
    vm = VirtualMachine(base)
    key = ["axis", "term"]
    diff = on.errors.value - off.errors.value
    touched = set()
    for eff in EFFECTS:
        if eff.kind == "sensor_fault":
            continue
        touched.add((eff.axis, eff.term))
        rows = (on.errors.axis == eff.axis) & (on.errors.term == eff.term)
        g = on.errors[rows]
        d = diff[rows].to_numpy()
        t, pos, direc = g.time_s.to_numpy(), g.position.to_numpy(), g.direction.to_numpy()
        dT = vm.true_dT_array(t)[:, SITE_INDEX[eff.channels[0]]] if eff.channels else None
        p = eff.params
        if eff.kind == "reversal":
            want = 0.5 * p["magnitude_mm"] * direc
        elif eff.kind == "screw_expansion":
            want = p["coef_per_mm_degC"] * pos * dT
        elif eff.kind == "unmapped_channel":
            want = p["coef_per_degC"] * dT
        elif eff.kind == "drift":
            want = p["rate_per_day"] * t / 86400.0
        elif eff.kind == "quadratic":
            want = p["coef_per_degC2"] * dT**2
        else:  # thermal_lag: an independent lag by fine Euler of the true temperature
            tau = p["tau_s"]
            fine = np.arange(-2 * 86400.0 + 60, t.max() + 1, 5.0)
            fine = fine[fine >= -6 * 3600]
            x = vm.true_temperatures_array(fine)[:, SITE_INDEX["T34"]]
            y = np.empty_like(x)
            y[0] = x[0] - (x[1] - x[0]) / 5.0 * tau  # quasi-steady start of a lag on a ramp
            for i in range(1, len(x)):
                y[i] = y[i - 1] + 5.0 * (x[i - 1] - y[i - 1]) / tau
            lag = np.interp(t, fine, y) - np.interp(0.0, fine, y)
            c = on.truth["hidden"][EFFECTS.index(eff)]["coef_per_degC"]
            want = c * (lag - dT)
            np.testing.assert_allclose(d, want, atol=2e-3 * np.abs(want).max() + 1e-12)
            assert np.sqrt(np.mean(want**2)) > 3 * on.meta["noise"]["angle_rad"]
            continue
        np.testing.assert_allclose(d, want, rtol=1e-9, atol=1e-12)
        sigma = on.meta["noise"]["angle_rad" if eff.term in ANGLE_TERMS else "length_mm"]
        rms = on.truth["hidden"][EFFECTS.index(eff)]["rms"]
        assert rms == pytest.approx(np.sqrt(np.mean(want**2)), rel=1e-9)
        assert rms > 2.5 * sigma  # plantable at a few times the noise
        beyond = on.truth["hidden"][EFFECTS.index(eff)]["rms_beyond_standard_model"]
        assert 0 < beyond <= rms * (1 + 1e-9)
    # nothing else moved
    other = ~on.errors.set_index(key).index.isin(list(touched))
    assert (diff[other] == 0).all()
    # the fault: only T9's readings after start_s differ; errors are untouched by it
    dt = on.temperatures.drop(columns="time_s") - off.temperatures.drop(columns="time_s")
    changed = dt.abs().gt(0).any()
    assert list(changed[changed].index) == ["T9"]
    assert (dt["T9"][on.temperatures.time_s < 14400] == 0).all()
    late = on.temperatures.time_s >= 14400
    offset = on.truth["hidden"][-1]["reading_offset_rms_degC"]
    assert offset == pytest.approx(np.sqrt(np.mean(dt["T9"][late] ** 2)), rel=0.05) and offset > 0.2


def test_effects_break_the_standard_model(planted):
    off, on, _ = planted
    broken = 0
    for eff, rec in zip(EFFECTS, on.truth["hidden"]):
        if eff.kind == "sensor_fault":
            continue
        r_on, sigma = _standard_residuals(on, eff.axis, eff.term)
        r_off, _ = _standard_residuals(off, eff.axis, eff.term)
        assert r_off.std() < 1.3 * sigma
        # what the standard model cannot absorb shows in its residual, in quadrature with the noise
        expect = np.hypot(r_off.std(), rec["rms_beyond_standard_model"])
        assert r_on.std() == pytest.approx(expect, rel=0.15), (eff.kind, r_on.std(), expect)
        broken += r_on.std() > 1.5 * r_off.std()
    assert broken >= 4


def test_bundle_round_trip_and_plain_pandas(tmp_path):
    fault = HiddenEffect(kind="sensor_fault", channels=["T30"], params={"start_s": 3600, "mode": "open"})
    sim = simulate_campaign(Scenario(hours=2, seed=2, hidden=[fault]))
    out = write_bundle(tmp_path / "b", sim.meta, sim.temperatures, sim.conditions, sim.errors)
    b = load_bundle(out)
    pd.testing.assert_frame_equal(b.errors.reset_index(drop=True), sim.errors, check_dtype=False)
    temps = pd.read_csv(out / "temperatures.csv")
    np.testing.assert_array_equal(temps.to_numpy(), sim.temperatures.to_numpy())
    assert temps["T30"].isna().sum() == (sim.temperatures.time_s >= 3600).sum()
    errs = pd.read_csv(out / "errors.csv")
    assert errs.direction.dtype.kind == "i" and set(errs.axis) == {"X", "Y", "Z", "A", "B"}
    pd.read_csv(out / "conditions.csv")
    assert json.loads((out / "campaign.json").read_text())["model_channels"]["X"][0] == "T7"


def test_deterministic_per_seed():
    a = simulate_campaign(Scenario(hours=1, seed=8))
    b = simulate_campaign(Scenario(hours=1, seed=8))
    c = simulate_campaign(Scenario(hours=1, seed=9))
    pd.testing.assert_frame_equal(a.errors, b.errors)
    pd.testing.assert_frame_equal(a.temperatures, b.temperatures)
    assert not np.array_equal(a.errors.value, c.errors.value)
    # the campaign is the virtual machine sampled: same physics, same numbers
    vm = VirtualMachine(Scenario(hours=1, seed=8))
    row = a.errors.iloc[1234]
    got = vm.measure_error(float(row.time_s), row.axis, float(row.position), int(row.direction))
    assert got[row.term] == row.value
    temps = vm.temperatures(float(a.temperatures.time_s.iloc[17]))
    assert [temps[f"T{i}"] for i in range(1, 51)] == a.temperatures.iloc[17, 1:].tolist()


def test_cli_writes_a_loadable_bundle(tmp_path, capsys):
    from driftlab.cli import main

    scen = tmp_path / "s.yaml"
    scen.write_text("seed: 3\nhours: 24\nhidden:\n  - {kind: drift, axis: X, term: dx, params: {rate_per_day: 1e-3}}\n")
    out = tmp_path / "bundle"
    assert main(["sim", "campaign", "--scenario", str(scen), "--out", str(out), "--hours", "1.5"]) == 0
    assert "wrote bundle" in capsys.readouterr().out
    b = load_bundle(out)
    assert b.temperatures.time_s.iloc[-1] == 5400.0
    assert b.meta.noise.length_mm == 0.0005
    bad = tmp_path / "bad.yaml"
    bad.write_text("hidden:\n  - {kind: drift, axis: X, term: dx}\n")
    assert main(["sim", "campaign", "--scenario", str(bad), "--out", str(out)]) != 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "hidden.0" in lines[0] and "rate_per_day" in lines[0]


def test_cli_module_entry_point(tmp_path):
    scen = tmp_path / "s.yaml"
    scen.write_text("hours: 0.5\n")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "driftlab.cli",
            "sim",
            "campaign",
            "--scenario",
            str(scen),
            "--out",
            str(tmp_path / "b"),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    assert pd.read_csv(tmp_path / "b" / "errors.csv").shape[1] == 6
