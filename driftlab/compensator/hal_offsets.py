"""Open-architecture correction on LinuxCNC: a userspace HAL component driving the external axis offsets.

The thesis streamed corrected motion code because its control offered nothing else; it named the
"open architecture" way, offsets applied to the axes independent of the motion code (ch. 7.2, last
paragraph), and could not test it. LinuxCNC offers it as *external axis offsets*. Written from
LinuxCNC's documentation and source (read at tag v2.9.10; the same on master at 5c41560ebb):

* docs/src/motion/external-offsets.adoc ("External Axis Offsets") and docs/man/man9/motion.9: for
  each axis letter L, ``[AXIS_L]OFFSET_AV_RATIO`` (0 < r <= 0.9; 0, the default, disables the
  offset) gives the offset r of the axis' velocity and acceleration; the pins
  ``axis.L.eoffset-enable`` (IN bit), ``axis.L.eoffset-scale`` (IN float), ``axis.L.eoffset-counts``
  (IN s32), ``axis.L.eoffset-clear`` (IN bit), ``axis.L.eoffset`` (OUT float, the applied offset),
  ``axis.L.eoffset-request`` (OUT float); each servo period the change of ``eoffset-counts`` times
  ``eoffset-scale`` is accumulated into the requested offset, so with a constant scale the request
  is counts x scale; the register is zeroed at each machine-on, and the docs recommend holding the
  counts at zero while the machine is off; all joints must be homed; a soft limit holds the axis
  (``motion.eoffset-limited``); ``axis.L.pos-cmd`` (OUT float) is the commanded position, the
  external offset reported separately;
* docs/src/hal/halmodule.adoc and src/hal/halmodule.cc (the ``hal`` Python module):
  ``hal.component(name)``, ``newpin(name, type, dir)`` with ``HAL_BIT``/``HAL_FLOAT``/``HAL_S32``
  and ``HAL_IN``/``HAL_OUT``, ``ready()``, ``comp[name]`` to read and write (an S32 pin refuses a
  value outside int32 with ``OverflowError``), ``exit()``; a ``halcmd unload`` arrives as
  ``KeyboardInterrupt``; HAL_OUT pins are to be driven every period.

What it does, each period: read the commanded pose (``<name>.L.pos`` wired from ``axis.L.pos-cmd``),
the current model and temperatures (the same sources as the streaming compensator: the API's
current model, hot-reloaded, and latest scan, or a file and a CSV), solve the correction at that
pose (eqs. 4.23-4.26, ``kinematics.compensate``), and drive ``<name>.L.counts`` = round(correction /
scale) to ``axis.L.eoffset-counts`` with ``<name>.L.scale`` to ``axis.L.eoffset-scale`` and
``<name>.L.enable`` to ``axis.L.eoffset-enable``. The envelope of the model (or a machine file)
holds: a correction larger than ``max_correction``, or temperatures beyond the fitted range plus
the margin, are not applied (the last good counts are held); an offset that would take an axis past
its travel is cut to end at the travel (motion would otherwise stop the axis at its soft limit with
no deceleration, external-offsets.adoc); either way ``<name>.fault`` is raised and the reason
logged once. While ``<name>.machine-on`` (wired from
``halui.machine.is-on``) is false the counts are held at zero, as the docs advise.

Untested on a real control: the tests run against a stand-in of the ``hal`` module and of the
motion pins written from the documentation above (tests/compensator/hal_standin.py).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from driftlab.compensator.compensate import ErrorModel
from driftlab.compensator.guard import Guard
from driftlab.errors import DriftlabError, ValidationError
from driftlab.physics import kinematics
from driftlab.vocabulary import AXES

log = logging.getLogger(__name__)

#: the largest count an ``eoffset-counts`` pin (s32) holds
S32_MAX = 2**31 - 1


class Models(Protocol):
    """Where the current model comes from (``compensator.stream.ApiModel``, ``StaticModel``)."""

    model: ErrorModel | None

    def refresh(self) -> bool:
        """Fetch the model if it changed; True when it did."""


class Temperatures(Protocol):
    """Where the latest temperatures come from (``compensator.stream.ApiTemperatures``, ``CsvTemperatures``)."""

    def read(self) -> dict[str, float]:
        """Return the latest reading per channel (degC)."""


def import_hal() -> Any:
    """Return LinuxCNC's ``hal`` module; a one-line error where LinuxCNC is not installed."""
    try:
        import hal  # type: ignore[import-not-found]  # LinuxCNC's own module, not on any package index
    except ImportError:
        raise ValidationError(
            "LinuxCNC's Python module 'hal' is not importable: run `driftlab hal-offsets` on the LinuxCNC "
            "machine, with LinuxCNC's Python (halcmd loadusr), docs/instruments.md"
        ) from None
    return hal


@dataclass
class HalOffsetsState:
    """What the component did: periods run, the offsets applied, the last fault (None when healthy)."""

    periods: int = 0
    applied: dict[str, float] = field(default_factory=dict)
    fault: str | None = None
    faults: int = 0
    model_reloads: int = 0


class HalOffsets:
    """The ``driftlab-hal`` userspace component: model and temperatures in, external axis offsets out."""

    def __init__(
        self,
        hal: Any,
        models: Models,
        temperatures: Temperatures,
        axes: str = "xyz",
        scale: Mapping[str, float] | None = None,
        name: str = "driftlab-hal",
        envelope: Any | None = None,
        allow_extrapolation: bool = False,
        refresh_s: float = 30.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        letters = [a.lower() for a in axes]
        if not letters or any(a.upper() not in AXES for a in letters) or len(set(letters)) != len(letters):
            raise ValidationError(f"--axes {axes!r}: distinct letters of {''.join(AXES).lower()}")
        self.hal, self.models, self.temperatures = hal, models, temperatures
        self.axes = letters
        # one count per 0.1 µm (X Y Z, mm) or 0.0001 deg (A B): under any positioning step, and
        # +-214 m / deg of range in an s32 counts pin
        self.scale = {a: float((scale or {}).get(a, 1e-4)) for a in letters}
        if not all(math.isfinite(s) and s > 0 for s in self.scale.values()):
            raise ValidationError("eoffset scale must be positive and finite")
        self.envelope, self.allow_extrapolation = envelope, allow_extrapolation
        self.refresh_s, self.clock = refresh_s, clock
        self.state = HalOffsetsState()
        self._counts = {a: 0 for a in letters}
        self._last_refresh: float | None = None
        self._last_q: np.ndarray | None = None
        self._direction = np.ones(5)
        self.comp = hal.component(name)
        for a in letters:
            self.comp.newpin(f"{a}.pos", hal.HAL_FLOAT, hal.HAL_IN)  # <= axis.L.pos-cmd
            self.comp.newpin(f"{a}.counts", hal.HAL_S32, hal.HAL_OUT)  # => axis.L.eoffset-counts
            self.comp.newpin(f"{a}.scale", hal.HAL_FLOAT, hal.HAL_OUT)  # => axis.L.eoffset-scale
            self.comp.newpin(f"{a}.enable", hal.HAL_BIT, hal.HAL_OUT)  # => axis.L.eoffset-enable
            self.comp.newpin(f"{a}.offset", hal.HAL_FLOAT, hal.HAL_OUT)  # what is requested, mm or deg
        self.comp.newpin("machine-on", hal.HAL_BIT, hal.HAL_IN)  # <= halui.machine.is-on
        self.comp.newpin("fault", hal.HAL_BIT, hal.HAL_OUT)
        self.comp.newpin("active", hal.HAL_BIT, hal.HAL_OUT)
        self.comp.ready()
        self._drive(enable=False)

    # -- one period
    def _pose(self) -> np.ndarray:
        """Return the commanded pose (5,) in mm and rad from the ``.pos`` pins (axes not wired: 0)."""
        q = np.zeros(5)
        for a in self.axes:
            k = AXES.index(a.upper())
            q[k] = float(self.comp[f"{a}.pos"])
        q[3:] = np.deg2rad(q[3:])
        return q

    def _refresh(self) -> ErrorModel:
        now = self.clock()
        if self.models.model is None or self._last_refresh is None or now - self._last_refresh >= self.refresh_s:
            if self.models.refresh():
                self.state.model_reloads += 1
            self._last_refresh = now
        assert self.models.model is not None
        return self.models.model

    def correction(self) -> tuple[dict[str, float], str | None]:
        """Return the offset per axis (mm, deg) at the commanded pose now, and why it is cut short (or None).

        A correction beyond ``max_correction`` or temperatures beyond the fitted range raise
        ValidationError (nothing new is applied); an offset that would take the axis past its travel
        is cut to end at the travel, and the reason returned.
        """
        model = self._refresh()
        guard = Guard.for_model(model, self.envelope, allow_extrapolation=self.allow_extrapolation)
        temps = self.temperatures.read()
        guard.check_temperatures(temps)
        q = self._pose()
        if self._last_q is not None:
            moved = np.sign(q - self._last_q)
            self._direction = np.where(moved != 0, moved, self._direction)
        self._last_q = q
        errors = model.predict(q[None, :], temps, self._direction[None, :])
        solved = kinematics.compensate(q[None, :], errors, model.dims)
        desired = (solved.q_cmd - q[None, :])[0]
        desired[3:] = np.rad2deg(desired[3:])
        if not np.all(np.isfinite(desired)):
            raise ValidationError("the model predicts non-finite errors for these temperatures")
        pose = q.copy()
        pose[3:] = np.rad2deg(pose[3:])
        out, note = {}, None
        for a in self.axes:
            k = AXES.index(a.upper())
            unit = "deg" if k >= 3 else "mm"
            if not abs(desired[k]) <= guard.max_correction[k]:
                raise ValidationError(
                    f"correction of {a.upper()} {desired[k]:.6g} {unit} exceeds the largest plausible "
                    f"{guard.max_correction[k]:.6g} {unit} (machine envelope)"
                )
            target = pose[k] + desired[k]
            if not guard.lo[k] - 1e-9 <= target <= guard.hi[k] + 1e-9:
                note = note or (
                    f"corrected {a.upper()} {target:.6g} {unit} is outside the travel "
                    f"{guard.lo[k]:.6g}..{guard.hi[k]:.6g} {unit}: the offset ends at the travel"
                )
                desired[k] = min(max(target, guard.lo[k]), guard.hi[k]) - pose[k]
            out[a] = float(desired[k])
        return out, note

    def step(self) -> None:
        """Run one period: drive every pin (HAL_OUT pins are driven each period, halmodule.adoc)."""
        self.state.periods += 1
        if not self.comp["machine-on"]:
            # the counts register is zeroed at machine-on: hold the counts at zero while off
            self._counts = {a: 0 for a in self.axes}
            self.state.applied = {}
            self._drive(enable=False)
            return
        try:
            offsets, note = self.correction()
        except DriftlabError as exc:
            self._fault(f"holding the offsets: {exc.one_line()}")
            self._drive(enable=True, fault=True)
            return
        if note is not None:
            self._fault(note)
        elif self.state.fault is not None:
            log.warning("driftlab-hal: offsets applied in full again")
            self.state.fault = None
        for a, v in offsets.items():
            # the nearest count; toward zero when cut at the travel, so no count takes the axis past it
            n = math.trunc(v / self.scale[a]) if note is not None else round(v / self.scale[a])
            self._counts[a] = max(-S32_MAX, min(S32_MAX, n))
        self.state.applied = {a: self._counts[a] * self.scale[a] for a in self.axes}
        self._drive(enable=True, fault=note is not None)

    def _fault(self, reason: str) -> None:
        """Note a fault, logged once until it changes."""
        if reason != self.state.fault:
            log.warning("driftlab-hal: %s", reason)
            self.state.faults += 1
        self.state.fault = reason

    def _drive(self, enable: bool, fault: bool = False) -> None:
        for a in self.axes:
            self.comp[f"{a}.counts"] = self._counts[a]
            self.comp[f"{a}.scale"] = self.scale[a]
            self.comp[f"{a}.enable"] = enable
            self.comp[f"{a}.offset"] = self._counts[a] * self.scale[a]
        self.comp["fault"] = fault
        self.comp["active"] = enable and any(self._counts.values())

    def run(
        self, period_s: float = 0.1, sleep: Callable[[float], None] = time.sleep, periods: int | None = None
    ) -> None:
        """Run periods until ``halcmd unload`` (KeyboardInterrupt) or ``periods`` have run; then exit the component."""
        try:
            while periods is None or self.state.periods < periods:
                self.step()
                sleep(period_s)
        except KeyboardInterrupt:
            pass
        finally:
            self.comp.exit()
