"""VirtualMachine -> simulated servers -> pyvisa / pyserial -> drivers: readings equal the VM's values."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import pyvisa

from driftlab.daq.laser import LaserInterferometer, SettleOptions
from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.probe import TouchProbe
from driftlab.daq.protocols import FLAG_OPEN
from driftlab.daq.proximity import ADCard, ReferenceSurfaceMeter, b_axis_array
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.sim import machine
from driftlab.daq.sim import scenario as scenario_mod
from driftlab.daq.sim.instruments import (
    FixedStage,
    ManualClock,
    SimADCard,
    SimController,
    SimLaser,
    SimSphere,
    SimThermocoupleCard,
    World,
    reference_surface_source,
    serial_url,
    visa_address,
    world_sphere_offset,
)
from driftlab.daq.thermocouple import ThermocoupleCard
from driftlab.daq.transport import LineChannel, SerialPort, VisaPort

FAST = RetryPolicy(attempts=3, base_delay_s=0.0)
CHANNELS = {k: f"T{k + 1}" for k in range(50)}


@pytest.fixture(scope="module")
def vm():
    scenario = scenario_mod.scenario_from_dict(
        {"name": "daq-e2e", "seed": 11, "hours": 4,
         "hidden": [{"kind": "sensor_fault", "channels": ["T34"], "params": {"start_s": 7200, "mode": "open"}}]}
    )  # fmt: skip
    return machine.VirtualMachine(scenario)


@pytest.fixture(scope="module")
def rm():
    manager = pyvisa.ResourceManager("@py")
    yield manager
    manager.close()


@pytest.fixture(autouse=True)
def no_leaked_server_threads():
    yield
    assert not [t.name for t in threading.enumerate() if t.name.startswith("sim-")]


def _visa(rm, server):
    return LineChannel(VisaPort.open(visa_address(server), 2.0, resource_manager=rm), server.name, FAST)


def test_virtual_machine_is_a_world(vm):
    assert isinstance(vm, World)


def test_thermocouples_read_the_vm(rm, vm):
    clock = ManualClock(1800.0)
    with SimThermocoupleCard(vm, clock, CHANNELS, cold_junction_c=22.5) as sim:
        card = ThermocoupleCard(_visa(rm, sim), CHANNELS, clock=clock.now)
        try:
            scan = card.scan()
            expected = vm.temperatures(1800.0)
            assert not scan.flags
            assert [scan.values[c] for c in CHANNELS.values()] == pytest.approx(
                [expected[c] for c in CHANNELS.values()], abs=1e-5
            )
            clock.advance_to(9000.0)  # T34's lead opened at 2 h
            scan = card.scan()
            assert scan.flags == {"T34": FLAG_OPEN} and math.isnan(scan.values["T34"])
            assert scan.values["T37"] == pytest.approx(vm.temperatures(9000.0)["T37"], abs=1e-5)
        finally:
            card.close()


@pytest.mark.parametrize(("axis", "term"), [("Z", "dz"), ("Z", "alpha"), ("X", "dy"), ("B", "beta")])
def test_laser_reads_the_vm_errors(rm, vm, axis, term):
    clock = ManualClock(3000.0)
    stage = FixedStage()
    with SimLaser(vm, clock, stage) as sim:
        settle = SettleOptions(sleep=clock.sleep, settle_tolerance_mm=0.005, settle_tolerance_rad=5e-6)
        laser = LaserInterferometer(_visa(rm, sim), settle=settle)
        try:
            laser.configure(axis, term)
            stage.move(axis, 0.0, 1)
            laser.reference(0.0)
            ref = vm.measure_error(clock.now(), axis, 0.0, 1)[term]
            for position, direction in [(-200.0 if axis != "B" else 30.0, 1), (-200.0 if axis != "B" else 30.0, -1)]:
                stage.move(axis, position, direction)
                sample = laser.measure_error(axis, term, position, direction)
                expected = vm.measure_error(clock.now(), axis, position, direction)[term] - ref
                assert sample.flag is None
                assert sample.value == pytest.approx(expected, abs=1e-7 if term.startswith("d") else 1e-9)
        finally:
            laser.close()


def test_proximity_array_reads_the_vm(rm, vm):
    clock = ManualClock(5400.0)
    stage = FixedStage()
    stage.move("B", 45.0, -1)
    array = b_axis_array(150.0)
    with SimADCard(clock) as sim:
        sim.wire([0, 1, 2, 3, 4], reference_surface_source(vm, stage, "B", array))
        card = ADCard(_visa(rm, sim))
        try:
            out = ReferenceSurfaceMeter(card, [0, 1, 2, 3, 4], array).read()
            err = vm.measure_error(5400.0, "B", 45.0, -1)
            for term in array.terms():
                assert out[term].value == pytest.approx(err[term], abs=3e-7 if term[0] == "d" else 3e-9)
        finally:
            card.close()


def test_probe_and_machine_link_against_the_vm(vm):
    clock = ManualClock(6000.0)
    spheres = {"S1": SimSphere((300.0, 100.0, -50.0), 12.7), "S2": SimSphere((-300.0, 100.0, -50.0), 12.7)}
    with SimController(vm, clock, spheres=spheres) as sim:
        link = SerialMachineLink(LineChannel(SerialPort.open(serial_url(sim), 2.0), "controller", FAST),
                                 poll_s=0.5, sleep=clock.sleep)  # fmt: skip
        probe = TouchProbe.on_link(link)
        try:
            link.send_program(["G0 Z100", "G1 X300 Y100 F3000", "G1 Z-20 F1000"], low_water=1)
            assert link.position() == {"X": 300.0, "Y": 100.0, "Z": -20.0, "A": 0.0, "B": 0.0}
            link.send_program(["G1 Z0 F100"], wait=False)  # 12 s of motion: the probe waits for it
            t0 = clock.now()
            offset = world_sphere_offset(vm)
            for name, s in spheres.items():
                m = probe.probe_sphere(name, s.centre, s.radius_mm)
                expected = np.array(s.centre) + offset(clock.now(), np.array(s.centre))
                assert m.centre == pytest.approx(expected, abs=1e-5)
            assert clock.now() >= t0 + 12.0
        finally:
            link.close()


def test_temperatures_block_is_bit_identical_to_per_time_calls(vm):
    """A block of instants, in any split, equals temperatures(t) of each instant bit for bit (faults too)."""
    times = np.concatenate([np.arange(120) * 0.1, 7190.0 + np.arange(150) * 0.1, [9000.25, 13000.0]])
    block = vm.temperatures_block(times)
    assert block.shape == (len(times), 50)
    for i, t in enumerate(times):
        assert np.array_equal(block[i], np.array(list(vm.temperatures(float(t)).values())), equal_nan=True)
    assert np.isnan(block[times >= 7200, 33]).all() and not np.isnan(block[times < 7200, 33]).any()
    for n in (1, 3, 64):
        parts = [vm.temperatures_block(times[i : i + n]) for i in range(0, len(times), n)]
        assert np.array_equal(np.concatenate(parts), block, equal_nan=True)
    cols = vm.temperatures_block(times[:5], ["T3", "nope", "T1"])
    assert np.array_equal(cols[:, 0], block[:5, 2]) and np.isnan(cols[:, 1]).all()
    with pytest.raises(Exception, match=">= 0 s"):
        vm.temperatures_block(np.array([1.0, -2.0]))


@pytest.mark.parametrize("transport", ["visa", "serial"])
def test_buffered_block_scans_read_the_vm(rm, vm, transport):
    """PACE + FETC? through the real transports: each scan of a block is the VM's reading at k * interval."""
    clock = ManualClock()
    with SimThermocoupleCard(vm, clock, CHANNELS, cold_junction_c=22.5) as sim:
        ch = (
            _visa(rm, sim)
            if transport == "visa"
            else LineChannel(SerialPort.open(f"socket://127.0.0.1:{sim.port}", 2.0), sim.name, FAST)
        )
        card = ThermocoupleCard(ch, CHANNELS, clock=clock.now)
        try:
            card.pace(0.1)
            clock.advance_to(71995 * 0.1)
            block = card.scan_block(71900, 96)  # across the fault of T34 at 7200 s
            truth = vm.temperatures_block(block.t_s)
            assert block.t_s.tolist() == [k * 0.1 for k in range(71900, 71996)]
            ok = ~np.isnan(truth)
            assert np.array_equal(block.open, ~ok)
            assert np.abs(block.values[ok] - truth[ok]).max() < 1e-6  # the inverse NIST function, not the transfer
            single = card.scan()  # the single-scan path still answers at the clock's instant
            assert single.values["T1"] == pytest.approx(truth[-1, 0], abs=1e-5)
            with pytest.raises(Exception, match="NOTREADY"):
                card.scan_block(71990, 10)
        finally:
            ch.close()
