"""Jobs on the embedded SQLite store: run in-process, one at a time, with the queue's retry policy.

SQLite has no job queue: a job runs in the process that serves the store (``driftlab serve``'s
``LocalRunner`` thread) or that asked for it (``driftlab fit``'s ``run_here``). The bodies and the
retry policy are the queue's (``tasks.execute``, ``policy.retry_in_s``); one runner per process
runs one job at a time, so two fits of a machine never overlap there. A record is taken only from
the queued state, so two processes on one file never run the same job. Parallel workers, locks
across hosts and periodic refits need the PostgreSQL store.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from typing import TYPE_CHECKING

from driftlab.jobs import policy
from driftlab.jobs.queue import default_worker_name
from driftlab.jobs.tasks import KINDS, OnModel, OnStage, execute

if TYPE_CHECKING:
    from driftlab.campaigns.store import JobInfo, Store

log = logging.getLogger(__name__)

INTERRUPTED = "interrupted: the process running it stopped before it ended; submit it again"


def _attempt(
    store: Store, job_id: int, worker: str, on_stage: OnStage | None, on_model: OnModel | None
) -> tuple[bool, float | None]:
    """Run one attempt of a queued job; return (it ran, seconds before its retry or None)."""
    wait: list[float | None] = [None]

    def will_retry(exc: BaseException, job: JobInfo) -> bool:
        wait[0] = policy.retry_in_s(exc, job.attempts)
        return wait[0] is not None

    try:
        ran = (
            execute(
                store, job_id, worker, will_retry=will_retry, only_if_queued=True, on_stage=on_stage, on_model=on_model
            )
            is not None
        )
    except Exception:  # recorded by execute
        return True, wait[0]
    return ran, None


def run_here(store: Store, job_id: int, *, on_stage: OnStage | None = None, worker: str | None = None) -> JobInfo:
    """Run a queued job in this process, retries included; return it as it ended."""
    name = worker or default_worker_name()
    while True:
        ran, wait = _attempt(store, job_id, name, on_stage, None)
        if not ran or wait is None:
            return store.jobs.get(job_id)
        time.sleep(wait)


class LocalRunner(threading.Thread):
    """A background thread running this process's jobs on SQLite, one at a time, oldest first.

    At start it takes the jobs left queued by an earlier process, and records as failed those it
    left running (interrupted).
    """

    def __init__(self, store: Store, *, on_model: OnModel | None = None, name: str | None = None) -> None:
        super().__init__(name="driftlab-jobs", daemon=True)
        self.store = store
        self.on_model = on_model
        self.worker = name or f"local-{default_worker_name()}"
        self.ran = 0
        self._due: list[tuple[float, int]] = []  # (monotonic time due, job id)
        self._cond = threading.Condition()
        self._stopping = False

    def submit(self, job_id: int, delay_s: float = 0.0) -> None:
        """Run a recorded job once it is due."""
        with self._cond:
            heapq.heappush(self._due, (time.monotonic() + delay_s, job_id))
            self._cond.notify()

    def stop(self, timeout_s: float = 30.0) -> None:
        """Ask the thread to finish after its current job and wait for it."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self.is_alive():
            self.join(timeout_s)

    def _next(self) -> int | None:
        """Return the next due job id, waiting for one; None when stopping."""
        with self._cond:
            while not self._stopping:
                now = time.monotonic()
                if self._due and self._due[0][0] <= now:
                    return heapq.heappop(self._due)[1]
                self._cond.wait(None if not self._due else self._due[0][0] - now)
            return None

    def run(self) -> None:
        """Take up what an earlier process left, then run jobs until stopped."""
        try:
            for left in self.store.jobs.in_state("running", list(KINDS)):
                self.store.jobs.fail(left, INTERRUPTED)
            for left in self.store.jobs.in_state("queued", list(KINDS)):
                self.submit(left)
        except Exception:
            log.exception("job runner: cannot read the jobs left by an earlier process")
        while (job_id := self._next()) is not None:
            try:
                _ran, wait = _attempt(self.store, job_id, self.worker, None, self.on_model)
            except Exception:  # the store itself failed: logged, the runner goes on
                log.exception("job %s: could not be run", job_id)
                continue
            if wait is not None:
                self.submit(job_id, wait)
            self.ran += 1
