"""Shared database fixtures: a throwaway PostgreSQL cluster and fresh database URLs on both engines.

- ``pg_url``: session-scoped URL of a throwaway PostgreSQL cluster (one per xdist worker).
- ``pg_cluster``: the cluster object itself (``create_database()`` gives a fresh empty database).
- ``db_url``: parametrised over sqlite and postgresql, a fresh empty database URL per test.
- ``store_url``: the same, but already at the head revision and empty (cheaper than a new database).

With DRIFTLAB_REQUIRE_PG=1 a missing PostgreSQL is a failure, otherwise the postgresql cases skip.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from driftlab.testing.pgcluster import PgCluster, PgClusterError, pg_binaries_available


def _require_pg() -> bool:
    return os.environ.get("DRIFTLAB_REQUIRE_PG", "") not in ("", "0")


def _unavailable(reason: str) -> None:
    if _require_pg():
        pytest.fail(f"PostgreSQL required (DRIFTLAB_REQUIRE_PG=1) but unavailable: {reason}")
    pytest.skip(f"PostgreSQL unavailable: {reason}")


@pytest.fixture(scope="session")
def pg_cluster() -> Iterator[PgCluster]:
    """A throwaway PostgreSQL cluster on 127.0.0.1 (trust auth), stopped at the end of the session."""
    if not pg_binaries_available():
        _unavailable("initdb/pg_ctl not on PATH")
    cluster = PgCluster()
    try:
        cluster.start()
    except PgClusterError as exc:
        cluster.stop()
        _unavailable(str(exc))
    try:
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="session")
def pg_url(pg_cluster: PgCluster) -> str:
    """URL (postgresql+psycopg://) of the throwaway cluster's ``postgres`` database."""
    return pg_cluster.url()


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh, empty database URL: a SQLite file, or a new database on the throwaway cluster."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'driftlab.sqlite'}"
    cluster: PgCluster = request.getfixturevalue("pg_cluster")
    return cluster.create_database()


@pytest.fixture(scope="session")
def _sqlite_head_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SQLite file already at the head schema revision, copied by ``store_url``."""
    from driftlab.campaigns.store import connect

    path = tmp_path_factory.mktemp("template") / "head.sqlite"
    store = connect(f"sqlite:///{path}", auto_upgrade=False)
    store.upgrade()
    store.close()
    return path


@pytest.fixture(scope="session")
def _pg_head_database(pg_cluster: PgCluster) -> str:
    """URL of a database of the throwaway cluster at the head schema, emptied before each use."""
    from driftlab.campaigns.store import connect

    url = pg_cluster.create_database("driftlab_store_tests")
    store = connect(url, auto_upgrade=False)
    store.upgrade()
    store.close()
    return url


#: the job queue's tables (procrastinate, migration 0006), emptied with the store's
QUEUE_TABLES = ("procrastinate_jobs", "procrastinate_events", "procrastinate_periodic_defers", "procrastinate_workers")


def _truncate_all(url: str) -> None:
    """Empty every table of the store schema and of the job queue, and restart their id sequences
    (much faster than CREATE DATABASE)."""
    import psycopg

    from driftlab.campaigns.schema import metadata

    tables = ", ".join([*metadata.tables, *QUEUE_TABLES])
    conninfo = url.replace("postgresql+psycopg://", "postgresql://")
    with psycopg.connect(conninfo, autocommit=True) as conn:
        conn.execute(f"TRUNCATE {tables} RESTART IDENTITY CASCADE")


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A database at the head schema with no rows (SQLite: a copy of a template file; PostgreSQL: one
    migrated database per worker, emptied with TRUNCATE ... RESTART IDENTITY before each test)."""
    import shutil

    if request.param == "sqlite":
        path = tmp_path / "driftlab.sqlite"
        shutil.copyfile(request.getfixturevalue("_sqlite_head_template"), path)
        return f"sqlite:///{path}"
    url: str = request.getfixturevalue("_pg_head_database")
    _truncate_all(url)
    return url
