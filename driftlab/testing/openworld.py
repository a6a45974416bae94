"""An open-world generator of campaign bundles for the diagnosis tests (tests only: nothing in production imports it).

The closed-world fixtures (``tests/effects_generator.py``) build the errors in the same form as
the standard model: a cubic in position plus dT of the model channels, effects added per
(axis, term). Passing tests on such data says little about a real machine. Here:

- **The base field is outside the model's span.** Each deforming body's temperature is a
  weighted mix of its sensor sites (a distributed field), lagging them a little (a few % of
  its change follows a lag of tens of minutes) plus a small component no sensor reads (heat
  from a source reaching the body by another path). ``Case.beyond_span`` records, per
  (axis, term), the RMS of the noise-free base error that the standard model fitted on the
  noise-free sensors cannot represent.
- **Effects are planted in the element errors** of the HTM chain (a joint's backlash, a
  screw's growth, a link's lag ...) and observed through it with
  ``kinematics.workspace_error`` (eq. 4.12), as the virtual machine builds its truth
  (``daq.sim.truth``): a reversal of the A joint is seen through the A rotation. The expected
  catalogue parameter on the observed (axis, term) is the least-squares coefficient of the
  observed change on the catalogue's regressor (``Case.expected``), not the planted number.
- **The readings are real-data-like**: AR(1) laser noise (rho 0.4-0.8 along each series in
  measuring order), single-scan glitches in temperatures and errors (EMI on the card),
  logger gaps (scans missing for 15-50 min), a laser gap, scattered missing readings, and a
  machine-state log (spindle rpm, feed) in conditions.csv.
- **Not shaped like ours** (issue 22), on request: other channel names (``channel_names``), other
  scan rates (``scan_s``) or irregular scan times (``irregular``), sweeps of all axes interleaved
  point by point (``interleave``), stages in random order and lengths (``random_stages``), and the
  kinds outside the closed-world catalogue: a thermocouple whose calibration drifts
  (``sensor_drift``, readings only), a re-zeroed measuring line (``datum_shift``: every reading
  of the term steps at one moment), a heat input no thermocouple reads (``unsensed_source``: a
  first-order lag of a heat source's input, not of its on/off schedule), and a reversal that
  opens as a temperature rises (``direction_thermal``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import Bundle, _as_meta
from driftlab.daq.sim import truth
from driftlab.metrics import rmse
from driftlab.physics import kinematics as kin
from driftlab.physics.lag import first_order_lag_even
from driftlab.physics.thermal import ALPHA_C

#: sensor sites: name -> (structure, heat sources it sees: spindle, x motor, y motor)
SITES: dict[str, tuple[str, tuple[float, float, float]]] = {
    "T1": ("spindle_arm_upper", (6.0, 0.0, 0.5)),
    "T2": ("spindle_arm_upper", (5.0, 0.3, 0.8)),
    "T3": ("spindle_arm_lower", (3.5, 0.0, 0.4)),
    "T4": ("spindle_arm_lower", (3.0, 0.2, 0.6)),
    "T5": ("column", (1.2, 0.3, 2.0)),
    "T6": ("column", (0.8, 0.5, 2.5)),
    "T7": ("x_screw", (0.2, 5.0, 0.2)),
    "T8": ("x_screw", (0.1, 4.0, 0.3)),
    "T9": ("y_motor", (0.3, 0.4, 6.0)),
    "T10": ("table", (0.6, 1.5, 0.8)),
    "T11": ("room", (0.0, 0.0, 0.0)),
    "T12": ("room", (0.0, 0.0, 0.0)),
}
ROOM = ("T11", "T12")
#: bodies that deform: their temperature is a mix of sensor sites (weights sum to 1)
BODIES: dict[str, dict[str, float]] = {
    "arm_upper": {"T1": 0.6, "T2": 0.4},
    "arm_lower": {"T3": 0.5, "T4": 0.5},
    "column": {"T5": 0.55, "T6": 0.45},
    "x_screw": {"T7": 0.7, "T8": 0.3},
    "table": {"T10": 1.0},
}
L_ARM, H_ARM, L_COLUMN, L_SCREW, H_TABLE = 400.0, 200.0, 1200.0, 150.0, 200.0
#: (element, parameter, coefficient per degC, body or gradient): base thermal element errors
#: (eqs. 3.1-3.5 with the magnitudes of Table 6.3, as the virtual machine's THERMAL_TERMS)
BASE_TERMS: tuple[tuple[str, str, float, str], ...] = (
    ("T1", "alpha", ALPHA_C * L_ARM / H_ARM, "arm_gradient"),  # eq. 3.4
    ("T1", "dz", ALPHA_C * L_ARM**2 / (2 * H_ARM), "arm_gradient"),  # eq. 3.5
    ("T1", "dy", ALPHA_C * L_ARM, "arm_upper"),  # eq. 3.1
    ("T2", "dz", ALPHA_C * L_COLUMN, "column"),  # eq. 3.3
    ("phi_x", "dx", ALPHA_C * L_SCREW, "x_screw"),  # eq. 3.2, fixed part of the screw
    ("T4", "dz", ALPHA_C * H_TABLE, "table"),  # eq. 3.1
)
#: the user's sensor selection: every site that feeds a body, and a room channel
MODEL_CHANNELS = ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T10", "T11"]


@dataclass
class OpenPlanted:
    """One effect planted in an element error, and the (axis, term) where the catalogue should name it.

    ``element``/``param``: where in the chain it is planted; ``kind``, ``axis``, ``term``,
    ``channels`` and ``params`` as the catalogue states it (``params`` holds the planted
    element-level numbers; ``Case.expected`` the ones observed through the chain).
    """

    kind: str
    axis: str
    term: str
    element: str = ""
    param: str = ""
    channels: list[str] = field(default_factory=list)
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class Case:
    """An open-world bundle, what was planted, and what the catalogue should report."""

    bundle: Bundle
    planted: list[OpenPlanted]
    expected: list[dict[str, Any]]  # per planted effect: the catalogue params observed through the chain
    noise: dict[str, float]
    rho: float
    beyond_span: dict[str, float]  # (axis/term) -> RMS of the base error outside the model's span
    signal_rms: list[float]  # per planted effect: RMS of its observed contribution
    beyond_model_rms: list[float]  # per planted effect: the part of it no standard model can absorb


def _ar1(n: int, rho: float, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Return AR(1) noise with marginal standard deviation ``sigma`` and lag-1 correlation ``rho``."""
    e = rng.normal(0.0, sigma * np.sqrt(1.0 - rho * rho), n)
    e[0] = rng.normal(0.0, sigma)
    # lazy: scipy.signal adds 1.3 s to `import driftlab.testing.openworld` (measured)
    from scipy.signal import lfilter

    zi = np.array([rho * e[0]])
    out, _ = lfilter([1.0], [1.0, -rho], e[1:], zi=zi)
    return np.concatenate([[e[0]], out])


@dataclass(frozen=True)
class OpenWorld:
    """How an open-world bundle is drawn (``openworld_case``): the campaign, the readings and the machine's shape.

    ``seed``: every random draw; ``hours``, ``scan_s``, ``sweep_s``, ``points``: the campaign; ``keep``: the
    (axis, term)s measured (default: those planted, else Z/dz); ``rho``: the AR(1) laser noise's lag-1
    correlation (default drawn in 0.4-0.8), ``noise_mm``/``noise_rad`` its RMS; ``glitches``, ``gaps``: EMI
    spikes and logger/laser gaps; ``lag_fraction``: the share of each body's change that lags its sites
    (default drawn in 0.01-0.03); ``unmeasured_degC``: heat no sensor reads; issue 22's shapes:
    ``channel_names``, ``irregular`` scans, ``interleave``d sweeps, ``random_stages``.
    """

    seed: int = 0
    hours: float = 30.0
    scan_s: float = 120.0
    sweep_s: float = 1200.0
    points: int = 6
    keep: list[tuple[str, str]] | None = None
    rho: float | None = None
    noise_mm: float = 5e-4
    noise_rad: float = 5e-7
    glitches: bool = True
    gaps: bool = True
    lag_fraction: float | None = None
    unmeasured_degC: float = 0.1
    channel_names: dict[str, str] | None = None
    irregular: bool = False
    interleave: bool = False
    random_stages: bool = False


@dataclass
class _Plan:
    """The staged heat-source plan of a campaign (ch. 5.2): the sources' inputs, spindle speed, feed, stages."""

    sources: list[str]
    u: np.ndarray  # (n, sources) heat input of each source
    rpm: np.ndarray
    feed: np.ndarray
    stages: list[dict[str, Any]]


def _stage_plan(rng: np.random.Generator, t: np.ndarray, planted: list[OpenPlanted], random_stages: bool) -> _Plan:
    """Return the staged single-heat-source plan: spindle at several speeds, X and Y motors, rests.

    Any heat source that only an unsensed_source effect names (a coolant pump) gets stages of its own that
    heat no sensor site.
    """
    n = t.size
    extra = sorted(
        {
            str(p.params["source"])
            for p in planted
            if p.kind == "unsensed_source" and str(p.params["source"]) not in ("spindle", "x_motor", "y_motor")
        }
    )
    sources = ["spindle", "x_motor", "y_motor", *extra]
    u = np.zeros((n, len(sources)))
    rpm = np.zeros(n)
    feed = np.zeros(n)
    stages: list[dict[str, Any]] = []
    cursor, k = 0.5 * 3600.0, 0
    while cursor < t[-1]:
        src = int(rng.integers(0, len(sources))) if random_stages else k % len(sources)
        if random_stages:
            on = round(rng.uniform(1.0, 6.0) * 60) * 60.0
            off = round(rng.uniform(0.5, 4.0) * 60) * 60.0
        else:
            on = round(rng.uniform(3, 4.5) * 60) * 60.0
            off = round(rng.uniform(1.5, 3) * 60) * 60.0
        m = (t >= cursor) & (t < cursor + on)
        if src == 0:
            speed = float(rng.choice([2000.0, 4000.0, 6000.0, 8000.0]))
            rpm[m] = speed
            u[m, 0] = (speed / 8000.0) ** 1.5  # bearing and motor losses grow faster than the speed
        elif src < 3:
            level = rng.uniform(0.6, 1.0)
            u[m, src] = level
            feed[m] = 2000.0 * level
        else:
            u[m, src] = rng.uniform(0.6, 1.0)
        top_rpm = float(rpm[m].max()) if m.any() else 0.0
        top_feed = float(feed[m].max()) if m.any() else 0.0
        ends = (min(cursor + on, t[-1]), min(cursor + on + off, t[-1]))
        stages += _stage_pair(k, sources[src], src, cursor, ends, top_rpm, top_feed)
        cursor += on + off
        k += 1
    return _Plan(sources, u, rpm, feed, stages)


def _stage_pair(
    k: int, source: str, src: int, start: float, ends: tuple[float, float], rpm: float, feed: float
) -> list[dict[str, Any]]:
    """Return a heating stage from ``start`` to ``ends[0]`` and the rest to ``ends[1]`` (campaign.json's stages)."""
    return [
        {
            "name": f"{source}-{k}",
            "start_s": start,
            "end_s": ends[0],
            "heat_source": source,
            "axis": "XYZ"[src] if src < 3 else "X",
            "spindle_rpm": rpm,
            "feed_mm_min": feed,
        },
        {
            "name": f"rest-{k}",
            "start_s": ends[0],
            "end_s": ends[1],
            "heat_source": "none",
            "axis": "X",
            "spindle_rpm": 0.0,
            "feed_mm_min": 0.0,
        },
    ]


def _site_temperatures(
    rng: np.random.Generator, t: np.ndarray, u: np.ndarray, scan_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return the room air and every sensor site's true temperature (a lag of the air and its heat sources)."""
    phase = rng.uniform(0, 2 * np.pi)
    room_air = 20.0 + 0.8 * np.sin(2 * np.pi * t / 86400 + phase) + 0.2 * np.sin(2 * np.pi * t / 15000 + 1.0)
    names = list(SITES)
    true = np.empty((t.size, len(names)))
    for j, ch in enumerate(names):
        struct, gains = SITES[ch]
        if struct == "room":
            true[:, j] = room_air + (0.15 if ch == "T12" else -0.15)
            continue
        g = np.array(gains) * rng.uniform(0.8, 1.2, 3)
        tau = rng.uniform(20, 120) * 60
        true[:, j] = first_order_lag_even(room_air + u[:, :3] @ g, scan_s, tau) + rng.uniform(-1, 1)
    return room_air, true


def _bodies(rng: np.random.Generator, dTs: np.ndarray, u: np.ndarray, w: OpenWorld) -> dict[str, np.ndarray]:
    """Return the deforming bodies' temperatures: a distributed field - a mix of sites, lagging them a little,
    plus heat no sensor reads."""
    names = list(SITES)
    frac = float(rng.uniform(0.01, 0.03)) if w.lag_fraction is None else float(w.lag_fraction)
    hidden_heat = first_order_lag_even(u[:, :3] @ rng.uniform(0.3, 1.0, 3), w.scan_s, rng.uniform(2, 5) * 3600)
    hidden_heat = w.unmeasured_degC * hidden_heat / max(float(np.abs(hidden_heat).max()), 1e-12)
    body: dict[str, np.ndarray] = {}
    for b, wts in BODIES.items():
        mix = cast(np.ndarray, sum(wk * dTs[:, names.index(c)] for c, wk in wts.items()))
        slow = first_order_lag_even(mix, w.scan_s, rng.uniform(1, 3) * 3600)
        body[b] = (1 - frac) * mix + frac * slow + hidden_heat * rng.uniform(0.5, 1.0)
    body["arm_gradient"] = body["arm_upper"] - body["arm_lower"]
    return body


def _readings(
    rng: np.random.Generator, true: np.ndarray, t: np.ndarray, room_air: np.ndarray, planted: list[OpenPlanted]
) -> np.ndarray:
    """Return the thermocouple readings: noise, drifting calibrations and faults (the bodies keep their truth)."""
    names = list(SITES)
    readings = true + rng.normal(0, 0.01, true.shape)
    for p in planted:  # a drifting calibration changes the readings only: appendix B
        if p.kind == "sensor_drift":
            j = names.index(p.channels[0])
            t0 = float(p.params["start_s"])
            readings[:, j] += float(p.params["rate_degC_per_day"]) * np.maximum(t - t0, 0.0) / 86400.0
    for p in planted:  # faults change the readings only: the bodies keep their true temperatures
        if p.kind != "sensor_fault":
            continue
        j = names.index(p.channels[0])
        after = t >= float(p.params["start_s"])
        if p.params.get("mode", "detached") == "open":
            readings[after, j] = np.nan
        else:
            k0 = int(np.argmax(after))
            target = room_air + 0.5
            dec = np.exp(-(t[after] - t[k0]) / 600.0)
            readings[after, j] = (
                target[after] + (readings[k0, j] - target[after]) * dec + rng.normal(0, 0.01, int(after.sum()))
            )
    return readings


def _sweeps(rng: np.random.Generator, t: np.ndarray, axes: list[str], w: OpenWorld) -> pd.DataFrame:
    """Return the laser sweeps: every axis, positions up then down, 10 s per point; a 1.5 h laser gap."""
    sweep_t0 = np.arange(0.0, t[-1] - 2 * w.points * 10.0 * len(axes) - 10.0, w.sweep_s)
    if w.gaps:
        g0 = rng.uniform(0.35, 0.55) * t[-1]
        sweep_t0 = sweep_t0[(sweep_t0 < g0) | (sweep_t0 > g0 + 5400.0)]
    rows = []
    for s0 in sweep_t0:
        i = 0
        if w.interleave:  # every axis at its k-th point before any axis moves on (a combined test)
            grids = {a: np.linspace(*truth.AXIS_RANGE[a], w.points) for a in axes}
            for d in (1, -1):
                for kpt in range(w.points):
                    for axis in axes:
                        g = grids[axis] if d > 0 else grids[axis][::-1]
                        rows.append((s0 + 10.0 * i, axis, float(g[kpt]), d))
                        i += 1
            continue
        for axis in axes:
            lo, hi = truth.AXIS_RANGE[axis]
            grid = np.linspace(lo, hi, w.points)
            for d, order in ((1, grid), (-1, grid[::-1])):
                for pos in order:
                    rows.append((s0 + 10.0 * i, axis, float(pos), d))
                    i += 1
    return pd.DataFrame(rows, columns=["time_s", "axis", "position", "direction"])


@dataclass
class _Chain:
    """The machine at every laser reading: the bodies, the sites' dT, the spindle speed, and the planted effects."""

    R: pd.DataFrame  # the readings: time_s, axis, position, direction
    t: np.ndarray  # the scan times
    plan: _Plan
    dTs: np.ndarray  # the sites' true dT on the scans
    body_at: dict[str, np.ndarray]
    dT_at: np.ndarray  # the sites' true dT at the readings
    rpm_at: np.ndarray
    scan_s: float

    @property
    def rt(self) -> np.ndarray:
        """Return the reading times."""
        return self.R["time_s"].to_numpy()

    def element_errors(self, q: np.ndarray, extra: list[OpenPlanted], idx: np.ndarray) -> dict[str, np.ndarray]:
        """Return the element errors at poses ``q`` (readings ``idx``): geometric, base thermal, and ``extra``."""
        errs = {e: v.copy() for e, v in truth.geometric_errors(q).items()}
        for element, param, coef, src in BASE_TERMS:
            e = errs.setdefault(element, np.zeros((len(q), 6)))
            e[:, kin.PARAMS.index(param)] += coef * self.body_at[src][idx]
        for p in extra:
            e = errs.setdefault(p.element, np.zeros((len(q), 6)))
            e[:, kin.PARAMS.index(p.param)] += self.planted_value(p, idx)
        return errs

    def planted_value(self, p: OpenPlanted, idx: np.ndarray) -> np.ndarray:
        """Return a planted effect's value in its element error at readings ``idx``."""
        pr, rt, t = p.params, self.rt, self.t
        d = self.R["direction"].to_numpy(dtype=float)[idx]
        x = self.R["position"].to_numpy(dtype=float)[idx]
        if p.kind == "reversal":  # backlash of the joint: half the span each way (3.3, 5.5)
            return 0.5 * float(pr["magnitude"]) * d
        days = rt[idx] / 86400.0
        if p.kind == "drift":
            return float(pr["rate_per_day"]) * days
        if p.kind == "operating_condition":  # centrifugal growth: coef x rpm^power (6.4.3)
            return float(pr["coef_per_unit"]) * self.rpm_at[idx] ** int(pr["power"])
        if p.kind == "unsensed_source":  # heat no thermocouple reads: a lag of the source's input (5.2)
            src = self.plan.sources.index(str(pr["source"]))
            heat = first_order_lag_even(self.plan.u[:, src], self.scan_s, float(pr["tau_s"]))
            return float(pr["coef"]) * np.interp(rt[idx], t, heat)
        if p.kind == "datum_shift":  # added to the readings, not to the machine
            return np.zeros(idx.size)
        j = list(SITES).index(p.channels[0])
        dT = self.dT_at[idx, j]
        if p.kind == "screw_expansion":  # eq. 3.2: pitch growth with the screw temperature
            return float(pr["coef_per_mm_degC"]) * x * dT
        if p.kind == "unmapped_channel":
            return float(pr["coef_per_degC"]) * dT
        if p.kind == "quadratic":
            return float(pr["coef_per_degC2"]) * dT * dT
        if p.kind == "direction_thermal":  # the reversal opens as the nut warms (3.3 with 3.5): full span
            return 0.5 * float(pr["coef_per_degC"]) * d * dT
        if p.kind == "thermal_lag":  # the body follows a lag of the site: c (lag(dT) - dT)
            lg = np.interp(rt[idx], t, first_order_lag_even(self.dTs[:, j], self.scan_s, float(pr["tau_s"])))
            return float(pr["coef_per_degC"]) * (lg - dT)
        raise ValueError(p.kind)


@dataclass
class _Observed:
    """What the chain shows of the planted effects per (axis, term), and the error rows measured."""

    expected: list[dict[str, Any]]
    signal: list[float]
    beyond_model: list[float]
    beyond: dict[str, float] = field(default_factory=dict)
    errors: list[pd.DataFrame] = field(default_factory=list)


#: kinds that change the readings (temperatures or errors), not the machine's element errors
NOT_IN_THE_CHAIN = ("sensor_fault", "sensor_drift", "datum_shift")


def _measure_axis(
    rng: np.random.Generator,
    chain: _Chain,
    planted: list[OpenPlanted],
    axis: str,
    terms: list[str],
    w: OpenWorld,
    ob: _Observed,
) -> None:
    """Measure every kept term of one axis through the chain (eq. 4.12) into ``ob``: noise, steps, glitches."""
    R, rt, names = chain.R, chain.rt, list(SITES)
    effects = [p for p in planted if p.kind not in NOT_IN_THE_CHAIN]
    idx = np.flatnonzero((R["axis"] == axis).to_numpy())
    q = truth.axis_pose(axis, R["position"].to_numpy()[idx])
    W0 = kin.workspace_error(q, chain.element_errors(q, [], idx))  # eq. 4.12 through the chain
    W = kin.workspace_error(q, chain.element_errors(q, effects, idx)) if effects else W0
    for term in terms:
        c = kin.PARAMS.index(term)
        angle = term in ("alpha", "beta", "gamma")
        sigma = w.noise_rad if angle else w.noise_mm
        ob.beyond[f"{axis}/{term}"] = _beyond_span(W0[:, c], R.iloc[idx], chain.dT_at[idx], names)
        for i, p in enumerate(planted):
            if p.kind in NOT_IN_THE_CHAIN or (p.axis, p.term) != (axis, term):
                continue
            Wi = kin.workspace_error(q, chain.element_errors(q, [p], idx))
            delta = Wi[:, c] - W0[:, c]
            ob.signal[i] = rmse(delta)
            ob.beyond_model[i] = _beyond_span(delta, R.iloc[idx], chain.dT_at[idx], names)
            ob.expected[i] = _expected_params(p, delta, idx, chain, angle)
        y = W[:, c] + _ar1(idx.size, float(w.rho) if w.rho is not None else 0.0, sigma, rng)
        for i, p in enumerate(planted):  # a re-zeroed line: every reading steps at one moment
            if p.kind == "datum_shift" and (p.axis, p.term) == (axis, term):
                after_step = rt[idx] >= float(p.params["time_s"])
                y[after_step] += float(p.params["step"])
                ob.signal[i] = rmse(float(p.params["step"]) * after_step)
                ob.expected[i] = {
                    "time_s": float(p.params["time_s"]),
                    f"step_{'rad' if angle else 'mm'}": float(p.params["step"]),
                }
        if w.glitches:  # single readings hit by EMI: 3 per series, 20-60 x the noise
            hit = rng.choice(idx.size, size=3, replace=False)
            y[hit] += rng.choice([-1, 1], 3) * rng.uniform(20, 60, 3) * sigma
        ob.errors.append(
            pd.DataFrame(
                {
                    "time_s": rt[idx],
                    "axis": axis,
                    "term": term,
                    "position": R["position"].to_numpy()[idx],
                    "direction": R["direction"].to_numpy()[idx].astype(int),
                    "value": y,
                }
            )
        )


def _logged(
    rng: np.random.Generator, readings: np.ndarray, t: np.ndarray, plan: _Plan, w: OpenWorld
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Return temperatures.csv and conditions.csv as a logger writes them: EMI spikes, gaps, irregular scans."""
    names = list(SITES)
    n = t.size
    temps = pd.DataFrame(np.round(readings, 4), columns=names)
    temps.insert(0, "time_s", t)
    cond = pd.DataFrame({"time_s": t, "spindle_rpm": plan.rpm, "feed_mm_min": plan.feed})
    if w.glitches:  # single-scan EMI spikes on a few channels
        vals = temps[names].to_numpy(copy=True)
        for _ in range(6):
            j, i = int(rng.integers(0, len(names))), int(rng.integers(5, n - 5))
            if np.isfinite(vals[i, j]):
                vals[i, j] += float(rng.choice([-1, 1]) * rng.uniform(2, 8))
        temps[names] = vals
    if w.gaps:  # logger gaps (no scan written) and scattered missing readings
        drop = np.zeros(n, dtype=bool)
        for length in (900.0, 3000.0):
            a = rng.uniform(0.1, 0.9) * t[-1]
            drop |= (t > a) & (t < a + length)
        temps = temps[~drop].reset_index(drop=True)
        cond = cond[~drop].reset_index(drop=True)
        vals = temps[names].to_numpy(copy=True)
        vals[rng.uniform(size=vals.shape) < 0.003] = np.nan
        temps[names] = vals
    if w.irregular:  # scans at irregular times: each scan late or early by up to 40 % of the period
        jitter = rng.uniform(-0.4, 0.4, len(temps)) * w.scan_s
        tj = np.clip(temps["time_s"].to_numpy(dtype=float) + jitter, 0.0, t[-1])
        tj = np.maximum.accumulate(tj + np.arange(tj.size) * 1e-3)
        vals = temps[names].to_numpy(dtype=float)
        for jj in range(len(names)):
            ok = np.isfinite(vals[:, jj])
            if ok.sum() > 1:
                vals[ok, jj] = np.interp(tj[ok], temps["time_s"].to_numpy(dtype=float)[ok], vals[ok, jj])
        temps["time_s"] = np.round(tj, 1)
        temps[names] = np.round(vals, 4)
    return temps, cond


def _bundle(
    temps: pd.DataFrame,
    cond: pd.DataFrame,
    err: pd.DataFrame,
    planted: list[OpenPlanted],
    axes: list[str],
    stages: list[dict[str, Any]],
    w: OpenWorld,
) -> tuple[Bundle, list[OpenPlanted]]:
    """Return the bundle (campaign.json from the sites; another lab's channel names on request) and the planted
    effects under those names."""
    names = list(SITES)
    meta = {
        "format": "driftlab-bundle/1",
        "machine": {"id": "open-world", "name": "open-world generator (tests)", "resolution_mm": 0.0001},
        "started_at": "2026-03-02T08:00:00Z",
        "channels": {
            c: {"location": f"{SITES[c][0].replace('_', ' ')} site {c}", "structure": SITES[c][0]} for c in names
        },
        "room_channels": list(ROOM),
        "model_channels": {a: list(MODEL_CHANNELS) for a in axes},
        "stages": stages,
        "noise": {"length_mm": w.noise_mm, "angle_rad": w.noise_rad},
    }
    if w.channel_names:  # another lab's names for the same sites
        cmap = {c: w.channel_names.get(c, c) for c in names}
        temps = temps.rename(columns=cmap)
        meta["channels"] = {cmap[c]: v for c, v in meta["channels"].items()}  # type: ignore[attr-defined]
        meta["room_channels"] = [cmap[c] for c in ROOM]
        meta["model_channels"] = {a: [cmap[c] for c in MODEL_CHANNELS] for a in axes}
        planted = [
            OpenPlanted(p.kind, p.axis, p.term, p.element, p.param, [cmap.get(c, c) for c in p.channels], p.params)
            for p in planted
        ]
    bundle = Bundle(name=f"open-{w.seed}", meta=_as_meta(meta), temperatures=temps, conditions=cond, errors=err)
    return bundle, planted


def openworld_case(planted: list[OpenPlanted] | None = None, world: OpenWorld | None = None) -> Case:
    """Return an open-world :class:`Case` with ``planted`` effects hidden in element errors, drawn as ``world`` says."""
    planted = list(planted or [])
    w = world or OpenWorld()
    rng = np.random.default_rng(w.seed)
    w = replace(w, rho=float(rng.uniform(0.4, 0.8)) if w.rho is None else float(w.rho))
    n = int(w.hours * 3600 / w.scan_s) + 1
    t = np.arange(n) * w.scan_s
    plan = _stage_plan(rng, t, planted, w.random_stages)
    room_air, true = _site_temperatures(rng, t, plan.u, w.scan_s)
    dTs = true - true[0]
    body = _bodies(rng, dTs, plan.u, w)
    readings = _readings(rng, true, t, room_air, planted)
    keep = w.keep or sorted({(p.axis, p.term) for p in planted if p.axis}) or [("Z", "dz")]
    axes = sorted({a for a, _ in keep})
    R = _sweeps(rng, t, axes, w)
    rt = R["time_s"].to_numpy()
    chain = _Chain(
        R,
        t,
        plan,
        dTs,
        {b: np.interp(rt, t, v) for b, v in body.items()},
        np.column_stack([np.interp(rt, t, dTs[:, j]) for j in range(len(SITES))]),
        plan.rpm[np.clip(np.searchsorted(t, rt, side="right") - 1, 0, n - 1)],
        w.scan_s,
    )
    ob = _Observed([{} for _ in planted], [0.0] * len(planted), [0.0] * len(planted))
    for axis in axes:
        _measure_axis(rng, chain, planted, axis, [tm for a, tm in keep if a == axis], w, ob)
    err = pd.concat(ob.errors, ignore_index=True).sort_values(["time_s", "axis", "term"], kind="stable")
    err = err.reset_index(drop=True)
    temps, cond = _logged(rng, readings, t, plan, w)
    bundle, planted = _bundle(temps, cond, err, planted, axes, plan.stages, w)
    noise = {"length_mm": w.noise_mm, "angle_rad": w.noise_rad}
    return Case(bundle, planted, ob.expected, noise, float(w.rho or 0.0), ob.beyond, ob.signal, ob.beyond_model)


def _beyond_span(w: np.ndarray, rows: pd.DataFrame, dT: np.ndarray, names: list[str]) -> float:
    """Return the RMS of a noise-free base error that the standard model (on noise-free sensors) cannot fit."""
    x = rows["position"].to_numpy(dtype=float)
    x = (x - x.mean()) / max(np.ptp(x), 1e-9)
    cols = [np.ones_like(x), x, x**2, x**3] + [dT[:, names.index(c)] for c in MODEL_CHANNELS]
    A = np.column_stack(cols)
    b, *_ = np.linalg.lstsq(A, w, rcond=None)
    return rmse(w - A @ b)


def _expected_params(p: OpenPlanted, delta: np.ndarray, idx: np.ndarray, chain: _Chain, angle: bool) -> dict[str, Any]:
    """Return the catalogue parameters of a planted effect as observed through the chain on its (axis, term).

    The observed change ``delta`` (at readings ``idx``) is regressed on the catalogue's own regressor
    (direction, position x dT, dT, days, rpm^power ...) with an intercept: what a perfect diagnosis reports.
    """
    R = chain.R
    d = R["direction"].to_numpy(dtype=float)[idx]
    x = R["position"].to_numpy(dtype=float)[idx]
    one = np.ones_like(delta)

    def coef(col: np.ndarray) -> float:
        b, *_ = np.linalg.lstsq(np.column_stack([one, col]), delta, rcond=None)
        return float(b[1])

    k = p.kind
    if k == "reversal":
        return {f"magnitude_{'rad' if angle else 'mm'}": 2.0 * coef(d)}
    if k == "drift":
        return {"rate_per_day": coef(chain.rt[idx] / 86400.0)}
    if k == "unsensed_source":
        return {"source": str(p.params["source"]), "tau_s": float(p.params["tau_s"])}
    if k == "operating_condition":
        pw = int(p.params["power"])
        return {"column": "spindle_rpm", "power": pw, "coef_per_unit": coef(chain.rpm_at[idx] ** pw)}
    j = list(SITES).index(p.channels[0])
    dT = chain.dT_at[idx, j]
    if k == "screw_expansion":
        return {"coef_per_mm_degC": coef(x * dT)}
    if k == "unmapped_channel":
        return {"coef_per_degC": coef(dT)}
    if k == "quadratic":
        return {"coef_per_degC2": coef(dT * dT)}
    if k == "thermal_lag":
        return {"tau_s": float(p.params["tau_s"])}
    if k == "direction_thermal":
        return {"coef_per_degC": 2.0 * coef(d * dT)}
    return {}
