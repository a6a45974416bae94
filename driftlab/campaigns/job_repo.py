"""The job records' repository: what a job was asked to do and what came of it (table ``jobs``).

The queue itself is ``driftlab.jobs`` (procrastinate on PostgreSQL, in-process on SQLite); while a
job is in procrastinate's queue its reported state is the queue's (``jobs_select``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy import Select, Text, case, cast, column, delete, insert, null, select, table, update

from driftlab.campaigns import schema as sc
from driftlab.campaigns.repository import Page, Repository
from driftlab.errors import NotFoundError, ValidationError

if TYPE_CHECKING:
    from datetime import datetime


@dataclass(frozen=True)
class JobInfo:
    """A job row as callers see it."""

    id: int
    kind: str
    state: str
    params: dict[str, Any]
    result: dict[str, Any] | None
    error: str | None
    worker: str | None
    attempts: int
    machine_id: str | None
    campaign_id: int | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    queue_job_id: int | None = None
    #: procrastinate's status of the job (PostgreSQL), None when it has no queue row
    queue_status: str | None = None


@dataclass(frozen=True)
class JobFilter:
    """Which jobs a listing shows: by state (as reported), kind, set of kinds and machine (None: any)."""

    state: str | None = None
    kind: str | None = None
    machine_id: str | None = None
    kinds: tuple[str, ...] | None = None


#: procrastinate's job statuses as the job states driftlab reports (queued, running, done, failed)
QUEUE_STATES = {
    "todo": "queued",
    "doing": "running",
    "aborting": "running",
    "succeeded": "done",
    "failed": "failed",
    "cancelled": "failed",
    "aborted": "failed",
}
_QUEUE_JOBS = table("procrastinate_jobs", column("id"), column("status"))


def jobs_select(dialect: str) -> Select[Any]:
    """Return the SELECT of job records with the state to report, as ``state``.

    A record that ended (done, failed) is final: the task wrote it. Before that, on PostgreSQL, the
    queue knows better than the record (a job waiting for its retry, taken back from a lost worker,
    cancelled with procrastinate's own tools), so its status, mapped by ``QUEUE_STATES``, wins.
    """
    cols = [c for c in sc.Job.__table__.c if c.name != "state"]
    if dialect != "postgresql":
        return select(*cols, sc.Job.state, null().label("queue_status"))
    status = cast(_QUEUE_JOBS.c.status, Text)
    by_queue = [(status == k, v) for k, v in QUEUE_STATES.items()]
    state = case((sc.Job.state.in_(("done", "failed")), sc.Job.state), *by_queue, else_=sc.Job.state)
    return select(*cols, state.label("state"), status.label("queue_status")).select_from(
        sc.Job.__table__.outerjoin(_QUEUE_JOBS, _QUEUE_JOBS.c.id == sc.Job.queue_job_id)
    )


def job_info(row: Any) -> JobInfo:
    """Return the JobInfo of a row of ``jobs_select``."""
    error = row.error
    if row.state == "failed" and error is None and row.queue_status in ("failed", "cancelled", "aborted"):
        error = f"the job queue reports it {row.queue_status} (see the worker's log)"
    return JobInfo(
        id=row.id,
        kind=row.kind,
        state=row.state,
        params=row.params or {},
        result=row.result,
        error=error,
        worker=row.worker,
        attempts=row.attempts,
        machine_id=row.machine_id,
        campaign_id=row.campaign_id,
        created_at=row.created_at,
        started_at=row.started_at,
        finished_at=row.finished_at,
        queue_job_id=row.queue_job_id,
        queue_status=row.queue_status,
    )


class JobRepository(Repository):
    """Job records: recorded queued, started, finished or failed, listed and read back."""

    def record(
        self,
        kind: str,
        params: dict[str, Any] | None = None,
        machine_id: str | None = None,
        campaign_id: int | None = None,
    ) -> int:
        """Record a new job, queued, and return its id."""
        if not kind:
            raise ValidationError("a job needs a kind")
        with self.write() as conn:
            return int(
                conn.execute(
                    insert(sc.Job)
                    .values(
                        kind=kind,
                        state="queued",
                        params=params or {},
                        machine_id=machine_id,
                        campaign_id=campaign_id,
                        attempts=0,
                        created_at=sc.utcnow(),
                    )
                    .returning(sc.Job.id)
                ).scalar_one()
            )

    def link_queue_job(self, job_id: int, queue_job_id: int) -> None:
        """Record the queue's id of a job (procrastinate_jobs.id)."""
        self._update(job_id, queue_job_id=int(queue_job_id))

    def start(self, job_id: int, worker: str, *, only_if_queued: bool = False) -> JobInfo | None:
        """Mark a job running under ``worker`` (one more attempt); return it.

        With ``only_if_queued`` the job is taken only from the queued state (None otherwise): the
        in-process runner's guard against a second process running the same record. A queue's
        worker passes False: the queue already gave the job to it alone, and a job it retries after
        a lost worker may still read "running".
        """
        now = sc.utcnow()
        with self.write() as conn:
            cond = [sc.Job.id == job_id]
            if only_if_queued:
                cond.append(sc.Job.state == "queued")
            n = conn.execute(
                update(sc.Job)
                .where(*cond)
                .values(state="running", worker=worker, started_at=now, finished_at=None, attempts=sc.Job.attempts + 1)
            ).rowcount
            if not n:
                if only_if_queued:
                    return None
                raise NotFoundError(f"no job {job_id}")
            return job_info(conn.execute(jobs_select(conn.dialect.name).where(sc.Job.id == job_id)).one())

    def finish(self, job_id: int, result: dict[str, Any]) -> None:
        """Record a job done with its result."""
        self._update(job_id, state="done", result=result, error=None, finished_at=sc.utcnow())

    def fail(self, job_id: int, error: str, *, retry: bool = False) -> None:
        """Record a job's one-line error: failed, or queued again when a retry comes."""
        line = " ".join(error.split())
        if retry:
            self._update(job_id, state="queued", error=line)
        else:
            self._update(job_id, state="failed", error=line, finished_at=sc.utcnow())

    def delete(self, job_id: int) -> None:
        """Delete a job record (one that never reached the queue)."""
        with self.write() as conn:
            conn.execute(delete(sc.Job).where(sc.Job.id == job_id))

    def _update(self, job_id: int, **values: Any) -> None:
        with self.write() as conn:
            if not conn.execute(update(sc.Job).where(sc.Job.id == job_id).values(**values)).rowcount:
                raise NotFoundError(f"no job {job_id}")

    def in_state(self, state: str, kinds: list[str] | None = None) -> list[int]:
        """Return the ids of the records in ``state`` (as recorded, not as the queue reports), oldest first."""
        with self.read() as conn:
            q = select(sc.Job.id).where(sc.Job.state == state).order_by(sc.Job.id)
            if kinds:
                q = q.where(sc.Job.kind.in_(kinds))
            return [int(j) for j in conn.execute(q).scalars()]

    def last_result(self, kind: str, machine_id: str) -> dict[str, Any] | None:
        """Return the result of the machine's last finished job of this kind (None when there is none)."""
        with self.read() as conn:
            row = conn.execute(
                select(sc.Job.result)
                .where(sc.Job.kind == kind, sc.Job.machine_id == machine_id, sc.Job.state == "done")
                .order_by(sc.Job.id.desc())
                .limit(1)
            ).first()
        return None if row is None else row[0]

    def get(self, job_id: int) -> JobInfo:
        """Return a job (its state as the queue reports it); NotFoundError if there is none with that id."""
        with self.read() as conn:
            row = conn.execute(jobs_select(conn.dialect.name).where(sc.Job.id == job_id)).first()
            if row is None:
                raise NotFoundError(f"no job {job_id}")
            return job_info(row)

    def find(self, where: JobFilter = JobFilter(), page: Page = Page()) -> list[JobInfo]:
        """Return jobs (newest first), filtered by state (as reported), kind (or set of kinds) and machine."""
        with self.read() as conn:
            jobs = jobs_select(conn.dialect.name).subquery()
            q = select(jobs).order_by(jobs.c.id.desc())
            if where.kinds:
                q = q.where(jobs.c.kind.in_(where.kinds))
            if where.state is not None:
                q = q.where(jobs.c.state == where.state)
            if where.kind is not None:
                q = q.where(jobs.c.kind == where.kind)
            if where.machine_id is not None:
                q = q.where(jobs.c.machine_id == where.machine_id)
            return [job_info(r) for r in conn.execute(page.apply(q)).all()]
