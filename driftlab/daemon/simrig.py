"""The simulated rig: the real drivers talking to simulated instruments that read the virtual machine.

Also what the plan asks of the virtual machine: its stages as a scenario, the travel it allows and
the campaign.json fields it adds (machine, model channels, noise).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from driftlab.campaigns.plan import Cursor, Plan
from driftlab.daemon.rig import InstrumentRig


class MemoWorld:
    """The virtual machine behind a small cache: it is a pure function of its arguments, so asking twice is waste.

    A sweep point asks the world for the same error and room air a dozen times at one instant (the
    laser's settle polls and ten averaged readings); the cache answers the repeats exactly.
    """

    def __init__(self, world: Any, size: int = 64) -> None:
        from functools import lru_cache

        self.world = world
        self._temps = lru_cache(maxsize=size)(world.temperatures)
        self._errors = lru_cache(maxsize=size)(world.measure_error)

    def temperatures(self, t_s: float) -> dict[str, float]:
        """Return the world's thermocouple readings at t_s (a fresh dict each call)."""
        return dict(self._temps(float(t_s)))

    def measure_error(self, t_s: float, axis: str, position: float, direction: int) -> dict[str, float]:
        """Return the world's measured error terms at (t_s, axis, position, direction)."""
        return dict(self._errors(float(t_s), axis, float(position), int(direction)))

    def state(self, t_s: float) -> Any:
        """Return the world's machine state at t_s."""
        return self.world.state(t_s)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.world, name)


def _no_wait(_dt: float) -> None:
    """Do not wait: on a simulated clock time only moves between steps."""


def build_sim_rig(
    plan: Plan,
    scenario: Any,
    clock: Any,
    channels: list[str],
    datum: Mapping[str, Any] | None = None,
    world: Any | None = None,
    cursor: Cursor = Cursor(),
    laser: str = "attocube-ids3010",
) -> InstrumentRig:
    """Return a rig whose drivers talk to simulated instruments reading the virtual machine at `clock`.

    The instruments are the ones a shop owns, answering their own command sets: a Keysight 34970A
    scanning the thermocouples (SCPI), LinuxCNC through linuxcncrsh, a second 34970A's DC-volt
    channels for the proximity sensors, an attocube IDS3010 laser interferometer (JSON-RPC).

    On a resume the simulated hardware is put back as the real hardware would have stayed while the
    PC restarted: each axis where its last sweep point left it, the laser head on its datum.

    ``laser="thesis-laser"`` puts the thesis' legacy HP-IB processor (driftlab's own protocol, with
    bursts) in the IDS3010's place: the benchmark's same-run baseline of the laser path.
    """
    import pyvisa

    from driftlab.daq.attocube_ids import AttocubeIDS, ids_url
    from driftlab.daq.keysight34970a import Keysight34970A, Keysight34970AVolts
    from driftlab.daq.laser import LaserInterferometer
    from driftlab.daq.linuxcnc import LinuxCNCLink
    from driftlab.daq.retry import RetryPolicy
    from driftlab.daq.sim.attocube_ids import SimIDS3010, ids_resource
    from driftlab.daq.sim.instruments import SimLaser, serial_url, visa_address
    from driftlab.daq.sim.keysight34970a import Sim34970A, sim_channel_map
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.daq.transport import LineChannel, SerialPort, VisaPort

    if laser not in ("attocube-ids3010", "thesis-laser"):
        raise ValueError(f"simulated laser {laser!r}: attocube-ids3010 or thesis-laser")
    if world is None:
        from driftlab.daq.sim.machine import VirtualMachine

        world = MemoWorld(VirtualMachine(plan_scenario(plan, scenario)))
    card_map = sim_channel_map(channels)  # 34901A channels 101.., 201.., 301.. -> the plan's names
    card = Sim34970A(world, clock, card_map).start()
    ctrl = SimLinuxCNC(world, clock)
    for axis, (pos, direction) in axis_positions(plan, cursor).items():
        ctrl.pos[axis], ctrl.direction[axis] = pos, direction
    ctrl.start()
    head: Any = (
        SimIDS3010(world, clock, ctrl) if laser == "attocube-ids3010" else SimLaser(world, clock, ctrl)
    ).start()
    ad = Sim34970A(world, clock).start()  # a second mainframe: its DC-volt channels read the proximity sensors
    closers: list[Callable[[], None]] = [card.close, ctrl.close, head.close, ad.close]
    try:
        rm = pyvisa.ResourceManager("@py")
        closers.append(rm.close)
        policy = RetryPolicy(attempts=3, base_delay_s=0.0)
        card_io = LineChannel(VisaPort.open(visa_address(card), resource_manager=rm), "34970A", policy, sleep=_no_wait)
        closers.append(card_io.close)
        scanner = Keysight34970A(card_io, card_map, tc_type="E", reference_junction="INT", clock=clock.now)
        scanner.identify()
        scanner.configure()
        meter: Any
        if isinstance(head, SimIDS3010):
            head_url = ids_url(ids_resource(head))
            meter = AttocubeIDS(lambda: SerialPort.open(head_url), sleep=_no_wait, max_settle_polls=20)
            closers.append(meter.close)
            meter.session()
        else:
            laser_io = LineChannel(
                VisaPort.open(visa_address(head), resource_manager=rm), "laser", policy, sleep=_no_wait
            )
            closers.append(laser_io.close)
            meter = LaserInterferometer(laser_io, sleep=_no_wait, max_settle_polls=20, burst=True)
        url = serial_url(ctrl)
        link = LinuxCNCLink(lambda: SerialPort.open(url), sleep=_no_wait, max_idle_polls=2)
        link.session()
        closers.append(link.close)
        ad_io = LineChannel(
            VisaPort.open(visa_address(ad), resource_manager=rm), "34970A volts", policy, sleep=_no_wait
        )
        closers.append(ad_io.close)
        adcard = Keysight34970AVolts(ad_io, AD_CHANNELS)
        adcard.identify()
        adcard.configure()
    except Exception:
        for c in reversed(closers):
            c()
        raise
    return InstrumentRig(
        plan,
        scanner,
        meter,
        link,
        clock=clock,
        datum=datum,
        laser_server=head,
        closers=closers,
        servers={"thermocouple": card, "laser": head, "controller": ctrl, "ad-card": ad},
        adcard=adcard,
        mount=sim_mounter(world, ctrl, head, ad),
    )


#: the proximity mainframe's DC-volt channels: A/D index i is channel AD_CHANNELS[i]
AD_CHANNELS = [101, 102, 103, 104, 105]


def sim_mounter(world: Any, stage: Any, head: Any, ad: Any) -> Callable[[Any], None]:
    """Return mount(setup): put the setup's optics on the simulated head or wire its fixture to the A/D card.

    The simulated instruments then answer only for what is mounted: the head for its optics' mode,
    axis and term within their range (fig. 5.9), the proximity sensors for the reference surface they
    face, reading the virtual machine's errors of the setup's axis at the controller's position.
    """
    from driftlab.daemon.rig import ROLL_CALIBRATION, ROLL_GAP, ROLL_SEPARATION_MM
    from driftlab.daq.laser import LASER_TERMS
    from driftlab.daq.proximity import a_axis_array, b_axis_array
    from driftlab.daq.sim.instruments import reference_surface_source, roll_pair_source
    from driftlab.errors import ValidationError

    def mount(setup: Any) -> None:
        """Mount one setup (None: take everything off)."""
        head.mount(None)
        ad.unwire()
        if setup is None:
            return
        if any(v != 0.0 for v in setup.pose.values()):
            raise ValidationError(
                f"setup on {setup.axis}: the virtual machine measures with the other axes at home (pose 0)"
            )
        if setup.instrument == "laser":
            term = setup.terms[0]
            head.mount(LASER_TERMS[setup.axis][term], setup.axis, term, setup.range_deg())
        elif setup.fixture == "reference_edge":
            roll = setup.terms[0]
            ad.wire(
                AD_CHANNELS[:2],
                roll_pair_source(
                    world, stage, setup.axis, ROLL_GAP[setup.axis], roll, ROLL_SEPARATION_MM, ROLL_CALIBRATION
                ),
            )
        else:
            array = a_axis_array() if setup.axis == "A" else b_axis_array()
            n = len(array.calibration.sensors)
            ad.wire(AD_CHANNELS[:n], reference_surface_source(world, stage, setup.axis, array))

    return mount


def axis_positions(plan: Plan, cursor: Cursor) -> dict[str, tuple[float, int]]:
    """Return where each swept axis was left (position, approach direction) before the cursor's next point."""
    out: dict[str, tuple[float, int]] = {}
    for p in plan.sweep_points()[: cursor.next_point]:
        out[p.axis] = (p.position, p.direction)
    return out


def scenario_stages(plan: Plan) -> list[dict[str, Any]]:
    """Return the plan's stages as virtual-machine scenario stages (the heat sources the world runs)."""
    from driftlab.errors import ValidationError

    out = []
    for stage, (start, end) in zip(plan.stages, plan.stage_bounds()):
        kinds = sorted(h.kind for h in stage.heat)
        if "motor_hold" in kinds:
            raise ValidationError(
                f"plan {plan.name}: stage {stage.name!r}: the virtual machine's scenarios have no "
                "motor_hold heat source; run this stage on the real machine"
            )
        axes = [h.axis for h in stage.heat if h.kind == "axis"]
        if len(axes) > 1:
            raise ValidationError(
                f"plan {plan.name}: stage {stage.name!r}: the virtual machine runs one oscillating axis at a time"
            )
        source = {(): "idle", ("spindle",): "spindle", ("axis",): "feed", ("axis", "spindle"): "combined"}[tuple(kinds)]
        out.append(
            {
                "name": stage.name,
                "start_s": start,
                "end_s": end,
                "heat_source": source,
                "axis": axes[0] if axes else (stage.axis if source == "spindle" else None),
                "spindle_rpm": stage.spindle_rpm(),
                "feed_mm_min": stage.feed_mm_min(),
            }
        )
    return out


def check_travel(plan: Plan) -> None:
    """Refuse sweep positions or oscillations outside the virtual machine's travel (Tables A.3, A.4)."""
    from driftlab.daq.sim.truth import AXIS_RANGE
    from driftlab.errors import ValidationError

    for i, what, axis, values, lo, hi in plan.travel_violations(AXIS_RANGE):
        if what == "sweep":
            raise ValidationError(
                f"plan {plan.name}: stages[{i}].sweep.positions: {values} outside "
                f"the virtual machine's {axis} travel {lo:g}..{hi:g}"
            )
        if what == "heat":
            raise ValidationError(
                f"plan {plan.name}: stages[{i}].heat: {axis} oscillation {values} "
                f"outside the virtual machine's travel {lo:g}..{hi:g}"
            )
        # a setup standing the other axes away from home is refused when it is mounted (simrig.sim_mounter)


def plan_scenario(plan: Plan, scenario: Any) -> Any:
    """Return the scenario with the plan's stages and length (the daemon's plan drives the world)."""
    from driftlab.daq.sim.scenario import Scenario

    check_travel(plan)
    doc = scenario.model_dump()
    doc["stages"] = scenario_stages(plan)
    doc["hours"] = max(doc["hours"], math.ceil(plan.total_s / 60.0) / 60.0)
    doc["machine"] = {**doc["machine"], "id": plan.machine.id}
    return Scenario.model_validate(doc)


def scenario_meta(scenario: Any) -> dict[str, Any]:
    """Return the virtual machine's channel map and room channels (Table 5.1 sites)."""
    from driftlab.daq.sim.sites import ROOM_CHANNELS, channel_map

    return {"channels": channel_map(), "room_channels": list(ROOM_CHANNELS)}


def sim_meta(plan: Plan, scenario: Any) -> dict[str, Any]:
    """Return what the virtual machine adds to campaign.json: machine details, model channels, noise."""
    from driftlab.daq.sim.campaign import campaign_meta

    meta = campaign_meta(plan_scenario(plan, scenario))
    return {k: meta[k] for k in ("machine", "model_channels", "noise") if k in meta}
