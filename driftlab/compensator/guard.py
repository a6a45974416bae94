"""What the compensator refuses to send: targets outside the travel, implausible corrections, extrapolation.

``Guard`` holds a machine envelope (``models.envelope``: the axes' travel, the largest correction
per axis, the extrapolation margin) and the temperature range each model input was fitted on. The
first pass over a program (``compensate.scan_program``) gives it every piece: each block's target
and its corrected target must stay inside the travel, and each block's correction, solved at its
target with the temperatures the second pass will use, must stay under the largest plausible one.
The second pass checks every point it sends again (what was sent, after subdivision and
quantisation), so nothing outside the envelope leaves even when the temperatures change during a
streamed run. Each refusal is one line ``PROGRAM:LINE: what, the limit and the value``.

Temperatures beyond a channel's fitted range by more than the margin are refused unless extrapolation
is allowed; then each such channel is logged once and listed in ``Guard.extrapolated``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import Any, Protocol

import numpy as np

from driftlab.compensator.gcode import ROTARY, Program
from driftlab.errors import ValidationError
from driftlab.models.envelope import Envelope, merge
from driftlab.vocabulary import AXES

log = logging.getLogger(__name__)


def _unit(k: int) -> str:
    """Return the unit of axis ``k`` as written in programs."""
    return "deg" if ROTARY[k] else "mm"


def _g(x: float) -> str:
    """Return a number for a message: short, exact enough to recognise."""
    return f"{x:.6g}"


def _refuse_first(program: Program, block: np.ndarray, bad: np.ndarray, what: Callable[[int, int], str]) -> None:
    """Refuse the first (point, axis) of ``bad`` (N, 5), if any: ``PROGRAM:LINE: what(point, axis); program not
    accepted``, the line that of the point's block (``block`` (N,))."""
    if bad.any():
        i, k = _first(bad)
        line = program.line_number(block[i])
        raise ValidationError(f"{program.name}:{line}: {what(i, k)}; program not accepted")


class Enveloped(Protocol):
    """What a guard reads of a model (``compensate.ErrorModel``): its envelope and fitted temperature ranges."""

    @property
    def envelope(self) -> Envelope | None:
        """The model document's machine envelope, if it has one."""

    @property
    def ranges(self) -> Mapping[str, tuple[float, float]]:
        """The temperature range (degC) each input was fitted on."""


class Guard:
    """The envelope checks of one run (see module docstring)."""

    def __init__(
        self,
        envelope: Envelope | None,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        *,
        allow_extrapolation: bool = False,
    ) -> None:
        self.envelope = envelope
        lo, hi, mc = envelope.limits() if envelope is not None else ([-math.inf] * 5, [math.inf] * 5, [math.inf] * 5)
        self.lo = np.array(lo, dtype=float)
        self.hi = np.array(hi, dtype=float)
        self.max_correction = np.array(mc, dtype=float)
        self.margin_degC = envelope.extrapolation_margin_degC if envelope is not None else math.inf
        self.ranges = dict(ranges or {})
        self.allow_extrapolation = allow_extrapolation
        #: channel -> the furthest reading beyond its range and the range (extrapolation allowed)
        self.extrapolated: dict[str, dict[str, float]] = {}

    @classmethod
    def for_model(
        cls, model: Enveloped, envelope: Envelope | None = None, *, allow_extrapolation: bool = False
    ) -> Guard:
        """Return the guard of a model: its own envelope merged with ``envelope`` (which wins), its fitted ranges."""
        return cls(merge(model.envelope, envelope), model.ranges, allow_extrapolation=allow_extrapolation)

    @property
    def limits_travel(self) -> bool:
        """Return True when some axis has a stated travel."""
        return bool(np.isfinite(self.lo).any() or np.isfinite(self.hi).any())

    # -- positions and corrections

    def check_positions(
        self, program: Program, block: np.ndarray, pose: np.ndarray, what: str, slack: np.ndarray | None = None
    ) -> None:
        """Refuse the first pose (N, 5) in mm / deg outside the travel; ``block`` (N,) names its line.

        ``slack`` (5,): how far the pose sent may still move from ``pose`` (the quantiser's band, when
        ``pose`` is a correction before quantisation): a pose that close to the travel's ends is refused too.
        """
        if not self.limits_travel or pose.shape[0] == 0:
            return
        _refuse_first(
            program,
            block,
            (pose < self.lo - 1e-9) | (pose > self.hi + 1e-9),
            lambda i, k: (
                f"{what} {AXES[k]} {_g(pose[i, k])} {_unit(k)} is outside the travel "
                f"{_g(self.lo[k])}..{_g(self.hi[k])} {_unit(k)}"
            ),
        )
        if slack is None:
            return
        _refuse_first(
            program,
            block,
            (pose - slack < self.lo - 1e-9) | (pose + slack > self.hi + 1e-9),
            lambda i, k: (
                f"{what} {AXES[k]} {_g(pose[i, k])} {_unit(k)} is within the positioning step "
                f"({_g(slack[k])} {_unit(k)}) of the travel {_g(self.lo[k])}..{_g(self.hi[k])} {_unit(k)}: "
                f"the step sent could leave it"
            ),
        )

    def check_corrections(self, program: Program, block: np.ndarray, correction: np.ndarray) -> None:
        """Refuse the first correction (N, 5) in mm / deg larger than the envelope's largest plausible one."""
        if correction.shape[0] == 0 or not np.isfinite(self.max_correction).any():
            return
        _refuse_first(
            program,
            block,
            ~(np.abs(correction) <= self.max_correction + 1e-12),
            lambda i, k: (
                f"correction of {AXES[k]} {_g(correction[i, k])} {_unit(k)} exceeds the "
                f"largest plausible {_g(self.max_correction[k])} {_unit(k)} (machine envelope)"
            ),
        )

    def check_sent(self, program: Program, block: np.ndarray, nominal_int: np.ndarray, sent_int: np.ndarray) -> None:
        """Refuse points about to be written or sent: their correction, then their commanded pose."""
        self.check_corrections(program, block, (sent_int - nominal_int) * program.scale)
        self.check_positions(program, block, sent_int * program.scale, "corrected target")

    # -- temperatures

    def check_temperatures(self, temperatures: Mapping[str, float] | Any, where: str = "temperatures") -> None:
        """Refuse readings further than the margin outside their channel's fitted range (or note them, allowed)."""
        if not self.ranges or not math.isfinite(self.margin_degC):
            return
        for channel, (lo, hi) in self.ranges.items():
            if channel not in temperatures:
                continue
            values = np.asarray(temperatures[channel], dtype=float).ravel()
            values = values[np.isfinite(values)]
            if values.shape[0] == 0:
                continue
            top, bottom = float(values.max()), float(values.min())
            above, below = top - hi, lo - bottom
            worst, value = (above, top) if above >= below else (below, bottom)
            if worst <= self.margin_degC:
                continue
            side = "above" if above >= below else "below"
            text = (
                f"{where}: {channel} {_g(value)} degC is {_g(worst)} degC {side} the range the model was fitted on "
                f"({_g(lo)}..{_g(hi)} degC, margin {_g(self.margin_degC)} degC)"
            )
            if not self.allow_extrapolation:
                raise ValidationError(f"{text}; refused (--allow-extrapolation to compensate anyway)")
            seen = self.extrapolated.get(channel)
            if seen is None:
                log.warning("extrapolating: %s", text)
            if seen is None or worst > seen["beyond_degC"]:
                self.extrapolated[channel] = {"value_degC": value, "beyond_degC": worst, "min": lo, "max": hi}

    def report(self) -> dict[str, dict[str, float]]:
        """Return what the run extrapolated (empty when nothing was)."""
        return {c: {k: round(v, 6) for k, v in d.items()} for c, d in self.extrapolated.items()}


def _first(bad: np.ndarray) -> tuple[int, int]:
    """Return (row, column) of the first True of a 2-D mask, row first."""
    i = int(np.argmax(bad.any(axis=1)))
    return i, int(np.argmax(bad[i]))
