"""The simulated rig: the real drivers talking to simulated instruments that read the virtual machine.

Also what the plan asks of the virtual machine: its stages as a scenario, the travel it allows and
the campaign.json fields it adds (machine, model channels, noise).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TYPE_CHECKING, Any

from driftlab.campaigns.plan import Cursor, Plan
from driftlab.daemon.rig import ROLL_CALIBRATION, ROLL_GAP, ROLL_SEPARATION_MM, InstrumentRig, RigOptions
from driftlab.daq.attocube_ids import AttocubeIDS, ids_url
from driftlab.daq.keysight34970a import Keysight34970A, Keysight34970AVolts
from driftlab.daq.laser import LASER_TERMS, LaserInterferometer, SettleOptions
from driftlab.daq.linuxcnc import LinuxCNCLink
from driftlab.daq.proximity import a_axis_array, b_axis_array
from driftlab.daq.retry import RetryPolicy
from driftlab.daq.transport import LineChannel, SerialPort, VisaPort, visa_resource_manager
from driftlab.errors import ValidationError

if TYPE_CHECKING:
    from driftlab.campaigns.clock import SimClock
    from driftlab.daq.sim.attocube_ids import SimIDS3010
    from driftlab.daq.sim.instruments import SimLaser
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC
    from driftlab.daq.sim.scenario import Scenario

# The virtual machine's modules (driftlab.daq.sim.*) are imported inside the functions that use them:
# they bring in scipy.signal, measured at 1.1-3.4 s of start-up on this machine, which a daemon on
# real instruments (run.py imports this module) does not pay.


class MemoWorld:
    """The virtual machine behind a small cache: it is a pure function of its arguments, so asking twice is waste.

    A sweep point asks the world for the same error and room air a dozen times at one instant (the
    laser's settle polls and ten averaged readings); the cache answers the repeats exactly.
    """

    def __init__(self, world: Any, size: int = 64) -> None:
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


@dataclass
class _SimServers:
    """The simulated instruments of the virtual machine, started, and how to stop them (and the drivers)."""

    card: Sim34970A
    ctrl: SimLinuxCNC
    head: SimIDS3010 | SimLaser
    ad: Sim34970A
    closers: list[Callable[[], None]] = field(default_factory=list)

    def close(self) -> None:
        """Close every driver opened so far, then the servers (last opened first)."""
        for c in reversed(self.closers):
            c()


@dataclass
class _SimDrivers:
    """The real drivers connected to the simulated instruments."""

    scanner: Keysight34970A
    meter: AttocubeIDS | LaserInterferometer
    link: LinuxCNCLink
    adcard: Keysight34970AVolts


def build_sim_rig(
    plan: Plan,
    scenario: Scenario,
    clock: SimClock,
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
    if laser not in ("attocube-ids3010", "thesis-laser"):
        raise ValueError(f"simulated laser {laser!r}: attocube-ids3010 or thesis-laser")
    if world is None:
        from driftlab.daq.sim.machine import VirtualMachine  # the virtual machine: lazy (module note)

        vm = VirtualMachine(plan_scenario(plan, scenario))
        # The machine exists before the daemon starts: its thermal network is solved here (over the
        # scenario, which plan_scenario makes as long as the plan: the same grid as solved on the
        # first read), not by the first instrument read of the run, which held the interpreter lock
        # for 55-65 ms while the writer thread waited for the first batch (measured).
        vm.advance_to(0.0)
        world = MemoWorld(vm)
    from driftlab.daq.sim.keysight34970a import sim_channel_map  # the virtual machine: lazy (module note)

    card_map = sim_channel_map(channels)  # 34901A channels 101.., 201.., 301.. -> the plan's names
    servers = _start_servers(plan, world, clock, card_map, cursor, laser)
    try:
        drivers = _open_drivers(servers, clock, card_map)
    except Exception:
        servers.close()
        raise
    return InstrumentRig(
        plan,
        drivers.scanner,
        drivers.meter,
        drivers.link,
        RigOptions(
            clock=clock,
            datum=datum,
            laser_server=servers.head,
            closers=servers.closers,
            servers={
                "thermocouple": servers.card,
                "laser": servers.head,
                "controller": servers.ctrl,
                "ad-card": servers.ad,
            },
            adcard=drivers.adcard,
            mount=sim_mounter(world, servers.ctrl, servers.head, servers.ad),
        ),
    )


def _start_servers(
    plan: Plan, world: Any, clock: SimClock, card_map: Mapping[int, str], cursor: Cursor, laser: str
) -> _SimServers:
    """Start the simulated card, controller (each axis where the cursor left it), laser head and A/D mainframe."""
    from driftlab.daq.sim.attocube_ids import SimIDS3010  # the virtual machine: lazy (module note)
    from driftlab.daq.sim.instruments import SimLaser
    from driftlab.daq.sim.keysight34970a import Sim34970A
    from driftlab.daq.sim.linuxcnc import SimLinuxCNC

    card = Sim34970A(world, clock, card_map).start()
    ctrl = SimLinuxCNC(world, clock)
    for axis, (pos, direction) in axis_positions(plan, cursor).items():
        ctrl.pos[axis], ctrl.direction[axis] = pos, direction
    ctrl.start()
    head: SimIDS3010 | SimLaser = (
        SimIDS3010(world, clock, ctrl) if laser == "attocube-ids3010" else SimLaser(world, clock, ctrl)
    ).start()
    ad = Sim34970A(world, clock).start()  # a second mainframe: its DC-volt channels read the proximity sensors
    return _SimServers(card, ctrl, head, ad, [card.close, ctrl.close, head.close, ad.close])


def _open_drivers(servers: _SimServers, clock: SimClock, card_map: Mapping[int, str]) -> _SimDrivers:
    """Connect the real drivers to the simulated instruments (their closers join ``servers.closers``)."""
    from driftlab.daq.sim.attocube_ids import SimIDS3010, ids_resource  # the virtual machine: lazy (module note)
    from driftlab.daq.sim.instruments import serial_url, visa_address

    closers = servers.closers
    rm = visa_resource_manager("@py")
    closers.append(rm.close)
    policy = RetryPolicy(attempts=3, base_delay_s=0.0)

    def visa(server: Any, name: str) -> LineChannel:
        """Return a line channel to a simulated VISA instrument, closed with the rig."""
        io = LineChannel(VisaPort.open(visa_address(server), resource_manager=rm), name, policy, sleep=_no_wait)
        closers.append(io.close)
        return io

    scanner = Keysight34970A(
        visa(servers.card, "34970A"), card_map, tc_type="E", reference_junction="INT", clock=clock.now
    )
    scanner.identify()
    scanner.configure()
    meter: AttocubeIDS | LaserInterferometer
    if isinstance(servers.head, SimIDS3010):
        head_url = ids_url(ids_resource(servers.head))
        meter = AttocubeIDS(
            lambda: SerialPort.open(head_url), settle=SettleOptions(sleep=_no_wait, max_settle_polls=20)
        )
        closers.append(meter.close)
        meter.session()
    else:
        meter = LaserInterferometer(
            visa(servers.head, "laser"), settle=SettleOptions(sleep=_no_wait, max_settle_polls=20), burst=True
        )
    url = serial_url(servers.ctrl)
    link = LinuxCNCLink(lambda: SerialPort.open(url), sleep=_no_wait, max_idle_polls=2)
    link.session()
    closers.append(link.close)
    adcard = Keysight34970AVolts(visa(servers.ad, "34970A volts"), AD_CHANNELS)
    adcard.identify()
    adcard.configure()
    return _SimDrivers(scanner, meter, link, adcard)


#: the proximity mainframe's DC-volt channels: A/D index i is channel AD_CHANNELS[i]
AD_CHANNELS = [101, 102, 103, 104, 105]


def sim_mounter(world: Any, stage: Any, head: Any, ad: Any) -> Callable[[Any], None]:
    """Return mount(setup): put the setup's optics on the simulated head or wire its fixture to the A/D card.

    The simulated instruments then answer only for what is mounted: the head for its optics' mode,
    axis and term within their range (fig. 5.9), the proximity sensors for the reference surface they
    face, reading the virtual machine's errors of the setup's axis at the controller's position.
    """
    from driftlab.daq.sim.instruments import reference_surface_source, roll_pair_source  # lazy (module note)

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
    from driftlab.daq.sim.truth import AXIS_RANGE  # the virtual machine: lazy (module note)

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
    # lazy: driftlab.daq.sim adds 0.9 s to the daemon on real instruments, which never simulates (measured)
    from driftlab.daq.sim.scenario import Scenario

    check_travel(plan)
    doc = scenario.model_dump()
    doc["stages"] = scenario_stages(plan)
    doc["hours"] = max(doc["hours"], math.ceil(plan.total_s / 60.0) / 60.0)
    doc["machine"] = {**doc["machine"], "id": plan.machine.id}
    return Scenario.model_validate(doc)


def scenario_meta(scenario: Any) -> dict[str, Any]:
    """Return the virtual machine's channel map and room channels (Table 5.1 sites)."""
    # lazy: driftlab.daq.sim adds 0.9 s to the daemon on real instruments, which never simulates (measured)
    from driftlab.daq.sim.sites import ROOM_CHANNELS, channel_map

    return {"channels": channel_map(), "room_channels": list(ROOM_CHANNELS)}


def sim_meta(plan: Plan, scenario: Any) -> dict[str, Any]:
    """Return what the virtual machine adds to campaign.json: machine details, model channels, noise."""
    # lazy: driftlab.daq.sim adds 0.9 s to the daemon on real instruments, which never simulates (measured)
    from driftlab.daq.sim.campaign import campaign_meta

    meta = campaign_meta(plan_scenario(plan, scenario))
    return {k: meta[k] for k in ("machine", "model_channels", "noise") if k in meta}
