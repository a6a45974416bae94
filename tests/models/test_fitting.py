"""The fitting pipeline end to end on campaigns with known truth (element errors through the HTM chain)."""

import json
from datetime import UTC

import numpy as np
import pandas as pd
import pytest

from driftlab.campaigns.bundle import Bundle, CampaignMeta
from driftlab.daq.sim.truth import SENSITIVITY
from driftlab.errors import ValidationError
from driftlab.models.diagnosis_report import to_json_dict as diagnosis_json
from driftlab.models.document import predict_element_errors, predict_workspace_errors
from driftlab.models.features import Inputs
from driftlab.models.fitting import FitOptions, fit_bundles, stage_elements
from driftlab.physics.kinematics import workspace_error

NOISE_MM = 0.0005
ALPHA = 12.1e-6
ARM = 0.0103  # mm/degC of T34-T32 on the spindle arm (table 6.3)

STAGES = [  # (name, start h, end h, heat, axis)
    ("spindle-10k", 0, 6, "spindle", "Z"),
    ("cool-1", 6, 9, "idle", None),
    ("feed-x", 9, 14, "feed", "X"),
    ("cool-2", 14, 17, "idle", None),
    ("feed-z", 17, 22, "feed", "Z"),
    ("cool-3", 22, 25, "idle", None),
    ("spindle+z", 25, 29, "combined", "Z"),
    ("cool-4", 29, 32, "idle", None),
]


def _lag(u, t, tau):
    y = np.zeros_like(u)
    a = np.exp(-np.diff(t) / tau)
    for k in range(1, u.size):
        y[k] = a[k - 1] * y[k - 1] + (1 - a[k - 1]) * u[k]
    return y


def synthetic_bundle(seed=0, room_offset=0.0, hours=32.0):
    """A small campaign: truth on T1 (arm gradient), phi_z and phi_x (ballscrews, reversal)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, hours * 3600 + 1, 60.0)
    h = t / 3600
    sp = np.zeros_like(t)
    fx = np.zeros_like(t)
    fz = np.zeros_like(t)
    for _name, a, b, heat, axis in STAGES:
        m = (h >= a) & (h < b)
        if heat in ("spindle", "combined"):
            sp[m] = 1.0
        if heat in ("feed", "combined") and axis == "X":
            fx[m] = 1.0
        if heat in ("feed", "combined") and axis == "Z":
            fz[m] = 1.0
    room = 20 + room_offset + 1.0 * np.sin(2 * np.pi * (h - 9) / 24)
    true = {
        "T49": room + 0.4,
        "T50": room - 0.6,
        "T32": room + _lag(2.5 * sp, t, 2100),
        "T34": room + _lag(6.5 * sp, t, 1800),
        "T37": room + _lag(20 * sp, t, 1200),
        "T9": room + _lag(5 * fx, t, 1500),
        "T10": room + _lag(8 * fx, t, 720),
        "T30": room + _lag(5 * fz + 0.5 * sp, t, 1500),
        "T31": room + _lag(7 * fz + 0.3 * sp, t, 720),
        "T24": room + _lag(0.6 * sp + 0.4 * fz, t, 11000),
        "T26": room + _lag(0.2 * sp + 1.5, t, 13000),
        "T7": room + _lag(1.1 * fx, t, 5000),
    }
    for i in (1, 2, 3, 4):
        true[f"T{i}"] = true["T7"] + 0.02 * i
    temps = pd.DataFrame({"time_s": t, **{c: v + 0.01 * rng.standard_normal(t.size) for c, v in true.items()}})
    d = {c: v - v[0] for c, v in true.items()}

    # error sweeps every 10 min on the stage's axis (cool-downs keep the previous axis)
    rows = []
    axis = "Z"
    for _name, a, b, _heat, ax in STAGES:
        axis = ax or axis
        for ts in np.arange(a * 3600, b * 3600, 600.0):
            k = int(ts // 60)
            for pos in np.linspace(0, 400, 5):
                for direction in (1, -1):
                    rows.append((ts, k, axis, pos, direction))
    ts, k, ax, pos, dr = (np.array(v) for v in zip(*rows))
    n = ts.size
    q = np.zeros((n, 5))
    q[ax == "X", 0] = pos[ax == "X"]
    q[ax == "Z", 2] = pos[ax == "Z"]
    grad = d["T34"][k] - d["T32"][k]
    e_t1 = np.zeros((n, 6))
    e_t1[:, 5] = ARM * grad
    e_t1[:, 0] = 2e-5 * grad  # alpha of the arm (rad/degC)
    e_z = np.zeros((n, 6))
    e_z[:, 5] = ALPHA * q[:, 2] * d["T30"][k] + 3e-6 * q[:, 2]
    e_x = np.zeros((n, 6))
    e_x[:, 3] = ALPHA * q[:, 0] * d["T9"][k] + np.where(ax == "X", 0.001 * dr, 0.0)
    e_x[:, 4] = 2e-6 * q[:, 0] + 0.0004 * d["T7"][k]
    W = workspace_error(q, {"T1": e_t1, "phi_z": e_z, "phi_x": e_x})
    W[:, 3:] += NOISE_MM * rng.standard_normal((n, 3))
    W[:, :3] += 5e-7 * rng.standard_normal((n, 3))
    terms = {"Z": ("dz", "alpha"), "X": ("dx", "dy")}
    err = []
    for term_axis, names in terms.items():
        m = ax == term_axis
        for name in names:
            j = ("alpha", "beta", "gamma", "dx", "dy", "dz").index(name)
            err.append(
                pd.DataFrame(
                    {
                        "time_s": ts[m],
                        "axis": term_axis,
                        "term": name,
                        "position": pos[m],
                        "direction": dr[m],
                        "value": W[m, j],
                    }
                )
            )
    errors = pd.concat(err).sort_values(["time_s", "axis", "term", "position"], kind="stable").reset_index(drop=True)
    structures = {
        "T49": "room",
        "T50": "room",
        "T32": "spindle_arm",
        "T34": "spindle_arm",
        "T37": "spindle",
        "T9": "x_screw",
        "T10": "x_motor",
        "T30": "z_screw",
        "T31": "z_motor",
        "T24": "z_column",
        "T26": "z_column",
        "T7": "xy_carriage",
        "T1": "x_table",
        "T2": "x_table",
        "T3": "x_table",
        "T4": "x_table",
    }
    locs = {
        "T9": "X axis ballscrew nut",
        "T10": "X axis motor",
        "T30": "Z axis ballscrew",
        "T31": "Z axis motor",
        "T37": "Main spindle motor",
    }
    meta = CampaignMeta.model_validate(
        {
            "format": "driftlab-bundle/1",
            "machine": {"id": "vmc-test"},
            "started_at": "2026-03-02T08:00:00Z",
            "channels": {c: {"location": locs.get(c, c), "structure": s} for c, s in structures.items()},
            "room_channels": ["T49", "T50"],
            "stages": [
                {"name": nm, "start_s": a * 3600, "end_s": b * 3600, "heat_source": hs, "axis": ax_}
                for nm, a, b, hs, ax_ in STAGES
            ],
            "noise": {"length_mm": NOISE_MM},
        }
    )
    return Bundle(name=f"synthetic-{seed}", meta=meta, temperatures=temps, conditions=None, errors=errors)


@pytest.fixture(scope="module")
def fitted():
    return fit_bundles([synthetic_bundle(0)], FitOptions(network=False))


def test_stage_elements_follow_the_heat_source_order():
    meta = synthetic_bundle(0).meta
    got = [(s.name, e, r) for s, e, r in stage_elements(meta.stages)]
    assert got[:4] == [
        ("spindle-10k", "T1", "train"),
        ("cool-1", "T1", "train"),
        ("feed-x", "phi_x", "train"),
        ("cool-2", "phi_x", "train"),
    ]
    assert got[6] == ("spindle+z", None, "validation")


def _response(model, dT):
    """Return what ``model`` predicts at home for the temperature changes ``dT`` (channel -> degC)."""
    chans = sorted({c for f in model.features for c in f.channels} | set(dT))
    inputs = Inputs(pd.DataFrame({c: [float(dT.get(c, 0.0))] for c in chans}))
    return float(model.predict(inputs, np.zeros((1, 5)), np.zeros((1, 5)))[0])


def test_physical_coefficients_within_ten_percent(fitted):
    p = fitted.models
    # Table 6.3's arm coefficient is a response to the T34-T32 gradient, whatever equivalent terms
    # (grad[T34-T32], or a structure mean beside one corner) the stepwise search expressed it with.
    arm = p[("T1", "dz")]
    assert _response(arm, {"T34": 0.5, "T32": -0.5}) == pytest.approx(ARM, rel=0.1)
    assert abs(_response(arm, {"T34": 1.0, "T32": 1.0, "T33": 1.0, "T35": 1.0})) < 0.1 * ARM
    assert p[("phi_x", "dx")].coefficient("pos[X]*dT[T9]") == pytest.approx(ALPHA, rel=0.1)
    assert p[("phi_z", "dz")].coefficient("pos[Z]*dT[T30]") == pytest.approx(ALPHA, rel=0.1)
    assert p[("phi_x", "dx")].coefficient("dir[X]") == pytest.approx(0.001, rel=0.1)
    # its table 6.3 row needs the machine's geometry: test_table_6_3_compares_with_the_geometry_the_campaign_states


def test_holdout_rmse_near_laser_noise(fitted):
    v = fitted.validation
    lin = v[v["unit"] == "mm"]
    assert len(lin) >= 3
    assert (lin["rmse_holdout"] < 1.5 * NOISE_MM).all(), lin[["axis", "term", "link", "rmse_holdout"]]
    assert (lin.loc[lin["term"] != "dy", "r2"] > 0.9).all()  # dy: a signal at the noise level
    zdz = v[(v["axis"] == "Z") & (v["term"] == "dz")].iloc[0]
    assert set(zdz["link"].split("+")) >= {"T1", "phi_z"}
    assert zdz["rmse_validation"] < 2 * NOISE_MM  # the combined spindle + Z stage, never trained on


def test_document_predicts_like_the_fit_without_training_data(fitted):
    doc = json.loads(json.dumps(fitted.report()))
    assert doc["machine"] == "vmc-test" and {"T9", "T30", "T32", "T34"} <= set(doc["kept_channels"])
    assert {e for r in doc["terms"] for e in r["link"].split("+")} >= {"T1", "phi_x", "phi_z"}
    b = synthetic_bundle(1)
    row = b.temperatures.iloc[13 * 60]  # late in the X feed stage: the X screw is warm
    q = np.zeros((3, 5))
    q[:, 0] = [0, 200, 400]
    W = predict_workspace_errors(fitted.document, row.to_dict(), q, direction=np.ones(3))
    dT9 = row["T9"] - b.temperatures["T9"].iloc[0]
    assert np.all(np.isfinite(W)) and dT9 > 3
    assert W[2, 3] - W[0, 3] == pytest.approx(ALPHA * 400 * dT9, rel=0.1)


def test_model_channels_of_the_bundle_are_honoured():
    b = synthetic_bundle(0)
    meta = b.meta.model_copy(update={"model_channels": {"X": ["T10", "T49", "T50"]}})
    res = fit_bundles(
        [Bundle(b.name, meta, b.temperatures, None, b.errors)], FitOptions(network=False, virtual_sensors=False)
    )
    used = {c for f in res.models[("phi_x", "dx")].features for c in f.channels}
    assert used <= {"T10", "T49", "T50"} and "T10" in used


# ----------------------------------------------------------------------------- store, jobs, CLI


def test_table_6_3_compares_with_the_geometry_the_campaign_states(fitted):
    from driftlab.daq.sim.truth import STATED_GEOMETRY

    assert fitted.physical_check["status"] == "no geometry" and fitted.physical.empty
    assert fitted.document.physical_check["status"] == "no geometry" and fitted.document.physical == []
    b = synthetic_bundle(0)
    doc = b.meta.document()
    doc["machine"]["geometry"] = {
        "screw_fixed_mm": STATED_GEOMETRY["screw_fixed_mm"],
        "bending": {
            "spindle_arm": {
                "length_mm": 400,
                "height_mm": 200,
                "across": "upper-lower",
                "deflection": "dz",
                "angle": "alpha",
            }
        },
    }
    res = fit_bundles(
        [Bundle(b.name, CampaignMeta.model_validate(doc), b.temperatures, None, b.errors)],
        FitOptions(network=False, virtual_sensors=False),
    )
    assert res.physical_check["status"] == "compared" and res.document.physical_check["geometry"]["screw_fixed_mm"]
    rows = res.physical.set_index("term")
    # the X ballscrew's truth is alpha_c x position x dT9 (eq. 3.2, L = position): ratio 1
    assert rows.loc["phi_x.dx pos[X]*dT[T9]", "ratio"] == pytest.approx(1.0, abs=0.1)
    assert rows.loc["phi_x.dx pos[X]*dT[T9]", "physical"] == pytest.approx(12.1e-6)
    # this geometry states no links: a structure mean on the spindle head is listed, not compared
    assert set(rows["status"]) <= {"compared", "not stated: links_mm.spindle_head"}


@pytest.fixture()
def store_with_campaign(tmp_path):
    from driftlab.campaigns.store import connect

    url = f"sqlite:///{tmp_path / 'fit.sqlite'}"
    store = connect(url)
    cid = store.campaigns.import_bundle(synthetic_bundle(0))
    yield url, store, cid
    store.close()


def test_cli_fit_states_its_split_and_scores_the_diagnosis_split_when_told(store_with_campaign, tmp_path):
    """`fit --split time` holds out the last quarter of every measured line, as the diagnosis does (issue 33)."""
    from driftlab.cli import main

    url, _, cid = store_with_campaign
    reps = {}
    for split in ("stage", "time"):
        path = tmp_path / f"{split}.json"
        assert (
            main(["fit", "--campaign", str(cid), "--db", url, "--no-network", "--split", split, "--json", str(path)])
            == 0
        )
        reps[split] = json.loads(path.read_text())
    assert [reps[s]["split"] for s in ("stage", "time")] == ["stage", "time"]
    # the same figures as the library's fit with that split: the job passed it through
    lib = fit_bundles([synthetic_bundle(0)], FitOptions(network=False, split="time")).validation
    want = {(r.axis, r.term): r.rmse_holdout for r in lib.itertuples()}
    got = {(r["axis"], r["term"]): r["rmse_holdout"] for r in reps["time"]["terms"]}
    assert got == pytest.approx(want, rel=1e-9)
    assert got != pytest.approx({(r["axis"], r["term"]): r["rmse_holdout"] for r in reps["stage"]["terms"]})
    with pytest.raises(ValidationError, match="split must be one of"):
        FitOptions(split="random")


def test_cli_fit_registers_versions_and_show_gives_the_document(store_with_campaign, tmp_path, capsys):
    from driftlab.cli import main
    from driftlab.jobs.registry import get_model

    url, store, cid = store_with_campaign
    report_path = tmp_path / "report.json"
    assert main(["fit", "--campaign", str(cid), "--db", url, "--json", str(report_path), "--no-network"]) == 0
    rep = json.loads(report_path.read_text())
    assert rep["model_version"] == 1 and rep["machine"] == "vmc-test"
    assert {"kept_channels", "terms", "physical", "physical_check"} <= set(rep)
    assert set(rep["terms"][0]) >= {"axis", "term", "link", "rmse_train", "rmse_holdout", "r2", "f", "form", "form_why"}
    assert {r["form"] for r in rep["terms"]} <= {"link", "link+stepwise", "link+full"}
    # the campaign states no geometry: table 6.3 says so instead of comparing with borrowed lengths
    assert rep["physical"] == [] and rep["physical_check"]["status"] == "no geometry"
    capsys.readouterr()
    assert main(["fit", "--campaign", str(cid), "--db", url, "--no-network"]) == 0
    out = capsys.readouterr().out
    assert "table 6.3): no geometry: no campaign of machine vmc-test states its geometry" in " ".join(out.split())
    assert main(["models", "list", "--machine", "vmc-test", "--db", url, "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["version"], r["status"]) for r in rows] == [(1, "retired"), (2, "current")]
    assert main(["models", "show", "current", "--machine", "vmc-test", "--db", url, "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["version"] == 2 and shown["format"] == "driftlab-model/1"
    old = get_model(store, "vmc-test", 1)  # a retired version stays readable
    q = np.zeros((2, 5))
    q[:, 0] = [0.0, 400.0]
    temps = synthetic_bundle(0).temperatures.iloc[780].to_dict()
    np.testing.assert_allclose(predict_workspace_errors(shown, temps, q), predict_workspace_errors(old, temps, q))
    job = store.jobs.get(1)
    assert job.kind == "fit" and job.state == "done" and job.result["model_version"] == 1
    assert main(["models", "show", "7", "--machine", "vmc-test", "--db", url]) != 0


def test_cli_errors_are_one_line(store_with_campaign, capsys):
    from driftlab.cli import main

    url, _, _ = store_with_campaign
    assert main(["fit", "--db", url]) == 2
    assert main(["models", "show", "current", "--machine", "nope", "--db", url]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("driftlab: error:") for e in err)


# ----------------------------------------------------------------------------- the virtual machine


def _vm_bundle(scenario):
    from driftlab.daq.sim.campaign import simulate_campaign

    sim = simulate_campaign(scenario)
    return Bundle(
        scenario.name, CampaignMeta.model_validate(sim.meta), sim.temperatures, sim.conditions, sim.errors
    ), sim


@pytest.fixture(scope="module")
def vm_campaigns():
    """A 16 h staged campaign on the virtual machine, plus one with the room 4 degC warmer (ch. 6.6)."""
    from driftlab.daq.sim.scenario import MachineInfo, Room, Scenario
    from driftlab.daq.sim.truth import STATED_GEOMETRY

    machine = MachineInfo(geometry=dict(STATED_GEOMETRY))  # the thesis machine states its lengths (table 6.3)
    train, sim = _vm_bundle(Scenario(name="vm-train", hours=16, seed=3, machine=machine))
    warm, _ = _vm_bundle(Scenario(name="vm-warm", hours=16, seed=4, room=Room(mean_degC=24.0), machine=machine))
    return train, warm, sim


@pytest.fixture(scope="module")
def vm_fit(vm_campaigns):
    """The model of the first campaign (the warm one is the neural comparison's, below)."""
    train, _, sim = vm_campaigns
    res = fit_bundles([train], FitOptions(network_max_samples=2000, network_max_iter=200))
    print("vm fit timings", res.timings_s)
    print(res.validation[["axis", "term", "link", "rmse_holdout", "r2"]].to_string())
    print(res.physical[["term", "regression", "physical", "ratio"]].to_string())
    return res, sim


def _truth_coef(sim, element, param, channels):
    """Return the planted coefficient of a thermal term (sim.truth['thermal_terms'])."""
    for t in sim.truth["thermal_terms"]:
        if t["element"] == element and t["param"] == param and set(t["weights"]) == set(channels):
            return t["coef"]
    raise KeyError((element, param, channels))


def test_vm_screening_keeps_the_channels_the_truth_uses(vm_fit):
    res, sim = vm_fit
    kept = set(res.document.kept_channels)
    assert 14 <= len(kept) <= 24  # the thesis kept 18 of 50
    # the single-site drivers of the truth (ballscrews, motors, spindle) and the room pair
    assert {"T9", "T10", "T20", "T30", "T37", "T42", "T48", "T49", "T50"} <= kept
    # the arm's bending follows a gradient weighted over its corners (table 6.3): the errors keep
    # every arm site the truth uses, and at least the two corners that span the gradient
    truth_used = {c for chans in sim.meta["model_channels"].values() for c in chans}
    arm_sites = {c for c, m in sim.meta["channels"].items() if m["structure"] == "spindle_arm"}
    assert arm_sites & truth_used <= kept
    assert len(arm_sites & kept) >= 2
    for structure in ("z_column", "base", "x_table", "xy_carriage", "rotary_base", "b_table"):
        members = {c for c, m in sim.meta["channels"].items() if m["structure"] == structure}
        assert len(members & kept) <= 2, structure  # eight corners collapse
    assert all(res.screening.dropped[c] for c in set(sim.meta["channels"]) - kept)


def test_vm_arm_and_screw_coefficients_within_ten_percent(vm_fit):
    res, sim = vm_fit
    arm = _truth_coef(sim, "T1", "alpha", ["T32", "T33", "T34", "T35"])
    assert res.models[("T1", "alpha")].coefficient("grad[spindle_arm upper-lower]") == pytest.approx(arm, rel=0.1)
    screw = _truth_coef(sim, "phi_x", "dx", ["T9", "T10"])  # 0.6 dT9 + 0.4 dT10, eq. 3.2
    m = res.models[("phi_x", "dx")]
    total = sum(m.coefficient(n) for n in ("dT[T9]", "dT[T10]") if n in [f.name for f in m.features])
    assert total == pytest.approx(screw, rel=0.1)
    row = res.physical[res.physical["term"].str.startswith("phi_x.dx dT[")].iloc[0]
    assert 0.9 < row["ratio"] < 1.1 and "eq. 3.2" in row["relationship"]
    # the arm's bending angle against eq. 3.4 with the stated L = 400, H = 200 mm
    arm_row = res.physical.set_index("term").loc["T1.alpha grad[spindle_arm upper-lower]"]
    assert arm_row["physical"] == pytest.approx(12.1e-6 * 400 / 200) and 0.9 < arm_row["ratio"] < 1.1
    assert res.physical_check["status"] == "compared"
    # the column (eq. 3.3, alpha_c 1200 mm on Z), the carriage and the table (-alpha_c 200 mm each) warm
    # together through this 16 h campaign and all act on Z at the table, so it splits them loosely: the
    # column's response to its sites warming evenly came out at 0.71 of alpha_c L (the prior allows 30%),
    # and the machine's Z growth per degC of even warming at 1.24 of the truth's (measured 27 Nov). Held
    # here within the prior's band, not the 10% of the arm and the screws, which single sites pin.
    column = _truth_coef(sim, "T2", "dz", ["T24", "T26"])
    c = res.models[("T2", "dz")]
    sites = ("mean[z_column]", "dT[T24]", "dT[T26]", "lag3600[T24]", "lag3600[T26]")
    total = sum(c.coefficient(f.name) for f in c.features if f.name in sites)
    assert 0.6 < total / column < 1.3, list(zip([f.name for f in c.features], c.coef))
    dz = _even_warming_dz(res.document.model_dump(mode="json"))
    truth = workspace_error(np.zeros((1, 5)), {e: s.sum(axis=0)[None, :] for e, s in SENSITIVITY.items()})[0, 5]
    assert 0.7 < dz / truth < 1.3


def _even_warming_dz(doc: dict) -> float:
    """Return the model's work-space dz (mm) at the home pose when every input channel is 1 degC warmer."""
    warm = {c: v["reference"] + 1.0 for c, v in doc["inputs"].items()}
    errors = predict_element_errors(doc, warm, np.zeros((1, 5)), np.ones((1, 5)))
    return float(workspace_error(np.zeros((1, 5)), errors)[0, 5])


def test_vm_holdout_rmse_near_the_laser_noise(vm_fit):
    res, sim = vm_fit
    v = res.validation.set_index(["axis", "term"])
    ang, length = sim.truth["noise"]["angle_rad"], sim.truth["noise"]["length_mm"]
    for axis in ("X", "Y", "Z", "A", "B"):
        for term in ("alpha", "beta", "gamma"):
            assert v.loc[(axis, term), "rmse_holdout"] < 1.5 * ang, (axis, term)
        for term in ("dx", "dy", "dz"):
            assert v.loc[(axis, term), "rmse_holdout"] < 1.5 * length, (axis, term)


def test_vm_neural_comparison_same_inputs_fixed_target_both_directions(vm_fit, vm_campaigns):
    """Ch. 6.6 made fair: least squares and the network on one matrix, Z/dz fixed in advance, both ways."""
    from driftlab.models.neural import neural_comparisons

    res, _ = vm_fit
    [c] = res.neural  # the fit's own: one campaign, its earlier half against its later half and back
    assert c.target == "Z/dz" and c.status == "compared" and c.split == "time" and c.offsets == []
    train, warm, _ = vm_campaigns
    # with the warm campaign: v1 campaigns count from their own start (zeroed), never an absolute target
    # across campaigns, so the split stays by time, each campaign's offset a column both models get
    [c] = neural_comparisons([train, warm], ["Z/dz"], c.channels, hidden=(30, 15, 7), max_samples=2000, max_iter=200)
    assert c.split == "time" and c.offsets == ["vm-warm"] and c.excluded == {}
    assert [d.direction for d in c.directions] == ["earlier -> later", "later -> earlier"]
    for d in c.directions:
        assert "datum[vm-warm]" in d.inputs and sum(i.startswith("dT[") for i in d.inputs) == len(c.channels)
        assert d.beyond_range > 0.3 and d.max_excess_degC > 2.0  # the heated half lies beyond the other
        assert d.network_train < 1.5 * d.regression_train  # both fit their own range
        assert d.network_test > 3 * d.regression_test, d  # the network extrapolates worse, either way
    with pytest.raises(ValidationError, match="zeroed campaign is not an absolute target"):
        from driftlab.models.neural import compare_models, comparison_data

        compare_models(comparison_data([train, warm], "Z/dz", c.channels), split="campaign")
    rep = res.report()["neural_comparison"][0]
    assert rep["directions"][1]["network_test"] == res.neural[0].directions[1].network_test
    assert res.document.neural_comparison[0]["target"] == "Z/dz"


def test_vm_report_names_each_measurement_as_tables_6_1_and_6_2(vm_fit):
    """Roll is the rotation about the moving axis; a rotary axis' own rotation is its positioning, the rest tilt it."""
    res, _ = vm_fit
    names = {(r["axis"], r["term"]): r["measurement"] for r in res.report()["terms"]}
    assert len(names) == 30
    assert [names[(a, t)] for a, t in (("X", "alpha"), ("Y", "beta"), ("Z", "gamma"))] == ["Roll"] * 3
    assert [names[("X", t)] for t in ("beta", "gamma")] == ["Pitch", "Yaw"]
    assert [names[("Z", t)] for t in ("alpha", "beta")] == ["Pitch", "Yaw"]
    assert names[("A", "alpha")] == names[("B", "beta")] == "Positioning"
    assert {names[("A", "beta")], names[("A", "gamma")], names[("B", "alpha")], names[("B", "gamma")]} == {
        "Beta Tilt",
        "Gamma Tilt",
        "Alpha Tilt",
    }
    assert names[("Z", "dz")] == "Position" and names[("Z", "dx")] == "X Straightness"
    assert names[("A", "dy")] == "Y Deflection"
    assert not any("Roll" in n for (a, _), n in names.items() if a in ("A", "B"))


def test_fit_compares_only_the_targets_it_was_given():
    res = fit_bundles(
        [synthetic_bundle(0)],
        FitOptions(virtual_sensors=False, network_targets=("X/dy",), network_hidden=(8, 4), network_max_iter=50),
    )
    assert [c.target for c in res.neural] == ["X/dy"] and res.neural[0].status == "compared"
    assert res.neural[0].unit == "mm" and len(res.neural[0].directions) == 2


# ----------------------------------------------------------------------------- diagnosis findings folded in


@pytest.fixture(scope="module")
def planted_vm(tmp_path_factory):
    """A 36 h virtual-machine campaign whose Z/dz follows T21 (outside model_channels), in a store, diagnosed."""
    from driftlab.campaigns.store import connect
    from driftlab.daq.sim.scenario import HiddenEffect, Scenario
    from driftlab.models.diagnosis import diagnose_bundle

    sc = Scenario(
        name="vm-t21",
        hours=36,
        seed=7,
        scan_interval_s=120,
        sweep_interval_s=1200,
        points_per_axis=6,
        hidden=[
            HiddenEffect(
                kind="unmapped_channel", axis="Z", term="dz", channels=["T21"], params={"coef_per_degC": 0.005}
            )
        ],
    )
    bundle, _ = _vm_bundle(sc)
    bundle = Bundle(
        bundle.name,
        bundle.meta,
        bundle.temperatures,
        bundle.conditions,
        bundle.errors[(bundle.errors.axis == "Z") & (bundle.errors.term == "dz")].reset_index(drop=True),
    )
    tmp = tmp_path_factory.mktemp("findings")
    url = f"sqlite:///{tmp / 'f.sqlite'}"
    with connect(url) as store:
        cid = store.campaigns.import_bundle(bundle)
        report = diagnosis_json(diagnose_bundle(store.campaigns.load(cid)))
    path = tmp / "report.json"
    path.write_text(json.dumps(report))
    return url, cid, path, report


def test_findings_fold_into_the_next_fit_and_lower_the_holdout_rmse(planted_vm, tmp_path, capsys):
    from driftlab.campaigns.store import connect
    from driftlab.cli import main
    from driftlab.jobs.registry import get_model

    url, cid, path, report = planted_vm
    assert [(e["kind"], e["channels"]) for e in report["effects"]] == [("unmapped_channel", ["T21"])]

    def holdout(rep_path):
        rep = json.loads(rep_path.read_text())
        return next(r["rmse_holdout"] for r in rep["terms"] if (r["axis"], r["term"]) == ("Z", "dz")), rep

    assert main(["fit", "--campaign", str(cid), "--db", url, "--no-network", "--json", str(tmp_path / "a.json")]) == 0
    assert (
        main(
            [
                "fit",
                "--campaign",
                str(cid),
                "--db",
                url,
                "--no-network",
                "--json",
                str(tmp_path / "b.json"),
                "--findings",
                str(path),
            ]
        )
        == 0
    )
    before, _ = holdout(tmp_path / "a.json")
    after, rep = holdout(tmp_path / "b.json")
    assert after < 0.8 * before, (before, after)
    assert rep["findings"][0]["entered"]["dT[T21]"]  # the term entered a link model
    with connect(url) as store:
        doc = get_model(store, "vmc-5ax-01", "current")
        job = store.jobs.get(2)
    assert job.params["findings"]["effects"][0]["kind"] == "unmapped_channel"
    assert "T21" in doc.inputs and doc.findings[0]["kind"] == "unmapped_channel"
    assert any(f.name == "dT[T21]" for t in doc.terms for f in t.features)
    # a bad report is a one-line error and no job
    bad = tmp_path / "bad.json"
    for text in (
        '{"format": "driftlab-diagnosis/9", "effects": []}',
        '{"format": "driftlab-diagnosis/1", "effects": [{"kind": "gremlin", "axis": "Z", "term": "dz"}]}',
        '{"format": "driftlab-diagnosis/1", "effects": [{"kind": "thermal_lag", "axis": "Z", "term": "dz", '
        '"channels": ["T34"], "params": {}}]}',
        "not json",
    ):
        bad.write_text(text)
        capsys.readouterr()
        assert main(["fit", "--campaign", str(cid), "--db", url, "--no-network", "--findings", str(bad)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("driftlab: error: findings"), err


def test_forced_lag_finding_and_its_prediction_from_the_document():
    """A forced thermal_lag term; the document alone predicts what the fit does (lags over the history)."""
    from driftlab.models.findings import Finding, Findings

    b = synthetic_bundle(0)
    f = Findings(
        b.name,
        (
            Finding("thermal_lag", "Z", "dz", ("T24",), {"tau_s": 5000.0}),
            Finding("drift", "X", "dy", (), {"rate_per_day": 0.0}),
        ),
    )
    res = fit_bundles([b], FitOptions(network=False, virtual_sensors=False, findings=f, force_findings=True))
    doc = res.document
    names = {f.name for t in doc.terms for f in t.features}
    assert {"lag5000[T24]", "days[X]"} <= names
    assert doc.findings[0]["forced"] and doc.findings[0]["entered"]["lag5000[T24]"]
    # predict along the campaign's own history: the lag is run over the frame's time_s
    temps = b.temperatures  # the whole history: the lag starts settled at its first row, as in the fit
    q = np.zeros((len(temps), 5))
    q[:, 2] = 200.0
    at = [b.meta.started_at.timestamp() + t for t in temps["time_s"]]
    W = predict_workspace_errors(doc, temps, q, at=at)
    from driftlab.models.features import build_inputs
    from driftlab.models.fitting import Sample, predict_models
    from driftlab.physics.kinematics import workspace_error

    ref = {c: r.reference for c, r in doc.inputs.items()}
    lags = sorted({(f.channels[0], f.tau_s) for t in doc.terms for f in t.features if f.kind == "lag"})
    inp = build_inputs(b.temperatures, temps["time_s"].to_numpy(), ref, list(ref), lags)
    inp.days = temps["time_s"].to_numpy() / 86400
    frame = pd.DataFrame({"axis": ["Z"] * len(temps), "direction": [0.0] * len(temps)})
    want = workspace_error(q, predict_models(res.models, Sample(frame, q, inp)), res.document.dims)
    np.testing.assert_allclose(W, want, rtol=1e-6, atol=1e-9)


def test_document_substitution_and_drift_are_evaluated_from_the_document():
    from datetime import datetime

    from driftlab.models.document import predict_element_errors

    doc = {
        "machine": "m",
        "time_origin": "2026-03-02T00:00:00Z",
        "inputs": {c: {"reference": 20.0, "min": 19.0, "max": 30.0} for c in ("T1", "T2", "T3")},
        "substitutions": [
            {"channel": "T1", "neighbours": ["T2", "T3"], "coef": [1.0, 0.5, 0.5], "since": "2026-03-03T00:00:00Z"}
        ],
        "terms": [
            {
                "element": "phi_x",
                "param": "dx",
                "features": [
                    {"kind": "dT", "name": "dT[T1]", "channels": ["T1"]},
                    {"kind": "time", "name": "days[X]", "label": "X"},
                    {"kind": "quad", "name": "dT[T2]^2", "channels": ["T2"]},
                ],
                "coefficients": [0.001, 0.01, 1e-4],
                "statistics": {"rmse_train": 0.0},
            }
        ],
    }
    q = np.zeros((1, 5))
    temps = {"T1": 25.0, "T2": 22.0, "T3": 24.0}
    before = predict_element_errors(doc, temps, q, at=datetime(2026, 3, 2, 12, tzinfo=UTC))["phi_x"][0, 3]
    assert before == pytest.approx(0.001 * 5 + 0.01 * 0.5 + 1e-4 * 4)
    after = predict_element_errors(doc, {"T2": 22.0, "T3": 24.0}, q, at="2026-03-04T00:00:00Z")["phi_x"][0, 3]
    assert after == pytest.approx(0.001 * (1 + 11 + 12 - 20) + 0.01 * 2 + 1e-4 * 4)
    from driftlab.compensator.compensate import ErrorModel

    ErrorModel.from_document(doc)  # the compensator falls back to the registry for these terms


def test_sensor_fault_finding_substitutes_the_channel_in_fit_and_prediction():
    """An open T35 from 18 h: the fit reads its virtual-sensor estimate from then on, and so does the document."""
    from driftlab.daq.sim.scenario import HiddenEffect, Scenario
    from driftlab.models.findings import Finding, Findings

    sc = Scenario(
        name="vm-t35",
        hours=36,
        seed=7,
        scan_interval_s=120,
        sweep_interval_s=1200,
        points_per_axis=6,
        hidden=[HiddenEffect(kind="sensor_fault", channels=["T35"], params={"start_s": 64800.0, "mode": "open"})],
    )
    b, _ = _vm_bundle(sc)
    b = Bundle(
        b.name,
        b.meta,
        b.temperatures,
        b.conditions,
        b.errors[(b.errors.axis == "Z") & (b.errors.term == "alpha")].reset_index(drop=True),
    )
    f = Findings(b.name, (Finding("sensor_fault", "Z", "alpha", ("T35",), {"start_s": 64800.0, "mode": "open"}),))
    opts = FitOptions(network=False, virtual_sensors=False)
    r0 = fit_bundles([b], opts)
    r1 = fit_bundles([b], FitOptions(network=False, virtual_sensors=False, findings=f))
    h0, h1 = (r.validation.set_index(["axis", "term"]).loc[("Z", "alpha"), "rmse_holdout"] for r in (r0, r1))
    assert h1 < h0, (h0, h1)
    doc = r1.document
    (sub,) = doc.substitutions
    assert sub.channel == "T35" and set(sub.neighbours) <= set(doc.inputs)
    assert doc.findings[0]["substituted"] == ["T35"]
    # the document alone: a dead T35 (absent or NaN) after the fault is replaced by its estimate
    row = b.temperatures.iloc[-1].to_dict()
    q = np.zeros((1, 5))
    with_nan = predict_workspace_errors(doc, row, q)
    row.pop("T35")
    np.testing.assert_allclose(predict_workspace_errors(doc, row, q), with_nan)
    assert np.all(np.isfinite(with_nan))


def test_joint_coordinates_follow_the_bundle_v2_pose():
    """A v2 reading states where every axis stood: the HTM chain is evaluated there, not at home (eq. 4.12)."""
    from driftlab.models.fitting import _points, _pose_q

    e = pd.DataFrame(
        {
            "time_s": [0.0, 0.0],
            "axis": ["X", "A"],
            "term": ["dx", "dy"],
            "position": [50.0, 30.0],
            "direction": [1, -1],
            "x": [50.0, 10.0],
            "y": [100.0, 0.0],
            "z": [-20.0, 0.0],
            "a": [0.0, 30.0],
            "b": [5.0, 0.0],
            "setup": ["s1", "s2"],
            "value": [1e-3, 2e-3],
        }
    )
    q = _pose_q(_points(e).sort_values("axis").reset_index(drop=True))
    assert q[0] == pytest.approx([10.0, 0.0, 0.0, np.deg2rad(30.0), 0.0])
    assert q[1] == pytest.approx([50.0, 100.0, -20.0, 0.0, np.deg2rad(5.0)])
    v1 = _pose_q(_points(e.drop(columns=["x", "y", "z", "a", "b", "setup"])).sort_values("axis"))
    assert v1[1] == pytest.approx([50.0, 0.0, 0.0, 0.0, 0.0])  # v1: only the moved axis is known


def test_measurement_names_follow_the_moving_axis():
    """Tables 6.1/6.2: roll is the rotation about the moving axis; pitch and yaw as the angular optics see them."""
    from driftlab.models.fitting import _measurement_name as name

    assert [name("X", t) for t in ("alpha", "beta", "gamma")] == ["Roll", "Pitch", "Yaw"]
    assert [name("Y", t) for t in ("alpha", "beta", "gamma")] == ["Pitch", "Roll", "Yaw"]
    assert [name("Z", t) for t in ("alpha", "beta", "gamma")] == ["Pitch", "Yaw", "Roll"]
    assert [name("A", t) for t in ("alpha", "beta", "gamma")] == ["Positioning", "Beta Tilt", "Gamma Tilt"]
    assert name("B", "beta") == "Positioning" and name("Y", "dy") == "Position" and name("Y", "dx") == "X Straightness"
