"""Bundles whose truth is exactly the standard model, written from the bundle spec's text alone.

Independent of the fit code and of ``effects_generator``: nothing here imports driftlab's models,
physics or lag filter. The bundle spec (section 2) defines the standard model of each (axis, term)
as ordinary least squares on an intercept, position, position^2, position^3 and
dT_k = T_k(t) - T_k(t_first) for each k in ``model_channels[axis]``, temperatures interpolated to
the error sample's time. So the truth here is exactly that, with coefficients of its own per line,
plus white laser noise:

- channels are named as a lab names them (``spindle_nose``, ``column_top`` ...) and sit on the
  structures of the bundle spec's vocabulary; two are room air;
- temperatures are first-order responses (exact exponential step per scan) of each site to the
  heat sources of a staged plan (spindle, X feed, Z feed) and a daily room cycle;
- each measured axis is swept only in the stages that name it (``lines only in some stages``);
- any scan rate and sweep interval; a bundle v2 with zeroed laser sessions (``datum: session``:
  every reading is the error less the error at the session's first reading) or v1 absolute readings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from driftlab.campaigns.bundle import Bundle, _as_meta

#: (name, structure, gains of (spindle, X feed, Z feed) in degC at full power, time constant min)
SITES: tuple[tuple[str, str, tuple[float, float, float], float], ...] = (
    ("spindle_nose", "spindle", (9.0, 0.2, 0.5), 25.0),
    ("spindle_rear", "spindle", (6.0, 0.1, 0.8), 45.0),
    ("arm_left", "spindle_arm", (3.0, 0.3, 1.0), 70.0),
    ("arm_right", "spindle_arm", (2.2, 0.2, 1.4), 90.0),
    ("column_top", "z_column", (1.5, 0.4, 2.5), 120.0),
    ("column_foot", "z_column", (0.6, 0.6, 1.2), 160.0),
    ("z_nut", "z_screw", (0.4, 0.2, 6.0), 30.0),
    ("z_motor_case", "z_motor", (0.3, 0.1, 4.0), 50.0),
    ("x_nut", "x_screw", (0.2, 7.0, 0.3), 28.0),
    ("x_motor_case", "x_motor", (0.1, 4.5, 0.2), 55.0),
    ("bed", "base", (0.4, 0.9, 0.5), 200.0),
    ("table_top", "x_table", (0.3, 2.0, 0.2), 100.0),
)
ROOM = ("air_high", "air_low")
LENGTHS = ("dx", "dy", "dz")
TERMS = ("dx", "dy", "dz", "alpha", "beta", "gamma")
STROKE_MM = {"X": 500.0, "Y": 400.0, "Z": 400.0}
SOURCES = ("spindle", "feed_X", "feed_Z")


@dataclass
class World:
    """A generated bundle, the true standard-model coefficients and the stated noise."""

    bundle: Bundle
    model_channels: dict[str, list[str]]
    noise_mm: float
    noise_rad: float


def _lag(u: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """Return the first-order response to ``u`` on an even grid (exact for a held step per scan)."""
    a = np.exp(-dt_s / tau_s)
    out = np.empty_like(u)
    acc = u[0]
    for i, v in enumerate(u):
        acc = a * acc + (1 - a) * v
        out[i] = acc
    return out


def _plan(
    hours: float, axes: tuple[str, ...], rng: np.random.Generator, order: tuple[str, ...] | None = None
) -> list[dict[str, object]]:
    """Return a staged single-heat-source plan: each axis' feed, then the spindle, each with a cool-down.

    ``order`` names the heating stages in turn ("feed-X", "feed-Z", "spindle"), repeated from its
    start when the campaign is longer: a plan that heats one source only late in the campaign.
    """
    stages: list[dict[str, object]] = []
    if order is None:
        order_ = [("feed", a) for a in axes if a in ("X", "Z")] + [("spindle", axes[-1])]
    else:
        order_ = [("spindle", axes[-1]) if o == "spindle" else ("feed", o.split("-")[1]) for o in order]
    t = 0.0
    span = hours * 3600.0
    k = 0
    while t < span - 3600:
        kind, axis = order_[k % len(order_)]
        on = float(round(rng.uniform(4.0, 6.0) * 60) * 60)
        off = float(round(rng.uniform(2.0, 3.0) * 60) * 60)
        stages.append(
            {
                "name": f"{kind}-{axis}-{k}",
                "start_s": t,
                "end_s": min(t + on, span),
                "heat_source": kind,
                "axis": axis,
                "spindle_rpm": float(rng.uniform(6000, 12000)) if kind == "spindle" else 0.0,
                "feed_mm_min": float(rng.uniform(2000, 8000)) if kind == "feed" else 0.0,
            }
        )
        if t + on < span:
            stages.append(
                {
                    "name": f"cool-{k}",
                    "start_s": t + on,
                    "end_s": min(t + on + off, span),
                    "heat_source": "none",
                    "axis": axis,
                }
            )
        t += on + off
        k += 1
    return stages


def standard_world(
    seed: int,
    *,
    axes: tuple[str, ...] = ("X", "Z"),
    terms: tuple[str, ...] = TERMS,
    hours: float = 60.0,
    scan_s: float = 60.0,
    sweep_s: float = 900.0,
    points: int = 9,
    noise_mm: float = 5e-4,
    noise_rad: float = 5e-7,
    zeroed: bool = False,
    lines_everywhere: bool = False,
    with_model_channels: bool = True,
    coef_um_per_degC: tuple[float, float] = (0.5, 3.0),
    order: tuple[str, ...] | None = None,
) -> World:
    """Return a bundle whose every (axis, term) is the spec's standard model plus white noise.

    An axis is swept in the stages whose ``axis`` names it (and in their cool-downs), unless
    ``lines_everywhere``. With ``zeroed`` the bundle is v2 and every stage's sweeps of an axis
    form one laser session whose readings are relative to its first sweep (the laser is zeroed
    when it is mounted). ``order``: the heating stages in turn (``_plan``).
    """
    rng = np.random.default_rng(seed)
    stages = _plan(hours, axes, rng, order)
    n = int(hours * 3600 / scan_s) + 1
    t = np.arange(n) * scan_s
    power = np.zeros((n, len(SOURCES)))
    for st in stages:
        on = (t >= float(st["start_s"])) & (t < float(st["end_s"]))  # type: ignore[arg-type]
        if st["heat_source"] == "spindle":
            power[on, 0] = float(st["spindle_rpm"]) / 12000.0  # type: ignore[arg-type]
        elif st["heat_source"] == "feed":
            power[on, 1 if st["axis"] == "X" else 2] = float(st["feed_mm_min"]) / 8000.0  # type: ignore[arg-type]
    phase = rng.uniform(0, 2 * np.pi)
    air = 21.0 + 1.2 * np.sin(2 * np.pi * t / 86400.0 + phase)
    temps = {}
    for name, _, gains, tau_min in SITES:
        drive = air + power @ np.asarray(gains) * rng.uniform(0.8, 1.2)
        temps[name] = _lag(drive, scan_s, tau_min * 60.0 * rng.uniform(0.8, 1.2)) + rng.uniform(-0.5, 0.5)
    temps[ROOM[0]] = air + 0.3 + 0.05 * np.sin(t / 3000.0)
    temps[ROOM[1]] = air - 0.3 + 0.05 * np.cos(t / 4100.0)
    names = [s[0] for s in SITES] + list(ROOM)
    readings = pd.DataFrame({c: temps[c] + rng.normal(0, 0.01, n) for c in names})
    readings.insert(0, "time_s", t)

    machine_sites = [s[0] for s in SITES]
    model_channels = {a: [*rng.choice(machine_sites, size=4, replace=False).tolist(), ROOM[0]] for a in axes}

    rows = []
    for st in stages:
        axis = str(st["axis"])
        start, end = float(st["start_s"]), float(st["end_s"])  # type: ignore[arg-type]
        measured = [a for a in axes if lines_everywhere or a == axis]
        for a in measured:
            grid = np.linspace(0.0, STROKE_MM[a], points)
            for s0 in np.arange(start, end - 2 * points * 8.0, sweep_s):
                seq = [(p, 1) for p in grid] + [(p, -1) for p in grid[::-1]]
                for i, (p, d) in enumerate(seq):
                    rows.append((s0 + 8.0 * i, a, p, d, f"{a}-{st['name']}"))
    pts = pd.DataFrame(rows, columns=["time_s", "axis", "position", "direction", "session"])
    pts = pts[pts["time_s"] <= t[-1]].sort_values("time_s", kind="stable").reset_index(drop=True)

    errors = []
    for a in axes:
        on = pts[pts["axis"] == a]
        rt = on["time_s"].to_numpy(float)
        # dT_k = T_k(t) - T_k(t_first): the readings interpolated to the sample's time (spec section 2)
        dT = {c: np.interp(rt, t, readings[c].to_numpy(float)) - readings[c].iloc[0] for c in model_channels[a]}
        x = on["position"].to_numpy(float)
        u = x / STROKE_MM[a]
        for term in terms:
            scale = 1e-3 if term in LENGTHS else 1e-6  # um or urad per unit
            shape = rng.normal(0, 6.0, 4) * scale
            value = shape[0] + shape[1] * u + shape[2] * u**2 + shape[3] * u**3
            for c in model_channels[a]:
                value = value + rng.choice([-1, 1]) * rng.uniform(*coef_um_per_degC) * scale * dT[c]
            value = value + rng.normal(0, noise_mm if term in LENGTHS else noise_rad, value.size)
            frame = on[["time_s", "axis", "position", "direction", "session"]].copy()
            frame["term"] = term
            frame["value"] = value
            if zeroed:
                first = frame.groupby("session")["value"].transform("first")
                frame["value"] = frame["value"] - first
            errors.append(frame)
    err = pd.concat(errors, ignore_index=True).sort_values(["time_s", "axis", "term"], kind="stable")
    err = err.reset_index(drop=True)
    err["direction"] = err["direction"].astype(int)
    meta: dict[str, object] = {
        "format": "driftlab-bundle/2" if zeroed else "driftlab-bundle/1",
        "machine": {"id": "foreign-vmc", "name": "a machine whose drift is the standard model"},
        "started_at": "2026-05-04T07:00:00Z",
        "channels": {
            **{name: {"location": name.replace("_", " "), "structure": st} for name, st, _, _ in SITES},
            **{c: {"location": "shop air", "structure": "room"} for c in ROOM},
        },
        "room_channels": list(ROOM),
        "stages": stages,
        "noise": {"length_mm": noise_mm, "angle_rad": noise_rad},
    }
    if with_model_channels:
        meta["model_channels"] = model_channels
    if zeroed:
        sessions = sorted(err["session"].unique())
        meta["setups"] = {
            s: {
                "instrument": "laser",
                "optics": "linear",
                "axis": s.split("-")[0],
                "terms": [f"{s.split('-')[0]}/{k}" for k in terms],
                "datum": "session",
            }
            for s in sessions
        }
        for c in "xyzab":
            err[c] = 0.0
        for a in axes:
            err.loc[err["axis"] == a, a.lower()] = err.loc[err["axis"] == a, "position"]
        err = err.rename(columns={"session": "setup"})
        err = err[["time_s", "axis", "term", "position", "direction", "x", "y", "z", "a", "b", "setup", "value"]]
    else:
        err = err[["time_s", "axis", "term", "position", "direction", "value"]]
    bundle = Bundle(
        name=f"standard-world-{seed}", meta=_as_meta(meta), temperatures=readings, conditions=None, errors=err
    )
    return World(bundle, model_channels, noise_mm, noise_rad)


def standard_holdout(world: World, holdout_fraction: float = 0.25, split: str = "stage") -> pd.DataFrame:
    """Return per (axis, term) the held-out RMSE of plain least squares on the standard model (spec section 2).

    ``split="stage"`` is the fit's stage split: the last ``holdout_fraction`` of every training
    stage's points is held out (a cool-down belongs to the stage before it). ``split="time"``: the
    last ``holdout_fraction`` of every line's rows in time order (the row at floor((1 - f) n) of
    its sorted times and every later one). With zeroed sessions each session gets an offset of its
    own (the intercept of its datum).
    """
    b = world.bundle
    temps = b.temperatures
    err = b.errors.copy()
    t = err["time_s"].to_numpy(float)
    role = np.full(len(err), "skip", dtype=object)
    stages = b.meta.stages
    i = 0
    if split == "time":
        for _, g in err.groupby(["axis", "term"]):
            ts = np.sort(g["time_s"].to_numpy(float))
            cut = ts[min(int(np.floor((1 - holdout_fraction) * ts.size)), ts.size - 1)]
            role[g.index.to_numpy()] = np.where(g["time_s"].to_numpy(float) >= cut, "holdout", "train")
        i = len(stages)
    while i < len(stages):
        start = stages[i].start_s
        end = stages[i + 1].end_s if i + 1 < len(stages) and stages[i + 1].heat_source == "none" else stages[i].end_s
        on = (t >= start) & (t <= end) & (role == "skip")
        ts = np.sort(np.unique(t[on]))
        if ts.size:
            cut = ts[min(int(np.floor((1 - holdout_fraction) * ts.size)), ts.size - 1)]
            role[on] = np.where(t[on] >= cut, "holdout", "train")
        i += 2 if end != stages[i].end_s else 1
    err["role"] = role
    out = []
    mc = world.model_channels
    for (axis, term), g in err.groupby(["axis", "term"]):
        rt = g["time_s"].to_numpy(float)
        u = g["position"].to_numpy(float) / STROKE_MM[str(axis)]
        cols = [np.ones_like(u), u, u**2, u**3]
        cols += [np.interp(rt, temps["time_s"], temps[c]) - temps[c].iloc[0] for c in mc[str(axis)]]
        if "setup" in g:
            for s in sorted(g["setup"].unique())[1:]:
                cols.append((g["setup"].to_numpy(object) == s).astype(float))
        A = np.column_stack(cols)
        y = g["value"].to_numpy(float)
        tr = (g["role"] == "train").to_numpy()
        ho = (g["role"] == "holdout").to_numpy()
        coef, *_ = np.linalg.lstsq(A[tr], y[tr], rcond=None)
        out.append(
            {"axis": axis, "term": term, "standard_holdout": float(np.sqrt(np.mean((y[ho] - A[ho] @ coef) ** 2)))}
        )
    return pd.DataFrame(out).set_index(["axis", "term"])
