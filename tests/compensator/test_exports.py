"""Controller tables round trip: a model fitted on the virtual machine, exported, read back and applied as
the controller would, reproduces the model's own correction within 0.5 um between grid points."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from driftlab.campaigns.bundle import Bundle, CampaignMeta, write_bundle
from driftlab.cli import main
from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.exports import FORMATS, write
from driftlab.compensator.exports.grid import axis_correction, correction_table
from driftlab.daq.sim.campaign import simulate_campaign
from driftlab.daq.sim.scenario import Scenario
from driftlab.models.fitting import FitOptions, fit_bundles
from tests.compensator import controllers

TOL_MM = 0.5e-3  # the target: 0.5 um between grid points
RANGES = {"X": (0.0, 250.0), "Y": (0.0, 250.0), "Z": (-250.0, 0.0), "A": (-45.0, 45.0)}
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


def _apply(fmt: str, export, table, p, d):
    if fmt == "linuxcnc":
        return controllers.linuxcnc(export.text, p, d)
    if fmt == "siemens-cec":
        return controllers.siemens(export.text, f"AX{'XYZAB'.index(table.axis) + 1}", p, d)
    if fmt == "heidenhain":
        backlash = export.settings[f"CfgAxisComp/{table.axis}/backLash"]
        return controllers.heidenhain(export.text, backlash, p, d)
    return controllers.fanuc(export.text, 0.0, export.settings["detection_unit"], p, d, "XYZAB".index(table.axis) + 1)


def _dense(positions: np.ndarray, per_interval: int = 16) -> np.ndarray:
    """Return the grid points and ``per_interval - 1`` points inside every interval."""
    f = np.linspace(0.0, 1.0, per_interval + 1)[:-1]
    inner = (positions[:-1, None] + f[None, :] * np.diff(positions)[:, None]).ravel()
    return np.r_[inner, positions[-1]]


def round_trip_error(model, temps, fmt: str, axis: str) -> float:
    """Return the largest |controller correction - model correction| between grid points (mm, or deg)."""
    lo, hi = RANGES[axis]
    table = correction_table(model, temps, axis, lo, hi, STEP[axis], reference=0.0 if fmt == "fanuc" else None)
    export = write(fmt, table, **({"reference": 0.0} if fmt == "fanuc" else {}))
    p = _dense(table.positions)
    worst = 0.0
    for d in (1, -1):
        got = _apply(fmt, export, table, p, d)
        want = axis_correction(model, temps, axis, p, d)
        worst = max(worst, float(np.abs(got - want).max()))
    return worst


@pytest.mark.parametrize("fmt", FORMATS)
def test_exported_tables_reproduce_the_models_correction_between_grid_points(fitted, fmt):
    model, temps, _ = fitted
    errors = {axis: round_trip_error(model, temps, fmt, axis) for axis in ("X", "Y", "Z")}
    print(f"round trip {fmt}: " + ", ".join(f"{a} {e * 1e3:.4f} um" for a, e in errors.items()))
    assert max(errors.values()) < TOL_MM, errors
    # sharper: at a 10 mm step the interpolation error is a few nm; fanuc's integer detection units
    # (0.1 um) add at most one unit (the point's rounding and the reference shift's)
    assert max(errors.values()) < (1.05e-4 if fmt == "fanuc" else 1e-5), errors
    # the correction itself is not negligible: the table carries something
    table = correction_table(model, temps, "Z", *RANGES["Z"], 10.0)
    assert np.abs(table.forward).max() > 20 * TOL_MM


@pytest.mark.parametrize("fmt", FORMATS)
def test_rotary_axis_tables_in_degrees(fitted, fmt):
    model, temps, _ = fitted
    err_deg = round_trip_error(model, temps, fmt, "A")
    # 0.5 um at 100 mm from the axis
    assert err_deg < np.rad2deg(TOL_MM / 100.0), err_deg


@pytest.mark.parametrize("fmt", FORMATS)
def test_the_round_trip_check_sees_a_wrong_table(fitted, fmt):
    """A table with one point 3 um off, or with the directions swapped, is caught by the readers."""
    model, temps, _ = fitted
    table = correction_table(model, temps, "X", 0.0, 250.0, 10.0, reference=0.0 if fmt == "fanuc" else None)
    fwd = table.forward.copy()
    fwd[7] += 0.003
    bad = type(table)(table.axis, table.positions, fwd, table.reverse + 0.002, table.model)
    export = write(fmt, bad, **({"reference": 0.0} if fmt == "fanuc" else {}))
    p = _dense(table.positions)
    got = _apply(fmt, export, bad, p, 1)
    assert np.abs(got - axis_correction(model, temps, "X", p, 1)).max() > TOL_MM


def test_formats_in_the_controllers_terms(fitted):
    model, temps, _ = fitted
    table = correction_table(model, temps, "X", 0.0, 250.0, 10.0, reference=0.0)
    lin = write("linuxcnc", table)
    first = lin.text.splitlines()[0].split()
    assert len(first) == 3 and float(first[0]) == 0.0 and lin.settings["[JOINT_0]COMP_FILE_TYPE"] == 1
    sie = write("siemens-cec", table).text
    assert "$AA_ENC_COMP[0,25,AX1]=" in sie and "$AN_CEC_DIRECTION[1]=-1" in sie and sie.rstrip().endswith("M17")
    hei = write("heidenhain", table).text.splitlines()
    assert hei[0] == "BEGIN X.COM MM" and hei[1].split() == ["NR", "X", "DX"] and hei[-1] == "[END]" and len(hei) == 29
    fan = write("fanuc", table).text.splitlines()
    assert fan[0] == "%" and "N3620A1P0" in fan and "N3624A1P100000" in fan and "N10000P0" in fan


def test_cli_export_comp_writes_each_format(fitted, tmp_path, capsys):
    model, temps, root = fitted
    import pandas as pd

    csv = tmp_path / "temps.csv"
    pd.DataFrame([{"time_s": 0.0, **temps}]).to_csv(csv, index=False)
    for fmt in FORMATS:
        out = tmp_path / f"x.{fmt}"
        assert (
            main(
                [
                    "export-comp",
                    "--model",
                    str(root / "model.json"),
                    "--temps",
                    str(csv),
                    "--format",
                    fmt,
                    "--axis",
                    "X",
                    "--range",
                    "0,250",
                    "-o",
                    str(out),
                    "--json",
                ]
            )
            == 0
        )
        summary = json.loads(capsys.readouterr().out)
        assert summary["points"] == 26 and summary["format"] == fmt and out.read_text()
    # the file applies as the controller would, at the same temperatures
    text = (tmp_path / "x.linuxcnc").read_text()
    p = np.linspace(0.0, 250.0, 101)
    assert np.abs(controllers.linuxcnc(text, p, 1) - axis_correction(model, temps, "X", p, 1)).max() < TOL_MM


def test_cli_export_comp_from_a_registered_version(fitted, tmp_path, capsys):
    from driftlab.campaigns.bundle import load_bundle
    from driftlab.campaigns.store import connect
    from driftlab.jobs.registry import register_model

    model, temps, root = fitted
    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    store = connect(url)
    store.import_bundle(load_bundle(root / "bundle"))
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
                "--format",
                "heidenhain",
                "--axis",
                "Z",
                "--range=-250,0",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    assert "CfgAxisComp/Z/backLash" in capsys.readouterr().out
    assert out.read_text().startswith("BEGIN Z.COM MM")


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--range", "250,0"], "the axis range 250..0 is empty"),
        (["--range", "0,250", "--axis", "W"], "axis 'W' is not one of X Y Z A B"),
        (["--range", "1,2,3"], "--range must be 2 numbers"),
        (["--range", "5,250", "--format", "fanuc"], None),
        (["--range", "0,250", "--model", "7"], "--model VERSION needs --machine ID"),
        (["--range", "0,250", "--step", "0"], "the grid step must be positive"),
    ],
)
def test_cli_export_comp_one_line_errors_and_nothing_written(fitted, tmp_path, extra, needle):
    _, temps, root = fitted
    out = tmp_path / "x.tbl"
    args = [
        "export-comp",
        "--model",
        str(root / "model.json"),
        "--temps",
        str(root / "bundle" / "temperatures.csv"),
        "--format",
        "linuxcnc",
        "--axis",
        "X",
        "-o",
        str(out),
    ]
    if needle is None:  # fanuc: the reference position 0 must be a grid point of 5..250
        args += ["--reference", "-10"]
        needle = "fanuc: the reference position -10 is outside 5..250"
    proc = subprocess.run([sys.executable, "-m", "driftlab.cli", *args, *extra], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines
    assert not out.exists()
