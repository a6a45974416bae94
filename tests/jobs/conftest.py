"""Fixtures of the job tests: stores on both databases with campaigns of one or two machines, and helpers.

The PostgreSQL stores are the throwaway cluster's (``_pg_head_database``, emptied, job queue
included, before each test): procrastinate runs against a real server, never an in-memory stand-in.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import pytest

from driftlab.campaigns.bundle import Bundle
from driftlab.campaigns.store import JobInfo, Store, connect
from tests.models.test_fitting import synthetic_bundle

MACHINE = "vmc-test"
OTHER = "vmc-other"


def bundle(machine: str = MACHINE, seed: int = 0, started_at: str | None = None) -> Bundle:
    """The fitting tests' small synthetic campaign, of ``machine``, started at ``started_at``."""
    b = synthetic_bundle(seed)
    update: dict = {"machine": b.meta.machine.model_copy(update={"id": machine})}
    if started_at is not None:
        update["started_at"] = datetime.fromisoformat(started_at.replace("Z", "+00:00"))
    return Bundle(f"{b.name}-{machine}", b.meta.model_copy(update=update), b.temperatures, b.conditions, b.errors)


def wait_ended(store: Store, job_ids: list[int], polls: int = 6000) -> list[JobInfo]:
    """Poll jobs until each is done or failed (a safety net of ``polls`` x 0.1 s, not a timing assertion)."""
    for _ in range(polls):
        jobs = [store.jobs.get(j) for j in job_ids]
        if all(j.state in ("done", "failed") for j in jobs):
            return jobs
        time.sleep(0.1)
    raise AssertionError(f"jobs still running: {[(j.id, j.state) for j in jobs]}")


@pytest.fixture
def no_retry_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    """Retries come at once (DRIFTLAB_JOB_RETRY_WAIT_S=0) in this process and in the workers it starts."""
    monkeypatch.setenv("DRIFTLAB_JOB_RETRY_WAIT_S", "0")


@pytest.fixture
def pg_store(request: pytest.FixtureRequest) -> Iterator[Store]:
    """An empty store (job queue included) on the throwaway PostgreSQL cluster."""
    from tests.conftest import _truncate_all

    url: str = request.getfixturevalue("_pg_head_database")
    _truncate_all(url)
    with connect(url) as store:
        yield store


@pytest.fixture
def sqlite_store(tmp_path: Path) -> Iterator[Store]:
    """An empty store on a SQLite file."""
    with connect(f"sqlite:///{tmp_path / 'jobs.sqlite'}") as store:
        yield store
