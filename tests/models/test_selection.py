"""Correlation screening (ch. 5.4): redundant sites collapse, heat sources, gradients and room stay."""

import numpy as np
import pandas as pd
import pytest

from driftlab.errors import ValidationError
from driftlab.models.selection import ScreeningOptions, correlation_matrix, screen_channels


def _campaign(seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 40 * 3600, 120.0)
    room = 20 + 1.2 * np.sin(2 * np.pi * t / 86400)
    on = ((t // 14400) % 2 == 0).astype(float)
    spindle = np.convolve(on, np.exp(-np.arange(200) * 120 / 5400), mode="full")[: t.size] * 120 / 5400 * 8
    xheat = np.convolve(1 - on, np.exp(-np.arange(200) * 120 / 7000), mode="full")[: t.size] * 120 / 7000 * 4
    n = lambda: 0.02 * rng.standard_normal(t.size)  # noqa: E731
    meta, cols = {}, {"time_s": t}

    def add(name, loc, struct, v):
        meta[name] = {"location": loc, "structure": struct}
        cols[name] = v + n()

    for i in range(1, 5):
        add(f"T{i}", f"X axis corner {i}", "x_table", room + 0.5 * xheat)
    for i in range(5, 9):
        add(f"T{i}", f"X-Y carriage corner {i}", "xy_carriage", room + 0.5 * xheat)
    add("T9", "X axis ballscrew nut", "x_screw", room + 1.6 * xheat)
    add("T10", "X axis motor", "x_motor", room + 1.0 * xheat + 0.3 * np.gradient(xheat) * 3000)
    add("T32", "Lower left spindle support arm", "spindle_arm", room + 0.3 * spindle)
    add("T33", "Upper left spindle support arm", "spindle_arm", room + 0.6 * spindle)
    add("T34", "Upper right spindle support arm", "spindle_arm", room + 0.9 * spindle)
    add("T35", "Lower right spindle support arm", "spindle_arm", room + 0.6 * spindle + 0.3 * xheat)
    add("T37", "Main spindle motor", "spindle", room + 1.5 * spindle)
    add("T49", "Room temperature at top of machine", "room", room + 0.3)
    add("T50", "Room temperature at floor", "room", room - 0.2)
    return pd.DataFrame(cols), meta


def test_screening_collapses_redundant_sites_and_keeps_physics():
    temps, meta = _campaign()
    res = screen_channels(temps, meta, ["T49", "T50"])
    kept = set(res.kept)
    assert {"T49", "T50"} <= kept  # room pair, though 0.99 correlated
    assert {"T9", "T10", "T37"} <= kept  # one per heat source
    assert len(kept & {f"T{i}" for i in range(1, 9)}) == 1  # table and carriage collapse to one
    assert {"T32", "T34"} <= kept and "T33" not in kept  # arm corners span the gradient; T33 is inside it
    assert "gradient" in res.kept_reason["T32"] and "gradient" in res.kept_reason["T34"]
    for c, why in res.dropped.items():
        assert c not in kept and why
    t1_8 = [c for c in res.dropped if c in {f"T{i}" for i in range(1, 9)}]
    assert len(t1_8) == 7 and all("no new information" in res.dropped[c] for c in t1_8)
    assert "explained by kept" in res.dropped["T33"]
    # a channel that sees a second source keeps its place when the others cannot explain it
    temps2 = temps.copy()
    temps2["T35"] = temps2["T35"] + 2.0 * np.sin(temps2["time_s"] / 7000.0)
    assert "T35" in screen_channels(temps2, meta, ["T49", "T50"]).kept
    tab = res.table()
    assert list(tab.columns) == res.kept and (np.diag(tab) == 1).all()
    assert set(res.to_dict()) == {"kept", "kept_reason", "dropped", "correlation_kept"}


def test_options_keep_the_users_channels_and_set_the_thresholds():
    """``ScreeningOptions``: the user's model channels stay whatever the screening finds; a looser bar drops more."""
    temps, meta = _campaign()
    base = screen_channels(temps, meta, ["T49", "T50"])
    assert "T33" in base.dropped
    kept = screen_channels(temps, meta, ["T49", "T50"], options=ScreeningOptions(always_keep=("T33", "T99")))
    assert kept.kept_reason["T33"] == "required by the user's model channels" and "T99" not in kept.kept
    # the arm's corners differ by less than 10 degC rms: with that bar they are no gradient to keep
    loose = screen_channels(temps, meta, ["T49", "T50"], options=ScreeningOptions(gradient_degC=10.0))
    assert "corner of" in base.kept_reason["T34"] and "corner of" not in loose.kept_reason.get("T34", "")


def test_correlation_matrix_is_eq_6_1():
    temps, _ = _campaign()
    R = correlation_matrix(temps)
    a, b = temps["T9"], temps["T37"]
    r = ((a - a.mean()) * (b - b.mean())).mean() / (a.std(ddof=0) * b.std(ddof=0))
    assert abs(R.loc["T9", "T37"] - r) < 1e-12


def test_dead_and_constant_channels_are_dropped_with_reason():
    temps, meta = _campaign()
    temps["T60"] = 21.0
    temps["T61"] = np.nan
    res = screen_channels(temps, meta, ["T49", "T50"])
    assert "constant" in res.dropped["T60"] and res.dropped["T61"] == "no readings"


# ----------------------------------------------------------------------------- the work-space errors choose


def _vm(hours=48.0, seed=1):
    from driftlab.daq.sim.campaign import simulate_campaign
    from driftlab.daq.sim.scenario import Scenario

    return simulate_campaign(
        Scenario(
            name="vm-screen", hours=hours, seed=seed, scan_interval_s=120, sweep_interval_s=1200, points_per_axis=6
        )
    )


def test_errors_choose_the_truth_channels_on_the_virtual_machine():
    """Issue 5: the kept set holds every channel the VM's truth reads, and stays near the thesis' 18."""
    sim = _vm()
    meta, room = sim.meta["channels"], sim.meta["room_channels"]
    used = {c for cs in sim.meta["model_channels"].values() for c in cs} | set(sim.truth["drivers"])
    without = screen_channels(sim.temperatures, meta, room)
    res = screen_channels(sim.temperatures, meta, room, errors=sim.errors)
    kept = set(res.kept)
    assert used <= kept, sorted(used - kept)
    assert 14 <= len(kept) <= 26
    assert not used <= set(without.kept)  # temperatures alone pick other stand-ins
    for c in set(sim.truth["drivers"]) - {*room}:
        assert "heat source" in res.kept_reason[c] or "work-space errors" in res.kept_reason[c]
    # the column pair and the arm's corners stay although their temperatures nearly agree
    assert "follows" in res.kept_reason["T26"] or "follows" in res.kept_reason["T24"]
    for c, why in res.dropped.items():
        assert c not in kept and why
    assert set(res.dropped) | kept == set(sim.temperatures.columns) - {"time_s"}
    # one errors frame per campaign when the temperatures concatenate several (time_s restarts)
    two = pd.concat([sim.temperatures, sim.temperatures], ignore_index=True)
    again = screen_channels(two, meta, room, errors=[sim.errors, sim.errors])
    assert used <= set(again.kept)
    with pytest.raises(ValidationError, match="campaign"):
        screen_channels(two, meta, room, errors=[sim.errors, sim.errors, sim.errors])


def test_errors_none_or_empty_keep_the_temperature_screening():
    temps, meta = _campaign()
    base = screen_channels(temps, meta, ["T49", "T50"])
    cols = ["time_s", "axis", "term", "position", "direction", "value"]
    # a live errors frame changes the screening: an X error that follows T3 (a table corner the
    # temperatures alone drop) keeps T3, so the comparisons below can tell the two paths apart
    t = temps["time_s"].to_numpy()
    live = pd.DataFrame({"time_s": t, "axis": "X", "term": "dx", "position": 0.0, "direction": 0,
                         "value": 0.004 * (temps["T3"] - temps["T3"].mean())})  # fmt: skip
    with_errors = screen_channels(temps, meta, ["T49", "T50"], errors=live)
    assert "T3" not in base.kept and "T3" in with_errors.kept
    for errs in (None, pd.DataFrame(columns=cols), live.iloc[:0]):
        res = screen_channels(temps, meta, ["T49", "T50"], errors=errs)
        assert res.kept == base.kept and res.dropped == base.dropped
