"""The virtual machine tool: the world that simulated instruments read.

``VirtualMachine(scenario)`` is a pure function of time given the scenario: the thermal network
(``driftlab.physics.thermal``) is solved once on a fixed grid from a two-day soak before t = 0 (so
slow structures start in their daily cycle) and cached; any instant is then evaluated exactly from
the grid point before it. Noise is a counter-based hash of (seed, stream, instant, channel or
measurement point), so a reading is the same whether asked once, repeatedly, out of order, or in
bulk by ``simulate_campaign`` - which uses the same array methods as the instrument simulators.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from driftlab.daq.sim import truth
from driftlab.daq.sim.scenario import ANGLE_TERMS, HiddenEffect, Scenario, Stage
from driftlab.daq.sim.sites import (
    CHANNELS,
    EXOGENOUS,
    FEED_REF_MM_MIN,
    ROOM_CHANNELS,
    SITE_INDEX,
    SITES,
    SOURCES,
    SPINDLE_REF_RPM,
)
from driftlab.errors import ValidationError
from driftlab.physics.thermal import ThermalNetwork, ThermalSolution, driven_node
from driftlab.vocabulary import AXES, TERMS

SOAK_S = 2 * 86400.0  # machine off before t = 0, room cycling
_EXTEND_S = 86400.0  # grid extension step beyond the scenario for long-running callers
_STREAM_TC, _STREAM_LASER, _STREAM_LOCAL = 1, 2, 3
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_HEAT = ("spindle", "feed", "combined")


def _mix(x: np.ndarray) -> np.ndarray:
    """Return the splitmix64 finaliser of uint64 array x (a bijective avalanche hash)."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def hash_normal(seed: int, stream: int, *keys: np.ndarray) -> np.ndarray:
    """Return standard-normal deviates that depend only on (seed, stream, keys...) - vectorised, order-free."""
    arrays = [np.asarray(k).astype(np.int64) for k in keys]
    shape = np.broadcast_shapes(*(k.shape for k in arrays))
    with np.errstate(over="ignore"):
        # The same integer steps as hashing the broadcast keys element by element, but each mix runs
        # on the smallest shape it depends on (a (N, 1) time key is mixed N times, not N x channels).
        h = _mix(np.full((1,) * len(shape), np.uint64(seed & 0xFFFFFFFFFFFFFFFF)) + np.uint64(stream) * _GOLD)
        for k in arrays:
            h = _mix(h ^ (k.reshape((1,) * (len(shape) - k.ndim) + k.shape).view(np.uint64) + _GOLD))
        h = np.broadcast_to(h, shape)
        h2 = _mix(h + _GOLD)
    u1 = ((h >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    u2 = ((h2 >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * math.pi * u2)  # Box-Muller


def _ms(t_s: np.ndarray) -> np.ndarray:
    """Return instants as integer milliseconds (the noise key of a reading)."""
    return np.rint(np.asarray(t_s, dtype=float) * 1000.0).astype(np.int64)


def build_network() -> ThermalNetwork:
    """Return the 50-site network of Table 5.1: room sites follow the hall, machine sites their local air."""
    n, m = len(SITES), len(SOURCES)
    tau = np.array([s.tau_min * 60.0 for s in SITES])
    gain = np.zeros((n, m))
    exo = np.zeros((n, len(EXOGENOUS)))
    coupling = np.zeros((n, n))
    i49, i50 = SITE_INDEX["T49"], SITE_INDEX["T50"]
    for i, s in enumerate(SITES):
        for src, g in s.gains.items():
            gain[i, SOURCES.index(src)] = g
        for e, w in s.exogenous.items():
            exo[i, EXOGENOUS.index(e)] = w
        if s.name not in ROOM_CHANNELS:  # local air: ceiling/floor mix by height (ch. 5.4, eq. 3.3)
            coupling[i, i49] = s.ceiling_weight
            coupling[i, i50] = 1.0 - s.ceiling_weight
    return ThermalNetwork(tuple(CHANNELS), tau, gain, exo, coupling)


@dataclass(frozen=True)
class _Plan:
    starts: np.ndarray
    ends: np.ndarray
    stages: tuple[Stage, ...]


class VirtualMachine:
    """The simulated five-axis machine: temperatures, machine state and work-space errors at any instant."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        stages = tuple(scenario.plan())
        self._plan = _Plan(np.array([s.start_s for s in stages]), np.array([s.end_s for s in stages]), stages)
        self.network = build_network()
        self._solution: ThermalSolution | None = None
        self._lags: dict[tuple[str, float], ThermalSolution] = {}
        self._t0_true: np.ndarray | None = None
        self._lock = threading.RLock()  # simulated instruments read the world from their server threads
        for eff in scenario.hidden:  # fail early, with the field named, on effects the truth cannot host
            if eff.kind == "thermal_lag":
                truth.lag_coefficient(eff)

    @property
    def stages(self) -> tuple[Stage, ...]:
        """Return the staged plan the machine runs (the scenario's stages or the default plan)."""
        return self._plan.stages

    # ------------------------------------------------------------------ drives
    def stage_index(self, t_s: np.ndarray) -> np.ndarray:
        """Return the index of the stage active at each instant (-1 = none: machine off)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if not len(self._plan.stages):
            return np.full(t.shape, -1)
        k = np.searchsorted(self._plan.starts, t, side="right") - 1
        ok = (k >= 0) & (t < self._plan.ends[np.clip(k, 0, None)])
        return np.where(ok, k, -1)

    def sources(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 10) heat-source levels (SOURCES order) held at each instant."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        k = self.stage_index(t)
        u = np.zeros((t.size, len(SOURCES)))
        for i, st in enumerate(self._plan.stages):
            rows = k == i
            if not rows.any() or st.heat_source == "off":
                continue
            u[rows, SOURCES.index("cabinet")] = 1.0  # the electronics panel is on whenever the machine is (ch. 5.2)
            feeding = st.axis if st.heat_source in ("feed", "combined") else None
            if st.heat_source in ("spindle", "combined"):
                u[rows, SOURCES.index("spindle")] = st.spindle_rpm / SPINDLE_REF_RPM
            if feeding is not None:
                u[rows, SOURCES.index(f"feed_{feeding.lower()}")] = st.feed_mm_min / FEED_REF_MM_MIN
            for ax in ("x", "y", "z"):  # linear motors hold position under servo when not feeding
                if feeding is None or feeding.lower() != ax:
                    u[rows, SOURCES.index(f"hold_{ax}")] = 1.0
        return u

    def hall(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 2) hall air at ceiling and floor: mean, ceiling/floor split, daily cycle."""
        r = self.scenario.room
        hour = self.scenario.start_hour_of_day + np.atleast_1d(np.asarray(t_s, dtype=float)) / 3600.0
        phase = 2.0 * math.pi * (hour - r.peak_hour) / 24.0
        ceiling = r.mean_degC + 0.5 * r.ceiling_floor_degC + r.daily_amplitude_degC * np.cos(phase)
        # the floor swings less and later than the ceiling
        floor = (
            r.mean_degC - 0.5 * r.ceiling_floor_degC + 0.6 * r.daily_amplitude_degC * np.cos(phase - 2 * math.pi / 24)
        )
        return np.stack([ceiling, floor], axis=1)

    def local_air(self, n: int) -> np.ndarray:
        """Return (n, 50) local air disturbances on the first n grid points (stationary OU per site)."""
        r = self.scenario.room
        phi = math.exp(-self.scenario.thermal_step_s / r.local_tau_s)
        # keyed by grid index from the soak start: extending the grid keeps the prefix unchanged
        eps = hash_normal(self.scenario.seed, _STREAM_LOCAL, np.arange(n)[:, None], np.arange(len(CHANNELS))[None, :])
        eps[1:] *= math.sqrt(1.0 - phi * phi)
        return r.local_sigma_degC * lfilter([1.0], [1.0, -phi], eps, axis=0)

    # ------------------------------------------------------------------ thermal state (cached)
    def advance_to(self, t_s: float) -> None:
        """Make sure the thermal solution covers [0, t_s] (extends the cached grid when needed)."""
        need = max(float(t_s), self.scenario.duration_s)
        sol = self._solution
        if sol is not None and sol.t_end_s >= need - 1e-9:
            return
        with self._lock:
            if self._solution is None or self._solution.t_end_s < need - 1e-9:
                self._extend(need)

    def _extend(self, need: float) -> None:
        """Solve the network on a grid from the soak start to at least ``need`` (replaces the cache)."""
        sol = self._solution
        h = self.scenario.thermal_step_s
        end = need if sol is None else max(need, sol.t_end_s + _EXTEND_S)
        n = int(math.ceil((end + SOAK_S) / h - 1e-9)) + 2  # one step past: t = end is never the last point
        grid = -SOAK_S + h * np.arange(n)
        start = np.full(len(CHANNELS), self.scenario.room.mean_degC)
        solution = self.network.simulate(
            -SOAK_S, h, self.sources(grid), self.hall(grid), y0=start, local=self.local_air(n)
        )
        self._lags = {}
        self._t0_true = solution.at(np.array([0.0]))[0]
        self._solution = solution

    def _sol(self, t: np.ndarray) -> ThermalSolution:
        if t.size:
            if t.min() < -SOAK_S:
                raise ValidationError(f"virtual machine time {float(t.min())} s is before the simulated soak")
            self.advance_to(float(t.max()))
        else:
            self.advance_to(0.0)
        assert self._solution is not None
        return self._solution

    def true_temperatures_array(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 50) true structure temperatures (degC) at instants t (s since start)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        return self._sol(t).at(t)

    def true_dT_array(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 50) true temperature changes since t = 0."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        temps = self.true_temperatures_array(t)
        assert self._t0_true is not None
        return temps - self._t0_true

    def lagged_dT(self, channel: str, tau_s: float, t_s: np.ndarray) -> np.ndarray:
        """Return the first-order lag (tau) of a channel's true temperature, as a change since t = 0."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        sol = self._sol(t)
        key = (channel, float(tau_s))
        lags = self._lags
        lag = lags.get(key)
        if lag is None or lag.t_end_s < sol.t_end_s:
            col = sol.y[:, SITE_INDEX[channel]]
            lag = driven_node(col, sol.h_s, tau_s, t0_s=sol.t0_s)
            lags[key] = lag
        return lag.at(t)[:, 0] - lag.at(np.array([0.0]))[0, 0]

    def readings_array(self, t_s: np.ndarray) -> np.ndarray:
        """Return (N, 50) thermocouple readings: truth + scan noise, with sensor faults applied (NaN = open)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        true = self.true_temperatures_array(t)
        sigma = self.scenario.noise.thermocouple_degC
        ch = np.arange(len(CHANNELS))
        noise = hash_normal(self.scenario.seed, _STREAM_TC, _ms(t)[:, None], ch[None, :])
        out = true + sigma * noise
        for eff in self.scenario.hidden:
            if eff.kind == "sensor_fault":
                self._apply_fault(eff, t, true, out)
        return out

    def _apply_fault(self, eff: HiddenEffect, t: np.ndarray, true: np.ndarray, out: np.ndarray) -> None:
        """Overwrite faulted channels from start_s on (ch. 6.6: dangling in the air, or an open lead)."""
        t0 = float(eff.params["start_s"])
        rows = t >= t0
        if not rows.any():
            return
        if eff.params["mode"] == "open":
            out[np.ix_(rows, np.array([SITE_INDEX[c] for c in eff.channels]))] = float(
                eff.params.get("rail_degC", math.nan)
            )
            return
        tau = float(eff.params.get("tau_s", 300.0))
        at0 = self.true_temperatures_array(np.array([t0]))[0]
        i49, i50 = SITE_INDEX["T49"], SITE_INDEX["T50"]
        for c in eff.channels:
            i = SITE_INDEX[c]
            w = SITES[i].ceiling_weight
            air = w * true[rows, i49] + (1 - w) * true[rows, i50]
            air0 = w * at0[i49] + (1 - w) * at0[i50]
            # a detached junction becomes an air thermometer: it relaxes from the structure to the air
            decay = np.exp(-(t[rows] - t0) / tau)
            noise = out[rows, i] - true[rows, i]
            out[rows, i] = air + (at0[i] - air0) * decay + noise

    def state_array(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        """Return the machine state log at instants t: spindle_rpm, feed_mm_min, x, y, z (mm), a, b (deg)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        k = self.stage_index(t)
        out = {c: np.zeros(t.size) for c in ("spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")}
        for i, st in enumerate(self._plan.stages):
            rows = k == i
            if not rows.any() or st.heat_source not in _HEAT:
                continue
            if st.heat_source in ("spindle", "combined"):
                out["spindle_rpm"][rows] = st.spindle_rpm
            if st.heat_source in ("feed", "combined") and st.axis is not None:
                out["feed_mm_min"][rows] = st.feed_mm_min
                lo, hi = truth.AXIS_RANGE[st.axis]
                span = hi - lo
                travel = (t[rows] - st.start_s) * st.feed_mm_min / 60.0  # back-and-forth over the travel
                phase = np.mod(travel, 2 * span)
                out[st.axis.lower()][rows] = lo + np.where(phase < span, phase, 2 * span - phase)
        return out

    # ------------------------------------------------------------------ work-space errors
    def true_errors_array(self, t_s: np.ndarray, axis: str, position: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return (N, 6) true work-space errors (base + hidden effects) moving ``axis``, others at home."""
        if axis not in AXES:
            raise ValidationError(f"unknown axis {axis!r}: expected one of {AXES}")
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        pos = np.broadcast_to(np.asarray(position, dtype=float), t.shape)
        d = np.broadcast_to(np.asarray(direction, dtype=float), t.shape)
        dT = self.true_dT_array(t)
        w = truth.base_workspace(axis, pos, dT)
        for eff in self.scenario.hidden:
            if eff.axis != axis or eff.kind == "sensor_fault":
                continue
            ch_dT = dT[:, SITE_INDEX[eff.channels[0]]] if eff.channels else None
            lag = self.lagged_dT(eff.channels[0], float(eff.params["tau_s"]), t) if eff.kind == "thermal_lag" else None
            w[:, TERMS.index(eff.term)] += truth.hidden_delta(eff, t, pos, d, ch_dT, lag)
        return w

    def measure_errors_array(
        self, t_s: np.ndarray, axis: str, position: np.ndarray, direction: np.ndarray
    ) -> np.ndarray:
        """Return (N, 6) measured work-space errors: truth plus laser noise (ch. 5.5), per term."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        pos = np.broadcast_to(np.asarray(position, dtype=float), t.shape)
        d = np.broadcast_to(np.asarray(direction, dtype=float), t.shape)
        w = self.true_errors_array(t, axis, pos, d)
        sigma = np.array(
            [self.scenario.noise.angle_rad if term in ANGLE_TERMS else self.scenario.noise.length_mm for term in TERMS]
        )
        keys = (
            _ms(t)[:, None],
            np.full((t.size, 1), AXES.index(axis)),
            np.arange(6)[None, :],
            np.rint(pos * 1e6).astype(np.int64)[:, None],
            (d > 0).astype(np.int64)[:, None],
        )
        return w + sigma * hash_normal(self.scenario.seed, _STREAM_LASER, *keys)

    # ------------------------------------------------------------------ scalar instrument API
    @staticmethod
    def _check_t(t_s: float) -> None:
        if not math.isfinite(t_s) or t_s < 0:
            raise ValidationError(f"virtual machine time must be >= 0 s since the campaign start, got {t_s!r}")

    def temperatures(self, t_s: float) -> dict[str, float]:
        """Return the thermocouple readings at t (noise and faults applied; NaN = open lead)."""
        self._check_t(t_s)
        row = self.readings_array(np.array([t_s]))[0]
        return {c: float(v) for c, v in zip(CHANNELS, row)}

    def temperatures_block(self, t_s: np.ndarray, channels: Sequence[str] | None = None) -> np.ndarray:
        """Return (N, C) thermocouple readings at N instants, each row exactly ``temperatures(t)`` (NaN = open).

        One vectorised pass over the instants (a buffered card's block of scans); columns follow
        ``channels`` (default: every site in Table 5.1 order), NaN for a name the machine does not have.
        """
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if t.size and not (np.isfinite(t).all() and t.min() >= 0):
            bad = t[~(np.isfinite(t) & (t >= 0))][0]
            raise ValidationError(f"virtual machine time must be >= 0 s since the campaign start, got {bad!r}")
        out = self.readings_array(t)
        if channels is None:
            return out
        idx = np.array([SITE_INDEX.get(c, -1) for c in channels], dtype=np.int64)
        cols = out[:, np.clip(idx, 0, None)] if len(idx) else np.empty((t.size, 0))
        if (idx < 0).any():
            cols[:, idx < 0] = math.nan
        return cols

    def true_temperatures(self, t_s: float) -> dict[str, float]:
        """Return the true structure temperatures at t."""
        self._check_t(t_s)
        row = self.true_temperatures_array(np.array([t_s]))[0]
        return {c: float(v) for c, v in zip(CHANNELS, row)}

    def state(self, t_s: float) -> dict[str, float | str | None]:
        """Return the machine state at t: stage, heat source, spindle rpm, feed and axis positions."""
        self._check_t(t_s)
        k = int(self.stage_index(np.array([t_s]))[0])
        st = self._plan.stages[k] if k >= 0 else None
        out: dict[str, float | str | None] = {
            "stage": st.name if st else None,
            "heat_source": st.heat_source if st else "off",
        }
        out.update({c: float(v[0]) for c, v in self.state_array(np.array([t_s])).items()})
        return out

    def measure_error(self, t_s: float, axis: str, position: float, direction: int) -> dict[str, float]:
        """Return the six measured work-space error terms at t for ``axis`` at ``position`` approached from
        ``direction``."""
        self._check_t(t_s)
        if direction not in (1, -1):
            raise ValidationError(f"direction must be +1 or -1, got {direction!r}")
        row = self.measure_errors_array(np.array([t_s]), axis, np.array([position]), np.array([direction]))[0]
        return {term: float(v) for term, v in zip(TERMS, row)}
