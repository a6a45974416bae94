"""procrastinate on the store's PostgreSQL database: the tasks, deferring a job, and workers.

The tasks are thin: each calls ``tasks.execute`` on a job record. A fit is deferred with its
machine's lock (``policy.machine_lock``), so two fits of one machine never run at once, on however
many workers; every job is retried by ``policy.RetryPolicy``. Two periodic tasks run on the
workers: ``driftlab.refit`` (DRIFTLAB_REFIT_CRON, nightly by default) queues a refit of every
machine that has finished campaigns newer than its current model, ``driftlab.retry_stalled``
(every five minutes) puts back in the queue the jobs of workers that stopped beating, and
``driftlab.partitions`` (daily) creates the reading tables' partitions of this month and the next
two ahead of any write (``campaigns.partitions.ensure_ahead``).

The queue's schema is created by the store's migrations (revision 0006), never by procrastinate's
own ``schema --apply``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import tempfile
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from procrastinate import App, JobContext, PsycopgConnector
from procrastinate.exceptions import AlreadyEnqueued, ProcrastinateException
from procrastinate.worker import Worker
from psycopg import AsyncConnection
from psycopg import Error as PsycopgError

from driftlab.errors import ServiceError, ValidationError
from driftlab.jobs import policy
from driftlab.jobs.tasks import DIAGNOSE, FIT, OnModel, OnStage, execute, one_line

if TYPE_CHECKING:
    from driftlab.campaigns.store import JobInfo, Store

log = logging.getLogger(__name__)

#: procrastinate task of each job kind
TASKS = {FIT: "driftlab.fit", DIAGNOSE: "driftlab.diagnose"}
REFIT_TASK = "driftlab.refit"
STALLED_TASK = "driftlab.retry_stalled"
#: every minute: with procrastinate's 30 s without a heartbeat, a dead worker's job is queued again
#: within 90 s (and at once by the next worker that starts, ``_retry_stalled``)
STALLED_CRON = "* * * * *"
#: a worker whose heartbeat (every 10 s) is older than this is dead: its running jobs are queued again
STALLED_AFTER_S = 30.0
#: how long a worker keeps trying to get its database back before it exits with status 1
RECONNECT_S = 300.0
RECONNECT_MAX_DELAY_S = 15.0
#: seconds between two writes of a worker's pulse file (``Pulse``)
PULSE_S = 5.0


def default_pulse_file() -> str:
    """Return where `driftlab worker` writes its pulse by default: the container's own temporary directory."""
    return os.environ.get("DRIFTLAB_WORKER_PULSE") or os.path.join(tempfile.gettempdir(), "driftlab-worker.pulse.json")


class Pulse(threading.Thread):
    """This worker process's liveness, written to a file every ``PULSE_S`` (read by `driftlab health --worker`).

    One JSON object, replaced atomically: ``pid``, ``name``, ``worker_id`` (procrastinate's id of the
    worker while it is connected, whose ``procrastinate_workers.last_heartbeat`` its event loop renews
    every 10 s), ``lost_since`` (POSIX s since when the database is away, while reconnecting) and
    ``written_at`` (POSIX s). A healthcheck in the same container can then tell this worker's state
    from any other worker's: a process that is gone, hung, reconnecting for too long or no longer
    beating in the queue. The file is removed when the worker ends.
    """

    def __init__(self, path: str, name: str, state: dict[str, Any]) -> None:
        super().__init__(name="driftlab-worker-pulse", daemon=True)
        self.path = path
        self.worker_name = name
        self.state = state  # run_worker's: "worker" (procrastinate Worker, while connected), "lost_since"
        self.done = threading.Event()

    def write(self) -> None:
        """Write the pulse once (atomically: a reader never sees half a file)."""
        worker = self.state.get("worker")
        body = {
            "pid": os.getpid(),
            "name": self.worker_name,
            "worker_id": getattr(worker, "worker_id", None),
            "lost_since": self.state.get("lost_since"),
            "written_at": time.time(),
        }
        tmp = f"{self.path}.{os.getpid()}.tmp"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(body, fh)
        os.replace(tmp, self.path)

    def run(self) -> None:
        """Write the pulse every PULSE_S until stopped (a write that fails is logged, the worker goes on)."""
        while not self.done.is_set():
            try:
                self.write()
            except OSError as exc:
                log.warning("worker: cannot write the pulse file %s (%s)", self.path, exc.strerror or exc)
            self.done.wait(PULSE_S)

    def stop(self) -> None:
        """Stop writing and remove the file."""
        self.done.set()
        self.join(timeout=5.0)
        try:
            os.unlink(self.path)
        except OSError:
            pass


#: longest wait for a connection of the queue's pool (procrastinate's own writes; jobs use the store's engine)
POOL_TIMEOUT_S = 10.0
PARTITIONS_TASK = "driftlab.partitions"
#: daily; with partitions made two months ahead, a month of workers down still finds them there
PARTITIONS_CRON = "41 3 * * *"


def default_worker_name() -> str:
    """Return a worker name unique to this process (host:pid)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def conninfo(url: str) -> str:
    """Return the libpq URI of a store's SQLAlchemy URL (PostgreSQL only)."""
    # lazy: sqlalchemy adds 0.16 s to `import driftlab.jobs.queue` (measured)
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "postgresql":
        raise ValidationError(f"the job queue needs PostgreSQL, not {parsed.get_backend_name()!r}")
    return parsed.set(drivername="postgresql").render_as_string(hide_password=False)


def store_url(store: Store) -> str:
    """Return the store's URL with its password (for the queue's own connections)."""
    return store.engine.url.render_as_string(hide_password=False)


# ----------------------------------------------------------------------------- tasks


def _store_of(context: JobContext) -> Store:
    """Return the store a worker handed to its tasks (DRIFTLAB_DB_URL's when run by another launcher)."""
    store = (context.additional_context or {}).get("store")
    if store is None:
        # lazy: the store adds 0.85 s to `import driftlab.jobs.queue` (measured)
        from driftlab.campaigns.store import connect

        store = connect(None)
        context.additional_context["store"] = store
    return store


def _run_task(context: JobContext, job_id: int) -> None:
    """Run a fit or diagnosis job's record (the task of every job kind)."""
    extra = context.additional_context or {}
    attempts_done = context.job.attempts + 1
    execute(
        _store_of(context),
        int(job_id),
        context.worker_name or default_worker_name(),
        will_retry=lambda exc, _job: policy.retry_in_s(exc, attempts_done) is not None,
        on_stage=extra.get("on_stage"),
        on_model=extra.get("on_model"),
    )
    # the result is in the job's record; procrastinate keeps no results


def _refit_task(context: JobContext, timestamp: int) -> None:
    """Queue a refit of every machine with finished campaigns newer than its current model."""
    ids = submit_refits(_store_of(context), context.app)
    log.info("refit at %s: %d job(s) queued %s", timestamp, len(ids), ids)


def _partitions_task(context: JobContext, timestamp: int) -> None:
    """Create the reading tables' partitions of this month and the next ones, when missing."""
    # lazy: the store's partitions add 0.18 s to `import driftlab.jobs.queue` (measured)
    from driftlab.campaigns.partitions import ensure_ahead

    made = ensure_ahead(_store_of(context).engine)
    log.info("partitions at %s: %s", timestamp, ", ".join(made) if made else "none missing")


async def _retry_stalled(app: App) -> int:
    """Put back in the queue the jobs of workers that stopped beating (killed, host lost); return how many."""
    manager = app.job_manager
    count = 0
    for job in await manager.get_stalled_jobs(seconds_since_heartbeat=STALLED_AFTER_S):
        log.warning("job %s of a lost worker: queued again", job.id)
        await manager.retry_job(job)
        count += 1
    return count


async def _retry_stalled_task(context: JobContext, timestamp: int) -> None:
    """Put back in the queue the jobs of workers that stopped beating (the periodic task)."""
    await _retry_stalled(context.app)


def build_app(url: str, *, pool_size: int = 4, refit_cron: str | None = None) -> App:
    """Return a procrastinate App over the store's database with driftlab's tasks (not opened)."""
    # lazy: driftlab.config (pydantic-settings) adds 0.10 s to `import driftlab.jobs.queue` (measured)
    from driftlab.config import get_settings

    # a connection the pool cannot give within POOL_TIMEOUT_S means the database is away: the worker
    # then stops and reconnects (run_worker) instead of waiting 30 s per pending write
    app = App(
        connector=PsycopgConnector(
            conninfo=conninfo(url), min_size=1, max_size=max(2, pool_size), timeout=POOL_TIMEOUT_S
        )
    )
    retry = policy.RetryPolicy()
    for name in TASKS.values():
        app.task(name=name, queue=policy.QUEUE, pass_context=True, retry=retry, priority=policy.PRIORITY_INTERACTIVE)(
            _run_task
        )
    refit = app.task(name=REFIT_TASK, queue=policy.QUEUE, pass_context=True, priority=policy.PRIORITY_UPKEEP)(
        _refit_task
    )
    cron = get_settings().refit_cron if refit_cron is None else refit_cron
    if cron:
        app.periodic(cron=cron, periodic_id="refit")(refit)
    stalled = app.task(name=STALLED_TASK, queue=policy.QUEUE, pass_context=True, priority=policy.PRIORITY_UPKEEP)(
        _retry_stalled_task
    )
    app.periodic(cron=STALLED_CRON, periodic_id="stalled")(stalled)
    parts = app.task(name=PARTITIONS_TASK, queue=policy.QUEUE, pass_context=True, priority=policy.PRIORITY_UPKEEP)(
        _partitions_task
    )
    app.periodic(cron=PARTITIONS_CRON, periodic_id="partitions")(parts)
    return app


# ----------------------------------------------------------------------------- deferring


def defer(
    app: App,
    store: Store,
    job_id: int,
    kind: str,
    machine_id: str | None,
    *,
    priority: int = policy.PRIORITY_INTERACTIVE,
    queueing_lock: str | None = None,
) -> int:
    """Queue a recorded job on procrastinate (a fit under its machine's lock); link and return the queue's id."""
    if kind not in TASKS:
        raise ValidationError(f"unknown job kind {kind!r}")
    lock = policy.machine_lock(machine_id) if kind == FIT and machine_id else None
    queue_id = app.configure_task(
        TASKS[kind], allow_unknown=False, lock=lock, priority=priority, queueing_lock=queueing_lock
    ).defer(job_id=job_id)
    store.jobs.link_queue_job(job_id, queue_id)
    return int(queue_id)


def submit_to_queue(
    app: App,
    store: Store,
    kind: str,
    params: dict[str, Any],
    *,
    machine_id: str | None,
    campaign_id: int | None,
    priority: int = policy.PRIORITY_INTERACTIVE,
    queueing_lock: str | None = None,
) -> int:
    """Record a job and queue it; return its id.

    AlreadyEnqueued (a job with the same queueing lock waits already) removes the record and is
    re-raised; any other failure to queue leaves the record failed with the reason.
    """
    job_id = store.jobs.record(kind, params, machine_id=machine_id, campaign_id=campaign_id)
    try:
        defer(app, store, job_id, kind, machine_id, priority=priority, queueing_lock=queueing_lock)
    except AlreadyEnqueued:
        store.jobs.delete(job_id)
        raise
    except Exception as exc:
        store.jobs.fail(job_id, f"could not be queued: {one_line(exc)}")
        raise
    return job_id


def submit_refits(store: Store, app: App) -> list[int]:
    """Queue a low-priority refit of each machine whose current model predates finished campaigns; return the job ids.

    A refit repeats the fit that made the current model (its network and findings options) on the
    model's campaigns plus the newer ones; at most one refit per machine waits in the queue.
    """
    ids = []
    for cand in store.models.refit_candidates():
        kept = {k: v for k, v in cand.params.items() if k in ("network", "findings", "force_findings")}
        params = {"network": False, **kept, "campaigns": cand.campaign_ids, "refit_of": cand.model_version}
        try:
            ids.append(
                submit_to_queue(
                    app,
                    store,
                    FIT,
                    params,
                    machine_id=cand.machine_id,
                    campaign_id=None,
                    priority=policy.PRIORITY_REFIT,
                    queueing_lock=policy.refit_queueing_lock(cand.machine_id),
                )
            )
        except AlreadyEnqueued:
            log.info("refit of %s: one is already waiting", cand.machine_id)
    return ids


# ----------------------------------------------------------------------------- workers


@dataclass(frozen=True)
class WorkerOptions:
    """How a procrastinate worker of driftlab runs: its job concurrency, whether it waits for jobs
    (or ends once nothing is runnable), its name, whether it installs signal handlers, the callbacks
    its tasks report to, and how often it polls the queue besides listening."""

    concurrency: int = 1
    wait: bool = True
    name: str | None = None
    signals: bool = False
    on_model: OnModel | None = None
    on_stage: OnStage | None = None
    polling_s: float = 5.0


def _worker(app: App, store: Store, options: WorkerOptions) -> Worker:
    return Worker(
        app=app,
        queues=[policy.QUEUE],
        name=options.name or default_worker_name(),
        concurrency=options.concurrency,
        wait=options.wait,
        install_signal_handlers=options.signals,
        fetch_job_polling_interval=options.polling_s,
        additional_context={"store": store, "on_model": options.on_model, "on_stage": options.on_stage},
    )


def run_worker(
    store: Store,
    *,
    concurrency: int = 1,
    wait: bool = True,
    name: str | None = None,
    on_stage: OnStage | None = None,
    reconnect_s: float = RECONNECT_S,
    pulse_file: str | None = None,
) -> None:
    """Run a worker in the foreground until SIGINT/SIGTERM (or, without ``wait``, until nothing is runnable).

    A stop lets the running jobs end first. When the database goes away (a restart, a network cut)
    procrastinate's worker stops by itself; this one then opens the queue again, waiting 1, 2, 4 ..
    15 s between attempts, and carries on where it was. After ``reconnect_s`` without the database
    it raises ServiceError (exit status 1), so that its supervisor restarts it: it never ends quietly
    while jobs wait. Each start first queues again the jobs of workers that stopped beating. With
    ``pulse_file`` its liveness is written there every PULSE_S while it runs (``Pulse``).
    """
    if concurrency < 1:
        raise ValidationError(f"concurrency must be at least 1, got {concurrency}")
    run = _ForegroundRun(store, WorkerOptions(concurrency, wait, name, on_stage=on_stage))
    pulse = Pulse(pulse_file, name or default_worker_name(), run.health) if pulse_file else None
    in_main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, run.on_signal) for s in (signal.SIGINT, signal.SIGTERM)} if in_main else {}
    if pulse is not None:
        pulse.start()
    try:
        run.reconnecting(reconnect_s)
    finally:
        if pulse is not None:
            pulse.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class _ForegroundRun:
    """One foreground worker's life (``run_worker``): its connections, its stop and its health."""

    def __init__(self, store: Store, options: WorkerOptions) -> None:
        self.store = store
        self.options = options
        self.stop = threading.Event()  # a stop asked for (signal): never reconnect after it
        self.current: dict[str, Any] = {}
        self.health: dict[str, Any] = {"worker": None, "lost_since": None}  # what the pulse reports

    def on_signal(self, signum: int, frame: Any) -> None:
        """Stop: once the running jobs end, or at once while still connecting."""
        self.stop.set()
        loop, worker, task = self.current.get("loop"), self.current.get("worker"), self.current.get("task")
        if loop is not None and worker is not None:
            loop.call_soon_threadsafe(worker.stop)  # running jobs end first
        elif loop is not None and task is not None:
            loop.call_soon_threadsafe(task.cancel)  # still connecting: nothing to finish

    async def once(self) -> None:
        """Open the queue and run the worker until it stops (asked to, or the connection lost)."""
        self.current.update(loop=asyncio.get_running_loop(), task=asyncio.current_task())
        # one plain connection first: a server that is down refuses it at once, where the queue's pool
        # would keep trying for 30 s
        probe = await AsyncConnection.connect(conninfo(store_url(self.store)), connect_timeout=10)
        await probe.close()
        app = build_app(store_url(self.store), pool_size=self.options.concurrency + 3)
        async with app.open_async():
            requeued = await _retry_stalled(app)
            if requeued:
                log.warning("worker: %d job(s) of lost workers queued again", requeued)
            worker = _worker(app, self.store, self.options)
            self.current.update(worker=worker)
            self.health.update(worker=worker, lost_since=None)
            try:
                if not self.stop.is_set():
                    self.current["connected"] = True
                    await worker.run()
            finally:
                self.current.pop("worker", None)
                self.health["worker"] = None

    def reconnecting(self, reconnect_s: float) -> None:
        """Run ``once`` again after each lost connection, 1 .. 15 s apart; ServiceError after ``reconnect_s``."""
        lost_since: float | None = None
        delay = 1.0
        while True:
            began = time.monotonic()
            connected = False
            try:
                asyncio.run(self.once())
                if self.stop.is_set() or not self.options.wait:
                    return
                reason = "the queue's connection was lost"
            except asyncio.CancelledError:
                if self.stop.is_set():
                    return
                raise
            except (PsycopgError, ProcrastinateException, OSError) as exc:
                if self.stop.is_set():
                    return
                reason = one_line(exc)
            finally:
                connected = bool(self.current.get("connected"))
                self.current.clear()
            now = time.monotonic()
            if connected and now - began > 2 * RECONNECT_MAX_DELAY_S:  # it worked a while: a new outage
                lost_since, delay = None, 1.0
            if lost_since is None:
                lost_since = now
                self.health["lost_since"] = time.time()
            if now - lost_since >= reconnect_s:
                raise ServiceError(
                    f"worker: no database for {now - lost_since:.0f} s ({reason}); exiting so that its "
                    "supervisor restarts it"
                )
            log.warning("worker: %s; connecting again in %g s", reason, delay)
            if self.stop.wait(delay):
                return
            delay = min(2 * delay, RECONNECT_MAX_DELAY_S)


def run_until_ended(store: Store, job_id: int, *, on_stage: OnStage | None = None, poll_s: float = 1.0) -> JobInfo:
    """Run queued jobs in this process until job ``job_id`` has ended (another worker may run it); return it."""
    while True:
        job = store.jobs.get(job_id)
        if job.state in ("done", "failed"):
            return job
        if job.state == "queued":
            run_worker(store, wait=False, on_stage=on_stage)
            job = store.jobs.get(job_id)
            if job.state in ("done", "failed"):
                return job
        time.sleep(poll_s)  # running elsewhere, held by its machine's lock, or waiting for its retry


class QueueWorker(threading.Thread):
    """A procrastinate worker in a thread of this process, with its own event loop (`driftlab serve`)."""

    def __init__(
        self,
        store: Store,
        *,
        concurrency: int = 1,
        name: str | None = None,
        on_model: OnModel | None = None,
        polling_s: float = 5.0,
    ) -> None:
        super().__init__(name="driftlab-queue-worker", daemon=True)
        self.store = store
        self.concurrency = concurrency
        self.worker_name = name
        self.on_model = on_model
        self.polling_s = polling_s
        self.ready = threading.Event()
        self.error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._worker: Worker | None = None
        self._stopping = False
        self._lock = threading.Lock()

    def run(self) -> None:
        """Run the worker until stopped; when the database goes away, open the queue again (1 .. 15 s apart)."""
        delay = 1.0
        try:
            while True:
                began = time.monotonic()
                try:
                    asyncio.run(self._main())
                    reason = "the queue's connection was lost"
                except (PsycopgError, ProcrastinateException, OSError) as exc:
                    reason = one_line(exc)
                with self._lock:
                    if self._stopping:
                        return
                if time.monotonic() - began > 2 * RECONNECT_MAX_DELAY_S:
                    delay = 1.0
                log.warning("job queue worker: %s; connecting again in %g s", reason, delay)
                time.sleep(delay)
                delay = min(2 * delay, RECONNECT_MAX_DELAY_S)
        except BaseException as exc:  # reported, not raised: the thread has nobody to raise to
            self.error = exc
            log.exception("job queue worker stopped")
        finally:
            self.ready.set()

    async def _main(self) -> None:
        app = build_app(store_url(self.store), pool_size=self.concurrency + 3)
        async with app.open_async():
            options = WorkerOptions(
                self.concurrency, name=self.worker_name, on_model=self.on_model, polling_s=self.polling_s
            )
            worker = _worker(app, self.store, options)
            with self._lock:
                if self._stopping:
                    return
                self._loop = asyncio.get_running_loop()
                self._worker = worker
            self.ready.set()
            try:
                await worker.run()
            finally:
                with self._lock:
                    self._loop, self._worker = None, None

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask the worker to stop once its running jobs end, and wait up to ``timeout_s`` for it."""
        with self._lock:
            self._stopping = True
            if self._loop is not None and self._worker is not None:
                self._loop.call_soon_threadsafe(self._worker.stop)
        if self.is_alive():
            self.join(timeout_s)
