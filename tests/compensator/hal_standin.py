"""A stand-in for LinuxCNC's ``hal`` Python module and for motion's external-offset pins, from the documentation.

Written from LinuxCNC's documentation and source (tag v2.9.10), not from driftlab's code:

* ``hal`` (docs/src/hal/halmodule.adoc, src/hal/halmodule.cc): ``component(name[, prefix])``;
  ``newpin(name, type, dir)``, a duplicate ``ValueError("Duplicate pin name ...")``; ``ready()``;
  ``comp[name]`` and ``comp[name] = v``: a missing pin ``AttributeError("Pin '...' does not exist")``,
  a float pin takes a number (``TypeError("Number expected, not ...")``), an s32 pin an int in
  int32 (``OverflowError("Value ... out of range")``), a bit pin the truth of the value;
  ``getpins()``; ``exit()``, after which every operation is ``RuntimeError("Invalid operation on
  closed HAL component")``; the constants HAL_BIT, HAL_FLOAT, HAL_S32, HAL_U32, HAL_IN, HAL_OUT, HAL_IO.
* motion's external axis offsets (docs/src/motion/external-offsets.adoc, docs/man/man9/motion.9):
  per axis, each servo period the change of ``eoffset-counts`` times ``eoffset-scale`` accumulates
  into the request (``eoffset-request``) while ``eoffset-enable`` is true; the applied offset
  (``eoffset``) follows the request at no more than OFFSET_AV_RATIO x MAX_VELOCITY; the register and
  the offset are zeroed at machine-on; a disabled axis keeps its offset; the axis is held at its
  soft limit (``motion.eoffset-limited``) when position plus offset would cross it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

HAL_BIT, HAL_FLOAT, HAL_S32, HAL_U32 = 1, 2, 3, 4
HAL_IN, HAL_OUT, HAL_IO = 16, 32, 48


class _Component:
    def __init__(self, name: str, prefix: str | None = None, presets: dict[str, Any] | None = None) -> None:
        self.name, self.prefix = name, prefix or name
        self.presets = dict(presets or {})  # what nets/setp in the HAL file put on input pins
        self.pins: dict[str, tuple[int, int]] = {}
        self.values: dict[str, Any] = {}
        self.is_ready = self.closed = False

    def _live(self) -> None:
        if self.closed:
            raise RuntimeError("Invalid operation on closed HAL component")

    def newpin(self, name: str, type_: int, dir_: int) -> None:
        self._live()
        if name in self.pins:
            raise ValueError(f"Duplicate pin name '{name}'")
        if type_ not in (HAL_BIT, HAL_FLOAT, HAL_S32, HAL_U32) or dir_ not in (HAL_IN, HAL_OUT, HAL_IO):
            raise ValueError("Invalid pin type or direction")
        self.pins[name] = (type_, dir_)
        self.values[name] = 0.0 if type_ == HAL_FLOAT else False if type_ == HAL_BIT else 0
        if dir_ == HAL_IN and name in self.presets:
            self[name] = self.presets[name]

    def ready(self) -> None:
        self._live()
        self.is_ready = True

    def __getitem__(self, name: str) -> Any:
        self._live()
        if name not in self.pins:
            raise AttributeError(f"Pin '{name}' does not exist")
        return self.values[name]

    def __setitem__(self, name: str, value: Any) -> None:
        self._live()
        if name not in self.pins:
            raise AttributeError(f"Pin '{name}' does not exist")
        kind = self.pins[name][0]
        if kind == HAL_BIT:
            self.values[name] = bool(value)
        elif kind == HAL_FLOAT:
            try:
                self.values[name] = float(value)
            except (TypeError, ValueError):
                raise TypeError(f"Number expected, not {type(value).__name__}") from None
        else:
            n = int(value)
            lo, hi = (-(2**31), 2**31 - 1) if kind == HAL_S32 else (0, 2**32 - 1)
            if not lo <= n <= hi:
                raise OverflowError(f"Value {n} out of range")
            self.values[name] = n

    def getpins(self) -> dict[str, Any]:
        self._live()
        return dict(self.values)

    def exit(self) -> None:
        self.closed = True


class HalModule:
    """The parts of ``import hal`` a userspace component uses; ``components`` lists those made."""

    HAL_BIT, HAL_FLOAT, HAL_S32, HAL_U32 = HAL_BIT, HAL_FLOAT, HAL_S32, HAL_U32
    HAL_IN, HAL_OUT, HAL_IO = HAL_IN, HAL_OUT, HAL_IO

    def __init__(self, presets: dict[str, Any] | None = None) -> None:
        self.components: dict[str, _Component] = {}
        self.presets = presets or {}

    def component(self, name: str, prefix: str | None = None) -> _Component:
        if name in self.components and not self.components[name].closed:
            raise RuntimeError(f"component '{name}' exists")  # hal_init fails on a duplicate name
        comp = _Component(name, prefix, self.presets)
        self.components[name] = comp
        return comp


@dataclass
class Axis:
    """One axis' external-offset pins and motion's handling of them (external-offsets.adoc)."""

    offset_av_ratio: float = 0.2
    max_velocity: float = 100.0  # axis units / s
    min_limit: float = -math.inf
    max_limit: float = math.inf
    pos_cmd: float = 0.0  # axis.L.pos-cmd, the planned position
    enable: bool = False
    scale: float = 0.0
    counts: int = 0
    request: float = 0.0  # axis.L.eoffset-request
    eoffset: float = 0.0  # axis.L.eoffset
    limited: bool = False
    _prev_counts: int = field(default=0, repr=False)

    def machine_on(self) -> None:
        """The register and the offset are zeroed at each machine-on (the counts pin is not)."""
        self.request = self.eoffset = 0.0
        self._prev_counts = self.counts

    def servo(self, dt_s: float) -> None:
        """One servo period: accumulate counts x scale, move the offset toward the request within limits."""
        delta, self._prev_counts = self.counts - self._prev_counts, self.counts
        if self.enable and self.offset_av_ratio > 0:
            self.request += delta * self.scale
        step = self.offset_av_ratio * self.max_velocity * dt_s
        want = self.eoffset + max(-step, min(step, self.request - self.eoffset))
        lo, hi = self.min_limit - self.pos_cmd, self.max_limit - self.pos_cmd
        self.limited = not lo <= want <= hi
        self.eoffset = max(lo, min(hi, want))

    @property
    def position(self) -> float:
        """Where the axis is: the planned position plus the external offset."""
        return self.pos_cmd + self.eoffset


class Machine:
    """Motion with external offsets on some axes, the component's pins netted to them (a HAL file's ``net``)."""

    def __init__(self, comp: _Component, axes: dict[str, Axis], servo_s: float = 0.001) -> None:
        self.comp, self.axes, self.servo_s = comp, axes, servo_s
        self.on = False

    def machine(self, on: bool) -> None:
        if on and not self.on:
            for ax in self.axes.values():
                ax.machine_on()
        self.on = on

    def run(self, seconds: float) -> None:
        """Copy the nets (component outputs -> motion inputs, motion outputs -> component inputs), run the servo."""
        for letter, ax in self.axes.items():
            self.comp[f"{letter}.pos"] = ax.pos_cmd  # net ... axis.L.pos-cmd => driftlab-hal.L.pos
            ax.counts = int(self.comp[f"{letter}.counts"])  # net driftlab-hal.L.counts => axis.L.eoffset-counts
            ax.scale = float(self.comp[f"{letter}.scale"])
            ax.enable = bool(self.comp[f"{letter}.enable"])
        self.comp["machine-on"] = self.on  # net halui.machine.is-on => driftlab-hal.machine-on
        for _ in range(max(1, round(seconds / self.servo_s))):
            for ax in self.axes.values():
                ax.servo(self.servo_s)
