"""Jobs on the embedded SQLite store: the same bodies and retry policy, run in-process (no PostgreSQL)."""

from __future__ import annotations

import json
from typing import Any

import pytest
from sqlalchemy.exc import OperationalError

from driftlab.campaigns.db import StoreError
from driftlab.campaigns.store import Store
from driftlab.cli import main
from driftlab.errors import ValidationError
from driftlab.jobs import FIT, Jobs, policy, run_until_ended, submit, submit_fit, tasks
from driftlab.jobs.local import INTERRUPTED, LocalRunner
from tests.jobs.conftest import MACHINE, bundle, wait_ended


def _store_url(store: Store) -> str:
    return store.engine.url.render_as_string(hide_password=False)


def test_a_fit_submitted_to_the_server_runs_in_its_thread_into_the_registry(sqlite_store: Store) -> None:
    cid = sqlite_store.campaigns.import_bundle(bundle())
    seen: list[str] = []
    jobs = Jobs(sqlite_store, run_here=True, on_model=seen.append)
    jobs.start()
    try:
        job_id = jobs.submit(FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
        [job] = wait_ended(sqlite_store, [job_id])
    finally:
        jobs.stop()
    assert job.state == "done" and job.attempts == 1 and job.result["model_version"] == 1, job.error
    assert job.queue_job_id is None and job.queue_status is None  # no queue on SQLite
    assert seen == [MACHINE]
    assert sqlite_store.models.current(MACHINE).source_campaigns == [cid]


def test_a_failing_job_is_retried_in_process_then_reported_failed(
    sqlite_store: Store, monkeypatch, no_retry_wait
) -> None:
    runs: list[int] = []

    def body(store: Store, params: dict, **kw: Any) -> dict:
        runs.append(1)
        raise OSError("scratch disk unavailable")

    monkeypatch.setitem(tasks.BODIES, FIT, body)
    cid = sqlite_store.campaigns.import_bundle(bundle())
    job = run_until_ended(sqlite_store, submit(sqlite_store, FIT, {"campaigns": [cid]}, machine_id=MACHINE))
    assert len(runs) == policy.MAX_ATTEMPTS and job.attempts == policy.MAX_ATTEMPTS
    assert job.state == "failed" and job.error == "OSError: scratch disk unavailable"


def test_bad_input_fails_at_once(sqlite_store: Store) -> None:
    cid = sqlite_store.campaigns.import_bundle(bundle())
    job = run_until_ended(sqlite_store, submit(sqlite_store, "diagnose", {"campaigns": [cid, cid]}))
    assert job.state == "failed" and job.attempts == 1 and job.error == "a diagnosis is of exactly one campaign"


def test_enqueued_jobs_wait_for_the_next_server_and_interrupted_ones_are_failed(sqlite_store: Store, capsys) -> None:
    cid = sqlite_store.campaigns.import_bundle(bundle())
    url = _store_url(sqlite_store)
    assert main(["fit", "--campaign", str(cid), "--db", url, "--enqueue", "--no-network"]) == 0
    queued = json.loads(capsys.readouterr().out)["job"]
    left_running = submit_fit(sqlite_store, [cid], network=False)
    sqlite_store.jobs.start(left_running, "a-process-that-died")
    runner = LocalRunner(sqlite_store)
    runner.start()
    try:
        done, interrupted = wait_ended(sqlite_store, [queued, left_running])
    finally:
        runner.stop()
    assert done.state == "done" and done.worker == runner.worker, done.error
    assert interrupted.state == "failed" and interrupted.error == INTERRUPTED
    assert [v.version for v in sqlite_store.models.versions(MACHINE)] == [1]


def test_a_record_is_run_once_even_with_two_runners(sqlite_store: Store) -> None:
    """Two processes' runners on one file (a server and a `driftlab fit`): the record is taken once."""
    cid = sqlite_store.campaigns.import_bundle(bundle())
    job_id = submit(sqlite_store, FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
    sqlite_store.jobs.start(job_id, "the-other-process", only_if_queued=True)
    job = run_until_ended(sqlite_store, job_id)  # not queued any more: this process leaves it alone
    assert job.state == "running" and job.worker == "the-other-process" and job.attempts == 1


def test_submit_refuses_an_unknown_kind_on_run(sqlite_store: Store) -> None:
    job = run_until_ended(sqlite_store, submit(sqlite_store, "sing", {}))
    assert job.state == "failed" and "unknown job kind" in job.error


@pytest.mark.parametrize(
    "exc,retried",
    [
        (OSError("disk"), True),
        (OperationalError("SELECT 1", {}, Exception("gone")), True),
        (StoreError("cannot open the store"), True),
        (ValueError("singular matrix"), False),
        (ValidationError("bad"), False),
    ],
)
def test_the_retry_policy(exc: BaseException, retried: bool, no_retry_wait, monkeypatch) -> None:
    assert (policy.retry_in_s(exc, 1) is not None) is retried
    assert policy.retry_in_s(exc, policy.MAX_ATTEMPTS) is None
    monkeypatch.setenv("DRIFTLAB_JOB_RETRY_WAIT_S", "7")
    if retried:
        assert policy.retry_in_s(exc, 2) == 14.0
