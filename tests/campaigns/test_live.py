"""The live queries against what the real daemon committed (SQLite and PostgreSQL), checked with plain SQL."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sqlalchemy import text

from driftlab.campaigns import live
from driftlab.campaigns.db import store_engine
from driftlab.campaigns.plan import load_plan
from driftlab.daemon.run import run_daemon

PLAN = """\
format: driftlab-plan/1
name: live-test
machine: {id: vmc-5ax-01, channels: from scenario}
scan_interval_s: 60
stages:
  - name: baseline
    axis: Z
    duration_s: 1200
    sweep: &sw {positions: [-250, -125, 0], interval_s: 600, point_s: 6, term: dz}
  - name: spindle-10k
    heat: [{kind: spindle, rpm: 10000}]
    axis: Z
    duration_s: 2400
    sweep: *sw
"""
# T34 goes open (the card reads over-range) 10 min in: the page must name it
SCENARIO = """\
name: open-t34
seed: 3
hours: 2
scan_interval_s: 60
sweep_interval_s: 600
hidden:
  - {kind: sensor_fault, channels: [T34], params: {start_s: 600, mode: open}}
"""


@pytest.fixture
def files(tmp_path: Path) -> tuple[Path, Path]:
    """Write the plan and the scenario."""
    plan, scen = tmp_path / "plan.yaml", tmp_path / "open.yaml"
    plan.write_text(PLAN)
    scen.write_text(SCENARIO)
    return plan, scen


def _run(files: tuple[Path, Path], url: str, commits: int, resume: bool = False) -> int:
    """Run the daemon on the virtual machine for a number of commits; return the campaign id."""
    plan, scen = files
    r = run_daemon(
        load_plan(plan),
        db_url=url,
        scenario_path=scen,
        speed=math.inf,
        resume=resume,
        max_batch=7,
        stop_after_commits=commits,
    )
    return r.campaign_id


def _raw(engine, cid: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Return the stored temperatures (channel, time_s, value) and errors, read with plain SQL."""
    with engine.connect() as c:
        temps = pd.DataFrame(
            c.execute(
                text(
                    "SELECT ch.name AS channel, s.time_s, s.value FROM temperature_samples s "
                    "JOIN channels ch ON ch.id = s.channel_id WHERE s.campaign_id = :c"
                ),
                {"c": cid},
            ).all(),
            columns=["channel", "time_s", "value"],
        )
        errs = pd.DataFrame(
            c.execute(
                text(
                    "SELECT seq, time_s, axis, term, position, direction, value, sweep FROM error_samples "
                    "WHERE campaign_id = :c ORDER BY seq"
                ),
                {"c": cid},
            ).all(),
            columns=["seq", "t", "axis", "term", "position", "direction", "value", "sweep"],
        )
    return temps, errs


def test_snapshot_is_what_the_store_holds(store_url: str, files) -> None:
    cid = _run(files, store_url, commits=6)
    engine = store_engine(store_url)
    assert live.live_marks(engine)[cid]["status"] == "running"
    window, points = 1800.0, 15  # buckets of 120 s: two scans each
    snap = live.snapshot(engine, cid, window, points)
    temps, errs = _raw(engine, cid)
    tmax = snap["progress"]["time_s"]
    times = np.sort(temps.time_s.unique())

    assert snap["progress"]["scans"] == times.size > 10
    assert snap["latest"]["time_s"] == times[-1]
    assert tmax == max(times[-1], errs.t.max())
    # the stage holding the latest reading, and the time left in it
    stage = next(s for s in snap["stages"] if s["start_s"] <= tmax < s["end_s"])
    assert snap["stage"]["name"] == stage["name"] and snap["stage"]["status"] == "running"
    assert snap["progress"]["stage_left_s"] == pytest.approx(stage["end_s"] - tmax)
    # the open thermocouple: NULL in the store, named by the page
    last = temps[temps.time_s == times[-1]].set_index("channel").value
    assert math.isnan(last["T34"]) and snap["latest"]["values"]["T34"] is None
    assert snap["health"]["open"] == ["T34"]
    assert snap["latest"]["values"]["T1"] == pytest.approx(last["T1"])
    # buckets: means of whole 120 s buckets over the window, the open channel None where all readings are
    width = snap["temperatures"]["width_s"]
    assert width == 120.0
    first = math.floor((tmax - window) / width) * width
    win = temps[temps.time_s > first - 1e-9].assign(b=lambda d: np.floor(d.time_s / width).astype(int))
    want = win.groupby(["b", "channel"]).value.mean().unstack()
    got = pd.DataFrame(snap["temperatures"]["values"], index=snap["temperatures"]["b"]).astype(float)
    assert list(got.index) == list(want.index)
    pd.testing.assert_frame_equal(
        got[want.columns],
        want.rename_axis(None).rename_axis(None, axis=1),
        check_exact=False,
        atol=1e-4,
        check_names=False,
    )
    assert snap["temperatures"]["t"] == list(win.groupby("b").time_s.max())
    # error readings: every stored reading of the window, in order
    e_want = errs[errs.t >= tmax - window]
    assert snap["errors"]["seq"] == list(e_want.seq) and len(e_want) > 0
    assert snap["errors"]["value"] == pytest.approx(list(e_want.value))
    assert {c["structure"] for c in snap["channels"]} >= {"spindle", "spindle_arm", "room"}


def _merge(cur: dict, upd: dict) -> None:
    """Merge an update into a snapshot the way the page does (the last bucket replaced, seq deduplicated)."""
    T, n = cur["temperatures"], upd["temperatures"]
    while T["b"] and n["b"] and T["b"][-1] >= n["b"][0]:
        T["b"].pop()
        T["t"].pop()
        for v in T["values"].values():
            v.pop()
    T["b"] += n["b"]
    T["t"] += n["t"]
    for k, v in T["values"].items():
        v += n["values"][k]
    E, ne = cur["errors"], upd["errors"]
    last = E["seq"][-1] if E["seq"] else -1
    for i, s in enumerate(ne["seq"]):
        if s > last:
            for k in E:
                E[k].append(ne[k][i])


def test_updates_rebuild_the_snapshot(store_url: str, files) -> None:
    """A snapshot plus every update since (one half-filled bucket re-sent each time) equals a later snapshot."""
    cid = _run(files, store_url, commits=3)
    engine = store_engine(store_url)
    window, points = 6 * 3600.0, 60  # buckets of 360 s (6 scans): updates land mid-bucket
    width = live.bucket_width(window, points)
    cur = live.snapshot(engine, cid, window, points)
    after_s, after_seq = max(cur["temperatures"]["t"]), live.latest_seq(engine, cid)
    chans = live.channels(engine, cid)
    for _ in range(3):
        _run(files, store_url, commits=2, resume=True)
        upd = live.update(engine, cid, chans, after_s, after_seq, width)
        assert upd["temperatures"]["t"] and min(upd["temperatures"]["t"]) > after_s - width
        assert all(s > after_seq for s in upd["errors"]["seq"])
        _merge(cur, upd)
        after_s = max(upd["temperatures"]["t"])
        after_seq = max([after_seq, *upd["errors"]["seq"]])
        assert upd["progress"]["scans"] > 0
    later = live.snapshot(engine, cid, window, points)
    assert cur["temperatures"]["b"] == later["temperatures"]["b"]
    assert cur["temperatures"]["t"] == later["temperatures"]["t"]
    for ch, v in later["temperatures"]["values"].items():
        assert cur["temperatures"]["values"][ch] == pytest.approx(v, nan_ok=True), ch
    assert cur["errors"] == later["errors"]


def test_a_finished_campaign_stays_on_show_until_a_newer_one(store_url: str, files) -> None:
    plan, scen = files
    r = run_daemon(load_plan(plan), db_url=store_url, scenario_path=scen, speed=math.inf)
    engine = store_engine(store_url)
    marks = live.live_marks(engine)
    assert marks == {r.campaign_id: marks[r.campaign_id]} and marks[r.campaign_id]["status"] == "done"
    head = live.header(engine, r.campaign_id)
    assert head["progress"]["fraction"] == 1.0 and head["progress"]["total_left_s"] == 0.0
    assert all(s["status"] == "done" for s in head["stages"])
    assert live.find_campaign(engine, "live-test") == r.campaign_id
    assert live.find_campaign(engine, str(r.campaign_id)) == r.campaign_id
    assert live.find_campaign(engine, "nope") is None
    assert live.live_marks(engine, recent_done=False) == {}


def test_health_counts_faults_by_instrument_and_timeouts() -> None:
    cur = {
        "faults": 23,
        "recent_faults": [
            {
                "t_s": 60.0,
                "step": "scan 1",
                "instrument": "thermocouple",
                "message": "thermocouple card: no complete reply within 2 s (gave up after 3 attempts)",
            },
            {"t_s": 70.0, "step": "point 3", "instrument": "laser", "message": "dz: beam"},
            {"t_s": 80.0, "step": "point 4", "instrument": "laser", "message": "laser: timed out"},
        ],
        "retries": {"laser": 4},
    }
    h = live._health(cur, {"t_s": 80.0, "values": {"T10": None, "T2": None, "T1": 20.0}})
    assert h["by_instrument"] == {"thermocouple": 1, "laser": 2}
    assert h["timeouts"] == 2 and h["faults"] == 23 and h["counted_over"] == 3
    assert h["open"] == ["T2", "T10"] and h["retries"] == {"laser": 4}
