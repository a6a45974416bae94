"""Fit, diagnose and refit jobs: submitted here, run by procrastinate on PostgreSQL, in-process on SQLite.

- ``tasks``: the bodies (load through the store, run the pure models, save through the store and
  the registry) and ``execute``, which runs one job record around its body.
- ``policy``: priorities, the per-machine lock of fits, the retry policy (both backends).
- ``queue``: procrastinate on the store's PostgreSQL: the tasks, the periodic refit, workers
  (``driftlab worker``, or a thread of ``driftlab serve``).
- ``local``: the embedded SQLite store's in-process runner.

Every job has a record in the store's ``jobs`` table (what was asked, its state, the result or a
one-line error); the API reports from it, with procrastinate's own state while a job is in the
queue. ``Jobs`` is what a server holds; ``submit`` and ``run_until_ended`` serve the command line.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Any, TypedDict, Unpack

from psycopg_pool import NullConnectionPool

from driftlab.errors import ValidationError
from driftlab.jobs import local, queue
from driftlab.jobs.local import LocalRunner
from driftlab.jobs.policy import PRIORITY_INTERACTIVE
from driftlab.jobs.queue import QueueWorker, build_app, conninfo, store_url, submit_to_queue
from driftlab.jobs.tasks import DIAGNOSE, FIT, KINDS, OnModel, OnStage

if TYPE_CHECKING:
    from procrastinate import App

    from driftlab.campaigns.store import JobInfo, Store

__all__ = ["DIAGNOSE", "FIT", "KINDS", "Jobs", "run_until_ended", "submit", "submit_fit"]

log = logging.getLogger(__name__)


def _queued(store: Store) -> bool:
    """Return True when the store's jobs go through the procrastinate queue (PostgreSQL)."""
    return store.dialect == "postgresql"


class Jobs:
    """Submits jobs to the store's queue and, with ``run_here``, runs them in this process too.

    PostgreSQL: jobs are deferred to procrastinate; ``run_here`` runs a worker thread beside the
    server (other ``driftlab worker`` processes share the queue). SQLite: jobs run in a thread of
    this process. ``on_model(machine_id)`` is called when a job run here registers a model, before
    its record reads done (the API drops its cached current model there).
    """

    def __init__(
        self, store: Store, *, run_here: bool = True, on_model: OnModel | None = None, concurrency: int = 1
    ) -> None:
        self.store = store
        self.run_here = run_here
        self.on_model = on_model
        self.concurrency = concurrency
        self.runner: LocalRunner | QueueWorker | None = None
        self._app: App | None = None
        self._pool: NullConnectionPool | None = None
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start running jobs in this process (when ``run_here``)."""
        if not self.run_here or self.runner is not None:
            return
        if _queued(self.store):
            self.runner = QueueWorker(self.store, concurrency=self.concurrency, on_model=self.on_model)
        else:
            self.runner = LocalRunner(self.store, on_model=self.on_model)
        self.runner.start()

    def stop(self) -> None:
        """Stop running jobs here (after the current one) and close the queue's connections."""
        if self.runner is not None:
            self.runner.stop()
            self.runner = None
        with self._lock:
            if self._app is not None:
                self._app.close()
                self._app = None
            if self._pool is not None:
                self._pool.close()
                self._pool = None

    def _deferrer(self) -> App:
        """Return the procrastinate App this object defers through (opened once, synchronously).

        Its pool keeps no idle connection (a submission opens one): an API that is never shut down
        cleanly, or a short-lived command, leaves none behind.
        """
        with self._lock:
            if self._app is None:
                url = store_url(self.store)
                self._pool = NullConnectionPool(conninfo(url), max_size=4, num_workers=1, open=False)
                self._pool.open()
                app = build_app(url)
                app.open(self._pool)
                self._app = app
            return self._app

    def submit(
        self,
        kind: str,
        params: dict[str, Any],
        *,
        machine_id: str | None = None,
        campaign_id: int | None = None,
        priority: int = PRIORITY_INTERACTIVE,
    ) -> int:
        """Record a job and queue it (PostgreSQL) or hand it to this process's runner (SQLite); return its id."""
        if _queued(self.store):
            return submit_to_queue(
                self._deferrer(),
                self.store,
                kind,
                params,
                machine_id=machine_id,
                campaign_id=campaign_id,
                priority=priority,
            )

        job_id = self.store.jobs.record(kind, params, machine_id=machine_id, campaign_id=campaign_id)
        if isinstance(self.runner, LocalRunner):
            self.runner.submit(job_id)
        return job_id


class JobKeywords(TypedDict, total=False):
    """The keywords of ``Jobs.submit``, which ``submit`` passes on: the job's machine, campaign and priority."""

    machine_id: str | None
    campaign_id: int | None
    priority: int


def submit(store: Store, kind: str, params: dict[str, Any], **keywords: Unpack[JobKeywords]) -> int:
    """Record and queue one job (nothing runs it here); return its id."""
    jobs = Jobs(store, run_here=False)
    try:
        return jobs.submit(kind, params, **keywords)
    finally:
        jobs.stop()


def submit_fit(
    store: Store,
    campaign_ids: list[int],
    *,
    network: bool = True,
    findings: Any = None,
    force_findings: bool = False,
    envelope: Any = None,
    split: str | None = None,
) -> int:
    """Queue a fit of these campaigns (of one machine); return the job id.

    ``split`` (``models.split``): which points the fit holds out (default: its own, ``stage``).

    ``findings`` (``models.findings.Findings``) are kept in the job's parameters and folded in by the fit;
    ``envelope`` (``models.envelope.Envelope``) is written into the model document.
    """
    ids = [int(c) for c in campaign_ids]
    if not ids:
        raise ValidationError("give at least one campaign")
    machine = store.campaigns.machine_of(ids[0])
    params: dict[str, Any] = {"campaigns": ids, "network": bool(network)}
    if findings is not None:
        params["findings"] = findings.to_dict()
        params["force_findings"] = bool(force_findings)
    if envelope is not None:
        params["envelope"] = envelope.model_dump(mode="json")
    if split is not None:
        params["split"] = str(split)
    return submit(store, FIT, params, machine_id=machine, campaign_id=ids[0])


def run_until_ended(store: Store, job_id: int, *, on_stage: OnStage | None = None) -> JobInfo:
    """Run a queued job in this process (PostgreSQL: a worker that also takes what is queued before it,
    unless another worker has the job first); return the job as it ended."""
    if _queued(store):
        return queue.run_until_ended(store, job_id, on_stage=on_stage)

    return local.run_here(store, job_id, on_stage=on_stage)
