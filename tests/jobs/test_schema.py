"""The job queue's schema comes from the store's migrations (revision 0006), equal to the installed procrastinate's."""

from __future__ import annotations

from importlib import resources
from importlib.metadata import version

import pytest

from driftlab.campaigns.store import Store
from driftlab.resources import migrations_dir


def test_the_vendored_schema_is_the_installed_procrastinates() -> None:
    """Bumping procrastinate past the pinned minor fails here until a revision applies its SQL migrations."""
    [vendored] = sorted((migrations_dir() / "sql").glob("procrastinate-*.sql"))
    installed = (resources.files("procrastinate.sql") / "schema.sql").read_text(encoding="utf-8")
    assert vendored.read_text(encoding="utf-8") == installed, (
        f"procrastinate {version('procrastinate')}'s schema differs from {vendored.name}: add a migration"
    )


@pytest.mark.postgres
def test_a_migrated_store_is_a_queue_procrastinate_accepts(pg_store: Store) -> None:
    from driftlab.jobs.queue import build_app, store_url

    app = build_app(store_url(pg_store), pool_size=2)
    app.open()
    try:
        assert app.check_connection()  # procrastinate's own check: its jobs table is there
        assert app.job_manager.list_jobs() == []
    finally:
        app.close()
