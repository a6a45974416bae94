"""The job queue on a real PostgreSQL (the throwaway cluster): procrastinate workers run fit, diagnose and refit.

A fit submitted like the API and the command line submit it is run by a ``driftlab worker``
process and its model lands in the registry; two fits of one machine never overlap (the machine's
lock) while fits of two machines do; a failing job is retried by the policy, then reported failed;
the API's states follow procrastinate's while a job is in its queue.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from typing import Any

import psycopg
import pytest

from driftlab.campaigns.job_repo import JobFilter
from driftlab.campaigns.repository import Page
from driftlab.campaigns.store import Store
from driftlab.cli import main
from driftlab.errors import ValidationError
from driftlab.jobs import FIT, Jobs, policy, submit, submit_fit, tasks
from driftlab.jobs.queue import QueueWorker, build_app, conninfo, store_url, submit_refits
from tests.jobs.conftest import MACHINE, OTHER, bundle, wait_ended

pytestmark = pytest.mark.postgres


def _queue_row(store: Store, queue_job_id: int) -> dict[str, Any]:
    """Return procrastinate's row of a job."""
    with psycopg.connect(conninfo(store_url(store))) as conn:
        cur = conn.execute(
            "SELECT status::text, attempts, lock, queueing_lock, priority, task_name "
            "FROM procrastinate_jobs WHERE id = %s",
            (queue_job_id,),
        )
        names = [c.name for c in cur.description or []]
        row = cur.fetchone()
    assert row is not None, f"no procrastinate job {queue_job_id}"
    return dict(zip(names, row))


def _set_queue_status(store: Store, queue_job_id: int, status: str) -> None:
    with psycopg.connect(conninfo(store_url(store)), autocommit=True) as conn:
        conn.execute(
            "UPDATE procrastinate_jobs SET status = %s::procrastinate_job_status WHERE id = %s", (status, queue_job_id)
        )


def _worker_env() -> dict[str, str]:
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "DRIFTLAB_JOB_RETRY_WAIT_S": "0"}
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


@pytest.fixture
def worker_thread(pg_store: Store):
    """Start an in-process procrastinate worker (a QueueWorker thread) on the store; stopped at the end."""
    started: list[QueueWorker] = []

    def start(concurrency: int = 1) -> QueueWorker:
        w = QueueWorker(pg_store, concurrency=concurrency, name=f"test-worker-{len(started)}", polling_s=0.5)
        w.start()
        assert w.ready.wait(120) and w.error is None, w.error
        started.append(w)
        return w

    yield start
    for w in started:
        w.stop()
        assert not w.is_alive()


# ----------------------------------------------------------------------------- a worker process


@pytest.mark.slow
def test_driftlab_worker_process_runs_a_queued_fit_into_the_registry(pg_store: Store, capsys) -> None:
    url = store_url(pg_store)
    cid = pg_store.campaigns.import_bundle(bundle())
    assert main(["fit", "--campaign", str(cid), "--db", url, "--enqueue", "--no-network"]) == 0
    job_id = json.loads(capsys.readouterr().out)["job"]
    job = pg_store.jobs.get(job_id)
    assert job.state == "queued" and job.queue_status == "todo" and job.queue_job_id
    row = _queue_row(pg_store, job.queue_job_id)
    assert row["lock"] == policy.machine_lock(MACHINE) and row["priority"] == policy.PRIORITY_INTERACTIVE
    assert row["task_name"] == "driftlab.fit"
    assert pg_store.models.current(MACHINE) is None

    proc = subprocess.run(
        [sys.executable, "-m", "driftlab.cli", "worker", "--db", url, "--until-idle"],
        capture_output=True,
        text=True,
        env=_worker_env(),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    job = pg_store.jobs.get(job_id)
    assert job.state == "done", job.error
    assert job.attempts == 1 and job.worker and job.worker.split(":")[-1] != str(os.getpid())
    assert job.result["model_version"] == 1 and job.result["machine"] == MACHINE
    assert _queue_row(pg_store, job.queue_job_id)["status"] == "succeeded"
    current = pg_store.models.current(MACHINE)
    assert current is not None and current.version == 1 and current.source_campaigns == [cid]


@pytest.mark.slow
def test_two_worker_processes_share_the_queue_and_run_each_job_once(pg_store: Store) -> None:
    """Two fits of each of two machines, two `driftlab worker` processes: every job once, each machine in order."""
    url = store_url(pg_store)
    cids = {
        MACHINE: pg_store.campaigns.import_bundle(bundle(MACHINE, seed=0)),
        OTHER: pg_store.campaigns.import_bundle(bundle(OTHER, seed=1)),
    }
    jobs = [submit_fit(pg_store, [cids[m]], network=False) for m in (MACHINE, OTHER, MACHINE, OTHER)]
    cmd = [sys.executable, "-m", "driftlab.cli", "worker", "--db", url, "--until-idle"]
    procs = [
        subprocess.Popen(
            [*cmd, "--name", f"w{k}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_worker_env()
        )
        for k in range(2)
    ]
    outs = [p.communicate() for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    # --until-idle leaves when nothing is runnable; a worker holding a machine's lock fetches again
    # after its job, so nothing is left behind when both have left
    infos = [pg_store.jobs.get(j) for j in jobs]
    assert [(j.state, j.attempts) for j in infos] == [("done", 1)] * 4, [j.error for j in infos]
    assert {j.worker for j in infos} <= {"w0", "w1"}
    for machine in (MACHINE, OTHER):
        mine = [j for j in infos if j.machine_id == machine]
        assert mine[1].started_at >= mine[0].finished_at
        assert [v.version for v in pg_store.models.versions(machine)] == [1, 2]


def test_driftlab_worker_refuses_the_sqlite_store(tmp_path, capsys) -> None:
    url = f"sqlite:///{tmp_path / 's.sqlite'}"
    assert main(["worker", "--db", url, "--until-idle"]) == 2
    assert main(["worker", "--db", url, "--concurrency", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "PostgreSQL" in err[0] and "--concurrency" in err[1]


@pytest.mark.slow
def test_cli_fit_on_postgresql_runs_its_job_here_through_the_queue(pg_store: Store) -> None:
    cid = pg_store.campaigns.import_bundle(bundle())
    assert main(["fit", "--campaign", str(cid), "--db", store_url(pg_store), "--no-network"]) == 0
    job = pg_store.jobs.get(1)
    assert job.state == "done" and job.queue_status == "succeeded" and job.result["model_version"] == 1
    assert pg_store.models.current(MACHINE).version == 1


# ----------------------------------------------------------------------------- the machine's lock


def _instrumented_fit(monkeypatch: pytest.MonkeyPatch, wait_for_other_s: float) -> list[tuple[str, str, float]]:
    """Wrap the fit body: log (event, machine, time); the first fit to start waits for a second to start."""
    events: list[tuple[str, str, float]] = []
    other_started = threading.Event()
    lock = threading.Lock()
    real = tasks.BODIES[FIT]

    def body(store: Store, params: dict, **kw: Any) -> dict:
        machine = store.campaigns.machine_of(params["campaigns"][0])
        with lock:
            first = not any(e == "start" for e, _, _ in events)
            events.append(("start", machine, time.monotonic()))
        if first:
            other_started.wait(wait_for_other_s)  # returns at once when another fit is running beside it
        else:
            other_started.set()
        try:
            return real(store, params, **kw)
        finally:
            with lock:
                events.append(("end", machine, time.monotonic()))

    monkeypatch.setitem(tasks.BODIES, FIT, body)
    return events


def _overlapped(events: list[tuple[str, str, float]]) -> bool:
    """Return True when a fit started while another was running."""
    running = 0
    for kind, _, _ in sorted(events, key=lambda e: e[2]):
        running += 1 if kind == "start" else -1
        if running > 1:
            return True
    return False


@pytest.mark.slow
def test_two_fits_of_one_machine_never_run_at_once(pg_store: Store, worker_thread, monkeypatch) -> None:
    """Two workers' worth of concurrency, two fits of one machine: the lock runs them one after the other."""
    events = _instrumented_fit(monkeypatch, wait_for_other_s=5.0)
    cid = pg_store.campaigns.import_bundle(bundle())
    jobs = [submit(pg_store, FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE) for _ in range(2)]
    worker_thread(concurrency=2)
    infos = wait_ended(pg_store, jobs)
    assert [j.state for j in infos] == ["done", "done"], [j.error for j in infos]
    assert not _overlapped(events), events
    first, second = infos
    assert second.started_at >= first.finished_at  # in submission order
    assert [v.version for v in pg_store.models.versions(MACHINE)] == [1, 2]


@pytest.mark.slow
def test_fits_of_two_machines_do_run_at_once(pg_store: Store, worker_thread, monkeypatch) -> None:
    """The control of the test above: with the same worker, fits of different machines overlap."""
    events = _instrumented_fit(monkeypatch, wait_for_other_s=600.0)
    a = pg_store.campaigns.import_bundle(bundle(MACHINE, seed=0))
    b = pg_store.campaigns.import_bundle(bundle(OTHER, seed=1))
    jobs = [
        submit(pg_store, FIT, {"campaigns": [c], "network": False}, machine_id=m) for c, m in ((a, MACHINE), (b, OTHER))
    ]
    worker_thread(concurrency=2)
    infos = wait_ended(pg_store, jobs)
    assert [j.state for j in infos] == ["done", "done"], [j.error for j in infos]
    assert _overlapped(events), events
    assert pg_store.models.current(MACHINE).version == 1 and pg_store.models.current(OTHER).version == 1


# ----------------------------------------------------------------------------- retries


def _failing_fit(monkeypatch: pytest.MonkeyPatch, failures: list[BaseException]) -> list[int]:
    """Make the fit body raise the given exceptions in turn, then fit for real; return the run count."""
    runs: list[int] = []
    real = tasks.BODIES[FIT]

    def body(store: Store, params: dict, **kw: Any) -> dict:
        runs.append(1)
        if len(runs) <= len(failures):
            raise failures[len(runs) - 1]
        return real(store, params, **kw)

    monkeypatch.setitem(tasks.BODIES, FIT, body)
    return runs


def test_a_failing_job_is_retried_then_reported_failed(
    pg_store: Store, worker_thread, monkeypatch, no_retry_wait
) -> None:
    runs = _failing_fit(monkeypatch, [OSError("scratch disk unavailable")] * policy.MAX_ATTEMPTS)
    cid = pg_store.campaigns.import_bundle(bundle())
    job_id = submit(pg_store, FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
    worker_thread()
    [job] = wait_ended(pg_store, [job_id])
    assert len(runs) == policy.MAX_ATTEMPTS
    assert job.state == "failed" and job.attempts == policy.MAX_ATTEMPTS
    assert job.error == "OSError: scratch disk unavailable" and job.finished_at is not None
    row = _queue_row(pg_store, job.queue_job_id)
    assert row["status"] == "failed" and row["attempts"] == policy.MAX_ATTEMPTS
    assert pg_store.models.current(MACHINE) is None


@pytest.mark.slow
def test_a_passing_failure_is_retried_and_the_job_ends_done(
    pg_store: Store, worker_thread, monkeypatch, no_retry_wait
) -> None:
    from sqlalchemy.exc import OperationalError

    runs = _failing_fit(monkeypatch, [OperationalError("SELECT 1", {}, Exception("server closed the connection"))])
    cid = pg_store.campaigns.import_bundle(bundle())
    job_id = submit(pg_store, FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
    worker_thread()
    [job] = wait_ended(pg_store, [job_id])
    assert len(runs) == 2 and job.state == "done" and job.attempts == 2 and job.error is None
    assert pg_store.models.current(MACHINE).version == 1


def test_bad_input_is_not_retried(pg_store: Store, worker_thread, monkeypatch, no_retry_wait) -> None:
    runs = _failing_fit(monkeypatch, [ValidationError("campaign 1 has no error readings")] * 3)
    cid = pg_store.campaigns.import_bundle(bundle())
    job_id = submit(pg_store, FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
    worker_thread()
    [job] = wait_ended(pg_store, [job_id])
    assert len(runs) == 1 and job.state == "failed" and job.attempts == 1
    assert job.error == "campaign 1 has no error readings"
    assert _queue_row(pg_store, job.queue_job_id)["status"] == "failed"


# ----------------------------------------------------------------------------- states and diagnosis


def test_states_follow_the_queue_until_the_record_ends(pg_store: Store) -> None:
    cid = pg_store.campaigns.import_bundle(bundle())
    job_id = submit(pg_store, FIT, {"campaigns": [cid]}, machine_id=MACHINE)
    qid = pg_store.jobs.get(job_id).queue_job_id
    assert pg_store.jobs.get(job_id).state == "queued"
    _set_queue_status(pg_store, qid, "doing")  # a worker took it
    assert pg_store.jobs.get(job_id).state == "running"
    assert [j.id for j in pg_store.jobs.find(JobFilter(state="running"), Page(10))] == [job_id]
    assert pg_store.jobs.find(JobFilter(state="queued"), Page(10)) == []
    _set_queue_status(pg_store, qid, "cancelled")  # with procrastinate's own tools
    job = pg_store.jobs.get(job_id)
    assert job.state == "failed" and "cancelled" in job.error
    pg_store.jobs.start(job_id, "w")
    pg_store.jobs.finish(job_id, {"model_version": 1})  # a record that ended is final
    _set_queue_status(pg_store, qid, "doing")
    assert pg_store.jobs.get(job_id).state == "done"


@pytest.mark.slow
def test_api_jobs_object_runs_a_diagnosis_on_its_worker_thread(pg_store: Store) -> None:
    cid = pg_store.campaigns.import_bundle(bundle())
    seen: list[str] = []
    jobs = Jobs(pg_store, run_here=True, on_model=seen.append)
    jobs.start()
    try:
        d = jobs.submit("diagnose", {"campaigns": [cid], "holdout_fraction": 0.25}, machine_id=MACHINE, campaign_id=cid)
        f = jobs.submit(FIT, {"campaigns": [cid], "network": False}, machine_id=MACHINE)
        dj, fj = wait_ended(pg_store, [d, f])
    finally:
        jobs.stop()
    assert dj.state == "done" and dj.result["report"]["format"].startswith("driftlab-diagnosis"), dj.error
    assert _queue_row(pg_store, dj.queue_job_id)["lock"] is None  # a diagnosis writes no model: no lock
    assert fj.state == "done" and seen == [MACHINE]  # the model cache is told before the job reads done


# ----------------------------------------------------------------------------- periodic refit


@pytest.mark.slow
def test_refit_queues_one_fit_per_machine_with_newer_campaigns(pg_store: Store, worker_thread) -> None:
    first = pg_store.campaigns.import_bundle(bundle(started_at="2026-03-02T08:00:00Z"))
    assert main(["fit", "--campaign", str(first), "--db", store_url(pg_store), "--no-network"]) == 0
    app = build_app(store_url(pg_store), pool_size=2)
    app.open()
    try:
        assert submit_refits(pg_store, app) == []  # nothing newer than the model
        newer = pg_store.campaigns.import_bundle(bundle(seed=1, started_at="2026-03-09T08:00:00Z"))
        [job_id] = submit_refits(pg_store, app)
        assert submit_refits(pg_store, app) == []  # one refit per machine waits at most
    finally:
        app.close()
    job = pg_store.jobs.get(job_id)
    assert job.params["campaigns"] == [first, newer] and job.params["refit_of"] == 1
    assert job.params["network"] is False  # as the fit that made the model
    row = _queue_row(pg_store, job.queue_job_id)
    assert row["priority"] == policy.PRIORITY_REFIT and row["queueing_lock"] == policy.refit_queueing_lock(MACHINE)
    assert row["lock"] == policy.machine_lock(MACHINE)
    worker_thread()
    [job] = wait_ended(pg_store, [job_id])
    assert job.state == "done", job.error
    current = pg_store.models.current(MACHINE)
    assert current.version == 2 and current.source_campaigns == [first, newer]
    assert pg_store.models.refit_candidates() == []


def test_the_refit_is_a_periodic_task_of_every_worker() -> None:
    app = build_app("postgresql+psycopg://u@localhost/db", refit_cron="0 3 * * *")
    periodic = {(p.task.name, p.cron) for p in app.periodic_registry.periodic_tasks.values()}
    assert ("driftlab.refit", "0 3 * * *") in periodic and ("driftlab.retry_stalled", "* * * * *") in periodic
    assert {"driftlab.fit", "driftlab.diagnose"} <= set(app.tasks)
    assert not any(
        p.task.name == "driftlab.refit"
        for p in build_app("postgresql+psycopg://u@h/d", refit_cron="").periodic_registry.periodic_tasks.values()
    )


def test_submit_fit_records_the_campaigns_machine(pg_store: Store) -> None:
    cid = pg_store.campaigns.import_bundle(bundle(OTHER))
    job = pg_store.jobs.get(submit_fit(pg_store, [cid], network=False))
    assert job.machine_id == OTHER and job.params == {"campaigns": [cid], "network": False}
    assert _queue_row(pg_store, job.queue_job_id)["lock"] == policy.machine_lock(OTHER)
