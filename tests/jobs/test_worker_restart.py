"""A `driftlab worker` survives `pg_ctl stop; pg_ctl start`, exits 1 when the database stays away, and a job
left running by a dead worker is queued again (issue 24).

The tests that stop the server share one private throwaway PostgreSQL server (``testing.pgcluster``),
started again after each of them if it was left down, and each gets its own fresh database there (a
copy of a migrated template); the others use the session's cluster (``pg_store``), which nobody stops.
"""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from driftlab.campaigns.store import connect
from driftlab.jobs import submit_fit
from driftlab.jobs.queue import _retry_stalled, build_app, store_url
from driftlab.testing.pgcluster import PgCluster
from tests.jobs.conftest import MACHINE, bundle, wait_ended
from tests.jobs.test_queue import _worker_env

pytestmark = pytest.mark.postgres


@pytest.fixture(scope="module")
def _private_server() -> Iterator[PgCluster]:
    """A private PostgreSQL server holding a migrated, empty store database ``head`` to copy."""
    cluster = PgCluster()
    cluster.start()
    try:
        with connect(cluster.create_database("head")) as store:
            store.ensure_schema()
        yield cluster
    finally:
        cluster.stop()


def _server_up(cluster: PgCluster) -> bool:
    import psycopg

    try:
        with psycopg.connect(cluster.url().replace("postgresql+psycopg://", "postgresql://"), connect_timeout=10):
            return True
    except psycopg.OperationalError:
        return False


@pytest.fixture
def own_cluster(_private_server: PgCluster) -> Iterator[tuple[PgCluster, str]]:
    """The private server (the test may stop it) and a fresh migrated, empty store database on it."""
    if not _server_up(_private_server):
        _private_server.resume()
    yield _private_server, _private_server.create_database(template="head")
    if not _server_up(_private_server):
        _private_server.resume()


def _worker(url: str, log: Path, *extra: str) -> subprocess.Popen[str]:
    """Start `driftlab worker` on ``url``, its output to the file ``log`` (a pipe nobody reads could fill up)."""
    cmd = [sys.executable, "-m", "driftlab.cli", "worker", "--db", url, "--name", "w-restart", *extra]
    with log.open("w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, text=True, env=_worker_env())


def _fit(url: str, cid: int) -> int:
    """Submit a fit of campaign ``cid`` through a new connection (the old pool died with the server)."""
    with connect(url) as store:
        return submit_fit(store, [cid], network=False)


def _done(url: str, job_id: int) -> None:
    """Wait for a job to end (a safety net of polls, not a timing assertion); require it done."""
    with connect(url) as store:
        (job,) = wait_ended(store, [job_id])
    assert job.state == "done", job.error


@pytest.mark.slow
def test_a_worker_survives_a_database_restart_and_runs_a_fit_queued_after_it(own_cluster, tmp_path) -> None:
    cluster, url = own_cluster
    with connect(url) as store:
        cid = store.campaigns.import_bundle(bundle())
    log = tmp_path / "worker.log"
    proc = _worker(url, log)
    try:
        _done(url, _fit(url, cid))  # the worker is up and running jobs
        cluster.halt()
        cluster.resume()
        job_id = _fit(url, cid)
        _done(url, job_id)
        assert proc.poll() is None  # still the same worker
        with connect(url) as store:
            assert store.jobs.get(job_id).worker == "w-restart"
            assert [v.version for v in store.models.versions(MACHINE)] == [1, 2]
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=600)
    err = log.read_text()
    assert proc.returncode == 0, err[-2000:]  # SIGTERM: a stop asked for
    assert "connecting again" in err


def test_a_worker_exits_1_when_the_database_stays_away(own_cluster, tmp_path) -> None:
    cluster, url = own_cluster
    log = tmp_path / "worker.log"
    proc = _worker(url, log, "--reconnect-s", "3")
    try:
        # the worker is up once its heartbeat row exists
        import time

        import psycopg

        dsn = url.replace("postgresql+psycopg://", "postgresql://")
        for _ in range(3000):
            if proc.poll() is not None:
                break
            with psycopg.connect(dsn) as conn:
                if conn.execute("SELECT count(*) FROM procrastinate_workers").fetchone()[0]:  # type: ignore[index]
                    break
            time.sleep(0.1)
        cluster.halt()
        proc.wait(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = log.read_text()
    assert proc.returncode == 1, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("driftlab: error: worker: no database for ") and "supervisor restarts it" in last


def test_a_job_of_a_dead_worker_is_queued_again(pg_store, monkeypatch, capsys) -> None:
    """A worker killed mid-job (kill -9) leaves its job `doing`; the next worker to start queues it again."""
    store = pg_store
    url = store_url(store)
    cid = store.campaigns.import_bundle(bundle())
    job_id = submit_fit(store, [cid], network=False)
    queue_id = store.jobs.get(job_id).queue_job_id
    dsn = url.replace("postgresql+psycopg://", "postgresql://")
    import psycopg

    # what a worker killed 40 s ago leaves: a worker row whose heartbeat stopped, its job in `doing`
    with psycopg.connect(dsn, autocommit=True) as conn:
        wid = conn.execute(
            "INSERT INTO procrastinate_workers (last_heartbeat) VALUES (now() - interval '40 seconds') RETURNING id"
        ).fetchone()[0]  # type: ignore[index]
        conn.execute("UPDATE procrastinate_jobs SET status = 'doing', worker_id = %s WHERE id = %s", (wid, queue_id))

    async def requeue() -> int:
        app = build_app(url)
        async with app.open_async():
            return await _retry_stalled(app)

    assert asyncio.run(requeue()) == 1
    with psycopg.connect(dsn) as conn:
        status = conn.execute("SELECT status FROM procrastinate_jobs WHERE id = %s", (queue_id,)).fetchone()[0]  # type: ignore[index]
    assert status == "todo"
    # and a worker runs it to the end (`driftlab worker --until-idle`, in this process: no kill is involved)
    from driftlab.cli import main

    monkeypatch.setenv("DRIFTLAB_JOB_RETRY_WAIT_S", "0")
    assert main(["worker", "--db", url, "--until-idle"]) == 0, capsys.readouterr().err[-2000:]
    _done(url, job_id)


def test_the_worker_refuses_a_negative_reconnect_time(pg_store, capsys) -> None:
    from driftlab.cli import main

    url = store_url(pg_store)
    assert main(["worker", "--db", url, "--reconnect-s", "-1"]) == 2
    assert "--reconnect-s must be at least 0" in capsys.readouterr().err
