"""Proximity sensors: appendix C calibration matrices, roll from sensor pairs, A/D card bytes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from driftlab.daq.protocols import AngleMeter, DisplacementMeter
from driftlab.daq.proximity import (
    FLAG_OUT_OF_RANGE,
    TABLE_C1,
    TABLE_C2,
    ADCard,
    CalibrationMatrix,
    ProximitySensor,
    ReferenceSurfaceMeter,
    RollPair,
    a_axis_array,
    angle_from_pair,
    b_axis_array,
    voltage_to_displacement,
)
from driftlab.errors import ValidationError
from tests.daq.protocol_helpers import expected_protocol


def test_single_sensor_line():
    # table C.1, P5 for X motion: 4.1980 V + 8.5811 V/mm
    assert float(voltage_to_displacement(4.1980 + 8.5811 * 0.05, 4.1980, 8.5811)) == pytest.approx(0.05)
    with pytest.raises(ValidationError):
        voltage_to_displacement(1.0, 0.0, 0.0)


def test_calibration_matrix_from_tables():
    c1 = CalibrationMatrix.from_table(TABLE_C1)
    assert c1.sensors == ("P1", "P2", "P3", "P4", "P5") and c1.motions == ("dx", "dy", "dz")
    assert c1.slopes[4, 0] == 8.5811 and c1.slopes[0, 1] == 8.4225 and c1.slopes[3, 2] == 8.7469
    assert c1.constants[0] == pytest.approx((5.1292 + 5.1095 + 5.1609) / 3)
    # primary directions: P1, P2 read Y; P3, P4 read Z; P5 reads X
    assert list(c1.primary()) == [1, 1, 2, 2, 0]
    c2 = CalibrationMatrix.from_table(TABLE_C2)
    assert list(c2.primary()) == [2, 2, 0, 0, 1]
    assert c2.slopes[4, 1] == -8.3337


def test_cross_axis_terms_matter():
    # a pure X motion read through table C.2 moves the Z sensors P1/P2 too (0.32-0.37 V/mm)
    array = b_axis_array()
    truth = np.array([0.1, 0.0, 0.0, 0.0, 0.0])  # dx, dy, dz, alpha, gamma
    volts = array.forward(truth)
    assert array.solve(volts) == pytest.approx(truth, abs=1e-12)
    naive_dz = (volts[0] - array.calibration.constants[0]) / array.calibration.slopes[0, 2]
    assert abs(naive_dz) > 0.003  # ignoring the cross-axis slope would invent 4 um of Z


@pytest.mark.parametrize("make", [a_axis_array, b_axis_array])
def test_reference_arrays_resolve_translations_and_angles(make):
    array = make(150.0)
    assert len(array.terms()) == 5
    rng = np.random.default_rng(1)
    truth = np.column_stack([rng.uniform(-0.05, 0.05, (20, 3)), rng.uniform(-2e-4, 2e-4, (20, 2))])
    assert array.solve(array.forward(truth)) == pytest.approx(truth, abs=1e-12)


def test_a_axis_array_angles_are_beta_gamma():
    assert a_axis_array().angles == ("beta", "gamma")
    assert b_axis_array().angles == ("alpha", "gamma")


def test_angle_from_pair():
    assert float(angle_from_pair(0.015, -0.015, 300.0)) == pytest.approx(math.atan(0.03 / 300.0))
    with pytest.raises(ValidationError):
        angle_from_pair(0.0, 0.0, 0.0)


def test_ad_card_exact_bytes_and_channel_order():
    pairs = [(b"VOLT? 2,5\n", b"5.000000,1.000000,2.000000,6.500000\n")]
    with expected_protocol(ADCard, pairs) as card:
        assert list(card.read_volts([5, 2])) == [6.5, 5.0]
    with pytest.raises(ValidationError):
        ADCard(None).read_volts([16])  # type: ignore[arg-type]


def test_sensor_and_roll_pair():
    pairs = [(b"VOLT? 0,0\n", b"5.430000\n"), (b"VOLT? 1,1\n", b"4.570000\n"),
             (b"VOLT? 0,0\n", b"5.430000\n"), (b"VOLT? 1,1\n", b"10.000000\n")]  # fmt: skip
    with expected_protocol(ADCard, pairs) as card:
        a, b = ProximitySensor(card, 0, 5.0, 8.6), ProximitySensor(card, 1, 5.0, 8.6)
        roll = RollPair(a, b, 200.0)
        assert isinstance(a, DisplacementMeter) and isinstance(roll, AngleMeter)
        r = roll.read_angle()
        assert r.value == pytest.approx(math.atan((0.43 / 8.6 + 0.43 / 8.6) / 200.0))
        rail = roll.read_angle()  # second sensor at the 10 V rail
        assert math.isnan(rail.value) and rail.flag == FLAG_OUT_OF_RANGE


def test_reference_surface_meter_over_the_card():
    array = a_axis_array(150.0)
    truth = np.array([0.01, -0.02, 0.005, 3e-5, -4e-5])
    volts = array.forward(truth)
    reply = ",".join(f"{v:.6f}" for v in volts).encode() + b"\n"
    with expected_protocol(ADCard, [(b"VOLT? 0,4\n", reply)]) as card:
        meter = ReferenceSurfaceMeter(card, [0, 1, 2, 3, 4], array)
        out = meter.read()
    assert [out[t].value for t in array.terms()] == pytest.approx(truth, abs=2e-6)
