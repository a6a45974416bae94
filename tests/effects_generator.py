"""Bundles with planted effects for the diagnosis tests.

``vm_case`` runs the virtual machine (``driftlab.daq.sim.simulate_campaign`` with
``Scenario.hidden``): the 50-site thermal network, the HTM error field and the
hidden effects of the catalogue, and keeps the (axis, term)s a test needs (a
bundle may hold any subset), returning the bundle and the planted truth.

``make_case`` is a small self-contained thermal world for cheap unit-level
checks (and bundles without model_channels): first-order thermocouple sites
driven by a staged single-heat-source plan and a daily room cycle (ch. 5.2),
errors = a cubic in position + a linear combination of the true temperature
rises of the model channels + laser noise, and the hidden effects applied
exactly as the catalogue defines them:

- reversal: + magnitude/2 x direction (full span = magnitude)
- screw_expansion: + coef x position x dT_k
- unmapped_channel: + coef x dT_k (k outside model_channels)
- thermal_lag: the structure follows a first-order lag of T_k: c_k x lag(dT_k, tau) replaces c_k x dT_k
- sensor_fault: from start_s, the readings of k relax to room air (detached) or go missing (open);
  the structure keeps its true temperature
- drift: + rate x days
- quadratic: + coef x dT_k^2
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import Bundle, _as_meta
from driftlab.physics.lag import first_order_lag_even
from driftlab.testing.openworld import OpenPlanted

TERMS_MM = ("dx", "dy", "dz")


def Planted(
    kind: str,
    axis: str,
    term: str,
    channels: list[str] | None = None,  # noqa: N802 - reads as the type
    params: dict[str, Any] | None = None,
) -> OpenPlanted:
    """Return one hidden effect as the catalogue of the bundle spec states it (no element: planted on the term)."""
    return OpenPlanted(kind, axis, term, "", "", list(channels or []), dict(params or {}))


@dataclass
class Case:
    """A generated bundle and what was planted in it."""

    bundle: Bundle
    planted: list[OpenPlanted]
    noise: dict[str, float]
    model_channels: dict[str, list[str]]
    signal_rms: dict[int, float]  # planted effect index -> RMS of its contribution to the errors


def _detectable_rms(
    add: np.ndarray, rp: np.ndarray, rt: np.ndarray, t: np.ndarray, readings: np.ndarray, model_idx: list[int]
) -> float:
    """RMS of the part of a planted signal that the standard model (cubic + model dT) cannot absorb."""
    x = (rp - rp.mean()) / max(np.ptp(rp), 1e-9)
    cols = [np.ones_like(x), x, x**2, x**3]
    for j in model_idx:
        r = np.interp(rt, t, np.nan_to_num(readings[:, j], nan=np.nanmean(readings[:, j])))
        cols.append(r - r[0])
    A = np.column_stack(cols)
    b, *_ = np.linalg.lstsq(A, add, rcond=None)
    res = add - A @ b
    return float(np.sqrt(np.mean(res * res)))


def make_case(
    planted: list[OpenPlanted],
    seed: int = 0,
    hours: float = 36.0,
    scan_s: float = 120.0,
    sweep_s: float = 1200.0,
    terms: dict[str, list[str]] | None = None,
    n_channels: int = 10,
    positions: int = 7,
    noise_mm: float = 5e-4,
    noise_rad: float = 5e-7,
    model_channels: dict[str, list[str]] | None = None,
    with_model_channels: bool = True,
    geometry_um: float = 8.0,
) -> Case:
    """Return a :class:`Case`: a bundle v1 with ``planted`` effects hidden in it, and the truth."""
    rng = np.random.default_rng(seed)
    terms = terms or {"X": ["dx"]}
    names = [f"T{i + 1}" for i in range(n_channels)]
    room = names[-2:]
    n = int(hours * 3600 / scan_s) + 1
    t = np.arange(n) * scan_s

    # heat sources: a staged single-heat-source plan, each source in turn on for 3-4 h then off 2-3 h
    n_src = 3
    u = np.zeros((n, n_src))
    cursor = 0.5 * 3600
    stages = []
    k = 0
    while cursor < t[-1]:
        s = k % n_src
        on = round(rng.uniform(3, 4) * 60) * 60.0
        off = round(rng.uniform(2, 3) * 60) * 60.0
        level = rng.uniform(0.5, 1.0)
        u[(t >= cursor) & (t < cursor + on), s] = level
        stages.append(
            {
                "name": f"src{s}-{k}",
                "start_s": cursor,
                "end_s": min(cursor + on, t[-1]),
                "heat_source": ["spindle", "x_motor", "cabinet"][s],
                "axis": "X",
                "spindle_rpm": 8000.0 * level if s == 0 else 0.0,
                "feed_mm_min": 0.0,
            }
        )
        stages.append(
            {
                "name": f"rest-{k}",
                "start_s": min(cursor + on, t[-1]),
                "end_s": min(cursor + on + off, t[-1]),
                "heat_source": "none",
                "axis": "X",
                "spindle_rpm": 0.0,
                "feed_mm_min": 0.0,
            }
        )
        cursor += on + off
        k += 1
    phase = rng.uniform(0, 2 * np.pi)
    room_air = 20.0 + 1.0 * np.sin(2 * np.pi * t / 86400 + phase) + 0.3 * np.sin(2 * np.pi * t / 17000 + 1)
    true = np.empty((n, n_channels))
    for j in range(n_channels):
        if names[j] in room:
            true[:, j] = room_air + (0.2 if j == n_channels - 1 else -0.2) + 0.05 * np.sin(t / 5000.0 + j)
            continue
        gains = rng.uniform(0, 6, n_src) * (rng.uniform(size=n_src) < 0.7)
        gains[j % n_src] += rng.uniform(2, 6)
        tau = rng.uniform(10, 150) * 60
        drive = room_air + u @ gains
        true[:, j] = first_order_lag_even(drive, scan_s, tau) + rng.uniform(-1, 1)
    readings = true + rng.normal(0, 0.01, true.shape)

    for p in planted:  # faults change the readings, not the structure
        if p.kind != "sensor_fault":
            continue
        j = names.index(p.channels[0])
        after = t >= p.params["start_s"]
        if p.params.get("mode", "detached") == "open":
            readings[after, j] = np.nan
        else:
            target = room_air + 0.5
            k0 = int(np.argmax(after))
            x = readings[:, j].copy()
            dec = np.exp(-(t[after] - t[k0]) / 600.0)
            x[after] = target[after] + (readings[k0, j] - target[after]) * dec + rng.normal(0, 0.01, after.sum())
            readings[:, j] = x
    noise = {"length_mm": noise_mm, "angle_rad": noise_rad}
    # sweeps: positions up then down, 10 s per point
    pos_grid = np.linspace(0.0, 254.0, positions)
    sweep_starts = np.arange(0.0, t[-1] - positions * 20 - 10, sweep_s)
    rows = []
    for s0 in sweep_starts:
        seq = [(p, 1) for p in pos_grid] + [(p, -1) for p in pos_grid[::-1]]
        for i, (p, d) in enumerate(seq):
            rows.append((s0 + 10.0 * i, p, d))
    rt = np.array([r[0] for r in rows])
    rp = np.array([r[1] for r in rows])
    rd = np.array([r[2] for r in rows], dtype=float)
    T_true_at = np.column_stack([np.interp(rt, t, true[:, j]) for j in range(n_channels)])
    dT_true = T_true_at - T_true_at[0]

    mc = model_channels or {}
    non_room = [c for c in names if c not in room]
    for axis in terms:
        if axis not in mc:
            mc[axis] = list(rng.choice(non_room, size=3, replace=False)) + [room[0]]
    errors = []
    signal_rms: dict[int, float] = {}
    for axis, tl in terms.items():
        for term in tl:
            unit_noise = noise_mm if term in TERMS_MM else noise_rad
            scale = 1e-3 if term in TERMS_MM else 1e-6  # um or urad
            geo = rng.normal(0, geometry_um, 4) * scale
            x = (rp - 127.0) / 127.0
            y = geo[0] + geo[1] * x + geo[2] * x**2 + geo[3] * x**3
            coefs = {c: rng.choice([-1, 1]) * rng.uniform(1.5, 4.0) * scale for c in mc[axis]}
            lagged = {
                p.channels[0]: p.params["tau_s"]
                for p in planted
                if p.kind == "thermal_lag" and p.axis == axis and p.term == term
            }
            for c, b in coefs.items():
                j = names.index(c)
                if c in lagged:
                    lg = first_order_lag_even(true[:, j], scan_s, lagged[c])
                    col = np.interp(rt, t, lg)
                    y = y + b * (col - col[0])
                else:
                    y = y + b * dT_true[:, j]
            for i, p in enumerate(planted):
                if p.axis != axis or p.term != term:
                    continue
                add = np.zeros_like(y)
                if p.kind == "reversal":
                    add = 0.5 * p.params[f"magnitude_{'mm' if term in TERMS_MM else 'rad'}"] * rd
                elif p.kind == "screw_expansion":
                    add = p.params["coef_per_mm_degC"] * rp * dT_true[:, names.index(p.channels[0])]
                elif p.kind == "unmapped_channel":
                    add = p.params["coef_per_degC"] * dT_true[:, names.index(p.channels[0])]
                elif p.kind == "drift":
                    add = p.params["rate_per_day"] * (rt - rt[0]) / 86400.0
                elif p.kind == "quadratic":
                    add = p.params["coef_per_degC2"] * dT_true[:, names.index(p.channels[0])] ** 2
                elif p.kind == "thermal_lag":
                    j = names.index(p.channels[0])
                    col = np.interp(rt, t, first_order_lag_even(true[:, j], scan_s, p.params["tau_s"]))
                    add = coefs[p.channels[0]] * ((col - col[0]) - dT_true[:, j])
                if p.kind == "sensor_fault":  # what the standard model suffers from the bad readings
                    j = names.index(p.channels[0])
                    rd_j = np.interp(rt, t, np.nan_to_num(readings[:, j], nan=float(np.nanmean(readings[:, j]))))
                    add = coefs.get(p.channels[0], 0.0) * (dT_true[:, j] - (rd_j - rd_j[0]))
                    signal_rms[i] = _detectable_rms(add, rp, rt, t, readings, [names.index(c) for c in mc[axis]])
                    continue
                y = y + add
                signal_rms[i] = _detectable_rms(add, rp, rt, t, readings, [names.index(c) for c in mc[axis]])
            y = y + rng.normal(0, unit_noise, y.size)
            errors.append(
                pd.DataFrame(
                    {"time_s": rt, "axis": axis, "term": term, "position": rp, "direction": rd.astype(int), "value": y}
                )
            )
    temps = pd.DataFrame(np.round(readings, 4), columns=names)
    temps.insert(0, "time_s", t)
    err = pd.concat(errors, ignore_index=True).sort_values(["time_s", "axis", "term"], kind="stable")
    err = err.reset_index(drop=True)
    meta = {
        "format": "driftlab-bundle/1",
        "machine": {"id": "synthetic", "name": "generated for diagnosis tests", "resolution_mm": 0.0001},
        "started_at": "2026-03-02T08:00:00Z",
        "channels": {
            c: {"location": "room air" if c in room else f"site {c}", "structure": "room" if c in room else "machine"}
            for c in names
        },
        "room_channels": room,
        "stages": stages,
        "noise": noise,
    }
    if with_model_channels:
        meta["model_channels"] = mc
    bundle = Bundle(name=f"case-{seed}", meta=_as_meta(meta), temperatures=temps, conditions=None, errors=err)
    return Case(bundle, planted, noise, mc, signal_rms)


@dataclass
class VMCase:
    """A bundle simulated on the virtual machine, with the truth record of the simulation."""

    bundle: Bundle
    planted: list[OpenPlanted]
    truth: dict[str, Any]
    noise: dict[str, float]

    def beyond_model_rms(self, i: int) -> float:
        """Return the RMS of planted effect i that no standard model can absorb (the simulation's figure)."""
        return float(self.truth["hidden"][i].get("rms_beyond_standard_model", float("nan")))


def vm_case(
    planted: list[OpenPlanted],
    seed: int = 0,
    hours: float = 36.0,
    scan_s: float = 120.0,
    sweep_s: float = 1200.0,
    points: int = 6,
    keep: list[tuple[str, str]] | None = None,
    thermocouple_degC: float | None = None,
    stated_noise: bool = True,
) -> VMCase:
    """Return a :class:`VMCase`: the virtual machine's campaign with ``planted`` hidden, reduced to ``keep``.

    ``keep`` lists the (axis, term)s written to errors.csv (default: the planted ones, or Z/dz).
    ``thermocouple_degC`` sets the scan noise of the thermocouples (the simulation's default otherwise);
    ``stated_noise=False`` leaves the optional ``noise`` field out of campaign.json (real data often has none).
    """
    from driftlab.daq.sim.campaign import simulate_campaign
    from driftlab.daq.sim.scenario import HiddenEffect, Noise, Scenario

    hidden = [
        HiddenEffect(
            kind=p.kind, axis=p.axis or None, term=p.term or None, channels=list(p.channels), params=dict(p.params)
        )
        for p in planted
    ]
    sc = Scenario(
        seed=seed,
        hours=hours,
        scan_interval_s=scan_s,
        sweep_interval_s=sweep_s,
        points_per_axis=points,
        hidden=hidden,
        noise=Noise() if thermocouple_degC is None else Noise(thermocouple_degC=thermocouple_degC),
    )
    sim = simulate_campaign(sc)
    keep = keep or sorted({(p.axis, p.term) for p in planted if p.axis and p.term}) or [("Z", "dz")]
    err = sim.errors
    mask = np.zeros(len(err), dtype=bool)
    for axis, term in keep:
        mask |= ((err["axis"] == axis) & (err["term"] == term)).to_numpy()
    errors = err[mask].reset_index(drop=True)
    meta = dict(sim.meta)
    if not stated_noise:
        meta.pop("noise", None)
    bundle = Bundle(
        name=f"vm-{seed}", meta=_as_meta(meta), temperatures=sim.temperatures, conditions=sim.conditions, errors=errors
    )
    return VMCase(bundle, planted, sim.truth, dict(sim.meta["noise"]))


def foreign(case: Case, seed: int = 0, nan_fraction: float = 0.01) -> Bundle:
    """Return ``case``'s bundle as another lab might write it: other channel names, no stages, no
    conditions, irregular scan times with gaps (30 min and 3 h), scattered missing readings.

    Channel names are arbitrary words (``spindle_front``, ``ch_a`` ...), not T1..Tn; ``model_channels``
    and ``room_channels`` follow the renaming.
    """
    rng = np.random.default_rng(seed)
    b = case.bundle
    old = [c for c in b.temperatures.columns if c != "time_s"]
    words = [
        "spindle_front",
        "spindle_rear",
        "ch_a",
        "ch_b",
        "column-top",
        "column_base",
        "x.nut",
        "y_motor",
        "bed_left",
        "bed_right",
        "head",
        "table",
        "coolant",
        "frame_1",
        "frame_2",
        "frame_3",
    ]
    new = {c: (words[i] if i < len(words) else f"extra_{i}") for i, c in enumerate(old)}
    temps = b.temperatures.rename(columns=new).copy()
    t = temps["time_s"].to_numpy(dtype=float)
    dt = float(np.median(np.diff(t)))
    t = t + rng.uniform(-0.2, 0.2, t.size) * dt  # irregular scan times
    t[0] = 0.0
    temps["time_s"] = t
    span = t[-1]
    drop = ((t > 0.30 * span) & (t < 0.30 * span + 1800.0)) | ((t > 0.55 * span) & (t < 0.55 * span + 3 * 3600.0))
    temps = temps[~drop].reset_index(drop=True)
    chans = [new[c] for c in old]
    vals = temps[chans].to_numpy(dtype=float, copy=True)
    vals[rng.uniform(size=vals.shape) < nan_fraction] = np.nan
    temps[chans] = vals
    meta = b.meta.model_dump() if hasattr(b.meta, "model_dump") else dict(b.meta)
    meta["channels"] = {new[c]: {"location": "", "structure": ""} for c in old}
    meta["room_channels"] = [new[c] for c in (meta.get("room_channels") or [])]
    if meta.get("model_channels"):
        meta["model_channels"] = {a: [new[c] for c in v] for a, v in meta["model_channels"].items()}
    meta.pop("stages", None)
    meta = {k: v for k, v in meta.items() if v is not None}
    return Bundle(name=f"{b.name}-foreign", meta=_as_meta(meta), temperatures=temps, conditions=None, errors=b.errors)
