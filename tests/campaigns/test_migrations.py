"""Migrations: every revision from empty to head gives exactly the declarative schema, on both databases."""

from __future__ import annotations

from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import inspect

from driftlab.campaigns import db
from driftlab.campaigns.schema import metadata
from driftlab.campaigns.store import connect


def test_upgrade_from_empty_matches_metadata(db_url: str) -> None:
    store = connect(db_url, auto_upgrade=False)
    try:
        assert store.revision() is None
        reached = store.upgrade()
        assert reached == db.head_revision()
        with store.engine.connect() as conn:
            ctx = MigrationContext.configure(conn, opts={"compare_type": True, "include_name": db.include_name})
            diff = compare_metadata(ctx, metadata)
        assert diff == []
        tables = set(inspect(store.engine).get_table_names())
        assert set(metadata.tables) <= tables
        queue = {"procrastinate_jobs", "procrastinate_events", "procrastinate_periodic_defers", "procrastinate_workers"}
        assert (queue <= tables) == (store.dialect == "postgresql")  # the job queue: PostgreSQL only (0006)
        assert store.upgrade() == reached  # idempotent
    finally:
        store.close()


def test_downgrade_to_base_and_back(db_url: str) -> None:
    store = connect(db_url, auto_upgrade=False)
    try:
        store.upgrade()
        db_downgrade(store)
        left = set(inspect(store.engine).get_table_names())
        assert not (set(metadata.tables) & left)
        assert not {t for t in left if t.startswith(db.QUEUE_TABLE_PREFIX)}  # the job queue's schema went too
        store.upgrade()
        assert store.revision() == db.head_revision()
    finally:
        store.close()


def db_downgrade(store) -> None:
    from alembic import command

    with db.write_transaction(store.engine) as conn:
        command.downgrade(db.alembic_config(conn), "base")


def test_store_upgrades_itself_on_first_use(db_url: str) -> None:
    store = connect(db_url)
    try:
        assert store.campaigns.summaries() == []
        assert store.revision() == db.head_revision()
    finally:
        store.close()


def test_sqlite_pragmas_and_parent_directories(tmp_path) -> None:
    path = tmp_path / "deep" / "er" / "store.sqlite"
    store = connect(f"sqlite:///{path}")
    try:
        store.ensure_schema()
        assert path.exists()
        with store.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    finally:
        store.close()


def test_cli_db_upgrade_and_current(db_url: str, capsys) -> None:
    from driftlab.cli import main

    assert main(["db", "current", "--db", db_url]) == 0
    assert capsys.readouterr().out.strip() == "empty"
    assert main(["db", "upgrade", "--db", db_url]) == 0
    assert f"at revision {db.head_revision()}" in capsys.readouterr().out
    assert main(["db", "current", "--db", db_url]) == 0
    assert capsys.readouterr().out.strip() == db.head_revision()
