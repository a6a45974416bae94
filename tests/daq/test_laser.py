"""Laser interferometer: Edlen compensation, table 5.3, exact bytes, settling, beam breaks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from driftlab.daq.laser import (
    Environment,
    LaserInterferometer,
    SettleOptions,
    air_refractive_index,
    fringes_to_value,
    remove_linear_trend,
    value_to_fringes,
    water_vapour_saturation_pa,
)
from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_REFERENCE_LOST, AngleMeter, DisplacementMeter
from driftlab.errors import InstrumentError, ValidationError
from tests.daq.protocol_helpers import expected_protocol

ENV = b"20.000,101325.0,50.0\n"
N_AIR = float(air_refractive_index(20.0, 101325.0, 50.0))


def test_edlen_at_standard_conditions():
    n = air_refractive_index(20.0, 101325.0, 50.0)
    assert 2.710e-4 < n - 1 < 2.718e-4


def test_edlen_sensitivities_match_the_rules_of_thumb():
    n0 = air_refractive_index(20.0, 101325.0, 50.0)
    # about -0.93 ppm per K, +0.27 ppm per hPa, -0.0085 ppm per %RH near 20 degC (Birch & Downs)
    assert (air_refractive_index(21.0, 101325.0, 50.0) - n0) == pytest.approx(-0.93e-6, rel=0.05)
    assert (air_refractive_index(20.0, 101425.0, 50.0) - n0) == pytest.approx(0.268e-6, rel=0.05)
    assert (air_refractive_index(20.0, 101325.0, 60.0) - n0) == pytest.approx(-0.085e-6, rel=0.12)


def test_saturation_vapour_pressure():
    assert float(water_vapour_saturation_pa(20.0)) == pytest.approx(2339.0, rel=2e-3)
    assert float(water_vapour_saturation_pa(0.01)) == pytest.approx(611.7, rel=3e-3)


@pytest.mark.parametrize(("mode", "value"), [("LIN", 123.456), ("STR", 0.0123), ("ANG", 2.5e-5)])
def test_fringe_conversion_round_trips(mode, value):
    fringes = value_to_fringes(mode, value, N_AIR)
    assert float(fringes_to_value(mode, fringes, N_AIR)) == pytest.approx(value, rel=1e-12)


def test_linear_fringes_follow_half_wavelength_in_air():
    # one fringe of a double-pass optic is half the wavelength in air
    assert float(fringes_to_value("LIN", 1.0, N_AIR)) == pytest.approx(632.991e-6 / 2 / N_AIR)


def test_remove_linear_trend():
    x = np.linspace(0.0, 500.0, 11)
    bow = 1e-3 * np.sin(np.pi * x / 500.0)
    y = bow + 2e-5 * x + 0.01
    out = remove_linear_trend(x, y)
    expected = bow - np.polyval(np.polyfit(x, bow, 1), x)
    assert out == pytest.approx(expected, abs=1e-12)


def _meas(mode, value, signal=90.0):
    return f"{float(value_to_fringes(mode, value, N_AIR)):.5f},{signal:.1f}\n".encode()


def _setup_pairs(mode, axis, term):
    return [(f"MODE {mode}\n".encode(), b"OK\n"), (f"AXIS {axis}\n".encode(), b"OK\n"),
            (f"TERM {term}\n".encode(), b"OK\n"), (b"REF\n", b"OK\n")]  # fmt: skip


def _laser(ch, max_settle_polls: int = 120, **kw):
    return LaserInterferometer(ch, settle=SettleOptions(max_settle_polls=max_settle_polls, sleep=lambda s: None), **kw)


def test_linear_point_exact_bytes_and_mean_of_ten():
    values = 100.003 + 1e-5 * np.arange(-5, 5)  # ten readings around the point
    pairs = _setup_pairs("LIN", "X", "dx") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS?\n", _meas("LIN", 100.0031)), (b"MEAS?\n", _meas("LIN", 100.0030))]  # settled
    pairs += [(b"MEAS?\n", _meas("LIN", v)) for v in values]
    with expected_protocol(_laser, pairs) as laser:
        laser.configure("X", "dx")
        laser.reference(0.0)
        sample = laser.measure_error("X", "dx", 100.0, -1)
    assert isinstance(laser, DisplacementMeter) and isinstance(laser, AngleMeter)
    assert sample.flag is None and sample.direction == -1
    assert sample.value == pytest.approx(np.mean(values) - 100.0, abs=1e-8)


def test_angle_point_uses_angle_optics():
    pairs = _setup_pairs("ANG", "Z", "beta") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS?\n", _meas("ANG", 3e-6))] * 12
    with expected_protocol(_laser, pairs) as laser:
        laser.configure("Z", "beta")
        laser.reference()
        assert laser.read_angle().value == pytest.approx(3e-6, abs=2e-10)


def test_waits_for_axis_to_settle():
    sleeps = []
    pairs = _setup_pairs("STR", "X", "dy") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS?\n", _meas("STR", v)) for v in (0.05, 0.02, 0.008, 0.0051, 0.0050)]
    pairs += [(b"MEAS?\n", _meas("STR", 0.005))] * 10
    with expected_protocol(
        lambda ch: LaserInterferometer(ch, settle=SettleOptions(sleep=sleeps.append, settle_poll_s=0.25)), pairs
    ) as laser:
        laser.configure("X", "dy")
        laser.reference()
        assert laser.read_displacement().value == pytest.approx(0.005, abs=1e-9)
    assert sleeps == [0.25] * 4


def test_never_settling_axis_is_an_instrument_error():
    pairs = _setup_pairs("LIN", "Y", "dy") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS?\n", _meas("LIN", 0.01 * k)) for k in range(5)]
    with expected_protocol(lambda ch: _laser(ch, max_settle_polls=5), pairs) as laser:
        laser.configure("Y", "dy")
        laser.reference()
        with pytest.raises(InstrumentError, match="did not settle"):
            laser.read()


@pytest.mark.parametrize("bad", [b"ERR BEAM\n", b"12.5,3.0\n"])
def test_beam_break_flags_sample_and_loses_reference(bad):
    pairs = _setup_pairs("LIN", "X", "dx") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS?\n", _meas("LIN", 1.0))] * 5 + [(b"MEAS?\n", bad)]
    # after the break: no traffic until the reference is re-established, then a new epoch
    pairs += [(b"REF\n", b"OK\n"), (b"ENV?\n", ENV)] + [(b"MEAS?\n", _meas("LIN", 0.0))] * 12
    with expected_protocol(_laser, pairs) as laser:
        laser.configure("X", "dx")
        laser.reference(0.0)
        epoch = laser.reference_epoch
        broken = laser.measure_error("X", "dx", 1.0, 1)
        assert math.isnan(broken.value) and broken.flag == FLAG_BEAM_BREAK
        assert laser.reference_lost
        again = laser.measure_error("X", "dx", 1.0, 1)
        assert math.isnan(again.value) and again.flag == FLAG_REFERENCE_LOST
        laser.reference(1.0)
        assert laser.reference_epoch == epoch + 1
        fresh = laser.measure_error("X", "dx", 1.0, 1)
        assert fresh.flag is None and fresh.value == pytest.approx(0.0, abs=1e-9)


def test_reconfiguring_optics_needs_a_new_reference():
    pairs = _setup_pairs("LIN", "X", "dx") + [(b"MODE STR\n", b"OK\n"), (b"TERM dy\n", b"OK\n")]
    with expected_protocol(_laser, pairs) as laser:
        laser.configure("X", "dx")
        laser.reference()
        laser.configure("X", "dy")
        assert laser.read().flag == FLAG_REFERENCE_LOST


def test_table_5_3_terms_only():
    with pytest.raises(ValidationError, match="table 5.3"):
        LaserInterferometer(None).configure("X", "alpha")  # roll of X: proximity sensors
    with pytest.raises(ValidationError):
        LaserInterferometer(None).configure("A", "dx")


def test_refused_setting_is_retried_then_raised():
    pairs = [(b"MODE LIN\n", b"ERR PARAM\n")] * 3
    with expected_protocol(_laser, pairs) as laser:
        with pytest.raises(InstrumentError, match="laser|dut"):
            laser.configure("X", "dx")


def test_manual_environment_skips_weather_station():
    env = Environment(22.0, 100000.0, 30.0)
    n = env.refractive_index()
    pairs = _setup_pairs("LIN", "Z", "dz")
    pairs += [(b"MEAS?\n", f"{float(value_to_fringes('LIN', 5.0, n)):.5f},90.0\n".encode())] * 12
    with expected_protocol(lambda ch: _laser(ch, environment=env), pairs) as laser:
        laser.configure("Z", "dz")
        laser.reference()
        assert laser.read().value == pytest.approx(5.0, abs=1e-8)


def _burst(mode, values, signal=90.0):
    return (";".join(f"{float(value_to_fringes(mode, v, N_AIR)):.5f},{signal:.1f}" for v in values) + "\n").encode()


def test_burst_point_exact_bytes_and_mean_of_ten():
    values = 100.003 + 1e-5 * np.arange(-5, 5)
    pairs = _setup_pairs("LIN", "X", "dx") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS? 12\n", _burst("LIN", [100.0031, 100.0030, *values]))]  # settled, then ten
    with expected_protocol(lambda ch: _laser(ch, burst=True), pairs) as laser:
        laser.configure("X", "dx")
        laser.reference(0.0)
        sample = laser.measure_error("X", "dx", 100.0, -1)
    assert sample.flag is None
    assert sample.value == pytest.approx(np.mean(values) - 100.0, abs=1e-8)


def test_burst_that_shows_motion_falls_back_to_polling_and_a_weak_burst_breaks_the_beam():
    values = [50.0] * 10
    pairs = _setup_pairs("LIN", "Y", "dy") + [(b"ENV?\n", ENV)]
    pairs += [(b"MEAS? 12\n", _burst("LIN", [49.0, 49.5, *values]))]  # still moving
    pairs += [(b"MEAS?\n", _meas("LIN", 50.0)), (b"MEAS?\n", _meas("LIN", 50.0))]
    pairs += [(b"MEAS?\n", _meas("LIN", v)) for v in values]
    sleeps: list[float] = []
    with expected_protocol(
        lambda ch: LaserInterferometer(ch, settle=SettleOptions(sleep=sleeps.append), burst=True), pairs
    ) as laser:
        laser.configure("Y", "dy")
        laser.reference(0.0)
        assert laser.measure_error("Y", "dy", 50.0, 1).value == pytest.approx(0.0, abs=1e-8)
    assert sleeps and sleeps[0] == laser.settle_poll_s
    pairs = _setup_pairs("LIN", "Y", "dy") + [(b"ENV?\n", ENV), (b"MEAS? 12\n", _burst("LIN", [50.0] * 12, 4.0))]
    with expected_protocol(lambda ch: _laser(ch, burst=True), pairs) as laser:
        laser.configure("Y", "dy")
        laser.reference(0.0)
        sample = laser.measure_error("Y", "dy", 50.0, 1)
    assert sample.flag == FLAG_BEAM_BREAK and laser.reference_lost
