"""Fleet scale: the reading tables partitioned by month of campaign start (PostgreSQL), one logical schema.

- partitions are made ahead of every write (import, daemon, the workers' periodic task), race-safe;
- the drift query's statements read one partition (pruning visible in EXPLAIN, also for a
  prepared statement's generic plan);
- revision 0008 converts a populated store (rows preserved, both ways, both databases);
- SQLite and PostgreSQL answer the same queries identically on the same data.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Iterator
from datetime import UTC, date, datetime
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pandas as pd
import pytest
import sqlalchemy as sa
from alembic import command
from sqlalchemy import event, func, select, text

from driftlab.campaigns import db, partitions
from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import Bundle, load_bundle
from driftlab.campaigns.partitions import start_day
from driftlab.campaigns.readings_repo import nearest_sql
from driftlab.campaigns.store import Store, connect
from driftlab.testing.pgcluster import PgCluster

MACHINE = "vmc-test-01"
#: campaigns of one machine over three months (the last one's readings run into April: same partition)
STARTS = ("2026-01-20T06:00:00Z", "2026-02-03T23:30:00-02:00", "2026-03-31T23:50:00Z")


def _rows(conn: Any, sql: str, **params: Any) -> list[Any]:
    return list(conn.execute(text(sql), params).all())


@pytest.fixture
def pg(request: pytest.FixtureRequest) -> Iterator[Store]:
    """An empty store at head on the throwaway cluster (shared database, emptied)."""
    from tests.conftest import _truncate_all

    url: str = request.getfixturevalue("_pg_head_database")
    _truncate_all(url)
    with connect(url) as store:
        yield store


@pytest.fixture
def fresh_pg(pg_cluster: PgCluster) -> Iterator[Store]:
    """A store at head in a database of its own (for tests that drop partitions)."""
    with connect(pg_cluster.create_database()) as store:
        store.ensure_schema()
        yield store


def _import_months(store: Store, bundle_factory) -> list[int]:
    return [
        store.campaigns.import_bundle(load_bundle(bundle_factory(seed=k, started_at=s))) for k, s in enumerate(STARTS)
    ]


def _where(store: Store, table: str, campaign_id: int) -> set[str]:
    """Return the partitions holding a campaign's rows of ``table``."""
    with store.engine.connect() as conn:
        return set(
            conn.execute(
                text(f"SELECT DISTINCT tableoid::regclass::text FROM {table} WHERE campaign_id = :c"),
                {"c": campaign_id},
            ).scalars()
        )


# ----------------------------------------------------------------------------- the key


def test_start_day_is_the_utc_date_of_the_start() -> None:
    assert start_day(datetime(1970, 1, 1, tzinfo=UTC)) == 0
    assert start_day(datetime.fromisoformat("2026-02-03T23:30:00-02:00")) == (date(2026, 2, 4) - date(1970, 1, 1)).days
    assert partitions.month_range(start_day(datetime(2026, 12, 31, 23, 59, tzinfo=UTC))) == (
        (date(2026, 12, 1) - date(1970, 1, 1)).days,
        (date(2027, 1, 1) - date(1970, 1, 1)).days,
    )
    with pytest.raises(ValueError):
        start_day(datetime(2026, 1, 1))


def test_every_reading_carries_its_campaign_start_day_on_both_databases(store_url: str, bundle_factory) -> None:
    with connect(store_url) as store:
        ids = _import_months(store, bundle_factory)
        with store.engine.connect() as conn:
            for cid, started in zip(ids, STARTS, strict=True):
                want = start_day(datetime.fromisoformat(started.replace("Z", "+00:00")))
                for table in partitions.PARTITIONED_TABLES:
                    days = (
                        conn.execute(
                            text(f"SELECT DISTINCT campaign_start_day FROM {table} WHERE campaign_id = :c"), {"c": cid}
                        )
                        .scalars()
                        .all()
                    )
                    assert days == [want], table


# ----------------------------------------------------------------------------- made ahead of writes


def test_an_import_makes_its_month_partition_before_writing(pg: Store, bundle_factory) -> None:
    ids = _import_months(pg, bundle_factory)
    for cid, name in zip(ids, ("p2026_01", "p2026_02", "p2026_03"), strict=True):
        for table in partitions.PARTITIONED_TABLES:
            assert _where(pg, table, cid) == {f"{table}_{name}"}
    # nothing is routed by default: a reading of a month nobody prepared is refused, not parked
    with pg.engine.connect() as conn:
        assert not [p for p in partitions.partitions(conn, "temperature_samples") if p.lo is None]
    far = start_day(datetime(2091, 6, 1, tzinfo=UTC))
    with pytest.raises(Exception, match="no partition of relation"), pg.engine.begin() as conn:
        conn.execute(
            sc.TemperatureSample.__table__.insert().values(
                campaign_id=ids[0], channel_id=1, time_s=0.0, value=1.0, campaign_start_day=far
            )
        )


def test_the_daemon_makes_its_partition_when_it_opens_a_campaign(fresh_pg: Store) -> None:
    from driftlab.campaigns.acquisition import open_campaign
    from driftlab.campaigns.plan import parse_plan

    this_day = start_day(datetime.now(UTC))
    this_month = partitions.month_range(this_day)[0]
    name = partitions._gap([], "temperature_samples", this_month).name.removeprefix("temperature_samples")
    with fresh_pg.engine.begin() as conn:  # as if the periodic task had never run this month
        for table in partitions.PARTITIONED_TABLES:
            conn.execute(text(f"DROP TABLE {table}{name}"))
    plan = parse_plan(
        {
            "name": "live",
            "machine": {"id": "vmc-5ax-01"},
            "scan_interval_s": 60,
            "stages": [{"name": "idle", "axis": "Z", "duration_s": 300}],
        }
    )
    handle = open_campaign(fresh_pg.engine, plan, {"T1": {}}, [], resume=False, origin={})
    assert handle.start_day in (this_day, start_day(datetime.now(UTC)))  # (a run across midnight)
    with fresh_pg.engine.connect() as conn:
        for table in partitions.PARTITIONED_TABLES:
            assert partitions.leaf(conn, table, handle.start_day) == f"{table}{name}"


def test_concurrent_creators_of_one_partition_all_succeed(fresh_pg: Store) -> None:
    day = start_day(datetime(2040, 7, 14, tzinfo=UTC))
    engines = [db.make_engine(fresh_pg.engine.url.render_as_string(hide_password=False)) for _ in range(4)]
    barrier = threading.Barrier(len(engines))
    made: list[list[str]] = []
    errors: list[BaseException] = []

    def create(engine: Any) -> None:
        try:
            barrier.wait()
            made.append(partitions.ensure_partitions(engine, [day]))
        except BaseException as exc:  # collected: a thread's failure is the test's
            errors.append(exc)

    threads = [threading.Thread(target=create, args=(e,)) for e in engines]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for e in engines:
        e.dispose()
    assert errors == []
    assert sorted(n for m in made for n in m) == sorted(f"{t}_p2040_07" for t in partitions.PARTITIONED_TABLES)
    with fresh_pg.engine.connect() as conn:
        assert partitions.ensure_partitions(fresh_pg.engine, [day]) == []
        covering = [p.name for p in partitions.partitions(conn, "error_samples") if p.covers(day)]
        assert covering == ["error_samples_p2040_07"]


def test_two_imports_into_a_new_month_at_once_both_land(fresh_pg: Store, bundle_factory) -> None:
    bundles = [load_bundle(bundle_factory(seed=s, started_at=f"2041-03-0{s}T08:00:00Z")) for s in (1, 2)]
    url = fresh_pg.engine.url.render_as_string(hide_password=False)
    stores = [connect(url) for _ in bundles]
    barrier = threading.Barrier(len(bundles))
    ids: list[int] = []
    errors: list[BaseException] = []

    def load(store: Store, bundle: Bundle) -> None:
        try:
            barrier.wait()
            ids.append(store.campaigns.import_bundle(bundle))
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=load, args=pair) for pair in zip(stores, bundles, strict=True)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for s in stores:
        s.close()
    assert errors == [] and len(ids) == 2
    for cid in ids:
        assert _where(fresh_pg, "temperature_samples", cid) == {"temperature_samples_p2041_03"}


def test_ensure_ahead_is_idempotent_and_fills_only_the_gaps(fresh_pg: Store) -> None:
    engine = fresh_pg.engine
    made = partitions.ensure_ahead(engine, months=2, today=date(2050, 11, 17))
    assert sorted(made) == sorted(
        f"{t}_p{m}" for t in partitions.PARTITIONED_TABLES for m in ("2050_11", "2050_12", "2051_01")
    )
    assert partitions.ensure_ahead(engine, months=2, today=date(2050, 11, 30)) == []
    # a partition made by hand for the second half of a month: the rest of the month is made around it
    lo, hi = partitions.month_range(start_day(datetime(2052, 5, 1, tzinfo=UTC)))
    with engine.begin() as conn:
        conn.execute(
            text(f"CREATE TABLE error_samples_manual PARTITION OF error_samples FOR VALUES FROM ({lo + 15}) TO ({hi})")
        )
    made = partitions.ensure_partitions(engine, [lo + 3, lo + 20])
    assert "error_samples_p2052_05" in made and "error_samples_p2052_05_16" not in made
    with engine.connect() as conn:
        covering = {
            p.name: (p.lo, p.hi)
            for p in partitions.partitions(conn, "error_samples")
            if p.lo is not None and lo <= p.lo < hi
        }
    assert covering == {"error_samples_p2052_05": (lo, lo + 15), "error_samples_manual": (lo + 15, hi)}


def test_the_workers_make_partitions_ahead_daily(fresh_pg: Store) -> None:
    from driftlab.jobs.queue import PARTITIONS_CRON, PARTITIONS_TASK, _partitions_task, build_app

    app = build_app("postgresql+psycopg://u@h/d")
    assert (PARTITIONS_TASK, PARTITIONS_CRON) in {
        (p.task.name, p.cron) for p in app.periodic_registry.periodic_tasks.values()
    }
    with fresh_pg.engine.begin() as conn:
        names = [p.name for p in partitions.partitions(conn, "condition_samples")]
        for table in partitions.PARTITIONED_TABLES:
            for n in names:
                conn.execute(text(f"DROP TABLE {n.replace('condition_samples', table)}"))
    _partitions_task(SimpleNamespace(additional_context={"store": fresh_pg}), 0)  # type: ignore[arg-type]
    with fresh_pg.engine.connect() as conn:
        today = datetime.now(UTC).date()
        for first in partitions.months_ahead(today):
            assert partitions.leaf(conn, "temperature_samples", first) is not None


def test_cli_db_partitions(pg: Store, capsys) -> None:
    from driftlab.cli import main

    assert main(["db", "partitions", "--db", pg.engine.url.render_as_string(hide_password=False)]) == 0
    out = capsys.readouterr().out
    assert "temperature_samples_p" in out and "partition(s) created" in out


# ----------------------------------------------------------------------------- pruning


def _explain_drift_statements(store: Store, call: Any) -> list[str]:
    """Run ``call`` and return the EXPLAIN text of every statement it sent that reads error_samples."""
    seen: list[tuple[str, Any]] = []

    def before(conn: Any, cursor: Any, statement: str, parameters: Any, context: Any, executemany: bool) -> None:
        if "error_samples" in statement:
            seen.append((statement, parameters))

    event.listen(store.engine, "before_cursor_execute", before)
    try:
        call()
    finally:
        event.remove(store.engine, "before_cursor_execute", before)
    plans = []
    with store.engine.connect() as conn:
        raw = conn.connection.driver_connection
        for statement, parameters in seen:
            with raw.cursor() as cur:
                cur.execute("EXPLAIN (COSTS OFF) " + statement, parameters)
                plans.append("\n".join(r[0] for r in cur.fetchall()))
    assert plans, "the drift query read no error_samples"
    return plans


def test_drift_statements_read_one_partition_each(pg: Store, bundle_factory) -> None:
    ids = _import_months(pg, bundle_factory)
    cases = [
        lambda: pg.readings.drift(MACHINE, "Z", "dz", position=130.0, direction=1),
        lambda: pg.readings.drift(MACHINE, "Z", "dz", position=130.0),
        lambda: pg.readings.drift(MACHINE, "Z", "dx", position=130.0, interpolate=True),
        lambda: pg.readings.drift(
            MACHINE, "Z", "gamma", start=datetime(2026, 2, 1, tzinfo=UTC), end=datetime(2026, 4, 1, tzinfo=UTC)
        ),
    ]
    months = {"error_samples_p2026_01", "error_samples_p2026_02", "error_samples_p2026_03"}
    for case in cases:
        for plan in _explain_drift_statements(pg, case):
            read = {m for m in months if m in plan}
            assert len(read) == 1, plan
    assert len(ids) == 3


def test_a_prepared_drift_statement_prunes_at_run_time(pg: Store, bundle_factory) -> None:
    """psycopg prepares a statement after a few executions; PostgreSQL may then run a generic plan,
    which must still read one partition (run-time pruning: the others are 'Subplans Removed')."""
    ids = _import_months(pg, bundle_factory)
    names = ["c", "day", "axis", "term", "t0", "t1", "p"]
    sql = re.sub(r":(\w+)", lambda m: f"${names.index(m.group(1)) + 1}", nearest_sql([1]))
    with pg.engine.connect() as conn:
        started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == ids[1])).scalar_one()
        raw = conn.connection.driver_connection
        with raw.cursor() as cur:
            cur.execute("SET plan_cache_mode = force_generic_plan")
            cur.execute(f"PREPARE drift_near (int, int, text, text, float8, float8, float8) AS {sql}")
            cur.execute(
                "EXPLAIN (ANALYZE, COSTS OFF, TIMING OFF, SUMMARY OFF) EXECUTE drift_near "
                f"({ids[1]}, {start_day(started)}, 'Z', 'dz', -1e300, 1e300, 130.0)"
            )
            plan = "\n".join(r[0] for r in cur.fetchall())
        raw.rollback()
    assert "Subplans Removed" in plan, plan  # decided at run time, with the parameters' values
    # the readings and both candidate seeks: each in the campaign's month, nothing anywhere else
    assert set(re.findall(r"on (error_samples_p\w+)", plan)) == {"error_samples_p2026_02"}, plan
    assert "(actual rows=4 loops=1)" in plan.splitlines()[0] or "rows=4" in plan, plan


# ----------------------------------------------------------------------------- SQLite = PostgreSQL


def test_sqlite_and_postgresql_answer_the_same(pg: Store, tmp_path: Path, bundle_factory) -> None:
    lite = connect(f"sqlite:///{tmp_path / 'same.sqlite'}")
    try:
        bundles = [load_bundle(bundle_factory(seed=k, started_at=s)) for k, s in enumerate(STARTS)]
        a, b = [pg.campaigns.import_bundle(x) for x in bundles], [lite.campaigns.import_bundle(x) for x in bundles]
        assert a == b
        win = dict(start=datetime(2026, 2, 4, 1, 35, tzinfo=UTC), end=datetime(2026, 4, 1, 0, 5, tzinfo=UTC))
        for kwargs in [
            dict(position=130.0, direction=1),
            dict(position=100.0),
            dict(position=130.0, interpolate=True),
            dict(position=333.0, direction=-1, interpolate=True, **win),
            {},
            dict(direction=-1, **win),
        ]:
            for term in ("dx", "dz", "gamma"):
                pd.testing.assert_frame_equal(
                    pg.readings.drift(MACHINE, "Z", term, **kwargs), lite.readings.drift(MACHINE, "Z", term, **kwargs)
                )
        for cid in a:
            for kwargs in [{}, dict(start_s=60.0, end_s=600.0), dict(buckets=7), dict(buckets=3, rollups=False)]:
                pd.testing.assert_frame_equal(
                    pg.readings.temperature_history(cid, "T2", **kwargs),
                    lite.readings.temperature_history(cid, "T2", **kwargs),
                    rtol=1e-12,
                )
            for kwargs in [{}, dict(buckets=4), dict(columns=["spindle_rpm", "z"], start_s=30.0, end_s=900.0)]:
                pd.testing.assert_frame_equal(
                    pg.readings.condition_history(cid, **kwargs),
                    lite.readings.condition_history(cid, **kwargs),
                    rtol=1e-12,
                )
            x, y = pg.campaigns.load(cid), lite.campaigns.load(cid)
            pd.testing.assert_frame_equal(x.temperatures, y.temperatures)
            pd.testing.assert_frame_equal(x.errors, y.errors)
            pd.testing.assert_frame_equal(x.conditions, y.conditions)
        assert [s.as_dict() for s in pg.campaigns.summaries()] == [s.as_dict() for s in lite.campaigns.summaries()]
    finally:
        lite.close()


# ----------------------------------------------------------------------------- revision 0008 on a populated store


def _at_0007(url: str, source: Store) -> Store:
    """Return a store at revision 0007 holding every row of ``source`` (readings without the key)."""
    old = connect(url, auto_upgrade=False)
    old.upgrade("0007")
    order = [
        "machines",
        "campaigns",
        "stages",
        "channels",
        "temperature_samples",
        "temperature_rollups",
        "condition_samples",
        "error_samples",
    ]
    with source.engine.connect() as src, db.write_transaction(old.engine) as dst:
        for name in order:
            table = sc.metadata.tables[name]
            cols = [c for c in table.c if c.name != partitions.PARTITION_KEY]
            rows = [dict(r._mapping) for r in src.execute(select(*cols))]
            if rows:  # the 0007 table, as a light table clause (without the key column)
                dst.execute(sa.table(name, *[sa.column(c.name, c.type) for c in cols]).insert(), rows)
        if dst.dialect.name == "postgresql":
            dst.execute(text("SELECT setval('campaigns_id_seq', (SELECT max(id) FROM campaigns))"))
            dst.execute(text("SELECT setval('channels_id_seq', (SELECT max(id) FROM channels))"))
    return old


def _readings(store: Store, with_key: bool) -> dict[str, list[tuple[Any, ...]]]:
    out = {}
    with store.engine.connect() as conn:
        for name in partitions.PARTITIONED_TABLES:
            table = sc.metadata.tables[name]
            cols = [c.name for c in table.c if with_key or c.name != partitions.PARTITION_KEY]
            key = [c.name for c in table.primary_key.columns if c.name in cols]
            out[name] = [
                tuple(r) for r in conn.execute(text(f"SELECT {', '.join(cols)} FROM {name} ORDER BY {', '.join(key)}"))
            ]
    return out


def test_revision_0008_converts_a_populated_store_and_back(db_url: str, tmp_path: Path, bundle_factory) -> None:
    source = connect(f"sqlite:///{tmp_path / 'source.sqlite'}")
    try:
        ids = _import_months(source, bundle_factory)
        want = _readings(source, with_key=True)
        drift = source.readings.drift(MACHINE, "Z", "dz", position=130.0)
        store = _at_0007(db_url, source)
    finally:
        source.close()
    try:
        before = _readings(store, with_key=False)
        assert {k: len(v) for k, v in before.items()} == {k: len(v) for k, v in want.items()}
        assert store.upgrade() == db.head_revision()
        assert _readings(store, with_key=True) == want  # every row, with its campaign's day
        pd.testing.assert_frame_equal(store.readings.drift(MACHINE, "Z", "dz", position=130.0), drift)
        if store.dialect == "postgresql":
            for cid, month in zip(ids, ("2026_01", "2026_02", "2026_03"), strict=True):
                assert _where(store, "temperature_samples", cid) == {f"temperature_samples_p{month}"}
            with store.engine.connect() as conn:  # and the months ahead of today are ready for writes
                assert partitions.missing(conn, partitions.months_ahead()) == []
        # ... and back: plain tables, the same rows
        with db.write_transaction(store.engine) as conn:
            command.downgrade(db.alembic_config(conn), "0007")
        assert store.revision() == "0007"
        assert _readings(store, with_key=False) == before
        if store.dialect == "postgresql":
            with store.engine.connect() as conn:
                assert conn.execute(text("SELECT COUNT(*) FROM pg_inherits")).scalar() == 0
        assert store.upgrade() == db.head_revision()
        assert _readings(store, with_key=True) == want
    finally:
        store.close()


def test_revision_0008_stops_on_readings_of_no_campaign(db_url: str, tmp_path: Path, bundle_factory) -> None:
    source = connect(f"sqlite:///{tmp_path / 'source.sqlite'}")
    try:
        source.campaigns.import_bundle(load_bundle(bundle_factory(seed=1)))
        store = _at_0007(db_url, source)
    finally:
        source.close()
    try:
        with db.write_transaction(store.engine) as conn:
            conn.execute(text("INSERT INTO condition_samples (campaign_id, time_s) VALUES (999, 0.0)"))
        with pytest.raises(Exception, match="belong to no stored campaign"):
            store.upgrade()
        assert store.revision() == "0007"  # nothing half-done: the upgrade is one transaction
        with db.write_transaction(store.engine) as conn:
            conn.execute(text("DELETE FROM condition_samples WHERE campaign_id = 999"))
        assert store.upgrade() == db.head_revision()
        with store.engine.connect() as conn:
            assert conn.execute(select(func.count()).select_from(sc.ConditionSample)).scalar() == 40
    finally:
        store.close()
