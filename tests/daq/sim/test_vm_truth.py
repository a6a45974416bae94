"""The true error field: physical magnitudes, and a base truth the standard model can represent."""

import math

import numpy as np
import pytest

from driftlab.daq.sim import truth
from driftlab.daq.sim.scenario import HiddenEffect
from driftlab.daq.sim.sites import CHANNELS, SITE_INDEX, SITES, channel_map, structure_channels
from driftlab.errors import ValidationError
from driftlab.physics import kinematics as kin
from driftlab.physics.thermal import ALPHA_C


def test_table_5_1_sites():
    assert CHANNELS == tuple(f"T{i}" for i in range(1, 51))
    cmap = channel_map()
    assert cmap["T9"] == {"location": "X axis ballscrew nut", "structure": "x_screw"}
    assert cmap["T49"]["structure"] == cmap["T50"]["structure"] == "room"
    assert structure_channels("z_column") == tuple(f"T{i}" for i in range(22, 30))
    assert structure_channels("spindle_arm") == ("T32", "T33", "T34", "T35")
    # minutes near a motor, hours for the column and the base
    tau = {s.name: s.tau_min for s in SITES}
    assert tau["T10"] < 20 and tau["T37"] < 30 and min(tau[c] for c in structure_channels("base")) > 240


def test_table_6_3_magnitudes():
    bc = truth.base_coefficients()
    grad = {"T33": 0.5, "T34": 0.5, "T32": -0.5, "T35": -0.5}
    # theta_x angle of Z motion per degC of the arm gradient: alpha_c L / H = 0.0014 deg/degC (eq. 3.4)
    alpha = sum(w * bc["Z"]["alpha"]["channels"][c] for c, w in grad.items())
    assert math.degrees(alpha) == pytest.approx(0.00139, rel=0.01)
    # Z position per degC of the gradient: eq. 3.5's tip deflection alpha_c L^2 / (2H) plus the arm
    # angle acting over the 400 mm head: 0.00484 + 0.00968 mm/degC (Table 6.3: 0.0103 to 0.0121)
    dz = sum(w * bc["Z"]["dz"]["channels"][c] for c, w in grad.items())
    assert abs(dz) == pytest.approx(ALPHA_C * (400.0**2 / 400.0 + 400.0 * 2.0), rel=1e-3)
    # column growth: alpha_c * 1200 mm per degC of the corner mean (eq. 3.3)
    col = sum(bc["Z"]["dz"]["channels"].get(c, 0.0) for c in structure_channels("z_column"))
    assert col == pytest.approx(ALPHA_C * 1200.0, rel=1e-3)


def test_model_channels_hold_every_driver_and_leave_candidates_out():
    for chans in truth.MODEL_CHANNELS.values():
        assert set(truth.DRIVERS) <= set(chans) <= set(truth.THESIS_SELECTION)
        assert {"T49", "T50", "T7", "T9", "T10", "T24", "T26", "T32", "T34"} <= set(chans)  # ch. 5.4
        assert not {"T1", "T11", "T22", "T36", "T47", "T48"} & set(chans)
    assert "T21" in truth.MODEL_CHANNELS["Y"] and "T21" not in truth.MODEL_CHANNELS["Z"]
    bc = truth.base_coefficients()
    for axis in truth.AXIS_RANGE:
        for term in kin.PARAMS:
            assert set(bc[axis][term]["channels"]) <= set(truth.DRIVERS)


@pytest.mark.parametrize("axis", ["X", "Y", "Z", "A", "B"])
def test_thermal_sensitivity_does_not_depend_on_position(axis):
    """No lever turns a thermal error into position x dT: the standard model can represent the base truth."""
    lo, hi = truth.AXIS_RANGE[axis]
    pos = np.linspace(lo, hi, 7)
    rng = np.random.default_rng(0)
    dT = rng.normal(0.0, 3.0, size=len(CHANNELS))
    w_hot = truth.base_workspace(axis, pos, dT)
    w_cold = truth.base_workspace(axis, pos, np.zeros(len(CHANNELS)))
    bc = truth.base_coefficients()[axis]
    predicted = np.array([sum(c * dT[SITE_INDEX[ch]] for ch, c in bc[t]["channels"].items()) for t in kin.PARAMS])
    diff = w_hot - w_cold
    # translations to 1e-6 mm and angles to 1e-9 rad: far below the laser noise (5e-4 mm, 4.8e-7 rad)
    np.testing.assert_allclose(diff[:, :3], np.broadcast_to(predicted[:3], (7, 3)), atol=1e-9)
    np.testing.assert_allclose(diff[:, 3:], np.broadcast_to(predicted[3:], (7, 3)), atol=1e-6)
    assert np.abs(predicted).max() > 1e-3  # something thermal is there


@pytest.mark.parametrize("axis", ["X", "Y", "Z", "A", "B"])
def test_geometric_shape_is_cubic(axis):
    lo, hi = truth.AXIS_RANGE[axis]
    pos = np.linspace(lo, hi, 23)
    geo = truth.base_workspace(axis, pos, np.zeros(len(CHANNELS)))
    V = np.vander(pos, 4, increasing=True)
    coef, *_ = np.linalg.lstsq(V, geo, rcond=None)
    resid = np.abs(geo - V @ coef).max(axis=0)
    assert resid[:3].max() < 1e-8 and resid[3:].max() < 2e-5
    assert np.ptp(geo[:, 3:], axis=0).max() > 1e-3  # some um of shape along the travel


def test_hidden_delta_formulas():
    t = np.array([0.0, 43200.0, 86400.0])
    pos = np.array([0.0, 100.0, 200.0])
    d = np.array([1, -1, 1])
    dT = np.array([0.0, 1.0, 2.0])
    rev = HiddenEffect(kind="reversal", axis="X", term="dx", params={"magnitude_mm": 0.004})
    np.testing.assert_allclose(truth.hidden_delta(rev, t, pos, d, None), [0.002, -0.002, 0.002])
    drift = HiddenEffect(kind="drift", axis="B", term="beta", params={"rate_per_day": 2e-6})
    np.testing.assert_allclose(truth.hidden_delta(drift, t, pos, d, None), [0, 1e-6, 2e-6])
    screw = HiddenEffect(
        kind="screw_expansion", axis="X", term="dx", channels=["T9"], params={"coef_per_mm_degC": 1e-5}
    )
    np.testing.assert_allclose(truth.hidden_delta(screw, t, pos, d, dT), [0, 1e-3, 4e-3])
    quad = HiddenEffect(kind="quadratic", axis="Z", term="dz", channels=["T37"], params={"coef_per_degC2": 1e-4})
    np.testing.assert_allclose(truth.hidden_delta(quad, t, pos, d, dT), [0, 1e-4, 4e-4])
    lag = HiddenEffect(kind="thermal_lag", axis="Z", term="dz", channels=["T34"], params={"tau_s": 1000})
    c = truth.lag_coefficient(lag)
    assert c == pytest.approx(truth.base_coefficients()["Z"]["dz"]["channels"]["T34"])
    np.testing.assert_allclose(truth.hidden_delta(lag, t, pos, d, dT, dT - 0.5), -0.5 * c)


def test_thermal_lag_needs_a_driving_channel():
    bad = HiddenEffect(kind="thermal_lag", axis="X", term="beta", channels=["T34"], params={"tau_s": 1000})
    with pytest.raises(ValidationError, match="no base coefficient"):
        truth.lag_coefficient(bad)
    ok = bad.model_copy(update={"params": {"tau_s": 1000, "coef_per_degC": 2e-6}})
    assert truth.lag_coefficient(ok) == 2e-6
