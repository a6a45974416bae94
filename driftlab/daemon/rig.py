"""The rig: the instruments of one machine wired to a campaign plan, on the DAQ drivers.

The same drivers talk to real hardware (``build_real_rig``: the resources named in the plan's
``instruments:``) and to the simulated servers of the virtual machine (``driftlab.daemon.simrig``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from driftlab.campaigns.clock import Clock, WallClock
from driftlab.campaigns.plan import Plan, Stage, SweepPoint
from driftlab.campaigns.setups import Setup
from driftlab.daemon.loop import term_means
from driftlab.daemon.rigfile import RigSpec, open_rig, thermocouple_channels
from driftlab.daq.laser import LaserInterferometer
from driftlab.daq.machine_link import SerialMachineLink
from driftlab.daq.protocols import Reading, TemperatureScanner
from driftlab.daq.proximity import ProximitySensor, ReferenceSurfaceMeter, RollPair, a_axis_array, b_axis_array
from driftlab.daq.thermocouple import ThermocoupleCard
from driftlab.daq.transport import LineChannel, open_port
from driftlab.errors import InstrumentError, ValidationError

#: proximity pair on two parallel reference lines (fig. 5.11): per linear axis, the gap term the two
#: sensors read and the axis along which they are separated (their difference over the separation is the roll)
ROLL_GAP = {"X": "dz", "Y": "dz", "Z": "dy"}
ROLL_SEPARATION_MM = 150.0
#: a proximity sensor's calibration on a reference line (constant V, slope V/mm), appendix C magnitudes
ROLL_CALIBRATION = ((5.0, 8.5), (5.1, 8.4))

log = logging.getLogger(__name__)


def stage_program(stage: Stage) -> list[str]:
    """Return the motion code that sets a stage's spindle (the heat cycles run as the controller's own program)."""
    rpm = stage.spindle_rpm()
    return [f"(stage {stage.name}: {stage.heat_label()})", f"S{rpm:.0f} M03" if rpm > 0 else "M05"]


def approach_program(point: SweepPoint, overtravel: float = 2.0, feed_mm_min: float = 2000.0) -> list[str]:
    """Return the motion code that reaches a sweep point from its approach side (ch. 5.5: backlash)."""
    before = point.position - point.direction * overtravel
    return [
        f"G00 {point.axis}{before:.4f}",
        f"G01 {point.axis}{point.position:.4f} F{feed_mm_min:.0f}",
        "G04 P0.5 (settle before reading, ch. 5.5)",
    ]


def proximity_meter(card: Any, setup: Setup) -> Any:
    """Return the driver that reads a proximity setup on the A/D card: a roll pair or a reference-surface array.

    A linear axis' roll comes from two sensors on parallel reference lines (fig. 5.11, channels 0-1);
    a rotary axis' run-outs and tilts from the five-sensor arrays on its reference arcs or cylinder
    (figs. 5.12-5.13, appendix C tables C.1/C.2, channels 0-4).
    """
    if setup.fixture == "reference_edge":
        (c_a, s_a), (c_b, s_b) = ROLL_CALIBRATION
        return RollPair(ProximitySensor(card, 0, c_a, s_a), ProximitySensor(card, 1, c_b, s_b), ROLL_SEPARATION_MM)
    if setup.fixture in ("cylinder", "sphere") and setup.axis in ("A", "B"):
        array = a_axis_array() if setup.axis == "A" else b_axis_array()
        return ReferenceSurfaceMeter(card, list(range(len(array.calibration.sensors))), array)
    raise ValidationError(f"no proximity driver for a {setup.fixture} on the {setup.axis} axis")


@dataclass(frozen=True)
class RigOptions:
    """What an `InstrumentRig` needs besides its drivers: the campaign clock (the datum's time), a
    resumed head's saved datum, the simulated laser server that restores it, how to close the
    instruments, the simulated servers by role (fault injection in tests), the A/D card of the
    proximity sensors and who mounts a setup (``mount``: the simulated rig's, else nobody)."""

    clock: Clock
    datum: Mapping[str, Any] | None = None
    laser_server: Any | None = None
    closers: Sequence[Callable[[], None]] = ()
    servers: Mapping[str, Any] = field(default_factory=dict)
    adcard: Any | None = None
    mount: Callable[[Setup | None], None] | None = None


class InstrumentRig:
    """A Rig on the DAQ drivers: thermocouple card, laser, proximity sensors on an A/D card, controller link.

    Each sweep point names the setup it is measured with (``campaigns.setups``): the rig mounts it
    when it changes (``mount``: an operator's job on a real machine, done by the simulated rig on
    the virtual one) and reads the terms that setup delivers - the laser through its optics, the
    proximity arrays through the A/D card (ten readings averaged, ch. 5.5).

    The laser is referenced (zeroed) once per set-up, at the first point it measures, so that every
    later reading refers to the state at the start of the test (ch. 5.5); the datum is stored with
    the readings. A resumed simulated run restores the simulated head's datum, as the real head keeps
    its count while the PC restarts; a real one whose head lost it is referenced afresh.
    """

    def __init__(
        self, plan: Plan, scanner: TemperatureScanner, laser: Any | None, link: Any | None, options: RigOptions
    ) -> None:
        self.plan = plan
        self.adcard = options.adcard
        self._mount = options.mount
        self._setups = plan.used_setups()
        self._mounted: str | None = None
        self._meter: Any | None = None
        self.servers = dict(options.servers)  # simulated instrument servers by role (fault injection in tests)
        self.scanner = scanner
        self.laser = laser
        self.link = link
        self.clock = options.clock
        self.laser_server = options.laser_server
        self._saved = dict(options.datum) if options.datum else None
        self._new_datum: dict[str, Any] | None = None
        self._closers = list(options.closers)
        self._stage: Stage | None = None
        # Axis positions read while the controller was known to be at rest: every block sent so far
        # executed, no heat cycle of the stage moving an axis. Nothing can move them until the rig
        # itself sends motion again, so the machine-state log need not ask for them at every scan.
        self._rest_positions: dict[str, float] | None = None
        self._at_rest = False

    def _moving(self) -> None:
        """Forget the positions at rest: motion (or a program) was just sent."""
        self._at_rest = False
        self._rest_positions = None

    def apply_stage(self, stage: Stage, t_s: float) -> None:
        """Send the stage's spindle command to the controller."""
        self._stage = stage
        self._moving()
        if self.link is not None:
            self.link.send_program(stage_program(stage), wait=False)

    def machine_state(self) -> dict[str, float]:
        """Return the commanded spindle speed and feed with the controller's axis positions."""
        stage = self._stage
        state = {
            "spindle_rpm": stage.spindle_rpm() if stage else 0.0,
            "feed_mm_min": stage.feed_mm_min() if stage else 0.0,
        }
        if self.link is not None:
            pos = self._rest_positions
            if pos is None:
                pos = {k.lower(): float(v) for k, v in self.link.position().items()}
                axis_heat = stage is not None and any(h.kind == "axis" for h in stage.heat)
                if self._at_rest and not axis_heat:
                    self._rest_positions = pos
            state.update(pos)
        return state

    def move_to(self, point: SweepPoint) -> None:
        """Queue the approach moves to the point on the controller."""
        self._moving()
        if self.link is not None:
            self.link.send_program(approach_program(point), wait=False)

    def _ensure_reference(self, point: SweepPoint) -> None:
        """Configure the optics for the point's term and make sure the head has its datum."""
        laser = self.laser
        if laser is None:
            raise InstrumentError("no laser interferometer configured for error sweeps")
        laser.configure(point.axis, point.term)
        if not laser.reference_lost:
            return
        saved = self._saved
        if (
            saved is not None
            and (saved.get("axis"), saved.get("term")) == (point.axis, point.term)
            and (self.laser_server is not None and "error" in saved)
        ):
            self.laser_server.restore_reference(saved["t_s"], saved["position"], saved["error"])
            laser.reference_lost = False
            laser.reference_position = float(saved["position"])
            self._saved = None
            return
        laser.reference(point.position)
        datum: dict[str, Any] = {
            "axis": point.axis,
            "term": point.term,
            "position": point.position,
            "t_s": self.clock.now(),
        }
        ref = self.laser_server.datum() if self.laser_server is not None else None
        if ref is not None:
            datum.update(ref)
        self._saved = None
        self._new_datum = datum

    def mount_setup(self, setup_id: str) -> Setup:
        """Mount the point's setup if another one is mounted (optics re-aligned: the laser needs a new datum)."""
        setup = self._setups.get(setup_id)
        if setup is None:
            raise ValidationError(f"sweep point names setup {setup_id!r}, which the plan does not have")
        if self._mounted != setup_id:
            log.info(
                "mount setup %s: %s %s on %s (%s)",
                setup_id,
                setup.instrument,
                setup.kind,
                setup.axis,
                ", ".join(setup.cells()),
            )
            if self._mount is not None:
                self._mount(setup)
            self._meter = None
            if setup.instrument == "proximity":
                if self.adcard is None:
                    raise InstrumentError(f"setup {setup_id}: no A/D card configured for the proximity sensors")
                self._meter = proximity_meter(self.adcard, setup)
            elif setup.instrument != "laser":
                raise InstrumentError(f"setup {setup_id}: the daemon does not drive {setup.instrument} setups")
            self._mounted = setup_id
        return setup

    def measure_point(self, point: SweepPoint) -> dict[str, Reading]:
        """Wait for the move, then read the terms of the point's setup (mean of `samples` readings)."""
        setup = self.mount_setup(point.setup) if point.setup else None
        if self.link is not None:
            self.link.wait_done()
            self._at_rest = True  # every block sent has executed
        if setup is not None and setup.instrument == "proximity":
            return self._read_proximity(setup, point.samples)
        if self.laser is None:
            raise InstrumentError("no laser interferometer configured for error sweeps")
        self._ensure_reference(point)
        self.laser.readings_per_point = point.samples
        sample = self.laser.measure_error(point.axis, point.term, point.position, point.direction)
        return {point.term: Reading(sample.value, sample.flag)}

    def _read_proximity(self, setup: Setup, samples: int) -> dict[str, Reading]:
        """Return the setup's terms from the proximity sensors, each the mean of ``samples`` readings."""
        meter = self._meter
        if meter is None:
            raise InstrumentError(f"{setup.instrument} setup on {setup.axis}: no proximity sensors mounted")
        reads: list[Mapping[str, Reading]] = []
        for _ in range(samples):
            if hasattr(meter, "read_angle"):
                reads.append({setup.terms[0]: meter.read_angle()})
            else:
                got = meter.read()
                reads.append({t: got.get(t, Reading.missing("not_resolved")) for t in setup.terms})
        return term_means(reads)

    def take_datum(self) -> dict[str, Any] | None:
        """Return the datum set since the last call, once."""
        datum, self._new_datum = self._new_datum, None
        return datum

    def close(self) -> None:
        """Close every instrument (and stop simulated servers)."""
        for close in reversed(self._closers):
            try:
                close()
            except Exception:  # noqa: BLE001 - closing must not mask the run's own outcome
                log.debug("error while closing an instrument", exc_info=True)


def build_real_rig(plan: Plan, channels: list[str], clock: WallClock) -> InstrumentRig:
    """Return a rig on the instruments named in the plan's `instruments:` section."""
    inst = plan.instruments
    if not inst.thermocouple:
        raise ValidationError(f"plan {plan.name}: instruments.thermocouple is required without --sim")
    closers: list[Callable[[], None]] = []
    card_io = LineChannel(open_port(inst.thermocouple), "thermocouple card")
    closers.append(card_io.close)
    scanner = ThermocoupleCard(card_io, dict(enumerate(channels)), clock=clock.now)
    laser = link = None
    if inst.laser:
        laser_io = LineChannel(open_port(inst.laser), "laser")
        closers.append(laser_io.close)
        laser = LaserInterferometer(laser_io)
    if inst.machine_link:
        link = SerialMachineLink.open(inst.machine_link)
        closers.append(link.close)
    if any(s.sweep is not None for s in plan.stages) and laser is None:
        raise ValidationError(f"plan {plan.name}: sweeps need instruments.laser without --sim")
    return InstrumentRig(plan, scanner, laser, link, RigOptions(clock=clock, closers=closers))


def build_file_rig(
    plan: Plan,
    rig: RigSpec,
    channels: list[str],
    clock: WallClock,
    readers: Mapping[str, Callable[..., Any]] | None = None,
) -> InstrumentRig:
    """Return a rig on the instruments of a rig file (``driftlab daemon --rig``), scanning the plan's channels."""
    spec = rig.role("thermocouples")
    if spec is None:
        raise ValidationError(f"rig {rig.name}: a campaign needs a thermocouples role")
    machine = rig.role("machine")
    if machine is not None and machine.driver == "heidenhain-lsv2":
        raise ValidationError(
            f"rig {rig.name}: heidenhain-lsv2 reads the control but cannot move the machine or start its spindle; "
            "a campaign needs linuxcnc or thesis-rs232 (or no machine role); `driftlab rig check` reads the TNC"
        )
    wired = thermocouple_channels(rig)
    missing = [c for c in channels if c not in wired]
    if missing:
        raise ValidationError(
            f"rig {rig.name}: the plan's channel{'s' if len(missing) > 1 else ''} {', '.join(missing[:5])} "
            "not wired in instruments.thermocouples.options.channels"
        )
    wanted = set(channels)
    cmap = {k: v for k, v in spec.options["channels"].items() if str(v) in wanted}
    scoped = rig.model_copy(
        update={
            "instruments": {
                **rig.instruments,
                "thermocouples": spec.model_copy(update={"options": {**spec.options, "channels": cmap}}),
            }
        }
    )
    if any(s.sweep is not None for s in plan.stages) and rig.role("laser") is None:
        raise ValidationError(f"plan {plan.name}: sweeps need a laser role in rig {rig.name}")
    opened = open_rig(scoped, clock.now, readers=readers)
    inst = opened.instruments
    return InstrumentRig(
        plan,
        inst["thermocouples"],
        inst.get("laser"),
        inst.get("machine"),
        RigOptions(clock=clock, closers=[opened.close], adcard=inst.get("proximity")),
    )
