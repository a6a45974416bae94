"""The virtual machine: deterministic, order-free, physically plausible temperatures and faults."""

import math

import numpy as np
import pytest

from driftlab.daq.sim.machine import VirtualMachine, hash_normal
from driftlab.daq.sim.scenario import HiddenEffect, Noise, Scenario, Stage
from driftlab.daq.sim.sites import SITE_INDEX
from driftlab.errors import ValidationError


def _vm(**kw) -> VirtualMachine:
    return VirtualMachine(Scenario(**{"hours": 6.0, **kw}))


def test_deterministic_and_order_free():
    t = np.arange(0, 6 * 3600 + 1, 300.0)
    a = _vm(seed=3)
    late_first = a.temperatures(20000.0)
    bulk = a.readings_array(t)
    b = _vm(seed=3)
    np.testing.assert_array_equal(b.readings_array(t), bulk)
    assert b.temperatures(20000.0) == late_first
    row = b.temperatures(float(t[7]))
    assert [row[f"T{i}"] for i in range(1, 51)] == bulk[7].tolist()
    c = _vm(seed=4)
    assert not np.array_equal(c.readings_array(t), bulk)
    # the seed drives the noise and the local air disturbances, never the heat sources or the room cycle
    diff = c.true_temperatures_array(t) - a.true_temperatures_array(t)
    assert 0 < np.abs(diff).max() < 2.0
    from driftlab.daq.sim.scenario import Room

    calm = Room(local_sigma_degC=0.0)
    np.testing.assert_array_equal(
        _vm(seed=4, room=calm).true_temperatures_array(t), _vm(seed=3, room=calm).true_temperatures_array(t)
    )
    e1 = a.measure_error(3600.0, "Z", -127.0, 1)
    assert e1 == _vm(seed=3).measure_error(3600.0, "Z", -127.0, 1)
    assert set(e1) == {"alpha", "beta", "gamma", "dx", "dy", "dz"}


def test_thermocouple_noise_is_what_the_scenario_says():
    vm = _vm(noise=Noise(thermocouple_degC=0.05))
    t = np.arange(0, 6 * 3600 + 1, 60.0)
    resid = vm.readings_array(t) - vm.true_temperatures_array(t)
    assert resid.std() == pytest.approx(0.05, rel=0.03)
    assert abs(resid.mean()) < 0.003
    z = hash_normal(1, 2, np.arange(200000))
    assert z.std() == pytest.approx(1.0, abs=0.01) and abs(z.mean()) < 0.01
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.01


def test_heat_sources_and_room():
    stages = [
        Stage(name="spindle", start_s=0, end_s=4 * 3600, heat_source="spindle", axis="Z", spindle_rpm=10000),
        Stage(name="rest", start_s=4 * 3600, end_s=8 * 3600, heat_source="idle"),
    ]
    vm = VirtualMachine(Scenario(hours=8, stages=stages))
    temp = vm.true_temperatures_array(np.array([0.0, 4 * 3600.0, 8 * 3600.0]))
    i37, i34, i32, i24 = (SITE_INDEX[c] for c in ("T37", "T34", "T32", "T24"))
    rise = temp[1] - temp[0]
    assert 15 < rise[i37] < 22  # ~20 degC near the spindle motor (ch. 5.3)
    assert rise[i34] - rise[i32] > 2.5  # the arm's upper/lower gradient (Fig. 5.16)
    assert 0 < rise[i24] < rise[i32]  # the column is slow
    assert temp[2, i37] < temp[1, i37] - 10  # and it cools down again
    # the room: daily cycle, ceiling warmer than floor
    day = VirtualMachine(Scenario(hours=24, stages=[]))
    t = np.arange(0, 24 * 3600 + 1, 600.0)
    room = day.true_temperatures_array(t)[:, [SITE_INDEX["T49"], SITE_INDEX["T50"]]]
    assert np.ptp(room[:, 0]) > 1.2
    assert (room[:, 0] - room[:, 1]).mean() == pytest.approx(1.5, abs=0.3)


def test_state_follows_the_plan():
    stages = [Stage(name="feed-x", start_s=0, end_s=3600, heat_source="feed", axis="X", feed_mm_min=3000)]
    vm = VirtualMachine(Scenario(hours=2, stages=stages))
    s = vm.state(3.0)
    assert s["stage"] == "feed-x" and s["feed_mm_min"] == 3000
    assert s["x"] == pytest.approx(3 * 3000 / 60)
    assert vm.state(6.0)["x"] == pytest.approx(254 - (300 - 254))  # turned at the end of the travel
    off = vm.state(5000.0)
    assert off["heat_source"] == "off" and off["feed_mm_min"] == 0 and off["x"] == 0
    xs = vm.state_array(np.arange(0, 3600, 7.0))["x"]
    assert xs.min() >= 0 and xs.max() <= 254 and np.ptp(xs) > 250


def test_sensor_faults_change_readings_not_the_structure():
    start = 3 * 3600.0
    det = HiddenEffect(kind="sensor_fault", channels=["T34"], params={"start_s": start, "mode": "detached"})
    opn = HiddenEffect(kind="sensor_fault", channels=["T9", "T30"], params={"start_s": start, "mode": "open"})
    base, faulty = _vm(seed=1), _vm(seed=1, hidden=[det, opn])
    t = np.arange(0, 6 * 3600 + 1, 60.0)
    a, b = base.readings_array(t), faulty.readings_array(t)
    before = t < start
    np.testing.assert_array_equal(a[before], b[before])
    others = [i for i in range(50) if i not in (SITE_INDEX["T34"], SITE_INDEX["T9"], SITE_INDEX["T30"])]
    np.testing.assert_array_equal(a[:, others], b[:, others])
    assert np.isnan(b[~before][:, [SITE_INDEX["T9"], SITE_INDEX["T30"]]]).all()
    # the detached junction reads the air near the arm after a few minutes
    true = faulty.true_temperatures_array(t)
    air = 0.85 * true[:, SITE_INDEX["T49"]] + 0.15 * true[:, SITE_INDEX["T50"]]
    late = t > start + 1800
    assert np.abs(b[late, SITE_INDEX["T34"]] - air[late]).max() < 0.1
    assert np.abs(true[late, SITE_INDEX["T34"]] - air[late]).max() > 1.0  # far from the truth
    # the error field keeps following the true temperature
    for axis in ("X", "Z"):
        np.testing.assert_array_equal(
            base.measure_errors_array(t, axis, 0.0, 1), faulty.measure_errors_array(t, axis, 0.0, 1)
        )


def test_runs_past_the_scenario_and_refuses_negative_time():
    vm = _vm()
    far = vm.true_temperatures(3 * 86400.0)  # the daemon may outlive the plan: machine off, room cycling
    assert math.isfinite(far["T37"])
    assert vm.true_temperatures(3600.0) == _vm().true_temperatures(3600.0)
    with pytest.raises(ValidationError):
        vm.temperatures(-1.0)
    with pytest.raises(ValidationError):
        vm.measure_error(0.0, "Q", 0.0, 1)
    with pytest.raises(ValidationError):
        vm.measure_error(0.0, "X", 0.0, 0)


def test_concurrent_readers_agree():
    import threading

    lag = HiddenEffect(kind="thermal_lag", axis="Z", term="dz", channels=["T34"], params={"tau_s": 900})
    vm = _vm(seed=2, hidden=[lag])
    ref = _vm(seed=2, hidden=[lag])
    times = [10 * 3600.0 + 97 * k for k in range(40)]  # beyond the plan: the grid is extended meanwhile
    out: dict[float, dict] = {}

    def read(t: float) -> None:
        out[t] = vm.measure_error(t, "Z", -100.0, -1)

    threads = [threading.Thread(target=read, args=(t,)) for t in times]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert all(out[t] == ref.measure_error(t, "Z", -100.0, -1) for t in times)
