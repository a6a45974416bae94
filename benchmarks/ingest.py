"""Import speed of a 70-hour, 50-channel, 1 Hz bundle on SQLite and PostgreSQL, beside raw baselines.

Prints ONE JSON line. The bundle (12.6 million temperature readings plus a laser error log) is
generated here with numpy into a temp dir, never committed. Baselines, measured in the same run
into the same table definition with the same connection settings:
- SQLite: sqlite3 ``executemany`` of prepared tuples, one transaction;
- PostgreSQL: psycopg binary COPY (``set_types``) of the same tuples;
each of the bundle's rows: the temperatures into temperature_samples, then the error and condition
rows the import stores into error_samples and condition_samples (``*_ratio_to_raw``). The time of the
temperatures alone (with the commit) is the baseline this benchmark had before 27 Nov 2026
(``*_ratio_to_raw_temperatures_only``): the import writes the other tables and the rollups besides.
The baseline's rows are deleted after it, and before the import the tables are vacuumed back to their
state before the baseline (SQLite ``VACUUM``, PostgreSQL ``VACUUM`` of each table): otherwise
the import would write among 12.6 million deleted rows (SQLite's free list, PostgreSQL's dead
primary-key entries above the import's keys, which cost its appends the rightmost-page fast path),
which an import into a store never meets, and measured 0.59-0.79 of the baseline for that alone.
The import figures are end to end (parse + validate + stage + hash + write + commit):
``store.campaigns.import_directory``, as `driftlab import` (on PostgreSQL the files are read while the
server writes: ``campaigns.import_pipeline``).
The ratio is also given in CPU seconds (``*_cpu_ratio_to_raw``): on SQLite of this process, where the
database works; on PostgreSQL of this process and the cluster's processes (read from /proc): on a
shared machine the wall clock also counts waiting for a core.
Also: median of 20 drift queries (nearest position, and interpolated) and 20 1,000-bucket histories.

Usage: python benchmarks/ingest.py [--hours 70] [--channels 50] [--skip-pg]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from itertools import repeat
from pathlib import Path

import numpy as np
import pandas as pd

from driftlab.campaigns import ingest
from driftlab.campaigns.bundle import FrameTable, load_bundle, write_bundle
from driftlab.campaigns.partitions import ensure_partitions, start_day
from driftlab.campaigns.store import Store, connect
from driftlab.testing.pgcluster import PgCluster, pg_binaries_available

MACHINE = "bench-vmc"


def make_bundle(root: Path, hours: float, channels: int, seed: int = 0) -> Path:
    """Write a synthetic campaign bundle: 1 Hz temperatures, a Z sweep (21 points, both ways) every 10 min."""
    rng = np.random.default_rng(seed)
    n = int(hours * 3600)
    t = np.arange(n, dtype=float)
    names = [f"T{k + 1}" for k in range(channels)]
    heat = 1.0 - np.exp(-t / 7200.0)
    temps = {"time_s": t}
    for k, name in enumerate(names):
        temps[name] = np.round(20.0 + (k % 7) * heat + 0.3 * np.sin(t / 3600.0 + k) + rng.normal(0, 0.02, n), 4)
    temperatures = pd.DataFrame(temps)
    temperatures.loc[rng.integers(0, n, 200), names[min(3, channels - 1)]] = np.nan  # a few missing readings
    cond = pd.DataFrame(
        {
            "time_s": t[::10],
            "spindle_rpm": np.where((t[::10] // 14400) % 2 == 0, 8000.0, 0.0),
            "feed_mm_min": 0.0,
            "x": 0.0,
            "y": 0.0,
            "z": 0.0,
            "a": 0.0,
            "b": 0.0,
        }
    )
    positions = np.linspace(0.0, 500.0, 21)
    terms = ("dx", "dy", "dz", "alpha", "beta", "gamma")
    rows = []
    for _s, t0 in enumerate(np.arange(0.0, n - 600, 600.0)):
        drift = 1 - np.exp(-t0 / 7200.0)
        for d, order in ((1, positions), (-1, positions[::-1])):
            for i, p in enumerate(order):
                ts = t0 + (i + (21 if d < 0 else 0)) * 5.0
                for term in terms:
                    scale = 1e-5 if term in ("alpha", "beta", "gamma") else 0.02
                    rows.append((ts, "Z", term, p, d, scale * (drift * p / 500 + 0.05 * d) + rng.normal(0, scale / 50)))
    errors = pd.DataFrame(rows, columns=["time_s", "axis", "term", "position", "direction", "value"])
    meta = {
        "format": "driftlab-bundle/1",
        "machine": {"id": MACHINE, "name": "benchmark VMC", "resolution_mm": 0.0025},
        "started_at": "2026-03-02T08:00:00Z",
        "channels": {name: {"location": f"site {name}", "structure": "column"} for name in names},
        "room_channels": names[-2:],
        "stages": [
            {
                "name": f"stage-{k}",
                "start_s": k * 14400.0,
                "end_s": min((k + 1) * 14400.0, n - 1.0),
                "heat_source": "spindle" if k % 2 == 0 else "none",
                "axis": "Z",
                "spindle_rpm": 8000.0 if k % 2 == 0 else 0.0,
                "feed_mm_min": 0.0,
            }
            for k in range(int(np.ceil(n / 14400.0)))
        ],
    }
    return write_bundle(root / "bench-bundle", meta, temperatures, cond, errors)


#: the bundle's campaign_start_day (partitions.start_day of 2026-03-02T08:00Z): the baseline writes the
#: same key, into the same partition, as the import
START_DAY = start_day(pd.Timestamp("2026-03-02T08:00:00Z").to_pydatetime())


def baseline_rows(n_scans: int, channels: int) -> list[tuple[int, int, float, float, int]]:
    """Return prepared (campaign, channel, time, value, start day) tuples, as a raw client would hold them."""
    t = np.arange(n_scans, dtype=float).tolist()
    v = (20.0 + np.arange(n_scans) * 1e-5).tolist()
    rows: list[tuple[int, int, float, float, int]] = []
    for ch in range(channels):
        rows.extend(zip(repeat(999, n_scans), repeat(ch, n_scans), t, v, repeat(START_DAY, n_scans)))
    return rows


#: CPU seconds of each raw run (SQLite: this process, where the database works; PostgreSQL: this
#: process and the cluster's, ``cpu_s``): the insert's whole cost, unlike the wall clock of a machine
#: shared with other work
LAST_RAW_CPU_S: list[float] = []

#: the PostgreSQL cluster's data directory while its backend is measured (None: SQLite)
PG_DATA: list[Path] = []


def _proc_times(pid: int | str) -> tuple[int, list[int]]:
    """Return a process's parent pid and its utime, stime, cutime, cstime in clock ticks (proc(5), stat)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return int(fields[1]), [int(x) for x in fields[11:15]]


def cpu_s() -> float:
    """Return the CPU seconds of this process, plus on PostgreSQL those of its cluster: the postmaster
    with the children it reaped (cutime, cstime) and every live child (backends, WAL writer, ...)."""
    total = time.process_time()
    if not PG_DATA:
        return total
    postmaster = int((PG_DATA[0] / "postmaster.pid").read_text().split()[0])
    ticks = sum(_proc_times(postmaster)[1])
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                parent, times = _proc_times(entry)
            except OSError:  # gone meanwhile
                continue
            if parent == postmaster:
                ticks += times[0] + times[1]
    return total + ticks / os.sysconf("SC_CLK_TCK")


@dataclass
class RawRows:
    """Prepared tuples of the bundle's readings, as a raw client would hold them: the temperatures
    (``baseline_rows``), and the error and condition rows the import stores (``ingest.error_rows``,
    ``ingest.condition_rows`` of the bundle, campaign 999)."""

    temperatures: list
    errors: list
    conditions: list


def raw_rows(bundle_dir: Path, n_scans: int, channels: int, postgres: bool) -> RawRows:
    """Return the raw baseline's tuples of the bundle in ``bundle_dir``."""
    bundle = load_bundle(bundle_dir)
    errors = list(ingest.error_rows(999, FrameTable(bundle.errors), False, START_DAY))
    conditions = list(ingest.condition_rows(999, FrameTable(bundle.conditions), postgres, START_DAY))
    return RawRows(baseline_rows(n_scans, channels), errors, conditions)


#: the raw baseline's tables: (table, columns, PostgreSQL types) of each kind of row
RAW_TABLES = {
    "temperatures": ("temperature_samples", ingest.TEMPERATURE_COLUMNS, ingest.TEMPERATURE_TYPES),
    "errors": ("error_samples", ingest.ERROR_COLUMNS, ingest.ERROR_TYPES),
    "conditions": ("condition_samples", ingest.CONDITION_ROW_COLUMNS, ingest.CONDITION_ROW_TYPES),
}


#: wall seconds of each raw run: (temperatures alone, every table) with their commit
LAST_RAW_S: list[tuple[float, float]] = []


def raw_sqlite(store: Store, rows: RawRows, clean: bool = True) -> float:
    """Return the wall seconds of sqlite3 executemany of every raw tuple in one transaction.

    The temperatures go first and their time alone is kept too (``LAST_RAW_S``). The rows are
    deleted again afterwards; with ``clean`` the file is vacuumed back to its state before.
    """
    with store.engine.connect() as conn:
        raw = conn.connection.driver_connection
        cpu0 = cpu_s()
        start = time.perf_counter()
        raw.execute("BEGIN")
        temperatures_s = 0.0
        for kind, (table, columns, _types) in RAW_TABLES.items():
            marks = ", ".join("?" * len(columns))
            raw.executemany(f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({marks})", getattr(rows, kind))
            if kind == "temperatures":
                temperatures_s = time.perf_counter() - start
        commit = time.perf_counter()
        raw.execute("COMMIT")
        commit_s = time.perf_counter() - commit
        elapsed = time.perf_counter() - start
        LAST_RAW_CPU_S.append(cpu_s() - cpu0)
        LAST_RAW_S.append((temperatures_s + commit_s, elapsed))
        raw.execute("BEGIN")
        for table, _columns, _types in RAW_TABLES.values():
            raw.execute(f"DELETE FROM {table} WHERE campaign_id = 999")
        raw.execute("COMMIT")
        if clean:
            # the deleted rows' pages would otherwise be the import's free list: 12.6 million rows'
            # worth of scattered pages to fill, which an import into a store never meets
            raw.execute("VACUUM")
    return elapsed


def raw_postgres(store: Store, rows: RawRows, clean: bool = True) -> float:
    """Return the wall seconds of psycopg binary COPY (set_types) of every raw tuple in one transaction."""
    ensure_partitions(store.engine, [START_DAY])
    with store.engine.connect() as conn:
        raw = conn.connection.driver_connection
        raw.commit()
        cpu0 = cpu_s()
        start = time.perf_counter()
        temperatures_s = 0.0
        with raw.cursor() as cur:
            for kind, (table, columns, types) in RAW_TABLES.items():
                with cur.copy(f"COPY {table} ({', '.join(columns)}) FROM STDIN (FORMAT BINARY)") as copy:
                    copy.set_types(list(types))
                    for row in getattr(rows, kind):
                        copy.write_row(row)
                if kind == "temperatures":
                    temperatures_s = time.perf_counter() - start
        commit = time.perf_counter()
        raw.commit()
        commit_s = time.perf_counter() - commit
        elapsed = time.perf_counter() - start
        LAST_RAW_CPU_S.append(cpu_s() - cpu0)
        LAST_RAW_S.append((temperatures_s + commit_s, elapsed))
        with raw.cursor() as cur:
            for table, _columns, _types in RAW_TABLES.values():
                cur.execute(f"DELETE FROM {table} WHERE campaign_id = 999")
        raw.commit()
        # VACUUM takes the deleted rows out of the primary key again: left there, their 12.6 million
        # dead entries (keys above every real campaign's) would stand in the way of the import's
        # appends, which a store never meets (a new campaign's keys are the largest)
        if clean:
            raw.autocommit = True
            try:
                for table, _columns, _types in RAW_TABLES.values():
                    raw.execute(f"VACUUM {table}")
            finally:
                raw.autocommit = False
    return elapsed


def median_ms(fn, runs: int = 20) -> float:
    """Return the median wall time of ``runs`` calls in milliseconds."""
    fn()  # warm caches once
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return round(statistics.median(times) * 1000, 2)


def run_backend(label: str, url: str, bundle_dir: Path, readings: int, n_scans: int, channels: int) -> dict:
    """Measure import, raw baseline, drift and history query times on one database."""
    store = connect(url)
    store.ensure_schema()
    rows = raw_rows(bundle_dir, n_scans, channels, postgres=label != "sqlite")
    raw = raw_sqlite if label == "sqlite" else raw_postgres
    raw(store, rows)
    cpu0 = cpu_s()
    start = time.perf_counter()
    with store.campaigns.import_directory(bundle_dir) as imported:  # what `driftlab import` does
        campaign_id = imported.campaign_id
    done = time.perf_counter()
    import_cpu = cpu_s() - cpu0
    total = done - start
    # the baseline again after the import; the better of the two is the one compared against
    # (the machine is shared, so a single baseline can be flattered by a quiet moment elsewhere)
    raw(store, rows, clean=False)  # nothing is imported after it
    del rows
    raw_all = min(r[1] for r in LAST_RAW_S[-2:])
    raw_temperatures = min(r[0] for r in LAST_RAW_S[-2:])
    mid = 250.0 + 7.0
    t0 = pd.Timestamp("2026-03-02T08:00:00Z")
    drift_ms = median_ms(lambda: store.readings.drift(MACHINE, "Z", "dz", position=mid, direction=1))
    interp_ms = median_ms(lambda: store.readings.drift(MACHINE, "Z", "dz", position=mid, direction=1, interpolate=True))
    window_ms = median_ms(
        lambda: store.readings.drift(
            MACHINE, "Z", "dz", position=mid, start=t0 + pd.Timedelta(hours=10), end=t0 + pd.Timedelta(hours=20)
        )
    )
    hist_ms = median_ms(lambda: store.readings.temperature_history(campaign_id, "T7", buckets=1000))
    n_drift = len(store.readings.drift(MACHINE, "Z", "dz", position=mid, direction=1))
    store.close()
    # the same comparison in CPU seconds (the better raw run, as above)
    raw_cpu = min(LAST_RAW_CPU_S[-2:])
    cpu = {f"{label}_import_cpu_s": round(import_cpu, 2), f"{label}_cpu_ratio_to_raw": round(raw_cpu / import_cpu, 3)}
    return {
        f"{label}_import_s": round(total, 2),
        f"{label}_readings_per_s": round(readings / total),
        f"{label}_raw_baseline_s": round(raw_all, 2),
        f"{label}_raw_baseline_runs_s": [round(r[1], 2) for r in LAST_RAW_S[-2:]],
        # the import beside the raw insert of the same rows (temperatures, conditions and errors)
        f"{label}_ratio_to_raw": round(raw_all / total, 3),
        # ... and beside the raw temperatures alone (the import also writes the errors, the
        # conditions and the rollups: this is the figure of the benchmark before 27 Nov 2026)
        f"{label}_raw_temperatures_only_s": round(raw_temperatures, 2),
        f"{label}_ratio_to_raw_temperatures_only": round(raw_temperatures / total, 3),
        f"{label}_drift_query_median_ms": drift_ms,
        f"{label}_drift_interpolated_median_ms": interp_ms,
        f"{label}_drift_window_median_ms": window_ms,
        f"{label}_drift_points": n_drift,
        f"{label}_history_1000_buckets_median_ms": hist_ms,
        **cpu,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one JSON line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=70.0)
    ap.add_argument("--channels", type=int, default=50)
    ap.add_argument("--skip-pg", action="store_true")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="driftlab-bench-"))
    figures: dict = {
        "benchmark": "ingest",
        "hours": args.hours,
        "channels": args.channels,
        "load_average_1m_at_start": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
    }
    try:
        start = time.perf_counter()
        bundle_dir = make_bundle(tmp, args.hours, args.channels)
        figures["generate_s"] = round(time.perf_counter() - start, 2)
        n_scans = int(args.hours * 3600)
        readings = n_scans * args.channels
        figures["readings"] = readings
        figures["error_samples"] = sum(1 for _ in open(bundle_dir / "errors.csv")) - 1
        figures.update(
            run_backend("sqlite", f"sqlite:///{tmp / 'bench.sqlite'}", bundle_dir, readings, n_scans, args.channels)
        )
        if not args.skip_pg and pg_binaries_available():
            with PgCluster() as pg:
                PG_DATA.append(pg.data)
                figures["postgres_settings"] = "fsync=off, synchronous_commit=off (throwaway cluster)"
                figures.update(
                    run_backend("postgres", pg.create_database(), bundle_dir, readings, n_scans, args.channels)
                )
        else:
            figures["postgres"] = "skipped"
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    sys.stdout.write(json.dumps(figures) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
