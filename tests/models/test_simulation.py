"""Appendix A error laws and the ch. 4.5 compensation study."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from driftlab.errors import ValidationError
from driftlab.models import simulation as sim
from driftlab.physics import kinematics as kin

H = sim.HOUR_S
REPO = Path(__file__).resolve().parents[2]  # run the CLI from the work tree, as `make test` does
LONG = 1e9  # s: the warm-up is over


def q_at(**axes: float) -> np.ndarray:
    q = np.zeros((1, 5))
    for name, value in axes.items():
        q[0, kin.AXES.index(name)] = value
    return q


def test_constants_match_appendix_tables():
    k, tau = sim.TABLE_A2["T2"]  # vertical column
    np.testing.assert_allclose(k, [-24e-6, -15e-6, 10e-6, -12.7e-3, 25.4e-3, -76.2e-3])
    assert tau == 2.5 * H
    k, tau = sim.TABLE_A2["T6"]  # part table
    np.testing.assert_allclose(k, [-2.5e-6, -3.3e-6, -5.0e-6, -1.6e-3, 1.2e-3, -0.8e-3])
    assert tau == 0.5 * H
    assert sim.TABLE_A2["T1"][1] == 1.5 * H and sim.TABLE_A2["T5"][0][4] == pytest.approx(9.6e-3)
    col, x_max, k_ang, k_dx, tau = sim.TABLE_A3["phi_y"]
    assert (col, x_max, k_dx, tau) == (1, 254.0, -60e-6, 3.0 * H)
    np.testing.assert_allclose(k_ang, [0.213e-6, 0.220e-6, -0.252e-6])
    assert sim.TABLE_A3["phi_z"][1] == -254.0 and sim.TABLE_A3["phi_x"][3] == 40e-6
    col, th_max, k, tau = sim.TABLE_A4["theta_x"]
    assert (col, th_max, tau) == (3, np.pi / 4, 1.4 * H)
    np.testing.assert_allclose(k, [12.7e-6, 19.1e-6, 25.5e-6, 32.3e-3, -24.3e-3, 16.2e-3])
    assert sim.TABLE_A4["theta_y"][3] == 2.0 * H
    assert (sim.RESOLUTION_MM, sim.RESOLUTION_DEG) == (0.0025, 0.001)


def test_link_law_a1_limits():
    q = np.zeros((3, 5))
    errs = sim.appendix_a_errors(np.array([0.0, 1.5 * H, LONG]), q)
    k = sim.TABLE_A2["T1"][0]
    np.testing.assert_allclose(errs["T1"][0], 0.3 * k)  # t = 0: 0.3 of the steady value
    np.testing.assert_allclose(errs["T1"][1], (0.3 + 0.7 * (1 - np.exp(-1))) * k)  # t = tau
    np.testing.assert_allclose(errs["T1"][2], k)  # t -> inf: 1.0
    assert set(errs) == set(kin.ELEMENTS)
    assert all(v.shape == (3, 6) for v in errs.values())


@pytest.mark.parametrize("joint", ["phi_x", "phi_y", "phi_z"])
def test_translational_law_a2_limits(joint):
    col, x_max, k_ang, k_dx, _ = sim.TABLE_A3[joint]
    q = np.zeros((3, 5))
    q[:2, col] = x_max
    errs = sim.appendix_a_errors(np.array([0.0, LONG, 0.0]), q, backlash=False)[joint]
    slot = 3 + col
    np.testing.assert_allclose(errs[0, :3], 0.3 * x_max * k_ang)
    np.testing.assert_allclose(errs[1, :3], x_max * k_ang)
    np.testing.assert_allclose(errs[0, slot], 0.3 * x_max * k_dx)
    np.testing.assert_allclose(errs[1, slot], x_max * k_dx)
    np.testing.assert_array_equal(errs[2], 0.0)  # at home, cold: nothing


def test_straightness_is_the_integral_of_the_angles():
    # eq. 4.10: dy(x) = int_0^x gamma dx and dz(x) = -int_0^x beta dx for the X axis
    x = np.linspace(0, 254, 2001)
    q = np.zeros((x.size, 5))
    q[:, 0] = x
    errs = sim.appendix_a_errors(2.0 * H, q, backlash=False)["phi_x"]
    cum = lambda f: np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(x))])  # noqa: E731
    np.testing.assert_allclose(errs[:, 4], cum(errs[:, 2]), atol=1e-9)
    np.testing.assert_allclose(errs[:, 5], -cum(errs[:, 1]), atol=1e-9)
    assert abs(errs[-1, 4]) > 1e-4  # worth checking: microns


@pytest.mark.parametrize("joint", ["theta_x", "theta_y"])
def test_rotary_law_a3_limits(joint):
    col, th_max, k, _ = sim.TABLE_A4[joint]
    q = np.zeros((2, 5))
    q[:, col] = th_max
    errs = sim.appendix_a_errors(np.array([0.0, LONG]), q, backlash=False)[joint]
    np.testing.assert_allclose(errs[0], 0.3 * th_max * k)
    np.testing.assert_allclose(errs[1], th_max * k)


def test_backlash_is_direction_dependent_in_the_positioning_slot():
    q = np.tile(q_at(X=100.0, Y=50.0, Z=-30.0, A=0.2, B=0.4), (2, 1))
    direction = np.array([[1, 1, 1, 1, 1], [-1, -1, -1, -1, -1]])
    errs = sim.appendix_a_errors(H, q, direction)
    for joint, slot, size in [
        ("phi_x", 3, sim.BACKLASH_MM),
        ("phi_y", 4, sim.BACKLASH_MM),
        ("phi_z", 5, sim.BACKLASH_MM),
        ("theta_x", 0, sim.BACKLASH_RAD),
        ("theta_y", 1, sim.BACKLASH_RAD),
    ]:
        diff = errs[joint][1] - errs[joint][0]
        expected = np.zeros(6)
        expected[slot] = size
        np.testing.assert_allclose(diff, expected, atol=1e-15, err_msg=joint)
    still = sim.appendix_a_errors(H, q, None)
    np.testing.assert_allclose(still["phi_x"][0], 0.5 * (errs["phi_x"][0] + errs["phi_x"][1]))


def test_gain_and_tau_scale_for_calibration():
    q = np.tile(q_at(X=200.0, A=0.5), (1, 1))
    base = sim.appendix_a_errors(H, q)
    doubled = sim.appendix_a_errors(H, q, gain={"A1": 2.0})
    np.testing.assert_allclose(doubled["T3"], 2 * base["T3"])
    np.testing.assert_allclose(doubled["phi_x"], base["phi_x"])
    only = sim.appendix_a_errors(H, q, gain={"A1": 2.0, "T3": 0.5})
    np.testing.assert_allclose(only["T3"], 0.5 * base["T3"])
    # a slower warm-up: at t = tau_L, scaling tau by 2 gives the level at t = tau_L / 2
    tau = sim.TABLE_A2["T1"][1]
    slow = sim.appendix_a_errors(tau, q, tau_scale=2.0, backlash=False)
    half = sim.appendix_a_errors(tau / 2, q, backlash=False)
    np.testing.assert_allclose(slow["T1"], half["T1"])
    with pytest.raises(ValidationError, match="unknown"):
        sim.appendix_a_errors(H, q, gain={"A9": 1.0})
    with pytest.raises(ValidationError, match="tau_scale"):
        sim.appendix_a_errors(H, q, tau_scale={"A3": 0.0})
    with pytest.raises(ValidationError):
        sim.appendix_a_errors(-1.0, q)
    with pytest.raises(ValidationError):
        sim.appendix_a_errors(H, q, direction=np.ones((3, 2)))


def test_contract_signature_with_dims():
    t = np.full(3, 4 * H)
    q = np.zeros((3, 5))
    moving = np.ones((3, 5))
    # with a direction the backlash law adds to the joint errors: the two calls below must differ
    assert not np.allclose(sim.appendix_a_errors(t, q, moving)["phi_x"], sim.appendix_a_errors(t, q)["phi_x"])
    # the contract's third positional argument may be the link dimensions: read as dims, not a direction
    np.testing.assert_allclose(sim.appendix_a_errors(t, q, kin.TABLE_A1)["phi_x"], sim.appendix_a_errors(t, q)["phi_x"])
    np.testing.assert_allclose(
        sim.appendix_a_errors(t, q, moving, dims=kin.TABLE_A1)["phi_x"], sim.appendix_a_errors(t, q, moving)["phi_x"]
    )
    # dims are validated, positional or keyword
    bad = {**kin.TABLE_A1, "T3": (1.0, float("nan"), 0.0)}
    with pytest.raises(kin.KinematicsError, match="T3"):
        sim.appendix_a_errors(t, q, bad)
    with pytest.raises(kin.KinematicsError, match="lack"):
        sim.appendix_a_errors(t, q, dims={"T1": (0, 0, 0)})


def test_compensation_of_the_appendix_a_errors_themselves():
    t = np.linspace(0, 8 * H, 500)
    q, direction = sim.sinusoidal_program(t, seed=4)
    errs = sim.appendix_a_errors(t, q, direction)
    before = kin.workspace_error(q, errs)
    assert np.abs(before[:, 3:]).max() > 0.05
    res = kin.compensate(q, errs)
    assert np.abs(res.residual[:, 3:]).max() < 1e-6
    assert np.abs(res.residual[:, :2]).max() < 1e-9
    np.testing.assert_allclose(res.uncompensable_roll, res.residual[:, 2])


def test_program_is_a_sinusoid_within_the_travels():
    t = np.arange(0, 8 * H, 10.0)
    q, direction = sim.sinusoidal_program(t, seed=3)
    assert q.shape == (t.size, 5) and direction.shape == (t.size, 5)
    assert q[:, 0].min() >= 0 and q[:, 0].max() <= 254.0
    assert q[:, 2].max() <= 0 and q[:, 2].min() >= -254.0  # Z moves down
    assert np.abs(q[:, 3:]).max() <= np.pi / 4 + 1e-12  # A stays clear of 90 deg
    assert np.ptp(q, axis=0).min() > 0.9 * np.array([254, 254, 254, np.pi / 4, np.pi / 4]).min()
    # the direction is the sign of the velocity
    np.testing.assert_array_equal(direction[1:-1, 0], np.sign(q[2:, 0] - q[:-2, 0])[:])


def test_thesis_study_meets_the_resolution():
    out = sim.thesis_study(hours=8.0, seed=0)
    unc, comp, res = out["uncompensated"], out["compensated"], out["resolution"]
    assert res == {"mm": 0.0025, "deg": 0.001}
    for block in (unc, comp):
        assert {"max_mm", "rms_mm", "max_deg", "rms_deg"} <= set(block)
    # the appendix errors are tens of resolution steps before compensation
    assert unc["max_mm"] > 20 * res["mm"] and unc["max_deg"] > 5 * res["deg"]
    # figs. 4.7-4.8: down to the resolution on the reachable degrees of freedom
    assert comp["max_mm"] <= res["mm"]
    assert comp["max_deg"] <= res["deg"]
    for axis in ("dx_mm", "dy_mm", "dz_mm"):
        assert comp["max_abs"][axis] <= 0.51 * res["mm"]  # within half a step per axis
    assert comp["rms_mm"] < unc["rms_mm"] / 30
    # the roll about the spindle is not compensable and is reported, not hidden
    assert comp["max_roll_deg"] > res["deg"]
    assert out["singular_poses"] == 0 and out["samples"] == 8 * 360 + 1


def test_thesis_study_is_seeded():
    a = sim.thesis_study(hours=1.0, seed=1)
    assert a == sim.thesis_study(hours=1.0, seed=1)
    assert a != sim.thesis_study(hours=1.0, seed=2)
    with pytest.raises(ValidationError):
        sim.thesis_study(hours=0.0)


def test_cli_sim_thesis_writes_json(tmp_path):
    out = tmp_path / "figs" / "thesis.json"
    proc = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "sim", "thesis", "--json", str(out), "--hours", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert {"uncompensated", "compensated", "resolution"} <= set(doc)
    assert set(doc["resolution"]) == {"mm", "deg"}
    for block in ("uncompensated", "compensated"):
        assert {"max_mm", "rms_mm", "max_deg", "rms_deg"} <= set(doc[block])
    assert doc["compensated"]["max_mm"] <= 0.0025
    assert json.loads(proc.stdout) == doc


def test_cli_sim_thesis_bad_hours_is_one_line():
    proc = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "sim", "thesis", "--json", "/dev/null", "--hours", "-1"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("driftlab: error:")
