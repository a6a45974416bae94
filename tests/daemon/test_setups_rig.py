"""The rig mounts each stage's setup; simulated instruments answer only for what is mounted (issue 11)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from driftlab.campaigns.clock import SimClock
from driftlab.campaigns.plan import parse_plan
from driftlab.daemon.simrig import build_sim_rig, plan_scenario, scenario_meta
from driftlab.daq.protocols import FLAG_BEAM_BREAK
from driftlab.daq.sim.machine import VirtualMachine
from driftlab.daq.sim.scenario import load_scenario
from driftlab.errors import InstrumentError

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "examples" / "scenarios" / "clean.yaml"


def _plan(setups: dict, stages: list[dict]):
    return parse_plan(
        {
            "format": "driftlab-plan/1",
            "name": "rig",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 60,
            "setups": setups,
            "stages": stages,
        },
        "rig.yaml",
    )


def _stage(name, axis, setup, positions, **kw):
    return {
        "name": name,
        "axis": axis,
        "setup": setup,
        "duration_s": 1800,
        "sweep": {"positions": positions, "interval_s": 900, "point_s": 6},
        **kw,
    }


@pytest.fixture
def rig_and_world():
    plan = _plan(
        {
            "x-roll": {"instrument": "proximity", "fixture": "reference_edge", "axis": "X", "terms": ["alpha"]},
            "b-run": {
                "instrument": "proximity",
                "fixture": "cylinder",
                "axis": "B",
                "terms": ["dx", "dy", "dz", "alpha", "gamma"],
            },
            "b-pos": {"instrument": "laser", "optics": "angular", "axis": "B", "terms": ["beta"]},
            "x-str": {"instrument": "laser", "optics": "straightness", "axis": "X", "terms": ["dz"]},
        },
        [
            _stage("roll", "X", "x-roll", [0, 127]),
            _stage("run", "B", "b-run", [-20, 20]),
            _stage("pos", "B", "b-pos", [-10, 10]),
            _stage("str", "X", "x-str", [0, 254]),
        ],
    )
    scenario = load_scenario(SCENARIO)
    world = VirtualMachine(plan_scenario(plan, scenario))
    clock = SimClock(speed=math.inf, start_s=0.0)
    rig = build_sim_rig(plan, scenario, clock, list(scenario_meta(scenario)["channels"]), world=world)
    try:
        yield plan, rig, world, clock
    finally:
        rig.close()


def _measure(plan, rig, clock, point):
    clock.wait_until(point.move_s)
    rig.move_to(point)
    clock.wait_until(point.t_s)
    return rig.measure_point(point)


def test_proximity_setups_read_the_machine_through_the_ad_card(rig_and_world):
    plan, rig, world, clock = rig_and_world
    pts = plan.sweep_points()
    roll = _measure(plan, rig, clock, pts[1])  # X at 0, reference edge: the roll alpha
    assert set(roll) == {"alpha"}
    true = world.measure_error(pts[1].t_s, "X", pts[1].position, pts[1].direction)["alpha"]
    assert roll["alpha"].value == pytest.approx(true, abs=2e-7)  # A/D quantisation of the two gaps
    b = next(p for p in pts if p.setup == "b-run")
    got = _measure(plan, rig, clock, b)
    assert set(got) == {"dx", "dy", "dz", "alpha", "gamma"}
    true = world.measure_error(b.t_s, "B", b.position, b.direction)
    for term in got:
        assert got[term].value == pytest.approx(true[term], abs=5e-4 if term.startswith("d") else 5e-6), term


def test_the_laser_answers_only_for_the_mounted_optics_and_within_their_range(rig_and_world):
    plan, rig, world, clock = rig_and_world
    pts = plan.sweep_points()
    b = next(p for p in pts if p.setup == "b-pos")
    assert set(_measure(plan, rig, clock, b)) == {"beta"}
    head = rig.servers["laser"]
    # asking for angle optics while linear optics are mounted: the second beam sees no reflector
    rig.laser.configure("B", "beta")
    head.mount("LIN", "X", "dx")
    rig.laser.reference(0.0)
    assert rig.laser.read().flag == FLAG_BEAM_BREAK
    # beyond the +-10 deg of the angular optics (fig. 5.9) the beam is lost
    head.mount("ANG", "B", "beta", 10.0)
    rig.servers["controller"].pos["B"] = 5.0
    rig.laser.reference(5.0)  # clears the head's latched measurement error first
    assert rig.laser.read().ok
    rig.servers["controller"].pos["B"] = 25.0
    assert rig.laser.read().flag == FLAG_BEAM_BREAK
    rig.servers["controller"].pos["B"] = 5.0
    with pytest.raises(InstrumentError, match="resetAxes"):
        rig.laser.command("com.attocube.sen.system.resetAxes")  # the error stays latched until resetError
    rig.laser.reference(5.0)
    assert rig.laser.read().ok


def test_a_fixture_taken_off_reads_out_of_range(rig_and_world):
    plan, rig, world, clock = rig_and_world
    ad = rig.servers["ad-card"]
    rig.mount_setup("x-roll")
    assert np.all(ad.voltages(0.0)[:2] > 1.0)
    rig.mount_setup("x-str")  # the reference-edge sensors come off with the proximity setup
    assert np.all(ad.voltages(0.0) == 0.0)


def test_the_daemon_refuses_a_probe_setup_before_it_starts(tmp_path):
    from driftlab.daemon.run import run_daemon
    from driftlab.errors import ValidationError

    plan = _plan(
        {"sq": {"instrument": "probe", "fixture": "reference_square", "axis": "X", "terms": ["gamma"]}},
        [_stage("square", "X", "sq", [0, 127])],
    )
    db = tmp_path / "s.sqlite"
    with pytest.raises(ValidationError, match=r"stages\[0\] \(square\): setup 'sq' is a probe setup"):
        run_daemon(plan, db_url=f"sqlite:///{db}", scenario_path=SCENARIO, speed=math.inf)
    assert not db.exists()  # nothing was opened, nothing stored
