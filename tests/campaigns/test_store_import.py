"""The campaign store on SQLite and PostgreSQL: exact round trips, refused and atomic imports."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sqlalchemy import func, insert, select
from sqlalchemy.exc import IntegrityError

from driftlab.campaigns import ingest
from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import load_bundle, write_bundle
from driftlab.campaigns.partitions import start_day
from driftlab.campaigns.store import Store, connect
from driftlab.cli import main
from driftlab.errors import ConflictError
from tests.campaigns.conftest import make_bundle


@pytest.fixture
def store(store_url: str):
    s = connect(store_url)
    yield s
    s.close()


def _assert_same_bundle(a, b) -> None:
    pd.testing.assert_frame_equal(a.temperatures, b.temperatures, check_exact=True)
    pd.testing.assert_frame_equal(a.errors, b.errors, check_exact=True)
    if a.conditions is None:
        assert b.conditions is None
    else:
        pd.testing.assert_frame_equal(a.conditions, b.conditions, check_exact=True)
    assert a.meta == b.meta
    assert a.content_hash() == b.content_hash()


def test_import_export_import_round_trips_exactly(
    store: Store, bundle_dir: Path, tmp_path: Path, store_url: str
) -> None:
    original = load_bundle(bundle_dir)
    cid = store.campaigns.import_bundle(original)
    stored = store.campaigns.load(cid)
    _assert_same_bundle(original, stored)
    out = write_bundle(tmp_path / "exported", stored.meta, stored.temperatures, stored.conditions, stored.errors)
    again = load_bundle(out)
    _assert_same_bundle(original, again)
    # the same content is the same campaign: re-importing the export is refused
    with pytest.raises(ConflictError, match=f"already stored as campaign {cid}"):
        store.campaigns.import_bundle(again)
    # into another database it lands and reads back identically
    other = connect(f"sqlite:///{tmp_path / 'other.sqlite'}")
    try:
        _assert_same_bundle(original, other.campaigns.load(other.campaigns.import_bundle(again)))
    finally:
        other.close()


def test_missing_cells_stay_missing(store: Store, bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    stored = store.campaigns.load(store.campaigns.import_bundle(b))
    assert np.isnan(stored.temperatures.loc[3, "T2"])
    assert stored.conditions is not None and stored.conditions["z"].isna().all()
    raw = store.readings.temperature_history(1, "T2")
    assert np.isnan(raw.loc[3, "value"]) and raw["value"].notna().sum() == len(raw) - 1


def test_real_bundle_round_trips(store: Store, fl_thermal: Path) -> None:
    b = load_bundle(fl_thermal)
    cid = store.campaigns.import_bundle(b)
    _assert_same_bundle(b, store.campaigns.load(cid))
    [summary] = store.campaigns.summaries()
    assert (summary.id, summary.channels, summary.scans, summary.error_samples, summary.stages) == (
        cid,
        16,
        11115,
        33345,
        16,
    )
    counts = store.table_counts()
    assert counts["temperature_samples"] == 11115 * 16
    assert counts["condition_samples"] == 11115


def test_duplicate_import_refused_and_changes_nothing(store: Store, bundle_dir: Path) -> None:
    b = load_bundle(bundle_dir)
    store.campaigns.import_bundle(b)
    before = store.table_counts()
    with pytest.raises(ConflictError) as info:
        store.campaigns.import_bundle(load_bundle(bundle_dir))
    assert "\n" not in str(info.value)
    assert store.table_counts() == before


@pytest.mark.parametrize("boom", [RuntimeError("disk on fire"), KeyboardInterrupt()], ids=["error", "ctrl-c"])
def test_failure_mid_write_leaves_database_as_it_was(store: Store, bundle_factory, monkeypatch, boom) -> None:
    store.campaigns.import_bundle(load_bundle(bundle_factory(seed=1)))
    before = store.table_counts()
    real = ingest.bulk_insert
    calls: list[str] = []
    seen_inside: list[int] = []

    def failing(conn, table, *args, **kwargs):
        calls.append(table)
        if table == "error_samples":  # temperatures and conditions are already written by now
            seen_inside.append(conn.execute(select(func.count()).select_from(sc.TemperatureSample)).scalar_one())
            raise boom
        return real(conn, table, *args, **kwargs)

    monkeypatch.setattr(ingest, "bulk_insert", failing)
    b = load_bundle(bundle_factory(seed=2))
    with pytest.raises(type(boom)):
        store.campaigns.import_bundle(b)
    assert calls[-2:] == ["condition_samples", "error_samples"]
    assert seen_inside[0] == before["temperature_samples"] + 40 * 4  # written, then rolled back
    assert store.table_counts() == before
    monkeypatch.setattr(ingest, "bulk_insert", real)
    store.campaigns.import_bundle(b)  # nothing was left behind that would block a clean retry
    assert store.table_counts()["campaigns"] == before["campaigns"] + 1


def test_unique_keys_refuse_a_reinserted_reading(store: Store, bundle_dir: Path) -> None:
    bundle = load_bundle(bundle_dir)
    cid = store.campaigns.import_bundle(bundle)
    day = start_day(bundle.meta.started_at)  # the key the import wrote: the same row again, in its partition
    with store.engine.connect() as conn:
        ch = conn.execute(sc.Channel.__table__.select().where(sc.Channel.campaign_id == cid)).first()
    for table, row in [
        (
            sc.TemperatureSample,
            {"campaign_id": cid, "channel_id": ch.id, "time_s": 0.0, "value": 1.0, "campaign_start_day": day},
        ),
        (sc.ConditionSample, {"campaign_id": cid, "time_s": 0.0, "campaign_start_day": day}),
        (
            sc.ErrorSample,
            {
                "campaign_id": cid,
                "seq": 10_000,
                "time_s": 0.0,
                "axis": "Z",
                "term": "dx",
                "position": 0.0,
                "direction": 1,
                "value": 0.0,
                "sweep": 0,
                "flags": 0,
                "campaign_start_day": day,
            },
        ),
    ]:
        with pytest.raises(IntegrityError), store.engine.begin() as conn:
            conn.execute(insert(table), row)


@pytest.mark.parametrize("limit", [None, 20], ids=["default-limit", "20-parameters"])
@pytest.mark.parametrize("n", [0, 1, 5, 6, 127, 128, 129, 255, 300, 1000])
def test_multi_row_inserts_store_every_row_in_order(n: int, limit: int | None) -> None:
    """SQLite's multi-row INSERTs (full statements, then the rest in powers of two) store exactly the rows
    given, in their order, whatever their count and the connection's limit of bound parameters (20:
    6 rows a statement, not a power of two)."""
    con = sqlite3.connect(":memory:")
    if limit is not None:
        con.setlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER, limit)
    con.execute("CREATE TABLE t (k INTEGER PRIMARY KEY, a REAL, b TEXT)")
    rows = [(k, k / 7 if k % 5 else float("nan"), f"r{k}" if k % 3 else None) for k in range(n)]
    flat = [v for row in rows for v in row]
    ingest.insert_flat_sqlite(con.cursor(), "INSERT INTO t (k, a, b) VALUES ", "(?, ?, ?)", 3, flat)
    got = con.execute("SELECT k, a, b FROM t ORDER BY rowid").fetchall()
    assert got == [(k, None if a != a else a, b) for k, a, b in rows]  # a bound NaN is stored as NULL


def test_multi_row_insert_refuses_a_repeated_key_within_one_statement() -> None:
    con = sqlite3.connect(":memory:")
    con.execute("CREATE TABLE t (k INTEGER PRIMARY KEY)")
    with pytest.raises(sqlite3.IntegrityError):
        ingest.insert_flat_sqlite(con.cursor(), "INSERT INTO t (k) VALUES ", "(?)", 1, [*range(200), 100])


@pytest.fixture(scope="module", params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def corpus_store_url(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> str:
    """One store per engine for the whole corpus, holding one imported campaign: each case proves it
    changed nothing (the row counts of every table), so the next case meets the same store as a fresh one."""
    tmp = tmp_path_factory.mktemp("corpus")
    if request.param == "sqlite":
        url = f"sqlite:///{tmp / 'driftlab.sqlite'}"
    else:
        url = request.getfixturevalue("pg_cluster").create_database()
    with connect(url) as store:
        store.campaigns.import_bundle(load_bundle(make_bundle(tmp / "stored", seed=5)))
    return url


def test_corrupted_bundle_via_cli_changes_nothing(corpus_store_url: str, bundle_factory, corruption, capsys) -> None:
    store_url = corpus_store_url
    store = connect(store_url)
    try:
        before = store.table_counts()
        assert before["campaigns"] == 1
        _, file, mutate, expected = corruption
        bad = bundle_factory(seed=6)
        mutate(bad / file)
        capsys.readouterr()
        assert main(["import", str(bad), "--db", store_url]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("driftlab: error:")
        assert expected in err[0]
        assert store.table_counts() == before
    finally:
        store.close()


def test_cli_import_prints_id_and_refuses_twice(store_url: str, bundle_dir: Path, tmp_path: Path, capsys) -> None:
    assert main(["import", str(bundle_dir), "--json", "--db", store_url]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["campaign_id"] == 1 and summary["machine"] == "vmc-test-01" and summary["scans"] == 40
    assert main(["import", str(bundle_dir), "--db", store_url]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already stored as campaign 1" in err[0]
    assert main(["export", "1", str(tmp_path / "out"), "--db", store_url]) == 0
    _assert_same_bundle(load_bundle(bundle_dir), load_bundle(tmp_path / "out"))
    assert main(["campaign", "list", "--json", "--db", store_url]) == 0
    [row] = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert row["id"] == 1 and row["machine_id"] == "vmc-test-01" and row["scans"] == 40
    assert main(["export", "7", str(tmp_path / "none"), "--db", store_url]) != 0
    assert "no campaign 7" in capsys.readouterr().err


def test_ctrl_c_during_commit_is_held_until_the_commit_is_done() -> None:
    import os
    import signal

    from driftlab.campaigns import db

    reached = []
    with pytest.raises(KeyboardInterrupt):
        with db._sigint_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            reached.append("after the signal")
    assert reached == ["after the signal"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
