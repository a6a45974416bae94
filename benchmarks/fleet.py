"""Fleet benchmark on PostgreSQL: load a fleet's readings, then drift-query latency and fit throughput.

Prints ONE JSON line. At full scale (the defaults): 20 machines x 90 days of 2-minute scans of 50
thermocouples (64.8 million temperature readings), as weekly campaigns from the virtual machine
(``daq.sim``, seeded, generated in this run and never written to disk), each with a five-axis laser
sweep every 2 hours (what a fit needs) and its machine-state log. On a throwaway PostgreSQL cluster
(fsync off, as the other benchmarks), at the store's head schema (reading tables partitioned by
month of campaign start):

- load: every campaign through ``store.campaigns.import_bundle`` (the bulk import path: numpy-encoded
  binary COPY of the temperatures, COPY of the error log and conditions, one transaction each),
  interleaved campaign by campaign with the baseline, a raw psycopg binary COPY (``set_types``,
  ``write_row`` of prepared tuples, one transaction per campaign) of the same temperature rows into
  a scratch table of the same definition (same columns, primary key and partitions). The ratio
  compares readings per second: the import's time covers everything it writes (errors,
  conditions, rollups, channels, statistics), the baseline's only the temperature rows.
- drift: ``--queries`` drift queries of one machine-quarter (the last 90 days of a machine, machines
  in turn) through the REST API in process (``GET /machines/{id}/drift``, FastAPI over ASGI: the
  route calls ``store.readings.drift``) and through ``store.readings.drift`` alone; median and p99. Also: how many
  partitions one of the drift query's statements reads (EXPLAIN).
- fits: ``--fit-jobs`` fit jobs (one per machine in turn, each over its latest ``--fit-campaigns``
  campaigns, network off) queued on procrastinate, then run by 1, 2, ... ``driftlab worker``
  processes (``--workers``); fits per minute from the jobs' own start and end times (worker start-up
  excluded). A 4-worker figure on a 2-core machine measures the machine, not the queue: say so.

Usage: python benchmarks/fleet.py [--machines 20] [--days 90] [--campaign-days 7] [--workers 1,2]
       (a smoke run: --machines 2 --days 3 --campaign-days 1 --queries 5 --fit-jobs 2)
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from itertools import repeat
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import emit, load_average  # noqa: E402  (pins BLAS threads before numpy loads)

# isort: split

import numpy as np  # noqa: E402
from sqlalchemy import select, text  # noqa: E402

from driftlab.campaigns import partitions  # noqa: E402
from driftlab.campaigns import schema as sc  # noqa: E402
from driftlab.campaigns.bundle import Bundle, CampaignMeta  # noqa: E402
from driftlab.campaigns.ingest import CONDITION_VALUE_COLUMNS, ERROR_COLUMNS, sweep_numbers  # noqa: E402
from driftlab.campaigns.store import Store, connect  # noqa: E402
from driftlab.daq.sim.campaign import simulate_campaign  # noqa: E402
from driftlab.daq.sim.scenario import MachineInfo, Scenario  # noqa: E402
from driftlab.testing.pgcluster import PgCluster  # noqa: E402

T0 = datetime(2026, 1, 5, 6, 0, tzinfo=UTC)
RAW_PREFIX = "bench_raw_"


def machine_id(m: int) -> str:
    """Return the id of the fleet's m-th machine."""
    return f"fleet-{m + 1:02d}"


def campaign_bundle(m: int, k: int, args: argparse.Namespace) -> Bundle | None:
    """Return machine m's k-th campaign (None past the end of the fleet's days), simulated."""
    start = T0 + timedelta(days=k * args.campaign_days, minutes=7 * m)
    hours = min(args.campaign_days, args.days - k * args.campaign_days) * 24.0
    if hours <= 0:
        return None
    scenario = Scenario(
        name=f"{machine_id(m)}-c{k + 1:03d}",
        seed=1000 * m + k,
        hours=hours,
        scan_interval_s=args.scan_s,
        sweep_interval_s=args.sweep_h * 3600.0,
        started_at=start.isoformat().replace("+00:00", "Z"),
        machine=MachineInfo(id=machine_id(m), name=f"fleet machine {m + 1}"),
    )
    sim = simulate_campaign(scenario)
    temps = sim.temperatures
    if args.channels < temps.shape[1] - 1:
        temps = temps.iloc[:, : args.channels + 1]
    meta = dict(sim.meta)
    names = [c for c in temps.columns if c != "time_s"]
    meta["channels"] = {c: meta["channels"][c] for c in names}
    meta["room_channels"] = [c for c in meta["room_channels"] if c in names]
    meta["model_channels"] = {a: [c for c in cs if c in names] for a, cs in (meta.get("model_channels") or {}).items()}
    return Bundle(scenario.name, CampaignMeta.model_validate(meta), temps, sim.conditions, sim.errors)


RAW_COLUMNS = {
    "temperature_samples": (
        ("campaign_id", "channel_id", "time_s", "value", "campaign_start_day"),
        ("int4", "int4", "float8", "float8", "int4"),
    ),
    "condition_samples": (
        ("campaign_id", "time_s", *CONDITION_VALUE_COLUMNS, "campaign_start_day"),
        ("int4", "float8", *["float8"] * len(CONDITION_VALUE_COLUMNS), "int4"),
    ),
    # the simulator writes bundle v1 error logs (no pose, no setup): the import leaves those columns NULL
    "error_samples": (
        ERROR_COLUMNS,
        ("int4", "int4", "float8", "varchar", "varchar", "float8", "int2", "float8", "int4", "int4", "int4"),
    ),
}


def make_raw_tables(store: Store) -> None:
    """Create the baseline's scratch tables: each reading table's definition, partitioning and keys."""
    with store.engine.begin() as conn:
        for table in RAW_COLUMNS:
            conn.execute(
                text(
                    f"CREATE TABLE {RAW_PREFIX}{table} (LIKE {table} INCLUDING DEFAULTS "
                    "INCLUDING CONSTRAINTS INCLUDING INDEXES) PARTITION BY RANGE (campaign_start_day)"
                )
            )


def raw_copy(store: Store, day: int, rows: dict[str, list[tuple[Any, ...]]]) -> float:
    """COPY prepared rows into the scratch tables (binary, set_types, one transaction); return the seconds."""
    with store.engine.begin() as conn:
        for table in RAW_COLUMNS:
            for p in partitions.missing(conn, [day], tables=[RAW_PREFIX + table]):
                conn.execute(text(f"CREATE TABLE {p.name} PARTITION OF {p.table} FOR VALUES FROM ({p.lo}) TO ({p.hi})"))
    with store.engine.connect() as conn:
        raw = conn.connection.driver_connection
        # straight into the month's partitions, as the import does (looked up off the clock)
        leaves = {t: partitions.leaf(conn, RAW_PREFIX + t, day) for t in RAW_COLUMNS}
        start = time.perf_counter()
        with raw.cursor() as cur:
            for table, (columns, types) in RAW_COLUMNS.items():
                with cur.copy(f"COPY {leaves[table]} ({', '.join(columns)}) FROM STDIN (FORMAT BINARY)") as copy:
                    copy.set_types(list(types))
                    for row in rows[table]:
                        copy.write_row(row)
        raw.commit()
        return time.perf_counter() - start


def _none(values: np.ndarray) -> list[Any]:
    return [None if x != x else x for x in values.tolist()]


def baseline_rows(
    campaign_id: int, first_channel_id: int, day: int, bundle: Bundle
) -> dict[str, list[tuple[Any, ...]]]:
    """Return the reading rows the import writes for a bundle (the same ids in a fresh database: campaigns
    and channels are numbered in import order), prepared as a raw client would hold them."""
    temps = bundle.temperatures
    t = temps["time_s"].to_numpy(dtype="f8").tolist()
    n = len(t)
    out: dict[str, list[tuple[Any, ...]]] = {"temperature_samples": []}
    for ch, name in enumerate((c for c in temps.columns if c != "time_s"), start=first_channel_id):
        out["temperature_samples"].extend(
            zip(repeat(campaign_id, n), repeat(ch, n), t, _none(temps[name].to_numpy(dtype="f8")), repeat(day, n))
        )
    cond = bundle.conditions
    assert cond is not None
    out["condition_samples"] = list(
        zip(
            repeat(campaign_id),
            cond["time_s"].tolist(),
            *[_none(cond[c].to_numpy(dtype="f8")) for c in CONDITION_VALUE_COLUMNS],
            repeat(day, len(cond)),
        )
    )
    err = bundle.errors
    assert not bundle.meta.v2
    out["error_samples"] = list(
        zip(
            repeat(campaign_id),
            range(len(err)),
            err["time_s"].tolist(),
            err["axis"].tolist(),
            err["term"].tolist(),
            err["position"].tolist(),
            err["direction"].tolist(),
            err["value"].tolist(),
            sweep_numbers(err).tolist(),
            repeat(0),
            repeat(day, len(err)),
        )
    )
    return out


def load(store: Store, args: argparse.Namespace, figures: dict[str, Any]) -> dict[str, list[int]]:
    """Load the fleet (import and baseline interleaved); return campaign ids per machine."""
    import_s = raw_s = gen_s = 0.0
    readings = errors = conditions = stored = channels = all_rows = 0
    ids: dict[str, list[int]] = {}
    k = 0
    while True:
        any_left = False
        for m in range(args.machines):
            g0 = time.perf_counter()
            bundle = campaign_bundle(m, k, args)
            if bundle is None:
                continue
            any_left = True
            day = partitions.start_day(bundle.meta.started_at)
            rows = baseline_rows(stored + 1, channels + 1, day, bundle) if args.baseline else {}
            gen_s += time.perf_counter() - g0
            if args.baseline:  # the raw COPY first on odd campaigns, the import first on even ones
                if k % 2:
                    raw_s += raw_copy(store, day, rows)
            t0 = time.perf_counter()
            cid = store.campaigns.import_bundle(bundle)
            import_s += time.perf_counter() - t0
            if args.baseline and not k % 2:
                raw_s += raw_copy(store, day, rows)
            ids.setdefault(machine_id(m), []).append(cid)
            stored += 1
            channels += bundle.temperatures.shape[1] - 1
            readings += bundle.temperatures.shape[0] * (bundle.temperatures.shape[1] - 1)
            all_rows += sum(len(v) for v in rows.values())
            errors += len(bundle.errors)
            conditions += 0 if bundle.conditions is None else len(bundle.conditions)
            del bundle, rows
        if not any_left:
            break
        k += 1
    rate = readings / import_s
    figures.update(
        {
            "campaigns": sum(len(v) for v in ids.values()),
            "readings": readings,
            "error_samples": errors,
            "condition_samples": conditions,
            "generate_s": round(gen_s, 1),
            "import_s": round(import_s, 1),
            "import_readings_per_s": round(rate),
        }
    )
    if args.baseline:
        figures.update(
            {
                "raw_copy_s": round(raw_s, 1),
                "raw_copy_rows_per_s": round(all_rows / raw_s),
                "import_rows_per_s": round(all_rows / import_s),
                "import_ratio_to_raw_copy": round(raw_s / import_s, 3),
                "import_ratio_target": 0.9,
            }
        )
    return ids


def pct(values: list[float], q: float) -> float:
    """Return the q-th percentile in milliseconds, rounded."""
    return round(float(np.percentile(np.array(values) * 1000, q)), 2)


def drift_latency(store: Store, args: argparse.Namespace, figures: dict[str, Any]) -> None:
    """Time drift queries of one machine-quarter, through the API in process and through the store."""
    from fastapi.testclient import TestClient

    from driftlab.api.app import create_app

    end = T0 + timedelta(days=args.days)
    start = end - timedelta(days=min(90, args.days))
    position = 250.0  # between measured points: the nearest one is looked up per campaign
    queries = [(machine_id(i % args.machines), "Z", ("dz", "dx", "alpha")[i % 3]) for i in range(args.queries)]
    params = {"position": position, "direction": 1, "start": start.isoformat(), "end": end.isoformat()}
    app = create_app(store.engine.url.render_as_string(hide_password=False), token="", run_jobs=False)
    api_s, store_s, points = [], [], []
    with TestClient(app) as client:
        for machine, axis, term in queries[:3]:  # warm-up: connections, statement caches
            client.get(f"/machines/{machine}/drift", params={"axis": axis, "term": term, **params})
        for machine, axis, term in queries:
            t0 = time.perf_counter()
            r = client.get(f"/machines/{machine}/drift", params={"axis": axis, "term": term, **params})
            api_s.append(time.perf_counter() - t0)
            r.raise_for_status()
            points.append(len(r.json()["points"]))
    for machine, axis, term in queries:
        t0 = time.perf_counter()
        store.readings.drift(machine, axis, term, position=position, direction=1, start=start, end=end)
        store_s.append(time.perf_counter() - t0)
    interp_s = []
    for machine, axis, term in queries[: max(5, len(queries) // 5)]:
        t0 = time.perf_counter()
        store.readings.drift(
            machine, axis, term, position=position, direction=1, start=start, end=end, interpolate=True
        )
        interp_s.append(time.perf_counter() - t0)
    figures.update(
        {
            "drift_queries": len(queries),
            "drift_window_days": (end - start).days,
            "campaigns_per_machine": len(store.campaigns.summaries(machine_id(0))),
            "drift_points_per_query_median": int(statistics.median(points)),
            "drift_api_median_ms": pct(api_s, 50),
            "drift_api_p99_ms": pct(api_s, 99),
            "drift_store_median_ms": pct(store_s, 50),
            "drift_store_p99_ms": pct(store_s, 99),
            "drift_interpolated_store_median_ms": pct(interp_s, 50),
            "drift_target_median_ms": 50.0,
        }
    )
    figures["drift_ok"] = figures["drift_api_median_ms"] < 50.0
    # pruning: the drift query's per-campaign statement reads one partition of error_samples
    with store.engine.connect() as conn:
        cid, started = conn.execute(
            select(sc.Campaign.id, sc.Campaign.started_at)
            .where(sc.Campaign.machine_id == machine_id(0))
            .order_by(sc.Campaign.started_at.desc())
        ).first()
        plan = (
            conn.execute(
                text(
                    "EXPLAIN SELECT time_s, position, direction, sweep, value FROM error_samples "
                    "WHERE campaign_id = :c AND campaign_start_day = :day "
                    "AND axis = 'Z' AND term = 'dz' AND direction = 1 AND position = 250.0"
                ),
                {"c": cid, "day": partitions.start_day(started)},
            )
            .scalars()
            .all()
        )
        n_parts = len(partitions.partitions(conn, "error_samples"))
    scanned = sorted({m for line in plan for m in re.findall(r" on (error_samples_p\w+)", line)})
    figures.update(
        {
            "error_samples_partitions": n_parts,
            "drift_statement_partitions_read": len(scanned),
            "drift_statement_plan": " | ".join(line.strip() for line in plan)[:300],
        }
    )


def fit_throughput(store: Store, ids: dict[str, list[int]], args: argparse.Namespace, figures: dict[str, Any]) -> None:
    """Queue fit jobs and run them with 1, 2, ... worker processes; fits per minute for each."""
    from driftlab.jobs import submit
    from driftlab.jobs.tasks import FIT

    url = store.engine.url.render_as_string(hide_password=False)
    machines = sorted(ids)
    per: dict[str, Any] = {}
    for workers in args.workers:
        jobs = []
        for j in range(args.fit_jobs):
            m = machines[j % len(machines)]
            jobs.append(
                submit(
                    store,
                    FIT,
                    {"campaigns": ids[m][-args.fit_campaigns :], "network": False},
                    machine_id=m,
                    campaign_id=ids[m][-1],
                )
            )
        env = {**os.environ, "DRIFTLAB_DB_URL": url}
        procs = [
            subprocess.Popen(
                [sys.executable, "-m", "driftlab", "worker", "--until-idle", "--name", f"bench-{w}"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            for w in range(workers)
        ]
        for p in procs:
            p.wait()
        done = [store.jobs.get(j) for j in jobs]
        failed = [j for j in done if j.state != "done"]
        if failed:
            raise SystemExit(f"{len(failed)} fit job(s) did not end done: {failed[0].state} {failed[0].error}")
        first = min(j.started_at for j in done)
        last = max(j.finished_at for j in done)
        span = (last - first).total_seconds()
        each = [(j.finished_at - j.started_at).total_seconds() for j in done]
        per[str(workers)] = {
            "fits": len(done),
            "span_s": round(span, 1),
            "fits_per_min": round(len(done) / span * 60, 2),
            "fit_s_median": round(statistics.median(each), 2),
        }
    figures["fit_jobs"] = per
    base = per.get("1")
    if base:
        figures["fit_speedup_vs_1_worker"] = {
            w: round(v["fits_per_min"] / base["fits_per_min"], 2) for w, v in per.items()
        }
    figures["fit_note"] = (
        f"{os.cpu_count()} cores: worker counts above the core count share the cores; "
        "the issue's 4-worker target needs a 4-core host"
    )


def sizes(store: Store, figures: dict[str, Any]) -> None:
    """Record the database's size and the reading tables' partitions."""
    with store.engine.connect() as conn:
        figures["database_gb"] = round(
            conn.execute(text("SELECT pg_database_size(current_database())")).scalar() / 2**30, 2
        )
        rows = partitions.describe(conn)
    figures["temperature_samples_gb"] = round(
        sum(r["bytes"] for r in rows if r["table"] == "temperature_samples") / 2**30, 2
    )
    figures["partitions"] = sorted({r["partition"].rsplit("_p", 1)[1] for r in rows})


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one JSON line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=20)
    ap.add_argument("--days", type=int, default=90)
    ap.add_argument("--campaign-days", type=int, default=7, help="length of each campaign (days)")
    ap.add_argument("--channels", type=int, default=50)
    ap.add_argument("--scan-s", type=float, default=120.0, help="thermocouple scan interval (s)")
    ap.add_argument("--sweep-h", type=float, default=2.0, help="laser sweep interval (h)")
    ap.add_argument("--queries", type=int, default=50)
    ap.add_argument("--workers", default="1,2", help="worker counts to time, comma-separated ('' = no fits)")
    ap.add_argument("--fit-jobs", type=int, default=20)
    ap.add_argument("--fit-campaigns", type=int, default=2, help="campaigns per fit (a machine's latest)")
    ap.add_argument("--no-baseline", dest="baseline", action="store_false", help="skip the raw COPY baseline")
    ap.add_argument("--pg-dir", default=None, help="where the throwaway cluster lives (default: a temp dir)")
    args = ap.parse_args(argv)
    args.workers = [int(w) for w in args.workers.split(",") if w.strip()]
    figures: dict[str, Any] = {
        "benchmark": "fleet",
        "machines": args.machines,
        "days": args.days,
        "campaign_days": args.campaign_days,
        "channels": args.channels,
        "scan_s": args.scan_s,
        "sweep_h": args.sweep_h,
        "cpus": os.cpu_count(),
        "load_average_1m_at_start": load_average(),
        "postgres_settings": "throwaway cluster: fsync=off, synchronous_commit=off, full_page_writes=off, "
        "defaults else",
    }
    if args.pg_dir:
        Path(args.pg_dir).mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="driftlab-fleet-"))
    try:
        with PgCluster(base_dir=args.pg_dir) as pg:
            store = connect(pg.create_database("fleet"))
            store.ensure_schema()
            if args.baseline:
                make_raw_tables(store)
            w0 = time.perf_counter()
            ids = load(store, args, figures)
            figures["load_wall_s"] = round(time.perf_counter() - w0, 1)
            if args.baseline:
                with store.engine.begin() as conn:
                    conn.execute(
                        text(", ".join(f"DROP TABLE {RAW_PREFIX}{t}" for t in RAW_COLUMNS).replace(", DROP TABLE", ","))
                    )
            with store.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
                conn.execute(text("VACUUM ANALYZE"))  # as after a while of autovacuum: every partition analysed
            sizes(store, figures)
            drift_latency(store, args, figures)
            if args.workers and args.fit_jobs:
                fit_throughput(store, ids, args, figures)
            figures["load_average_1m_at_end"] = load_average()
            store.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    emit(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
