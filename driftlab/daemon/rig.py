"""The rig: the instruments of one machine wired to a campaign plan, on the DAQ drivers.

The same drivers talk to real hardware (``build_real_rig``: the resources named in the plan's
``instruments:``) and to the simulated servers of the virtual machine (``driftlab.daemon.simrig``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

from driftlab.campaigns.clock import Clock
from driftlab.campaigns.plan import Plan, Stage, SweepPoint
from driftlab.daq.protocols import Reading, TemperatureScanner
from driftlab.errors import InstrumentError

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


class InstrumentRig:
    """A Rig on the DAQ drivers: thermocouple card, laser interferometer and the controller link.

    The laser is referenced (zeroed) once per set-up, at the first point it measures, so that every
    later reading refers to the state at the start of the test (ch. 5.5); the datum is stored with
    the readings. A resumed simulated run restores the simulated head's datum, as the real head keeps
    its count while the PC restarts; a real one whose head lost it is referenced afresh.
    """

    def __init__(
        self,
        plan: Plan,
        scanner: TemperatureScanner,
        laser: Any | None,
        link: Any | None,
        *,
        clock: Clock,
        datum: Mapping[str, Any] | None = None,
        laser_server: Any | None = None,
        closers: list[Callable[[], None]] | None = None,
        servers: Mapping[str, Any] | None = None,
    ) -> None:
        self.plan = plan
        self.servers = dict(servers or {})  # simulated instrument servers by role (fault injection in tests)
        self.scanner = scanner
        self.laser = laser
        self.link = link
        self.clock = clock
        self.laser_server = laser_server
        self._saved = dict(datum) if datum else None
        self._new_datum: dict[str, Any] | None = None
        self._closers = list(closers or [])
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
        state = {"spindle_rpm": stage.spindle_rpm() if stage else 0.0,
                 "feed_mm_min": stage.feed_mm_min() if stage else 0.0}
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
        self.laser.configure(point.axis, point.term)
        if not self.laser.reference_lost:
            return
        saved = self._saved
        if saved is not None and (saved.get("axis"), saved.get("term")) == (point.axis, point.term) and (
            self.laser_server is not None and "error" in saved
        ):
            self.laser_server.restore_reference(saved["t_s"], saved["position"], saved["error"])
            self.laser.reference_lost = False
            self.laser.reference_position = float(saved["position"])
            self._saved = None
            return
        self.laser.reference(point.position)
        datum: dict[str, Any] = {"axis": point.axis, "term": point.term, "position": point.position,
                                 "t_s": self.clock.now()}
        ref = self.laser_server.datum() if self.laser_server is not None else None
        if ref is not None:
            datum.update(ref)
        self._saved = None
        self._new_datum = datum

    def measure_point(self, point: SweepPoint) -> dict[str, Reading]:
        """Wait for the move, then read the point's term with the laser (mean of `samples` readings)."""
        if self.laser is None:
            raise InstrumentError("no laser interferometer configured for error sweeps")
        if self.link is not None:
            self.link.wait_done()
            self._at_rest = True  # every block sent has executed
        self._ensure_reference(point)
        self.laser.readings_per_point = point.samples
        sample = self.laser.measure_error(point.axis, point.term, point.position, point.direction)
        return {point.term: Reading(sample.value, sample.flag)}

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


def build_real_rig(plan: Plan, channels: list[str], clock: Any) -> InstrumentRig:
    """Return a rig on the instruments named in the plan's `instruments:` section."""
    from driftlab.daq.laser import LaserInterferometer
    from driftlab.daq.machine_link import SerialMachineLink
    from driftlab.daq.thermocouple import ThermocoupleCard
    from driftlab.daq.transport import LineChannel, open_port
    from driftlab.errors import ValidationError

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
    return InstrumentRig(plan, scanner, laser, link, clock=clock, closers=closers)
