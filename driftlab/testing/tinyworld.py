"""A small deterministic world for unit tests of the simulated instruments.

It satisfies the simulated instruments' ``World`` protocol (``daq.sim.instruments``) with smooth
closed forms instead of the virtual machine's thermal network, so driver and protocol tests run
in milliseconds and their expected values can be written down by hand.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from driftlab.vocabulary import AXES, TRANSLATIONS


class TinyWorld:
    """A small deterministic world for unit tests: smooth warm-up, a reversal, open channels."""

    def __init__(
        self,
        channels: int = 8,
        tau_s: float = 1800.0,
        open_channels: Mapping[str, float] | None = None,
        reversal_mm: float = 0.002,
    ) -> None:
        self.names = [f"T{k}" for k in range(1, channels + 1)]
        self.tau_s = tau_s
        self.open_channels = dict(open_channels or {})  # channel -> time it broke
        self.reversal_mm = reversal_mm
        self.positions = {a: 0.0 for a in AXES}

    def warmup(self, t_s: float) -> float:
        """Return the 0..1 warm-up fraction at ``t_s``."""
        return 1.0 - math.exp(-max(t_s, 0.0) / self.tau_s)

    def true_temperatures(self, t_s: float) -> dict[str, float]:
        """Return the noiseless temperatures (degC)."""
        w = self.warmup(t_s)
        return {name: 20.0 + 0.25 * k + (1.0 + 0.5 * k) * w for k, name in enumerate(self.names)}

    def temperatures(self, t_s: float) -> dict[str, float]:
        """Return temperatures (degC) with broken channels as NaN."""
        temps = self.true_temperatures(t_s)
        for name, t_break in self.open_channels.items():
            if t_s >= t_break:
                temps[name] = float("nan")
        return temps

    def state(self, t_s: float) -> dict[str, float]:
        """Return a machine state (idle spindle, positions as set on the world)."""
        return {"spindle_rpm": 0.0, "feed_mm_min": 0.0, **{a.lower(): p for a, p in self.positions.items()}}

    def measure_error(self, t_s: float, axis: str, position: float, direction: int) -> dict[str, float]:
        """Return smooth, position- and time-dependent error terms plus a reversal on the axial term."""
        w = self.warmup(t_s)
        k = AXES.index(axis) + 1
        s = position / 500.0
        err = {
            "dx": (0.004 * s + 0.001 * k) * w,
            "dy": (-0.003 * s * s + 0.0005 * k) * w,
            "dz": (0.002 * s - 0.0008) * w * k,
            "alpha": (4e-6 * s + 1e-6 * k) * w,
            "beta": (-3e-6 * s + 2e-6) * w,
            "gamma": (2e-6 * s * s - 1e-6 * k) * w,
        }
        axial = {"X": "dx", "Y": "dy", "Z": "dz", "A": "alpha", "B": "beta"}[axis]
        # backlash: half the span either side; rotary axes see it over a 500 mm lever (rad)
        span = self.reversal_mm if axial in TRANSLATIONS else self.reversal_mm / 500.0
        err[axial] += 0.5 * direction * span
        return err
