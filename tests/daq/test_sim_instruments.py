"""End to end on the simulated backends: world -> loopback servers -> pyvisa / pyserial -> drivers."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from driftlab.daq.laser import LaserInterferometer, SettleOptions, air_refractive_index, fringes_to_value
from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.probe import LobingMap, SpindleBarMeter, TouchProbe
from driftlab.daq.protocols import FLAG_BEAM_BREAK, FLAG_OPEN, FLAG_REFERENCE_LOST
from driftlab.daq.proximity import ADCard, ProximitySensor, ReferenceSurfaceMeter, RollPair, a_axis_array
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.sim.instruments import (
    Clock,
    FixedStage,
    ManualClock,
    SimADCard,
    SimController,
    SimLaser,
    SimSphere,
    SimThermocoupleCard,
    WallClock,
    World,
    WorldStage,
    reference_surface_source,
    roll_pair_source,
    serial_url,
    spindle_bar_source,
    visa_address,
)
from driftlab.daq.thermocouple import ThermocoupleCard
from driftlab.daq.transport import LineChannel, SerialPort, VisaPort
from driftlab.errors import InstrumentError
from driftlab.testing.tinyworld import TinyWorld

FAST = RetryPolicy(attempts=3, base_delay_s=0.0)


@pytest.fixture(autouse=True)
def no_leaked_server_threads():
    yield
    alive = [t.name for t in threading.enumerate() if t.name.startswith("sim-")]
    assert not alive, f"simulated servers left running: {alive}"


@pytest.fixture(scope="module")
def rm():
    pyvisa = pytest.importorskip("pyvisa")
    manager = pyvisa.ResourceManager("@py")
    yield manager
    manager.close()


@pytest.fixture
def clock():
    return ManualClock()


@pytest.fixture
def world():
    return TinyWorld(channels=6, open_channels={"T3": 100.0})


def _visa_channel(rm, server, timeout_s=2.0):
    return LineChannel(VisaPort.open(visa_address(server), timeout_s, resource_manager=rm), server.name, FAST)


def _serial_channel(server, timeout_s=2.0):
    return LineChannel(SerialPort.open(serial_url(server), timeout_s), server.name, FAST)


def test_tiny_world_and_manual_clock_satisfy_protocols(world, clock):
    assert isinstance(world, World) and isinstance(clock, Clock)
    clock.sleep(5.0)
    clock.advance_to(3.0)
    assert clock.now() == 5.0


@pytest.mark.parametrize("transport", ["visa", "serial"])
def test_thermocouple_card_end_to_end(rm, world, clock, transport):
    cmap = {k: f"T{k + 1}" for k in range(6)}
    with SimThermocoupleCard(world, clock, cmap, cold_junction_c=23.0) as sim:
        ch = _visa_channel(rm, sim) if transport == "visa" else _serial_channel(sim)
        card = ThermocoupleCard(ch, cmap, clock=clock.now)
        try:
            clock.advance_to(50.0)
            scan = card.scan()
            truth = world.true_temperatures(50.0)
            assert not scan.flags
            for name in cmap.values():
                assert scan.values[name] == pytest.approx(truth[name], abs=1e-5)
            clock.advance_to(150.0)  # T3 breaks at t = 100 s
            scan = card.scan()
            assert scan.flags == {"T3": FLAG_OPEN} and math.isnan(scan.values["T3"])
            assert scan.values["T4"] == pytest.approx(world.true_temperatures(150.0)["T4"], abs=1e-5)
        finally:
            card._io.close()


def test_garbled_reply_over_visa_is_retried(rm, world, clock):
    with SimThermocoupleCard(world, clock, {0: "T1"}) as sim:
        ch = _visa_channel(rm, sim)
        try:
            card = ThermocoupleCard(ch, {0: "T1"}, clock=clock.now)
            sim.inject("garble")
            assert card.scan().values["T1"] == pytest.approx(20.0, abs=1e-5)
            assert sim.received.count("CJC?") == 2  # the garbled reply was asked again
        finally:
            ch.close()


def test_timeouts_over_visa_raise_one_line_error(rm, world, clock):
    with SimThermocoupleCard(world, clock, {0: "T1"}) as sim:
        ch = _visa_channel(rm, sim, timeout_s=0.15)
        try:
            card = ThermocoupleCard(ch, {0: "T1"}, clock=clock.now)
            sim.inject("timeout", "timeout", "timeout")
            with pytest.raises(InstrumentError) as info:
                card.scan()
            assert "timeout" in str(info.value) and "\n" not in str(info.value)
            assert card.scan().values["T1"] == pytest.approx(20.0, abs=1e-5)  # link recovers
        finally:
            ch.close()


def test_laser_end_to_end_over_pyvisa(rm, world, clock):
    stage = FixedStage()
    clock.advance_to(900.0)
    with SimLaser(world, clock, stage) as sim:
        ch = _visa_channel(rm, sim)
        laser = LaserInterferometer(ch, settle=SettleOptions(sleep=clock.sleep))
        try:
            assert laser.identify().startswith("DRIFTLAB,SIM-LASER")
            laser.configure("X", "dx")
            stage.move("X", 0.0, 1)
            laser.reference(0.0)
            ref = world.measure_error(clock.now(), "X", 0.0, 1)
            for pos, direction in [(250.0, 1), (250.0, -1), (480.0, -1)]:
                stage.move("X", pos, direction)
                s = laser.measure_error("X", "dx", pos, direction)
                # the ten readings follow the settle wait: the world is read at the clock's time
                expected = world.measure_error(clock.now(), "X", pos, direction)["dx"] - ref["dx"]
                assert s.flag is None and s.value == pytest.approx(expected, abs=5e-8)
            for term in ("dy", "gamma"):
                laser.configure("X", term)
                stage.move("X", 0.0, 1)
                laser.reference(0.0)
                ref = world.measure_error(clock.now(), "X", 0.0, 1)
                stage.move("X", 300.0, 1)
                s = laser.measure_error("X", term, 300.0, 1)
                truth = world.measure_error(clock.now(), "X", 300.0, 1)[term] - ref[term]
                assert s.value == pytest.approx(truth, abs=5e-8 if term == "dy" else 5e-10)
            # a beam break: flagged, reference lost; REF refused until the optics are realigned
            sim.break_beam("weak")
            assert laser.measure_error("X", "gamma", 300.0, 1).flag == FLAG_BEAM_BREAK
            assert laser.read().flag == FLAG_REFERENCE_LOST
            sim.break_beam("broken")
            with pytest.raises(InstrumentError):
                laser.reference(300.0)
            sim.restore_beam()
            laser.reference(300.0)
            assert laser.read().value == pytest.approx(0.0, abs=1e-9)
        finally:
            ch.close()


def test_proximity_arrays_end_to_end(rm, world, clock):
    stage = FixedStage()
    stage.move("A", 5.0, 1)
    clock.advance_to(1200.0)
    array = a_axis_array(150.0)
    with SimADCard(clock) as sim:
        sim.wire([0, 1, 2, 3, 4], reference_surface_source(world, stage, "A", array))
        sim.wire([6, 7], roll_pair_source(world, stage, "X", "dz", "alpha", 200.0, ((5.0, 8.6), (5.1, 8.4))))
        ch = _visa_channel(rm, sim)
        try:
            card = ADCard(ch)
            out = ReferenceSurfaceMeter(card, [0, 1, 2, 3, 4], array).read()
            err = world.measure_error(1200.0, "A", 5.0, 1)
            for term in array.terms():
                assert out[term].value == pytest.approx(err[term], abs=3e-7 if term[0] == "d" else 3e-9)
            roll = RollPair(ProximitySensor(card, 6, 5.0, 8.6), ProximitySensor(card, 7, 5.1, 8.4), 200.0)
            assert roll.read_angle().value == pytest.approx(world.measure_error(1200.0, "X", 0.0, 1)["alpha"], abs=2e-9)
        finally:
            ch.close()


def test_controller_streams_executes_and_reports_positions(world, clock):
    program = [f"G1 X{10 * k} Y{-k} F600" for k in range(1, 31)] + ["G0 Z50", "G1 A5 B-10 F1200"]
    with SimController(world, clock, capacity=8) as sim:
        link = SerialMachineLink(_serial_channel(sim), poll_s=0.5, sleep=clock.sleep)
        try:
            assert link.buffer_free() == 8
            sim.inject("garble", on="STAT?")
            sim.inject("timeout", on="BLK 3 ")  # the block is queued but its ACK is lost: resent, not doubled
            report = link.send_program(program, low_water=2, high_water=6)
            assert report.blocks_sent == len(program)
            assert sim.executed == program  # every block exactly once, in order
            assert sum(r.startswith("BLK 3 ") for r in sim.received) == 2  # the lost ACK was resent
            assert sim.max_queued <= 6
            pos = link.position()
            assert pos == {"X": 300.0, "Y": -30.0, "Z": 50.0, "A": 5.0, "B": -10.0}
            # 30 moves of sqrt(100 + 1) mm at 600 mm/min, a 50 mm rapid, a 11.18 deg rotary move
            expected_s = 30 * 60 * math.sqrt(101) / 600 + 60 * 50 / 10000 + 60 * math.hypot(5, 10) / 1200
            assert clock.now() == pytest.approx(expected_s, abs=1.0)
        finally:
            link.close()


def test_laser_waits_for_the_moving_axis(rm, world, clock):
    with SimController(world, clock) as ctl, SimLaser(world, clock, ctl) as sim:
        link = SerialMachineLink(_serial_channel(ctl), poll_s=0.5, sleep=clock.sleep)
        laser = LaserInterferometer(_visa_channel(rm, sim), settle=SettleOptions(sleep=clock.sleep, settle_poll_s=0.5))
        try:
            laser.configure("X", "dx")
            laser.reference(0.0)
            link.send_program(["G1 X200 F1200"], wait=False)  # 10 s of motion
            sample = laser.measure_error("X", "dx", 200.0, 1)
            assert clock.now() >= 10.0  # the reading waited for the axis to stop
            t = clock.now()
            expected = world.measure_error(t, "X", 200.0, 1)["dx"] - world.measure_error(0.0, "X", 0.0, 1)["dx"]
            assert sample.value == pytest.approx(expected, abs=1e-6)
        finally:
            link.close()
            laser._io.close()


def test_probe_through_the_controller_finds_displaced_spheres(world, clock):
    clock.advance_to(3600.0)
    spheres = {"S1": SimSphere((400.0, 50.0, 20.0), 12.7), "S2": SimSphere((-50.0, 300.0, 25.0), 12.7)}
    with SimController(world, clock, spheres=spheres, stylus_radius_mm=1.5) as sim:
        probe = TouchProbe(_serial_channel(sim), stylus_radius_mm=1.5)
        try:
            for name, s in spheres.items():
                m = probe.probe_sphere(name, s.centre, s.radius_mm)
                offset = sim.sphere_offset(3600.0, np.array(s.centre))
                assert np.linalg.norm(offset) > 1e-3  # the world really moved it
                assert m.centre == pytest.approx(np.array(s.centre) + offset, abs=1e-5)
                assert m.radius_mm == pytest.approx(12.7, abs=1e-5)
        finally:
            probe._io.close()


def test_lobing_calibration_improves_the_sphere_centre(world, clock):
    lobing = LobingMap(0.003, (3,), (0.004,), (0.001,))
    spheres = {"cal": SimSphere((0.0, 0.0, 0.0), 10.0), "S1": SimSphere((200.0, 0.0, 0.0), 10.0)}
    no_drift = lambda t, c: np.zeros(3)  # noqa: E731
    with SimController(world, clock, spheres=spheres, lobing=lobing, sphere_offset=no_drift) as sim:
        probe = TouchProbe(_serial_channel(sim))
        try:
            raw = probe.probe_sphere("S1", (200.0, 0.0, 0.0), 10.0)
            fitted = probe.calibrate_lobing(0.0, (0.0, 0.0), 10.0)
            assert fitted.cos[0] == pytest.approx(0.004, abs=1e-6)
            comp = probe.probe_sphere("S1", (200.0, 0.0, 0.0), 10.0)
            raw_err = np.linalg.norm(raw.centre - [200.0, 0.0, 0.0])
            comp_err = np.linalg.norm(comp.centre - [200.0, 0.0, 0.0])
            assert raw_err > 1e-3 and comp_err < 1e-5
            assert comp.radius_mm == pytest.approx(10.0, abs=1e-5)
        finally:
            probe._io.close()


def test_drivers_open_by_address(world, clock):
    with SimThermocoupleCard(world, clock, {0: "T1", 1: "T2"}) as tc, SimLaser(world, clock, FixedStage()) as las:
        card = ThermocoupleCard.open(visa_address(tc), {0: "T1", 1: "T2"}, timeout_s=0.5)
        laser = LaserInterferometer.open(visa_address(las), timeout_s=0.5)
        also = ThermocoupleCard.open(serial_url(tc), {1: "T2"}, timeout_s=0.5)
        try:
            assert card.scan().values["T2"] == pytest.approx(20.25, abs=1e-5)
            assert also.scan().values["T2"] == pytest.approx(20.25, abs=1e-5)
            assert laser.identify() == "DRIFTLAB,SIM-LASER,0,1.0"
        finally:
            card.close()
            also.close()
            laser.close()


def test_open_failure_is_one_line_instrument_error():
    with pytest.raises(InstrumentError, match="cannot open serial port"):
        ThermocoupleCard.open("socket://127.0.0.1:1", {0: "T1"}, timeout_s=0.2)


def test_spindle_bar_array_follows_the_world(rm, world, clock):
    world.positions["Z"] = -150.0
    stage = WorldStage(world)
    assert stage.where("Z", 10.0) == (-150.0, 1)
    clock.advance_to(2000.0)
    cals = ((5.0, 8.5), (5.1, 8.6), (4.9, 8.4), (5.2, 8.7))
    with SimADCard(clock) as sim:
        sim.wire([8, 9, 10, 11], spindle_bar_source(world, stage, 120.0, cals))
        ch = _visa_channel(rm, sim)
        try:
            card = ADCard(ch)
            meter = SpindleBarMeter([ProximitySensor(card, 8 + i, c, k) for i, (c, k) in enumerate(cals)], 120.0)
            out = meter.read()
            err = world.measure_error(2000.0, "Z", -150.0, 1)
            assert abs(err["alpha"]) > 1e-6 and abs(err["beta"]) > 1e-7
            for term in ("alpha", "beta"):
                assert out[term].value == pytest.approx(err[term], abs=2e-9)
            for term in ("dx", "dy"):
                assert out[term].value == pytest.approx(err[term], abs=2e-7)
        finally:
            ch.close()


def test_laser_datum_survives_a_pc_restart(rm, world, clock):
    stage = FixedStage()
    clock.advance_to(600.0)
    with SimLaser(world, clock, stage) as sim:
        ch = _visa_channel(rm, sim)
        try:
            laser = LaserInterferometer(ch, settle=SettleOptions(sleep=clock.sleep))
            laser.configure("Y", "dy")
            assert sim.datum() is None
            laser.reference(0.0)
            saved = sim.datum()
            assert saved == {"t_s": 600.0, "position": 0.0, "error": world.measure_error(600.0, "Y", 0.0, 1)["dy"]}
            # a new PC session re-sends the set-up, which clears the head; the saved datum is put back
            again = LaserInterferometer(ch, settle=SettleOptions(sleep=clock.sleep))
            again.configure("Y", "dy")
            sim.restore_datum(**saved)
            stage.move("Y", 100.0, 1)
            raw = again._io.query("MEAS?", lambda s: float(s.split(",")[0]))
            n_air = float(air_refractive_index(20.0, 101325.0, 50.0))
            expected = 100.0 + world.measure_error(clock.now(), "Y", 100.0, 1)["dy"] - saved["error"]
            assert float(fringes_to_value("LIN", raw, n_air)) == pytest.approx(expected, abs=1e-7)
            assert sim.datum() == saved
        finally:
            ch.close()


def test_wall_clock_runs_accelerated():
    clock = WallClock(acceleration=1e4, t0_s=100.0)
    clock.sleep(2.0)  # 0.2 ms of real time
    assert clock.now() >= 102.0


def test_refused_visa_connection_is_one_line_instrument_error(rm):
    laser = LaserInterferometer(LineChannel(VisaPort.open("TCPIP0::127.0.0.1::1::SOCKET", 0.2, resource_manager=rm),
                                            "laser", FAST))  # fmt: skip
    try:
        with pytest.raises(InstrumentError, match="laser \\*IDN\\?: VISA write failed"):
            laser.identify()
    finally:
        laser.close()


def test_controller_rejects_bad_blocks_without_changing_modal_state(world, clock):
    with SimController(world, clock) as sim:
        assert sim.handle("BLK 1 G1 X10 F-5").startswith("ERR SYNTAX")
        assert sim.handle("BLK 1 G1 X10 Q3").startswith("ERR SYNTAX")
        assert sim.handle("BLK 3 G1 X10") == "ERR SEQ 0"
        assert sim.handle("BLK 1 G1 X10") == "ACK 1"
        assert sim.handle("BLK 1 G1 X10") == "ACK 1"  # duplicate: acknowledged, not queued
        assert sim.handle("STAT?") == "STAT 15 16 0"
        clock.sleep(0.6)  # 10 mm at the default 1000 mm/min
        assert sim.handle("STAT?") == "STAT 16 16 1"
        assert sim.handle("POS?") == "POS X10.0000 Y0.0000 Z0.0000 A0.0000 B0.0000"
        assert sim.handle("PRB 0,0,0,1,0,0,5") == "MISS"


def test_laser_restore_reference_is_the_public_datum_api(world, clock):
    sim = SimLaser(world, clock, FixedStage())
    assert sim.datum() is None
    sim.restore_reference(12.0, -50.0, 0.0015)
    assert sim.datum() == {"t_s": 12.0, "position": -50.0, "error": 0.0015}
