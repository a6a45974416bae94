"""How jobs are queued and retried: priorities, the per-machine lock, the retry policy.

One policy for both ways a job runs: procrastinate applies ``RetryPolicy`` on PostgreSQL, the
in-process runner on SQLite asks ``retry_in_s`` the same question.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from procrastinate import BaseRetryStrategy, RetryDecision
from procrastinate.exceptions import ConnectorException
from procrastinate.jobs import Job

from driftlab.errors import DriftlabError

#: the procrastinate queue of driftlab's jobs
QUEUE = "driftlab"

#: a job somebody is waiting for (submitted through the API or the command line) goes first
PRIORITY_INTERACTIVE = 10
#: refits that nobody asked for wait behind them
PRIORITY_REFIT = 0
#: the periodic bookkeeping (finding refits, taking back jobs of lost workers) is quick: first
PRIORITY_UPKEEP = 20

#: runs of a job at most (the first and two retries)
MAX_ATTEMPTS = 3


def machine_lock(machine_id: str) -> str:
    """Return the procrastinate lock of a machine's fits: they run one at a time, in submission order."""
    return f"driftlab:fit:{machine_id}"


def refit_queueing_lock(machine_id: str) -> str:
    """Return the queueing lock of a machine's refits: at most one waits in the queue."""
    return f"driftlab:refit:{machine_id}"


def transient(exc: BaseException) -> bool:
    """Return True when the failure may pass by itself: the database, the file system, the queue.

    A fit is a function of the stored data: bad input (any other DriftlabError) or a numerical
    failure fails the same way every time, and is not retried.
    """
    # lazy: sqlalchemy and the store add 0.11 s to `import driftlab.jobs.policy` (measured)
    from sqlalchemy.exc import SQLAlchemyError

    from driftlab.campaigns.db import StoreError

    try:
        # lazy: sqlalchemy and the store add 0.11 s to `import driftlab.jobs.policy` (measured)
        import psycopg

        db_errors: tuple[type[BaseException], ...] = (SQLAlchemyError, psycopg.Error)
    except ImportError:  # pragma: no cover - psycopg is a dependency
        db_errors = (SQLAlchemyError,)
    if isinstance(exc, StoreError):
        return True
    if isinstance(exc, DriftlabError):
        return False
    return isinstance(exc, (*db_errors, ConnectorException, OSError, MemoryError))


def retry_wait_s() -> float:
    """Return the wait before the first retry (DRIFTLAB_JOB_RETRY_WAIT_S; the n-th retry waits n times it)."""
    # lazy: driftlab.config (pydantic-settings) adds 0.10 s to `import driftlab.jobs.policy` (measured)
    from driftlab.config import get_settings

    return max(0.0, float(get_settings().job_retry_wait_s))


def retry_in_s(exc: BaseException, attempts_done: int) -> float | None:
    """Return the seconds to wait before running a failed job again, or None when it has failed for good."""
    if attempts_done >= MAX_ATTEMPTS or not transient(exc):
        return None
    return retry_wait_s() * attempts_done


class RetryPolicy(BaseRetryStrategy):
    """procrastinate's side of ``retry_in_s``."""

    def get_retry_decision(self, *, exception: BaseException, job: Job) -> RetryDecision | None:
        """Return when to run the job again (``job.attempts`` counts the runs before this one), or None."""
        wait = retry_in_s(exception, job.attempts + 1)
        if wait is None:
            return None
        return RetryDecision(retry_at=datetime.now(UTC) + timedelta(seconds=wait))
