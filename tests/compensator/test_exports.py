"""Controller tables round trip: a model fitted on the virtual machine, exported, read back and applied as
the controller would, reproduces the model's own correction within 0.5 um between grid points."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from driftlab.campaigns.bundle import Bundle, CampaignMeta, write_bundle
from driftlab.cli import main
from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.exports import FORMATS, controller
from driftlab.compensator.exports.grid import AxisTable, axis_correction, controller_grid, correction_table
from driftlab.compensator.exports.writers import write
from driftlab.daq.sim.campaign import simulate_campaign
from driftlab.daq.sim.scenario import Scenario
from driftlab.errors import ValidationError
from driftlab.models.fitting import FitOptions, fit_bundles
from tests.compensator import controllers

TOL_MM = 0.5e-3  # the target: 0.5 um between grid points
TRAVEL = {"X": (0.0, 254.0), "Y": (0.0, 254.0), "Z": (-254.0, 0.0), "A": (-45.0, 45.0)}  # the virtual machine's
STEP = {"X": 10.0, "Y": 10.0, "Z": 10.0, "A": 5.0}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A model fitted by the pipeline on a 24 h staged virtual campaign, and a warm scan of that campaign."""
    sim = simulate_campaign(Scenario(name="exp", hours=24, seed=3))
    bundle = Bundle("exp", CampaignMeta.model_validate(sim.meta), sim.temperatures, sim.conditions, sim.errors)
    doc = fit_bundles([bundle], FitOptions(network=False, virtual_sensors=False)).document.model_dump(mode="json")
    warm = sim.temperatures.iloc[int(np.argmax(sim.temperatures["T1"].to_numpy()))]  # end of a spindle stage
    temps = {c: float(v) for c, v in warm.items() if c != "time_s"}
    root = tmp_path_factory.mktemp("exp")
    (root / "model.json").write_text(json.dumps(doc))
    write_bundle(root / "bundle", sim.meta, sim.temperatures, sim.conditions, sim.errors)
    return ErrorModel.from_document(doc), temps, root


def _table(model, temps, ctl_name: str, axis: str, lo=None, hi=None, step=None):
    ctl = controller(ctl_name)
    t_lo, t_hi = TRAVEL[axis]
    grid = controller_grid(
        ctl.spacing, ctl.max_points, t_lo if lo is None else lo, t_hi if hi is None else hi, step or STEP[axis]
    )
    return correction_table(model, temps, axis, grid.positions)


def _apply(ctl_name: str, export, table, p, d):
    """Apply the exported file(s) as the controller's own loader would (tests/compensator/controllers.py)."""
    ctl = controller(ctl_name)
    axis_no = "XYZAB".index(table.axis) + 1
    if ctl.family == "linuxcnc":
        return controllers.linuxcnc(export.text, p, d)
    if ctl.family == "siemens":
        return controllers.siemens(export.files, export.settings, f"AX{axis_no}", ctl.name, p, d)
    if ctl.family == "heidenhain":
        return controllers.heidenhain(export.text, export.settings, ctl.name, p, d)
    ref_return = 1 if export.settings["reference position return"] == "+" else -1
    return controllers.fanuc(export.text, 0.0, export.settings["detection unit"], p, d, axis_no, ref_return)


def _dense(positions: np.ndarray, lo: float, hi: float, per_interval: int = 16) -> np.ndarray:
    """Return the grid points and ``per_interval - 1`` points inside every interval, within [lo, hi]."""
    f = np.linspace(0.0, 1.0, per_interval + 1)[:-1]
    inner = (positions[:-1, None] + f[None, :] * np.diff(positions)[:, None]).ravel()
    p = np.r_[inner, positions[-1]]
    return p[(p >= lo) & (p <= hi)]


def round_trip_error(model, temps, ctl_name: str, axis: str, **options) -> float:
    """Return the largest |controller correction - model correction| over the travel (mm, or deg)."""
    table = _table(model, temps, ctl_name, axis)
    export = write(ctl_name, table, **options)
    p = _dense(table.positions, *TRAVEL[axis])
    worst = 0.0
    for d in (1, -1):
        got = _apply(ctl_name, export, table, p, d)
        want = axis_correction(model, temps, axis, p, d)
        worst = max(worst, float(np.abs(got - want).max()))
    return worst


@pytest.mark.parametrize("ctl_name", FORMATS)
def test_exported_tables_reproduce_the_models_correction_between_grid_points(fitted, ctl_name):
    model, temps, _ = fitted
    errors = {axis: round_trip_error(model, temps, ctl_name, axis) for axis in ("X", "Y", "Z")}
    print(f"round trip {ctl_name}: " + ", ".join(f"{a} {e * 1e3:.4f} um" for a, e in errors.items()))
    assert max(errors.values()) < TOL_MM, errors
    # sharper: at a 10 mm step the interpolation error is a few nm; fanuc's integer detection units
    # (0.1 um) add at most one unit (the point's rounding and the reference shift's)
    fine = 1.05e-4 if ctl_name.startswith("fanuc") else 2e-5
    assert max(errors.values()) < fine, errors
    # the correction itself is not negligible: the table carries something
    table = _table(model, temps, ctl_name, "Z")
    assert np.abs(table.forward).max() > 20 * TOL_MM


@pytest.mark.parametrize("ctl_name", FORMATS)
def test_rotary_axis_tables_in_degrees(fitted, ctl_name):
    model, temps, _ = fitted
    err_deg = round_trip_error(model, temps, ctl_name, "A")
    # 0.5 um at 100 mm from the axis
    assert err_deg < np.rad2deg(TOL_MM / 100.0), err_deg


def test_fanuc_reference_return_in_the_negative_direction(fitted):
    """No. 3627 is relative to the direction of reference position return: both settings load and round trip."""
    model, temps, _ = fitted
    table = _table(model, temps, "fanuc-30i", "X")
    tapes = {r: write("fanuc-30i", table, reference_return=r) for r in (1, -1)}
    assert (
        tapes[1].settings["reference position return"] == "+" and tapes[-1].settings["reference position return"] == "-"
    )
    p = _dense(table.positions, *TRAVEL["X"])
    for r, tape in tapes.items():
        for d in (1, -1):
            got = controllers.fanuc(tape.text, 0.0, 1e-4, p, d, 1, r)
            assert np.abs(got - axis_correction(model, temps, "X", p, d)).max() < 1.05e-4
    # read with the wrong return direction the tape is off by the reversal at the reference
    reversal = abs(table.reverse[0] - table.forward[0])
    wrong = controllers.fanuc(tapes[-1].text, 0.0, 1e-4, p, 1, 1, 1)
    assert np.abs(wrong - axis_correction(model, temps, "X", p, 1)).max() > 0.9 * reversal - 1e-4


@pytest.mark.parametrize("ctl_name", FORMATS)
def test_the_round_trip_check_sees_a_wrong_table(fitted, ctl_name):
    """A table with one point 3 um off is caught by the loaders."""
    model, temps, _ = fitted
    table = _table(model, temps, ctl_name, "X")
    fwd, rev = table.forward.copy(), table.reverse.copy()
    fwd[7] += 0.003
    rev[7] += 0.003  # the same in both directions: the 808D's and the TNC 426's one backlash still holds it
    bad = type(table)(table.axis, table.positions, fwd, rev, table.model)
    export = write(ctl_name, bad)
    p = _dense(table.positions, *TRAVEL["X"])
    got = _apply(ctl_name, export, bad, p, 1)
    assert np.abs(got - axis_correction(model, temps, "X", p, 1)).max() > TOL_MM


@pytest.mark.parametrize(
    "ctl_name,points",
    [("linuxcnc", 257), ("828d", 201), ("808d", 201), ("tnc426", 257), ("fanuc-0i", 103)],
)
def test_point_limits_of_each_controller(fitted, ctl_name, points):
    """One point over the controller's limit is refused by the writer, and the loader refuses it too."""
    model, temps, _ = fitted
    pos = np.linspace(0.0, 254.0, points)
    if ctl_name == "tnc426":
        pos = 6.5536e-3 * np.arange(points)
    table = correction_table(model, temps, "X", pos)
    with pytest.raises(ValidationError, match="at most|per direction"):
        write(ctl_name, table)
    ok = correction_table(model, temps, "X", pos[:-1] if ctl_name != "fanuc-0i" else pos[:102])
    export = write(ctl_name, ok)
    assert export.text
    if ctl_name == "linuxcnc":  # the loader itself refuses the 257th entry
        lines = export.text.splitlines()
        with pytest.raises(controllers.Refused):
            controllers.linuxcnc("\n".join([*lines, "300.0 0.0 0.0"]), pos, 1)


def test_grids_follow_each_controllers_spacing_rule():
    g = controller_grid("any", 256, 0.0, 254.0, 10.0)
    assert g.positions[0] == 0.0 and g.positions[-1] == 254.0 and g.positions.size == 27 and g.notes
    assert np.allclose(np.diff(g.positions), 254.0 / 26)
    f = controller_grid("detection-unit", 1024, 0.0, 254.0, 10.0, reference=0.0, unit=1e-4)
    steps = np.diff(f.positions) / 1e-4
    assert f.positions[-1] == 254.0 and np.allclose(steps, np.round(steps)) and steps[0] <= 1e5
    f2 = controller_grid("detection-unit", 1024, -100.0, 100.0, 10.0, reference=30.0, unit=1e-4)
    assert np.isclose(f2.positions, 30.0).any() and f2.positions[-1] == 100.0
    t = controller_grid("power-of-two", 256, 0.0, 254.0, 10.0)
    assert np.isclose(t.step if hasattr(t, "step") else t.positions[1] - t.positions[0], 6.5536)
    assert t.positions[0] == 0.0 and t.positions[-1] >= 254.0 and t.positions[-2] < 254.0
    with pytest.raises(ValidationError, match="at most 256"):
        controller_grid("power-of-two", 256, 0.0, 2000.0, 7.0)


def _reversal(p: np.ndarray, varying: bool) -> np.ndarray:
    """A reversal of 4 um, varying smoothly by 3 um along the axis when ``varying`` (mm)."""
    return 0.004 + (0.003 * np.sin(np.asarray(p) / 40.0) if varying else 0.0)


def _forward(p: np.ndarray) -> np.ndarray:
    return 0.02 * np.sin(np.asarray(p) / 80.0) - 0.01


@pytest.mark.parametrize("ctl_name", FORMATS)
def test_direction_dependent_tables_round_trip(ctl_name):
    """A correction whose directions differ (a reversal of 4 um, varying along the axis where the controller
    has a table per direction, constant where it has one backlash value) loads within 0.5 um both ways."""
    ctl = controller(ctl_name)
    varying = ctl_name not in ("808d", "tnc426")
    grid = controller_grid(ctl.spacing, ctl.max_points, 0.0, 254.0, 10.0)
    pos = grid.positions
    table = AxisTable("X", pos, _forward(pos), _forward(pos) + _reversal(pos, varying), "synthetic")
    export = write(ctl_name, table)
    p = _dense(pos, 0.0, 254.0)
    for d in (1, -1):
        want = _forward(p) + (_reversal(p, varying) if d < 0 else 0.0)
        got = _apply(ctl_name, export, table, p, d)
        assert np.abs(got - want).max() < (2e-4 if ctl.family == "fanuc" else 1e-4), (ctl_name, d)  # interpolation
    # the directions are told apart: read the other direction's way, the error is the reversal
    wrong = _apply(ctl_name, export, table, p, 1)
    assert np.abs(wrong - (_forward(p) + _reversal(p, varying))).max() > 0.9e-3


def test_one_backlash_value_refuses_a_varying_reversal():
    pos = np.linspace(0.0, 250.0, 26)
    table = AxisTable("X", pos, _forward(pos), _forward(pos) + _reversal(pos, True), "synthetic")
    for name in ("808d", "tnc426"):
        with pytest.raises(ValidationError, match="the reversal varies by"):
            write(name, table)


def test_formats_in_the_controllers_terms():
    pos = np.linspace(0.0, 250.0, 26)
    table = AxisTable("X", pos, _forward(pos), _forward(pos) + _reversal(pos, False), "synthetic")
    lin = write("linuxcnc", table)
    first = lin.text.splitlines()[0].split()
    assert len(first) == 3 and float(first[0]) == 0.0 and lin.settings["[JOINT_0]COMP_FILE_TYPE"] == 1
    sie = write("840d-sl", table)
    lec = sie.text.splitlines()
    assert lec[:2] == ["%_N_AX_EEC_INI", "CHANDATA(1)"] and lec[-1] == "M17"
    assert "$AA_ENC_COMP[0,25,AX1]=" in sie.text
    cec = sie.files["_CEC"]
    assert cec.startswith("%_N_NC_CEC_INI\nCHANDATA(1)\n") and "$AN_CEC_INPUT_AXIS[0]=(AX1)" in cec
    assert "$AN_CEC_DIRECTION[1]=-1" in cec and cec.rstrip().endswith("M17")
    assert sie.settings["MD18342 $MN_MM_CEC_MAX_POINTS[0]"] == 26
    assert "MD18342 $MN_MM_CEC_MAX_POINTS[0]" not in write("828d", table).settings
    s808 = write("808d", table)
    assert set(s808.files) == {""} and "MD32450 $MA_BACKLASH[0,AX1]" in s808.settings
    hei = write("tnc640", table).text.splitlines()
    assert hei[0] == "BEGIN X.COM MM" and hei[1].split() == ["NR", "AXISPOS", "X", "BACKLASH"] and hei[-1] == "[END]"
    fan = write("fanuc-0i", table).text.splitlines()
    assert fan[0] == "%" and "N3605A1P00000011" in fan and "N3620A1P0" in fan and "N3624A1P100000" in fan
    assert "N10000P0" in fan and not any("." in ln for ln in fan)


def test_cli_export_comp_writes_each_format(fitted, tmp_path, capsys):
    model, temps, root = fitted
    import pandas as pd

    csv = tmp_path / "temps.csv"
    pd.DataFrame([{"time_s": 0.0, **temps}]).to_csv(csv, index=False)
    for fmt in FORMATS:
        out = tmp_path / f"x.{fmt}.txt"
        assert (
            main(
                [
                    "export-comp",
                    "--model",
                    str(root / "model.json"),
                    "--temps",
                    str(csv),
                    "--controller",
                    fmt,
                    "--axis",
                    "X",
                    "--range",
                    "0,254",
                    "-o",
                    str(out),
                    "--json",
                ]
            )
            == 0
        )
        summary = json.loads(capsys.readouterr().out)
        assert summary["controller"] == fmt and out.read_text() and summary["from"] == 0.0
        # the table ends exactly at the range it was given (tnc426: a power-of-two spacing runs past it)
        assert summary["to"] == 254.0 if fmt != "tnc426" else 254.0 < summary["to"] < 254.0 + 6.6
        assert all(Path(f).exists() for f in summary["files"])
    # the file applies as the controller would, at the same temperatures
    text = (tmp_path / "x.linuxcnc.txt").read_text()
    p = np.linspace(0.0, 254.0, 101)
    assert np.abs(controllers.linuxcnc(text, p, 1) - axis_correction(model, temps, "X", p, 1)).max() < TOL_MM


def test_cli_export_comp_from_a_registered_version(fitted, tmp_path, capsys):
    from driftlab.campaigns.bundle import load_bundle
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import register_model

    model, temps, root = fitted
    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    store = connect(url)
    store.campaigns.import_bundle(load_bundle(root / "bundle"))
    doc = register_model(store, json.loads((root / "model.json").read_text()))
    store.close()
    csv = root / "bundle" / "temperatures.csv"
    out = tmp_path / "x.com"
    assert (
        main(
            [
                "export-comp",
                "--model",
                str(doc.version),
                "--machine",
                doc.machine,
                "--db",
                url,
                "--temps",
                str(csv),
                "--controller",
                "tnc640",
                "--axis",
                "Z",
                "--range=-250,0",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    assert "compensation assignment (*.CMA)" in capsys.readouterr().out
    assert out.read_text().startswith("BEGIN Z.COM MM")


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--range", "250,0"], "the axis range 250..0 is empty"),
        (["--range", "0,250", "--axis", "W"], "axis 'W' is not one of X Y Z A B"),
        (["--range", "1,2,3"], "--range must be 2 numbers"),
        (["--range", "5,250", "--controller", "fanuc-0i"], None),
        (["--range", "0,1000"], "the range 0..1000 mm lies outside the X travel 0..254 mm"),
        (["--range", "0,254", "--step", "0.5"], "509 points: a table holds at most 256"),
        (["--range", "0,254", "--travel", "0,300", "--step", "1", "--controller", "828d"], "at most 200"),
        (["--range", "0,250", "--model", "7"], "--model VERSION needs --machine ID"),
        (["--range", "0,250", "--step", "0"], "the grid step must be positive"),
    ],
)
def test_cli_export_comp_one_line_errors_and_nothing_written(fitted, tmp_path, capsys, extra, needle):
    _, temps, root = fitted
    out = tmp_path / "x.tbl"
    args = [
        "export-comp",
        "--model",
        str(root / "model.json"),
        "--temps",
        str(root / "bundle" / "temperatures.csv"),
        "--controller",
        "linuxcnc",
        "--axis",
        "X",
        "-o",
        str(out),
    ]
    if needle is None:  # fanuc: the reference position 0 must be a grid point of 5..250
        args += ["--reference", "-10"]
        needle = "the reference position -10 is outside 5..250"
    assert main([*args, *extra]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines
    assert not out.exists()


def test_cli_export_comp_takes_the_travel_from_the_models_envelope(fitted, tmp_path, capsys):
    """A model document that states the machine's travel bounds the range; --travel overrides it."""
    _, _, root = fitted
    doc = json.loads((root / "model.json").read_text())
    doc["envelope"] = {"travel": {"X": [0.0, 200.0]}, "source": "machine file"}
    model = tmp_path / "model.json"
    model.write_text(json.dumps(doc))
    argv = ["export-comp", "--model", str(model), "--temps", str(root / "bundle" / "temperatures.csv")]
    argv += ["--controller", "linuxcnc", "--axis", "X", "-o", str(tmp_path / "x.comp")]
    assert main([*argv, "--range", "0,254"]) == 2
    err = capsys.readouterr().err
    assert "lies outside the X travel 0..200 mm (the model's envelope (machine file))" in err
    assert not (tmp_path / "x.comp").exists()
    assert main([*argv, "--range", "0,200", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["travel"] == [0.0, 200.0]
    assert main([*argv, "--range", "0,254", "--travel", "0,300", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["to"] == 254.0
