"""`store.campaigns.import_directory`: on PostgreSQL the files are read while the server writes (``import_pipeline``).

A duplicate refused, also one imported at the same moment. (The same rows as an import from memory, and
a failure beside the parse rolling all back: ``test_staging``, for both ways of importing.)
"""

from __future__ import annotations

import threading
from pathlib import Path

import psycopg
import pytest

from driftlab.campaigns import import_pipeline, ingest
from driftlab.campaigns.bundle import load_bundle
from driftlab.campaigns.store import connect
from driftlab.cli import main
from driftlab.errors import ConflictError

from .conftest import make_bundle

SMALL = 512  # bytes of CSV text per chunk: every file spans many chunks


def test_a_bundle_already_stored_is_refused_and_nothing_is_added(store_url: str, tmp_path: Path) -> None:
    path = make_bundle(tmp_path / "b", scans=300, sweeps=9)
    store = connect(store_url)
    try:
        with store.campaigns.import_directory(path) as first:
            cid = first.campaign_id
        before = store.table_counts()
        with pytest.raises(ConflictError, match=f"already stored as campaign {cid} .*nothing imported"):
            store.campaigns.import_directory(path)
        assert store.table_counts() == before
    finally:
        store.close()


@pytest.mark.postgres
def test_a_duplicate_is_refused_while_the_temperatures_are_written(pg_cluster, tmp_path: Path, monkeypatch) -> None:
    """The hash is known before the temperatures' COPY ends: the COPY is cut there, not run to its end."""
    store = connect(pg_cluster.create_database())
    try:
        path = make_bundle(tmp_path / "b", scans=300, sweeps=9)
        store.campaigns.import_directory(path).close()
        before = store.table_counts()
        hashed = threading.Event()
        real_hash, real_copy = import_pipeline._hash_unless_stored, ingest.copy_temperatures_pg
        cut: list[str] = []

        def hash_then_signal(engine, bundle):
            try:
                return real_hash(engine, bundle)
            finally:
                hashed.set()

        def copy_after_the_hash(*args, between, **kwargs):
            def wait_then_check() -> None:
                assert hashed.wait(60)
                between()

            try:
                real_copy(*args, between=wait_then_check, **kwargs)
            except ConflictError as exc:
                cut.append(str(exc))
                raise

        monkeypatch.setattr(import_pipeline, "_hash_unless_stored", hash_then_signal)
        monkeypatch.setattr(ingest, "copy_temperatures_pg", copy_after_the_hash)
        with pytest.raises(ConflictError, match="already stored"):
            store.campaigns.import_directory(path)
        assert len(cut) == 1 and "already stored" in cut[0]
        assert store.table_counts() == before
    finally:
        store.close()


@pytest.mark.postgres
def test_two_imports_of_one_bundle_at_once_store_it_once(pg_cluster, tmp_path: Path) -> None:
    path = make_bundle(tmp_path / "b", scans=2000, sweeps=9)
    store = connect(pg_cluster.create_database())
    outcomes: list[object] = []
    start = threading.Barrier(2)

    def run() -> None:
        start.wait()
        try:
            with store.campaigns.import_directory(path) as imported:
                outcomes.append(imported.campaign_id)
        except ConflictError as exc:
            outcomes.append(exc)

    try:
        before = store.table_counts()
        threads = [threading.Thread(target=run) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        stored = [o for o in outcomes if isinstance(o, int)]
        refused = [o for o in outcomes if isinstance(o, ConflictError)]
        assert len(stored) == 1 and len(refused) == 1, outcomes
        after = store.table_counts()
        assert after["campaigns"] == before["campaigns"] + 1
        whole = load_bundle(path)
        readings = len(whole.temperatures) * len(whole.channels)
        assert after["temperature_samples"] - before["temperature_samples"] == readings
        assert store.campaigns.load(stored[0]).content_hash() == whole.content_hash()
    finally:
        store.close()


@pytest.mark.postgres
def test_a_server_connection_killed_during_the_write_leaves_nothing_and_a_retry_lands(
    pg_cluster, tmp_path: Path, monkeypatch, capsys
) -> None:
    """The import's backend terminated in the middle of the temperatures' COPY (as a server restart would)."""
    url = pg_cluster.create_database()
    store = connect(url)
    try:
        store.campaigns.import_directory(make_bundle(tmp_path / "first")).close()
        before = store.table_counts()
        real_copy = ingest.copy_temperatures_pg
        killed: list[int] = []

        def copy_then_kill(conn, *args, between, **kwargs):
            pid = conn.connection.driver_connection.info.backend_pid

            def kill_once() -> None:
                if not killed:
                    with psycopg.connect(url.replace("postgresql+psycopg://", "postgresql://"), autocommit=True) as c:
                        c.execute("SELECT pg_terminate_backend(%s)", (pid,))
                    killed.append(pid)
                between()

            real_copy(conn, *args, between=kill_once, **kwargs)

        monkeypatch.setattr(ingest, "copy_temperatures_pg", copy_then_kill)
        path = make_bundle(tmp_path / "second", seed=3, scans=300, sweeps=9)
        capsys.readouterr()
        assert main(["import", str(path), "--db", url]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("driftlab: error: database: "), err
        assert len(killed) == 1
        assert store.table_counts() == before
        monkeypatch.setattr(ingest, "copy_temperatures_pg", real_copy)
        with store.campaigns.import_directory(path) as imported:
            assert store.campaigns.load(imported.campaign_id).content_hash() == load_bundle(path).content_hash()
    finally:
        store.close()
