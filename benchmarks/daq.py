"""Daemon throughput on the virtual machine: 50 thermocouples at 10 Hz plus a sweep a minute at 3600x.

Prints one JSON line. The end-to-end run drives the real drivers against the simulated servers
and commits through the store exactly as `driftlab daemon` does; it is then taken apart so the
figures say where the time goes:

* ``e2e_*``: the daemon itself (scans/s stored, how far behind the 3600x pace it fell, commit
  latency p99 and reading-to-committed latency p99);
* ``demo_*``: the shipped Z-axis demo plan (thesis-like rates: 60 s scans, sweeps every 15 min) at 3600x;
* ``instruments_scans_per_s``: one thermocouple scan through pyvisa to the simulated card, no store;
* ``store_*``: the scheduler's sink committing the same scans in the same batches, no instruments;
* ``baseline_raw_*``: in-run baseline, plain sqlite3 executemany of the same rows into a table with
  the same key, same batches, same WAL settings.
"""

from __future__ import annotations

import _common  # noqa: F401  (first: pins numeric thread pools)

import math
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import emit, load_average  # noqa: E402

from driftlab.campaigns.clock import SimClock  # noqa: E402
from driftlab.campaigns.plan import Cursor, Plan, parse_plan  # noqa: E402
from driftlab.campaigns.scheduler import (  # noqa: E402
    Batch,
    StoreSink,
    percentile,
    build_sim_rig,
    open_campaign,
    plan_scenario,
    run_daemon,
    scenario_meta,
    store_engine,
)
from driftlab.daq.protocols import TemperatureScan  # noqa: E402
from driftlab.daq.sim.machine import VirtualMachine  # noqa: E402
from driftlab.daq.sim.scenario import load_scenario  # noqa: E402

SPEED = 3600.0
SCAN_S = 0.1  # 10 Hz
SWEEP_S = 60.0  # a sweep every (simulated) minute
SIM_S = float(__import__("os").environ.get("DAQ_SIM_S", 120.0))  # simulated seconds in the end-to-end run
SCENARIO = ROOT / "examples" / "scenarios" / "clean.yaml"


def bench_plan() -> Plan:
    """Return the benchmark plan: one spindle stage, 10 Hz scans, a 10-point Z sweep every minute."""
    return parse_plan({
        "name": "bench-daq", "machine": {"id": "vmc-5ax-01", "channels": "from scenario"},
        "scan_interval_s": SCAN_S, "state_every": 10,
        "stages": [{"name": "spindle-10k", "axis": "Z", "duration_s": SIM_S,
                    "heat": [{"kind": "spindle", "rpm": 10000}],
                    "sweep": {"positions": [-250, -190, -125, -60, 0], "interval_s": SWEEP_S, "point_s": 3.0,
                              "term": "dz"}}],
    })


def end_to_end(tmp: Path) -> dict:
    """Run the daemon path on the virtual machine at 3600x and return its figures."""
    plan = bench_plan()
    result = run_daemon(plan, db_url=f"sqlite:///{tmp / 'e2e.sqlite'}", scenario_path=SCENARIO, speed=SPEED)
    s = result.stats
    return {
        "e2e_finished": s.finished,
        "e2e_scans": s.scans,
        "e2e_sweep_points": s.points,
        "e2e_faults": s.faults,
        "e2e_wall_s": round(s.wall_s, 3),
        "e2e_scans_per_s": round(s.scans_per_s(), 1),
        "required_scans_per_s": round(SPEED / SCAN_S, 1),
        "e2e_keeps_up": s.max_lag_s < SWEEP_S,
        "e2e_max_lag_sim_s": round(s.max_lag_s, 2),
        "e2e_sustainable_speed_x": round(s.scans_per_s() * SCAN_S, 1),
        "e2e_commit_p99_ms": round(s.p99_commit_s() * 1e3, 3),
        "e2e_reading_to_commit_p99_ms": round(s.p99_latency_s() * 1e3, 3),
        "e2e_commits": s.commits,
    }


def demo_plan_run(tmp: Path) -> dict:
    """Run the shipped Z-axis demo plan (60 s scans, 6-point sweeps every 15 min) at 3600x: does it keep up?"""
    from driftlab.campaigns.plan import load_plan

    plan = load_plan(ROOT / "examples" / "plans" / "z-axis-demo.yaml")
    s = run_daemon(plan, db_url=f"sqlite:///{tmp / 'demo.sqlite'}", scenario_path=SCENARIO, speed=SPEED).stats
    return {
        "demo_sim_h": round(plan.total_s / 3600, 2),
        "demo_wall_s": round(s.wall_s, 3),
        "demo_paced_wall_s": round(plan.total_s / SPEED, 3),
        "demo_max_lag_sim_s": round(s.max_lag_s, 2),
        "demo_keeps_up": s.max_lag_s < plan.scan_interval_s,
        "demo_commit_p99_ms": round(s.p99_commit_s() * 1e3, 3),
    }


def instruments_only(n: int = 300) -> dict:
    """Return scans/s of the thermocouple card through pyvisa to the simulated card (no store)."""
    plan = bench_plan()
    scenario = plan_scenario(plan, load_scenario(SCENARIO))
    channels = list(scenario_meta(scenario)["channels"])
    clock = SimClock(speed=math.inf)
    rig = build_sim_rig(plan, scenario, clock, channels)
    try:
        rig.scanner.scan()
        t0 = time.perf_counter()
        for k in range(n):
            clock.wait_until(k * SCAN_S)
            rig.scanner.scan()
        dt = time.perf_counter() - t0
    finally:
        rig.close()
    vm = VirtualMachine(scenario)
    vm.temperatures(0.0)
    t0 = time.perf_counter()
    for k in range(n):
        vm.temperatures(k * SCAN_S)
    vm_dt = time.perf_counter() - t0
    return {"instruments_scans_per_s": round(n / dt, 1), "vm_temperatures_per_s": round(n / vm_dt, 1)}


def scans_from_vm(n: int) -> tuple[list[str], list[TemperatureScan]]:
    """Return n 10 Hz scans of the virtual machine's 50 channels (computed in bulk)."""
    plan = bench_plan()
    vm = VirtualMachine(plan_scenario(plan, load_scenario(SCENARIO)))
    channels = list(scenario_meta(None)["channels"])
    temps = [vm.temperatures(k * SCAN_S) for k in range(min(n, 50))]
    scans = [TemperatureScan(k * SCAN_S, temps[k % len(temps)]) for k in range(n)]
    return channels, scans


def store_only(tmp: Path, channels: list[str], scans: list[TemperatureScan], batch: int) -> dict:
    """Return the sink's rows/s and commit p99 for the same scans in batches (no instruments)."""
    plan = bench_plan()
    engine = store_engine(f"sqlite:///{tmp / 'store.sqlite'}")
    meta = scenario_meta(None)
    handle = open_campaign(engine, plan, meta["channels"], meta["room_channels"], resume=False, origin={})
    sink = StoreSink(engine, plan, handle)
    lat = []
    t0 = time.perf_counter()
    for i in range(0, len(scans), batch):
        chunk = scans[i : i + batch]
        b = Batch(scans=[(i + j, s) for j, s in enumerate(chunk)], cursor=Cursor(i + len(chunk), 0), t_s=chunk[-1].t_s)
        c0 = time.perf_counter()
        sink.commit(b)
        lat.append(time.perf_counter() - c0)
    dt = time.perf_counter() - t0
    return {"store_scans_per_s": round(len(scans) / dt, 1), "store_rows_per_s": round(len(scans) * 50 / dt),
            "store_commit_p99_ms": round(percentile(lat, 99) * 1e3, 3)}


def raw_baseline(tmp: Path, channels: list[str], scans: list[TemperatureScan], batch: int) -> dict:
    """Return plain sqlite3 executemany rows/s and commit p99 for the same rows (same key, WAL)."""
    con = sqlite3.connect(tmp / "raw.sqlite", isolation_level=None)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=NORMAL")
    con.execute("CREATE TABLE t (campaign_id INTEGER, channel_id INTEGER, time_s REAL, value REAL, "
                "PRIMARY KEY (campaign_id, channel_id, time_s)) WITHOUT ROWID")
    ids = {c: i for i, c in enumerate(channels)}
    lat = []
    t0 = time.perf_counter()
    for i in range(0, len(scans), batch):
        rows = [(1, ids[c], s.t_s, v) for s in scans[i : i + batch] for c, v in s.values.items()]
        c0 = time.perf_counter()
        con.execute("BEGIN IMMEDIATE")
        con.executemany("INSERT INTO t VALUES (?, ?, ?, ?)", rows)
        con.execute("COMMIT")
        lat.append(time.perf_counter() - c0)
    dt = time.perf_counter() - t0
    con.close()
    return {"baseline_raw_scans_per_s": round(len(scans) / dt, 1), "baseline_raw_rows_per_s": round(len(scans) * 50 / dt),
            "baseline_raw_commit_p99_ms": round(percentile(lat, 99) * 1e3, 3)}


def main() -> None:
    """Run every part and print one JSON line."""
    figures: dict = {"benchmark": "daq", "channels": 50, "scan_hz": 1 / SCAN_S, "sweep_every_s": SWEEP_S,
                     "speed_x": SPEED, "sim_s": SIM_S, "load_avg_1m": load_average()}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        figures.update(end_to_end(tmp))
        figures.update(demo_plan_run(tmp))
        figures.update(instruments_only())
        channels, scans = scans_from_vm(6000)
        figures.update(store_only(tmp, channels, scans, batch=200))
        figures.update(raw_baseline(tmp, channels, scans, batch=200))
    figures["store_vs_raw"] = round(figures["store_rows_per_s"] / figures["baseline_raw_rows_per_s"], 3)
    emit(figures)


if __name__ == "__main__":
    main()
