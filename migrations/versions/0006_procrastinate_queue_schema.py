"""The job queue's schema on PostgreSQL: procrastinate 3.10's tables, types, functions and triggers.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-02 10:00:00

Fit, diagnose and refit jobs run on procrastinate (driftlab/jobs) when the store is PostgreSQL. Its
schema is applied here, with the store's own, so that ``driftlab db upgrade`` (compose's ``migrate``
service, or a store's first use) leaves the database ready for ``driftlab worker`` and a downgrade
removes it again. The SQL is procrastinate's ``schema.sql`` of the pinned version, copied verbatim
into ``migrations/sql/`` (tests/jobs/test_schema.py checks it still equals the installed package's):
a revision must give the same schema whatever version is installed when it runs. A procrastinate
release that brings SQL migrations of its own gets a new revision applying them.

SQLite has no queue (its jobs run in-process): nothing to do there.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

SCHEMA_SQL = Path(__file__).resolve().parents[1] / "sql" / "procrastinate-3.10.0.sql"

DROP_SQL = """
DROP TABLE IF EXISTS procrastinate_events, procrastinate_periodic_defers, procrastinate_jobs,
    procrastinate_workers CASCADE;
DO $$
DECLARE f record;
BEGIN
    FOR f IN SELECT p.oid::regprocedure AS sig FROM pg_proc p
             WHERE p.proname LIKE 'procrastinate\\_%' AND p.pronamespace = current_schema()::regnamespace
    LOOP
        EXECUTE 'DROP FUNCTION ' || f.sig || ' CASCADE';
    END LOOP;
END;
$$;
DROP TYPE IF EXISTS procrastinate_job_to_defer_v1, procrastinate_job_event_type, procrastinate_job_status CASCADE;
"""


def _execute_script(sql: str) -> None:
    """Run a multi-statement script on the migration's own connection (and transaction), unparsed.

    The driver connection is used directly: the script has ``%`` and ``:name`` that neither
    SQLAlchemy's text() nor a parameterised execute may interpret.
    """
    op.get_bind().connection.driver_connection.execute(sql)  # type: ignore[union-attr]


def upgrade() -> None:
    """Create procrastinate's schema (PostgreSQL only)."""
    if op.get_bind().dialect.name != "postgresql":
        return
    _execute_script(SCHEMA_SQL.read_text(encoding="utf-8"))


def downgrade() -> None:
    """Drop everything procrastinate's schema created (PostgreSQL only)."""
    if op.get_bind().dialect.name != "postgresql":
        return
    _execute_script(DROP_SQL)
