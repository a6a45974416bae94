"""Diagnosis: the standard model of spec section 2, the data cleaning, and the effect search on planted effects."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm

from driftlab.models.diagnosis import diagnose_bundle
from driftlab.models.diagnosis_report import to_html as diagnosis_html
from driftlab.models.diagnosis_report import to_json_dict as diagnosis_json
from driftlab.models.standard_model import fit_standard_model, prepare_bundle, spike_mask
from tests import effects_generator as gen

Planted = gen.Planted


# ---------------------------------------------------------------------------------------------
# the standard model and the data preparation


def test_standard_model_is_plain_ols_of_spec_section_2():
    case = gen.make_case([], seed=3, hours=24, terms={"X": ["dx"]})
    prep = prepare_bundle(case.bundle)
    td = prep.terms[0]
    std = fit_standard_model(td, prep)
    assert std.selection.source == "model_channels"
    assert std.channels == case.model_channels["X"]
    # the same regression written naively: raw powers of position, dT from the first error sample
    pos = td.pos
    cols = [np.ones_like(pos), pos, pos**2, pos**3]
    temps = case.bundle.temperatures
    for ch in std.channels:
        T = np.interp(td.t, temps["time_s"], temps[ch])
        cols.append(T - T[0])
    X = np.column_stack(cols)
    tr = td.train
    ref = sm.OLS(td.y[tr], X[tr]).fit()
    pred_ref = X @ ref.params
    assert np.allclose(std.fit.residual, td.y - pred_ref, atol=1e-9)
    assert std.fit.rmse_train == pytest.approx(np.sqrt(np.mean(ref.resid**2)), rel=1e-6)
    # train = the rows before the time of the row at 75 % (the split depends on times, never values)
    hold_t = np.sort(case.bundle.errors["time_s"].to_numpy())[int(np.floor(0.75 * len(case.bundle.errors)))]
    assert td.n_train == int(np.sum(td.t < hold_t))
    assert td.t[: td.n_train].max() < td.t[td.n_train :].min()


def test_spikes_are_isolated_excursions_not_steps_or_fast_transients():
    rng = np.random.default_rng(0)
    x = 20 + 0.01 * rng.standard_normal(400)
    x[200:] += 3.0  # a step (a heat source switching on): not a spike
    x[:3] += np.array([2.0, 1.0, 0.5])  # a fast start transient at the edge: not a spike
    x[100] += 1.0  # an isolated spike
    x[300] -= 0.8
    m = spike_mask(x)
    assert set(np.flatnonzero(m)) == {100, 300}


def test_cleaning_flags_spikes_and_does_not_invent_effects():
    case = gen.make_case([], seed=5, hours=24, terms={"X": ["dx"]})
    b = case.bundle
    temps = b.temperatures.copy()
    errs = b.errors.copy()
    temps.loc[300, "T1"] += 5.0  # a thermocouple spike
    temps.loc[400:402, "T2"] = np.nan  # a short gap
    errs.loc[500, "value"] += 0.05  # a laser glitch (100 x the noise)
    bad = type(b)(name=b.name, meta=b.meta, temperatures=temps, conditions=None, errors=errs)
    res = diagnose_bundle(bad)
    flags = {f.series: f for f in res.flags}
    assert flags["T1"].spikes == 1
    assert flags["X/dx"].spikes == 1
    assert res.effects == []
    doc = diagnosis_json(res)
    assert any(f["series"] == "T1" for f in doc["flags"])


def test_channel_screening_without_model_channels_finds_the_drivers():
    case = gen.make_case([], seed=11, hours=36, terms={"X": ["dx"]}, with_model_channels=False)
    prep = prepare_bundle(case.bundle)
    std = fit_standard_model(prep.terms[0], prep)
    assert std.selection.source == "screening"
    assert set(case.model_channels["X"]) <= set(std.channels)
    assert len(std.channels) <= 8
    noise = case.noise["length_mm"]
    assert std.fit.rmse_holdout < 1.3 * noise


# ---------------------------------------------------------------------------------------------
# planted effects on the virtual machine


def _find(res, p: Planted):
    return [
        e
        for e in res.effects
        if e.kind == p.kind and e.axis == p.axis and e.term == p.term and set(e.channels) == set(p.channels)
    ]


def _close(value: float, truth: float, rel: float = 0.30) -> bool:
    return abs(value - truth) <= rel * abs(truth)


PLANTED = {
    "reversal-Y-dy": [Planted("reversal", "Y", "dy", [], {"magnitude_mm": 0.003})],
    "reversal-B-beta": [Planted("reversal", "B", "beta", [], {"magnitude_rad": 3e-6})],
    "screw-X-dx-T9": [Planted("screw_expansion", "X", "dx", ["T9"], {"coef_per_mm_degC": 1.2e-5})],
    "unmapped-Z-dz-T21": [Planted("unmapped_channel", "Z", "dz", ["T21"], {"coef_per_degC": 0.005})],
    "lag-Z-dz-T34": [Planted("thermal_lag", "Z", "dz", ["T34"], {"tau_s": 2400.0})],
    "lag-Y-alpha-T33": [Planted("thermal_lag", "Y", "alpha", ["T33"], {"tau_s": 3600.0})],
    "drift-A-gamma": [Planted("drift", "A", "gamma", [], {"rate_per_day": 7e-6})],
    "quadratic-Y-dz-T37": [Planted("quadratic", "Y", "dz", ["T37"], {"coef_per_degC2": 2e-5})],
    "fault-open-T35": [Planted("sensor_fault", "Z", "alpha", ["T35"], {"start_s": 18 * 3600.0, "mode": "open"})],
    "fault-detached-T26": [Planted("sensor_fault", "X", "dz", ["T26"], {"start_s": 12 * 3600.0, "mode": "detached"})],
    "lag-outside-model-Z-dz-T21": [
        Planted("thermal_lag", "Z", "dz", ["T21"], {"tau_s": 3000.0, "coef_per_degC": 0.006})
    ],
    "fault-in-held-out-part-T35": [
        Planted("sensor_fault", "Z", "alpha", ["T35"], {"start_s": 31 * 3600.0, "mode": "open"})
    ],
    "fault-two-channels-rail": [
        Planted(
            "sensor_fault", "Z", "alpha", ["T35", "T13"], {"start_s": 14 * 3600.0, "mode": "open", "rail_degC": 0.0}
        )
    ],
    "two-reversal-X-dx+lag-Z-dz": [
        Planted("reversal", "X", "dx", [], {"magnitude_mm": 0.004}),
        Planted("thermal_lag", "Z", "dz", ["T34"], {"tau_s": 3000.0}),
    ],
    "two-drift+screw-Y-dy": [
        Planted("drift", "Y", "dy", [], {"rate_per_day": 0.008}),
        Planted("screw_expansion", "Y", "dy", ["T20"], {"coef_per_mm_degC": 1.2e-5}),
    ],
}
SEEDS = {
    "fault-open-T35": 3,
    "fault-detached-T26": 3,
    "lag-outside-model-Z-dz-T21": 3,
    "fault-in-held-out-part-T35": 3,
    "fault-two-channels-rail": 3,
}


@pytest.mark.parametrize("name", list(PLANTED))
def test_planted_effects_are_found_with_their_parameters(name):
    planted = PLANTED[name]
    keep = sorted({(p.axis, p.term) for p in planted})
    # a sensor fault belongs to the thermocouple: the bundle's term is where the test looks for it
    case = gen.vm_case(
        [
            Planted(
                p.kind,
                "" if p.kind == "sensor_fault" else p.axis,
                "" if p.kind == "sensor_fault" else p.term,
                p.channels,
                p.params,
            )
            for p in planted
        ],
        seed=SEEDS.get(name, 7),
        keep=keep,
    )
    for i, p in enumerate(planted):
        if p.kind != "sensor_fault":  # planted signals of about 3x the laser noise (RMS) and up
            noise = case.noise["angle_rad" if p.term in ("alpha", "beta", "gamma") else "length_mm"]
            assert 2.9 * noise <= case.truth["hidden"][i]["rms"] <= 40 * noise
    res = diagnose_bundle(case.bundle)
    for p in planted:
        found = _find(res, p)
        assert found, f"{p.kind} on {p.axis}/{p.term} {p.channels} not found: {[e.to_dict() for e in res.effects]}"
        e = found[0]
        if p.kind != "sensor_fault":  # a repair's gain is reported as it comes out
            # (each effect's own held-out gain depends on the order of acceptance: the term's is checked below)
            t = next(t for t in res.terms if (t.td.axis, t.td.term) == (p.axis, p.term))
            assert t.extended.rmse_holdout < 0.9 * t.standard.fit.rmse_holdout
            assert e.p_value < res.alpha_each
        else:
            assert e.p_value < res.alpha_fault
        for key, truth in p.params.items():
            if key == "rail_degC":
                continue
            if key == "mode":
                assert e.params["mode"] == truth
            elif key == "start_s":
                assert abs(e.params["start_s"] - truth) <= 3600.0
            else:
                assert _close(e.params[key], truth), (key, e.params[key], truth)
    # nothing else: every accepted effect is a planted one (a fault shows on every term its channel drives)
    keys = {(p.kind, frozenset(p.channels)) for p in planted}
    assert all((e.kind, frozenset(e.channels)) in keys for e in res.effects), [e.to_dict() for e in res.effects]
    # the extended model keeps the gain of the planted extensions
    for t in res.terms:
        if not any(e.kind == "sensor_fault" for e in t.effects):
            assert t.extended.rmse_holdout <= t.standard.fit.rmse_holdout + 1e-15
    doc = diagnosis_json(res)
    assert json.loads(json.dumps(doc, allow_nan=False)) == doc


def test_no_false_findings_over_20_clean_seeds():
    found = []
    for seed in range(20):  # issue 6: at least 20 random seeds
        # vary axes and terms across seeds; short campaigns keep the check cheap (more seeds, full
        # 30-term bundles and 0.02/0.05 degC thermocouples: docs/diagnosis.md section 6, run by hand)
        axis = "XYZAB"[seed % 5]
        terms = [("dx", "gamma"), ("dy", "alpha"), ("dz", "beta")][seed % 3]
        case = gen.vm_case([], seed=100 + seed, hours=24, points=5, keep=[(axis, terms[0]), (axis, terms[1])])
        res = diagnose_bundle(case.bundle)
        found += [(seed, e.kind, e.axis, e.term, e.channels) for e in res.effects]
    assert found == []


def test_clean_synthetic_bundles_without_model_channels_give_no_findings():
    found = []
    for seed in range(4):
        case = gen.make_case([], seed=200 + seed, hours=24, terms={"X": ["dx", "gamma"]}, with_model_channels=False)
        found += [e.to_dict() for e in diagnose_bundle(case.bundle).effects]
    assert found == []


def test_virtual_machine_without_model_channels_screens_all_drivers_and_finds_nothing():
    case = gen.vm_case([], seed=50, hours=30, points=5, keep=[("Z", "dz"), ("X", "dx")])
    b = case.bundle
    meta = b.meta.model_copy(update={"model_channels": None})
    res = diagnose_bundle(
        type(b)(name=b.name, meta=meta, temperatures=b.temperatures, conditions=None, errors=b.errors)
    )
    drivers = {"X": {"T9", "T10", "T45"}, "Z": {"T7", "T24", "T26", "T30", "T32", "T33", "T34", "T35", "T37", "T42"}}
    for t in res.terms:
        assert t.standard.selection.source == "screening"
        assert drivers[t.td.axis] <= set(t.standard.channels)
    assert res.effects == []


def test_simulation_sentences_come_from_the_residuals():
    case = gen.vm_case([Planted("reversal", "X", "dx", [], {"magnitude_mm": 0.004})], seed=7, hours=24)
    res = diagnose_bundle(case.bundle)
    sim = res.terms[0].simulation
    assert "approach directions disagree by" in sim.gets_wrong
    um = float(sim.gets_wrong.split("disagree by ")[1].split(" µm")[0])
    assert 3.0 < um < 5.0  # the planted 4 um span
    assert "largest during stage" in sim.gets_wrong
    assert sim.rmse > res.terms[0].standard.fit.rmse_train  # time alone explains less than temperatures


def test_report_has_the_spec_keys_and_a_self_contained_page():
    case = gen.vm_case([Planted("drift", "A", "gamma", [], {"rate_per_day": 7e-6})], seed=7)
    res = diagnose_bundle(case.bundle, holdout_fraction=0.3)
    doc = diagnosis_json(res)
    assert doc["format"] == "driftlab-diagnosis/1"
    assert doc["bundle"] == case.bundle.name
    assert doc["holdout"]["method"] == "last 30% of time"
    t = res.terms[0].td
    assert doc["holdout"]["start_s"] == pytest.approx(t.t[t.n_train])
    assert set(doc["simulation"][0]) >= {"axis", "term", "rmse_mm", "gets_wrong"}
    assert set(doc["baseline"][0]) >= {"axis", "term", "rmse_train", "rmse_holdout"}
    assert set(doc["extended"][0]) >= {"axis", "term", "rmse_train", "rmse_holdout"}
    eff = doc["effects"][0]
    assert set(eff) == {
        "kind",
        "axis",
        "term",
        "channels",
        "params",
        "p_value",
        "cause",
        "rmse_holdout_before",
        "rmse_holdout_after",
        "holdout_verdict",  # extras (issue 22): better / worse / same / null, and physics or not
        "physical",
        "in_model",  # extra (issue 33): the fitted model already carries it
    }
    assert eff["holdout_verdict"] in ("better", "worse", "same") and eff["physical"] is True
    assert isinstance(doc["unexplained"], list)
    assert eff["kind"] == "drift" and eff["channels"] == []
    assert "thesis 3.2" in eff["cause"]
    page = diagnosis_html(res)
    assert page.count("data:image/png;base64,") >= 2
    assert eff["cause"].split(":")[0] in page
    assert "http" not in page  # nothing fetched from elsewhere
    # the regressor an effect adds, for folding into the next fit
    frame = res.effects[0].regressor_frame()
    assert list(frame.columns) == ["time_s", "position", "direction", "time_days"]
    assert len(frame) == t.n


def test_holdout_fraction_is_validated():
    case = gen.make_case([], seed=1, hours=12)
    from driftlab.errors import ValidationError

    with pytest.raises(ValidationError):
        diagnose_bundle(case.bundle, holdout_fraction=0.95)


def test_a_missing_channel_does_not_break_the_model():
    case = gen.make_case([], seed=4, hours=24, terms={"X": ["dx"]})
    b = case.bundle
    temps = b.temperatures.copy()
    temps["T8"] = np.nan  # a channel that never read anything
    res = diagnose_bundle(type(b)(name=b.name, meta=b.meta, temperatures=temps, conditions=None, errors=b.errors))
    assert np.isfinite(res.terms[0].standard.fit.rmse_holdout)
    assert isinstance(diagnosis_json(res)["baseline"][0]["rmse_holdout"], float)
    assert isinstance(pd.DataFrame(diagnosis_json(res)["extended"]), pd.DataFrame)


def test_too_few_samples_give_an_empty_report_not_a_crash():
    case = gen.make_case([], seed=1, hours=2, sweep_s=3600)
    b = case.bundle
    tiny = type(b)(name="tiny", meta=b.meta, temperatures=b.temperatures, conditions=None, errors=b.errors.head(5))
    res = diagnose_bundle(tiny)
    doc = diagnosis_json(res)
    assert doc["baseline"] == [] and doc["effects"] == [] and doc["holdout"]["start_s"] is None
    assert "too few to diagnose" in doc["flags"][0]["series"]
    assert diagnosis_html(res).startswith("<!doctype html>")


# ---------------------------------------------------------------------------------------------
# other noise levels, bundles without stated noise, other labs' bundles


@pytest.mark.parametrize("seed", [3, 6])
def test_noisy_thermocouples_give_no_false_findings(seed):
    # 0.05 degC scan noise (a raw thermocouple reading): the standard model's dT regressors carry it
    # (errors in variables) and, unguarded, a lag, a proxy channel or a drift "improves" the model
    # of these seeds (thermal_lag X/alpha T15, unmapped_channel X/dz T27, thermal_lag Z/dz T28 ...)
    case = gen.vm_case([], seed=seed, hours=36, keep=[("X", "alpha"), ("Z", "dz"), ("X", "dz")], thermocouple_degC=0.05)
    res = diagnose_bundle(case.bundle)
    assert [e.to_dict() for e in res.effects] == []


def test_without_stated_noise_the_repeatability_is_estimated_and_findings_are_the_same():
    planted = [Planted("reversal", "Y", "dy", [], {"magnitude_mm": 0.003})]
    keep = [("Y", "dy"), ("Z", "dz"), ("X", "alpha")]
    stated = gen.vm_case(planted, seed=7, keep=keep)
    unstated = gen.vm_case(planted, seed=7, keep=keep, stated_noise=False)
    assert unstated.bundle.meta.noise is None
    a, b = diagnose_bundle(stated.bundle), diagnose_bundle(unstated.bundle)
    assert [(e.kind, e.axis, e.term, e.channels) for e in b.effects] == [("reversal", "Y", "dy", [])]
    assert [(e.kind, e.axis, e.term, e.channels) for e in a.effects] == [("reversal", "Y", "dy", [])]
    from driftlab.models.diagnosis import estimate_repeatability

    for t in b.terms:  # the estimate (departures along the axis within a sweep) is the laser's noise
        noise = stated.noise["angle_rad" if t.td.unit == "rad" else "length_mm"]
        est = estimate_repeatability(t.td, t.standard.fit.residual)
        assert 0.8 * noise < est < 1.25 * noise, (t.td.axis, t.td.term, est / noise)


def test_another_labs_bundle_runs_cleanly_and_stays_correct():
    # channels not named T1..Tn, 12 of them, axes X and Z only, three terms, no conditions, no stages,
    # irregular scan times with a 30 min and a 3 h gap, 1 % missing readings
    found = []
    for seed in range(3):
        case = gen.make_case([], seed=300 + seed, hours=24, n_channels=12, terms={"X": ["dx", "gamma"], "Z": ["dz"]})
        res = diagnose_bundle(gen.foreign(case, seed=seed))
        assert len(res.terms) == 3
        assert any("scan gaps left out" in f.series for f in res.flags)
        json.dumps(diagnosis_json(res), allow_nan=False)
        found += [e.to_dict() for e in res.effects]
    assert found == []
    # a planted reversal is found, with model_channels and noise stated or not
    case = gen.make_case(
        [Planted("reversal", "X", "dx", [], {"magnitude_mm": 0.003})],
        seed=301,
        hours=24,
        n_channels=12,
        terms={"X": ["dx", "gamma"], "Z": ["dz"]},
    )
    b = gen.foreign(case, seed=1)
    bare = type(b)(
        name=b.name,
        meta=b.meta.model_copy(update={"model_channels": None, "noise": None}),
        temperatures=b.temperatures,
        conditions=None,
        errors=b.errors,
    )
    for bundle in (b, bare):
        res = diagnose_bundle(bundle)
        assert [(e.kind, e.axis, e.term) for e in res.effects] == [("reversal", "X", "dx")]
        assert _close(res.effects[0].params["magnitude_mm"], 0.003, 0.1)


def test_a_faulty_model_channel_is_one_sensor_fault_not_many_lags():
    # examples/scenarios/fault-t34.yaml on two terms: T34 (a model channel) comes loose at 25 h
    case = gen.vm_case(
        [Planted("sensor_fault", "", "", ["T34"], {"start_s": 90000.0, "mode": "detached"})],
        seed=5,
        hours=48,
        keep=[("Z", "dz"), ("X", "alpha")],
    )
    res = diagnose_bundle(case.bundle)
    assert {(e.kind, tuple(e.channels)) for e in res.effects} == {("sensor_fault", ("T34",))}
    for e in res.effects:
        assert abs(e.params["start_s"] - 90000.0) <= 3600.0 and e.params["mode"] == "detached"
