"""The machining side of the virtual machine: the simulated bench the ch. 7.3 cutting test runs on.

``MachiningMachine`` is the virtual machine powered on and cutting (the program's spindle speed and
mean feeds are its heat sources); ``LoggingController`` the simulated controller keeping a log of
every executed block with its times; ``true_errors`` the machine's true link and joint errors at
any 5-axis pose (base truth plus the scenario's hidden effects allocated to their joints, eq. 4.20);
``open_bench`` wires the clock, the controller and the thermocouple card of one cutting run.

The compensator's cutting test (``driftlab.compensator.cutting_test``) reaches the virtual machine
only through this module.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from driftlab.daq.sim import truth
from driftlab.daq.sim.instruments import ManualClock, SimController, SimSphere, SimThermocoupleCard, serial_url
from driftlab.daq.sim.machine import VirtualMachine
from driftlab.daq.sim.scenario import Scenario, Stage
from driftlab.daq.sim.sites import CHANNELS, FEED_REF_MM_MIN, SITE_INDEX, SOURCES, SPINDLE_REF_RPM
from driftlab.physics import kinematics as kin
from driftlab.vocabulary import AXES, TERMS, Axis

__all__ = [
    "CHANNELS",
    "ExecutedBlock",
    "LoggingController",
    "MachiningMachine",
    "ManualClock",
    "Scenario",
    "SimSphere",
    "default_spheres",
    "hidden_element_errors",
    "open_bench",
    "serial_url",
    "travel",
    "true_errors",
    "true_workspace_translation",
]

#: ch. 7.3 cutting conditions
SPINDLE_RPM = 10000.0
JOINT_OF_AXIS = {"X": "phi_x", "Y": "phi_y", "Z": "phi_z", "A": "theta_x", "B": "theta_y"}


class MachiningMachine(VirtualMachine):
    """The virtual machine powered on (motors holding) from t = 0, cutting between ``cut_start_s`` and ``cut_end_s``.

    ``age_s`` places the session after the campaign (a later day): drifts have gone on meanwhile.

    While it cuts, the spindle runs at the program's speed and each axis' motor heats with its mean
    feed (the heat sources of the thermal network, normalised as in ``daq.sim.sites``).
    """

    def __init__(
        self,
        scenario: Scenario,
        cut_start_s: float,
        cut_end_s: float,
        mean_feed: Mapping[str, float],
        spindle_rpm: float = SPINDLE_RPM,
        age_s: float = 0.0,
    ) -> None:
        end = max(cut_end_s + 3600.0, scenario.duration_s)
        base = scenario.model_copy(
            update={
                "hours": end / 3600.0,
                "stages": [Stage(name="powered", start_s=0.0, end_s=end, heat_source="idle")],
            }
        )
        self.cut_start_s, self.cut_end_s = float(cut_start_s), float(cut_end_s)
        self.mean_feed = dict(mean_feed)
        self.spindle_rpm = float(spindle_rpm)
        #: time from the campaign's start to this session's t = 0: the machine has cooled down to the
        #: room again (the thermal state starts soaked), but what does not depend on temperature
        #: (a drift: wear, settling) has gone on
        self.age_s = float(age_s)
        super().__init__(base)

    def sources(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 10) heat-source levels: powered and holding, plus spindle and feeds while cutting."""
        u = super().sources(t_s)
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        cut = (t >= self.cut_start_s) & (t < self.cut_end_s)
        u[cut, SOURCES.index("spindle")] = self.spindle_rpm / SPINDLE_REF_RPM
        for a, f in self.mean_feed.items():
            u[cut, SOURCES.index(f"feed_{a.lower()}")] = f / FEED_REF_MM_MIN
        return u


def hidden_element_errors(
    vm: VirtualMachine, t_s: np.ndarray, q: np.ndarray, direction: np.ndarray
) -> dict[str, np.ndarray]:
    """Return the scenario's hidden effects as errors of each effect's own joint at poses q (N, 5).

    Each effect is the work-space error of spec section 3 with its axis moved and the others at
    home; the joint error that produces exactly it there is found by eq. 4.20 and then acts at q.
    """
    t = np.atleast_1d(np.asarray(t_s, float))
    out: dict[str, np.ndarray] = {}
    dT = None
    for eff in vm.scenario.hidden:
        if eff.kind == "sensor_fault" or eff.axis is None or eff.term is None:
            continue
        k = AXES.index(eff.axis)
        pos = np.rad2deg(q[:, k]) if eff.axis in truth.ROTARY else q[:, k]
        ch_dT = lag = None
        if eff.channels:
            if dT is None:
                dT = vm.true_dT_array(t)
            ch_dT = dT[:, SITE_INDEX[eff.channels[0]]]
            if eff.kind == "thermal_lag":
                lag = vm.lagged_dT(eff.channels[0], float(eff.params["tau_s"]), t)
        W = np.zeros((len(t), 6))
        t_eff = t + float(getattr(vm, "age_s", 0.0)) if eff.kind == "drift" else t
        W[:, TERMS.index(eff.term)] = truth.hidden_delta(eff, t_eff, pos, direction[:, k], ch_dT, lag)
        joint = JOINT_OF_AXIS[eff.axis]
        E = kin.allocate(W, truth.axis_pose(eff.axis, pos), None, joint)  # eq. 4.20
        out[joint] = out[joint] + E if joint in out else E
    return out


def true_errors(vm: VirtualMachine, t_s: np.ndarray, q: np.ndarray, direction: np.ndarray) -> dict[str, np.ndarray]:
    """Return the virtual machine's true link and joint errors at times t and poses q (base truth + hidden)."""
    t = np.atleast_1d(np.asarray(t_s, float))
    errs = dict(truth.element_errors(q, vm.true_dT_array(t)))
    for e, v in hidden_element_errors(vm, t, q, direction).items():
        errs[e] = errs[e] + v if e in errs else v
    return errs


def true_workspace_translation(vm: VirtualMachine, t_s: float, xyz: Sequence[float]) -> np.ndarray:
    """Return the (3,) true work-space translation error at pose (X, Y, Z, A = B = 0) at time t."""
    q = np.array([[xyz[0], xyz[1], xyz[2], 0.0, 0.0]])
    return kin.workspace_error(q, true_errors(vm, np.array([t_s]), q, np.ones((1, 5))))[0, 3:]


@dataclass(frozen=True)
class ExecutedBlock:
    """A block as the simulated controller ran it: sequence number, target (mm, deg), start and end time."""

    seq: int
    target: tuple[float, ...]
    start: tuple[float, ...]
    t_start_s: float
    t_end_s: float


class _LoggedQueue(deque):
    """The controller's block queue, noting each block as it starts executing."""

    def __init__(self, ctrl: LoggingController) -> None:
        super().__init__()
        self._ctrl = ctrl

    def popleft(self) -> Any:
        """Return the next block and log it with its start time and duration."""
        blk = super().popleft()
        c = self._ctrl
        start = dict(c.pos)
        t0 = c._t_exec
        dur = c._duration(start, blk)
        c.log.append(
            ExecutedBlock(blk.seq, tuple(blk.target[a] for a in AXES), tuple(start[a] for a in AXES), t0, t0 + dur)
        )
        return blk


class LoggingController(SimController):
    """The simulated controller, keeping a log of every executed block with its times."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.log: list[ExecutedBlock] = []
        self._queue = _LoggedQueue(self)


#: the virtual controller's soft limits beyond the range its errors are known over (Tables A.3, A.4):
#: a tenth of each axis' measured travel of overtravel on either side (a machine's soft limits lie
#: outside the range its errors were measured on; the cutting test's part spans X -18..259 mm)
OVERTRAVEL_FRACTION = 0.1


def travel() -> dict[Axis, tuple[float, float]]:
    """Return the virtual controller's soft limits per axis (mm for X, Y, Z; degrees for A, B).

    The measured travel of Tables A.3, A.4 (``daq.sim.truth.AXIS_RANGE``) widened on either side by
    ``OVERTRAVEL_FRACTION`` of it: what the compensator's envelope holds a program to on the bench.
    """
    out: dict[Axis, tuple[float, float]] = {}
    axes: tuple[Axis, ...] = ("X", "Y", "Z", "A", "B")
    for axis in axes:
        lo, hi = truth.AXIS_RANGE[axis]
        extra = OVERTRAVEL_FRACTION * (hi - lo)
        out[axis] = (lo - extra, hi + extra)
    return out


def default_spheres() -> dict[str, SimSphere]:
    """Return four reference spheres (radius 12.7 mm) at the extremes of the X, Y travel, low in Z."""
    pts = {
        "s1": (15.0, 15.0, -235.0),
        "s2": (239.0, 15.0, -235.0),
        "s3": (15.0, 239.0, -235.0),
        "s4": (239.0, 239.0, -235.0),
    }
    return {k: SimSphere(c, 12.7) for k, c in pts.items()}


def open_bench(
    scenario: Scenario,
    cut_start_s: float,
    cut_end_s: float,
    mean_feed: Mapping[str, float],
    *,
    spheres: Mapping[str, SimSphere],
    capacity: int = 16,
    age_s: float = 0.0,
) -> tuple[ManualClock, MachiningMachine, LoggingController, SimThermocoupleCard]:
    """Return the started simulated bench of one cutting run: clock, machine, controller, thermocouple card.

    The machine is switched on at t = 0 (soaked at room temperature) and cuts between the two times;
    the controller probes ``spheres`` displaced by the machine's true work-space translation, and the
    card carries the 50 thermocouples of Table 5.1.
    """
    clock = ManualClock(0.0)
    vm = MachiningMachine(scenario, cut_start_s, cut_end_s, mean_feed, age_s=age_s)
    ctrl = LoggingController(
        vm,
        clock,
        capacity=capacity,
        spheres=dict(spheres),
        sphere_offset=lambda t, c: true_workspace_translation(vm, t, c),
    )
    ctrl.start()
    card = SimThermocoupleCard(vm, clock, dict(enumerate(CHANNELS))).start()
    return clock, vm, ctrl, card
