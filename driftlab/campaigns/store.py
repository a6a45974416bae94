"""The campaign store: one object over SQLite or PostgreSQL for ingest, queries, registry and job records.

Writes happen in one transaction each (``db.write_transaction``): an import either lands whole or
leaves the database exactly as it was, whatever interrupts it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import pandas as pd
from sqlalchemy import Engine, Select, Text, case, cast, column, delete, func, insert, null, select, table, text, update
from sqlalchemy.exc import IntegrityError

from driftlab.campaigns import db, ingest, partitions, queries
from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import Bundle
from driftlab.campaigns.staging import StagedBundle
from driftlab.errors import ConflictError, NotFoundError, ValidationError

log = logging.getLogger(__name__)

CampaignSummary = queries.CampaignSummary


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
class RefitCandidate:
    """A machine with finished campaigns newer than its current model: what a refit would fit."""

    machine_id: str
    model_version: int
    campaign_ids: list[int]
    #: the parameters of the fit that made the current model ({} when none is recorded)
    params: dict[str, Any]


@dataclass(frozen=True)
class ModelVersionInfo:
    """A model registry entry."""

    id: int
    machine_id: str
    version: int
    created_at: datetime
    source_campaigns: list[int]
    document: dict[str, Any]
    status: str


@dataclass(frozen=True)
class ProgressInfo:
    """The acquisition scheduler's resume point of a campaign."""

    campaign_id: int
    stage_ordinal: int
    sweep: int
    last_sample_time_s: float | None
    cursor: dict[str, Any] | None
    updated_at: datetime


@dataclass(frozen=True)
class OnlineStateInfo:
    """A machine's stored on-line (RLS) state: per probed term theta and P, and the concurrency version."""

    machine_id: str
    model_version_id: int | None
    model_version: int
    lam: float
    n_updates: int
    theta: dict[str, Any]
    p: dict[str, Any]
    updated_at: datetime
    version: int


class StaleOnlineState(ConflictError):
    """The on-line state changed since it was read: recompute from the new state and try again."""


def _online(row: Any) -> OnlineStateInfo:
    return OnlineStateInfo(
        row.machine_id,
        row.model_version_id,
        int(row.model_version),
        float(row.lam),
        int(row.n_updates),
        dict(row.theta or {}),
        dict(row.p or {}),
        row.updated_at,
        int(row.version),
    )


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
        row.id,
        row.kind,
        row.state,
        row.params or {},
        row.result,
        error,
        row.worker,
        row.attempts,
        row.machine_id,
        row.campaign_id,
        row.created_at,
        row.started_at,
        row.finished_at,
        row.queue_job_id,
        row.queue_status,
    )


def _model(row: Any) -> ModelVersionInfo:
    return ModelVersionInfo(
        row.id, row.machine_id, row.version, row.created_at, list(row.source_campaigns or []), row.document, row.status
    )


class Store:
    """A campaign store on one database; the schema is brought to head on first use."""

    def __init__(self, engine: Engine, auto_upgrade: bool = True) -> None:
        """Wrap an engine; with ``auto_upgrade`` the schema is upgraded on first use."""
        self.engine = engine
        self._ready = not auto_upgrade

    @property
    def url(self) -> str:
        """Return the database URL (password hidden)."""
        return self.engine.url.render_as_string(hide_password=True)

    @property
    def dialect(self) -> str:
        """Return ``sqlite`` or ``postgresql``."""
        return self.engine.dialect.name

    def upgrade(self, revision: str = "head") -> str:
        """Bring the schema to ``revision`` (head by default) and return the revision reached."""
        reached = db.upgrade(self.engine, revision)
        self._ready = True
        return reached

    def revision(self) -> str | None:
        """Return the database's current schema revision (None when empty)."""
        return db.current_revision(self.engine)

    def ensure_schema(self) -> None:
        """Upgrade the schema to head if it is not there yet (done once per Store)."""
        if self._ready:
            return
        if db.current_revision(self.engine) != db.head_revision():
            self.upgrade()
        self._ready = True

    def close(self) -> None:
        """Release the engine's connections."""
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ campaigns

    def import_bundle(self, bundle: Bundle | StagedBundle) -> int:
        """Store a validated bundle (in memory, or staged: ``staging.stage_bundle``) in one transaction.

        Returns its campaign id. Refused (ConflictError) when a campaign with the same content hash
        is already stored. A staged bundle's rows are written a chunk at a time.
        """
        self.ensure_schema()
        content_hash = bundle.content_hash()
        day = partitions.start_day(bundle.meta.started_at)
        # the month's partition, made (in a transaction of its own) before the import writes into it
        partitions.ensure_partitions(self.engine, [day])
        try:
            with db.write_transaction(self.engine) as conn:
                existing = conn.execute(select(sc.Campaign.id).where(sc.Campaign.content_hash == content_hash)).scalar()
                if existing is not None:
                    raise ConflictError(
                        f"bundle {bundle.name!r} is already stored as campaign {existing} (same content hash "
                        f"{content_hash[:12]}); nothing imported"
                    )
                campaign_id = ingest.import_bundle(conn, bundle, content_hash)
        except IntegrityError as exc:
            # A concurrent import of the same content committed first.
            if "content_hash" in str(exc.orig):
                raise ConflictError(f"bundle {bundle.name!r} was imported concurrently; nothing imported") from None
            raise
        self.analyze(day)
        return campaign_id

    def analyze(self, start_day: int | None = None) -> None:
        """Refresh the planner statistics of the sample tables (after a bulk load or a campaign's end).

        Without them both planners may scan a campaign's error samples instead of seeking the
        drift indexes. SQLite samples a bounded number of rows per index (fast on any size). On
        PostgreSQL, with ``start_day``, only the partitions of that day's month (and the rollups) that
        were never analysed are, now (the planner reads a partition's own statistics once it has
        pruned to it); their growth is left to autovacuum. A whole-table ANALYZE samples every
        partition, a cost that grows with the fleet.
        """
        with self.engine.connect() as conn:
            if self.dialect == "postgresql":
                # temperature_samples is left to autovacuum: its queries are primary-key ranges whose
                # plan does not depend on statistics, and sampling 12 million rows costs a second
                if start_day is None:
                    conn.execute(text("ANALYZE temperature_rollups, condition_samples, error_samples"))
                else:
                    leaves = [partitions.leaf(conn, t, start_day) for t in ("condition_samples", "error_samples")]
                    partitions.analyze_new(conn, ["temperature_rollups", *[x for x in leaves if x]])
            else:
                conn.exec_driver_sql("PRAGMA analysis_limit=1000")
                conn.exec_driver_sql("ANALYZE")
            conn.commit()

    def load_campaign(self, campaign_id: int) -> Bundle:
        """Return a stored campaign as a Bundle with exactly the values stored."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.load_campaign(conn, campaign_id)

    def campaign_machine(self, campaign_id: int) -> str:
        """Return the machine id of a campaign; NotFoundError if there is no such campaign."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            machine = conn.execute(select(sc.Campaign.machine_id).where(sc.Campaign.id == campaign_id)).scalar()
        if machine is None:
            raise NotFoundError(f"no campaign {campaign_id}")
        return str(machine)

    def list_campaigns(self, machine_id: str | None = None) -> list[CampaignSummary]:
        """Return a summary of every campaign, oldest first."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.list_campaigns(conn, machine_id)

    def delete_campaign(self, campaign_id: int) -> None:
        """Delete a campaign with all its samples, stages, channels and progress (one transaction)."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            # FOR UPDATE (PostgreSQL; SQLite's BEGIN IMMEDIATE already serialises writers): a concurrent
            # delete of the same campaign waits here, then finds no row and answers "no campaign"
            row = conn.execute(select(sc.Campaign.id).where(sc.Campaign.id == campaign_id).with_for_update()).first()
            if row is None:
                raise NotFoundError(f"no campaign {campaign_id}")
            # every partition is looked at (one index probe each), not just the campaign's: a delete
            # must not depend on the readings' key being what the campaign's start says
            for table in (sc.TemperatureSample, sc.TemperatureRollup, sc.ConditionSample, sc.ErrorSample):
                conn.execute(delete(table).where(table.campaign_id == campaign_id))
            gone = conn.execute(delete(sc.Campaign).where(sc.Campaign.id == campaign_id))
            if gone.rowcount != 1:  # pragma: no cover - the row lock above makes this unreachable
                raise NotFoundError(f"no campaign {campaign_id}")

    def table_counts(self) -> dict[str, int]:
        """Return the row count of every table (used to prove a failed write changed nothing)."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return {
                name: int(conn.execute(select(func.count()).select_from(table)).scalar_one())
                for name, table in sorted(sc.metadata.tables.items())
            }

    # ------------------------------------------------------------------ queries

    def drift(
        self,
        machine_id: str,
        axis: str,
        term: str,
        position: float | None = None,
        direction: int | None = None,
        start: datetime | None = None,
        end: datetime | None = None,
        interpolate: bool = False,
    ) -> pd.DataFrame:
        """Return the error history of (axis, term) across a machine's campaigns (see queries.drift)."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.drift(conn, machine_id, axis, term, position, direction, start, end, interpolate)

    def temperature_history(
        self,
        campaign_id: int,
        channel: str,
        start_s: float | None = None,
        end_s: float | None = None,
        buckets: int | None = None,
        rollups: bool = True,
    ) -> pd.DataFrame:
        """Return a channel's readings, or min/mean/max per bucket computed in SQL (see queries)."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.temperature_history(conn, campaign_id, channel, start_s, end_s, buckets, rollups)

    def refresh_rollups(self, campaign_id: int) -> int:
        """Recompute a campaign's per-minute temperature rollups (e.g. when a live campaign ends)."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            if conn.execute(select(sc.Campaign.id).where(sc.Campaign.id == campaign_id)).first() is None:
                raise NotFoundError(f"no campaign {campaign_id}")
            return ingest.refresh_rollups(conn, campaign_id)

    def condition_history(
        self,
        campaign_id: int,
        columns: list[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
        buckets: int | None = None,
    ) -> pd.DataFrame:
        """Return machine-state values, raw or min/mean/max per bucket computed in SQL."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.condition_history(conn, campaign_id, columns, start_s, end_s, buckets)

    # ------------------------------------------------------------------ model registry

    def register_model(
        self, machine_id: str, document: dict[str, Any], source_campaigns: list[int] | None = None
    ) -> ModelVersionInfo:
        """Store a new model version as the machine's current one, retiring the previous current."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            lock = select(sc.Machine.id).where(sc.Machine.id == machine_id)
            if conn.dialect.name == "postgresql":
                lock = lock.with_for_update()  # serialises registrations of one machine
            if conn.execute(lock).first() is None:
                raise NotFoundError(f"no machine {machine_id!r}")
            last = conn.execute(
                select(func.max(sc.ModelVersion.version)).where(sc.ModelVersion.machine_id == machine_id)
            ).scalar()
            now = sc.utcnow()
            conn.execute(
                update(sc.ModelVersion)
                .where(sc.ModelVersion.machine_id == machine_id, sc.ModelVersion.status == "current")
                .values(status="retired", retired_at=now)
            )
            new_id = conn.execute(
                insert(sc.ModelVersion)
                .values(
                    machine_id=machine_id,
                    version=(last or 0) + 1,
                    created_at=now,
                    source_campaigns=list(source_campaigns or []),
                    document=document,
                    status="current",
                )
                .returning(sc.ModelVersion.id)
            ).scalar_one()
            row = conn.execute(select(sc.ModelVersion.__table__).where(sc.ModelVersion.id == new_id)).one()
            return _model(row)

    def current_model(self, machine_id: str) -> ModelVersionInfo | None:
        """Return the machine's current model version, or None when it has none."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(
                select(sc.ModelVersion.__table__).where(
                    sc.ModelVersion.machine_id == machine_id, sc.ModelVersion.status == "current"
                )
            ).first()
            return None if row is None else _model(row)

    def model_versions(self, machine_id: str) -> list[ModelVersionInfo]:
        """Return every model version of a machine, oldest first."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            rows = conn.execute(
                select(sc.ModelVersion.__table__)
                .where(sc.ModelVersion.machine_id == machine_id)
                .order_by(sc.ModelVersion.version)
            ).all()
            return [_model(r) for r in rows]

    def machine_ids(self) -> list[str]:
        """Return the id of every machine in the store, in order."""
        self.ensure_schema()
        with self.engine.connect() as conn:
            return [m for (m,) in conn.execute(select(sc.Machine.id).order_by(sc.Machine.id))]

    # ------------------------------------------------------------------ job records
    # The queue itself is driftlab.jobs (procrastinate on PostgreSQL, in-process on SQLite); these
    # rows are what a job was asked to do and what came of it.

    def record_job(
        self,
        kind: str,
        params: dict[str, Any] | None = None,
        machine_id: str | None = None,
        campaign_id: int | None = None,
    ) -> int:
        """Record a new job, queued, and return its id."""
        self.ensure_schema()
        if not kind:
            raise ValidationError("a job needs a kind")
        with db.write_transaction(self.engine) as conn:
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
        self._update_job(job_id, queue_job_id=int(queue_job_id))

    def start_job(self, job_id: int, worker: str, *, only_if_queued: bool = False) -> JobInfo | None:
        """Mark a job running under ``worker`` (one more attempt); return it.

        With ``only_if_queued`` the job is taken only from the queued state (None otherwise): the
        in-process runner's guard against a second process running the same record. A queue's
        worker passes False: the queue already gave the job to it alone, and a job it retries after
        a lost worker may still read "running".
        """
        self.ensure_schema()
        now = sc.utcnow()
        with db.write_transaction(self.engine) as conn:
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

    def finish_job(self, job_id: int, result: dict[str, Any]) -> None:
        """Record a job done with its result."""
        self._update_job(job_id, state="done", result=result, error=None, finished_at=sc.utcnow())

    def fail_job(self, job_id: int, error: str, *, retry: bool = False) -> None:
        """Record a job's one-line error: failed, or queued again when a retry comes."""
        line = " ".join(error.split())
        if retry:
            self._update_job(job_id, state="queued", error=line)
        else:
            self._update_job(job_id, state="failed", error=line, finished_at=sc.utcnow())

    def delete_job(self, job_id: int) -> None:
        """Delete a job record (one that never reached the queue)."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            conn.execute(delete(sc.Job).where(sc.Job.id == job_id))

    def _update_job(self, job_id: int, **values: Any) -> None:
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            if not conn.execute(update(sc.Job).where(sc.Job.id == job_id).values(**values)).rowcount:
                raise NotFoundError(f"no job {job_id}")

    def jobs_in_state(self, state: str, kinds: list[str] | None = None) -> list[int]:
        """Return the ids of the records in ``state`` (as recorded, not as the queue reports), oldest first."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            q = select(sc.Job.id).where(sc.Job.state == state).order_by(sc.Job.id)
            if kinds:
                q = q.where(sc.Job.kind.in_(kinds))
            return [int(j) for j in conn.execute(q).scalars()]

    def last_job_result(self, kind: str, machine_id: str) -> dict[str, Any] | None:
        """Return the result of the machine's last finished job of this kind (None when there is none)."""
        self.ensure_schema()
        with self.engine.connect() as conn:
            row = conn.execute(
                select(sc.Job.result)
                .where(sc.Job.kind == kind, sc.Job.machine_id == machine_id, sc.Job.state == "done")
                .order_by(sc.Job.id.desc())
                .limit(1)
            ).first()
        return None if row is None else row[0]

    def get_job(self, job_id: int) -> JobInfo:
        """Return a job (its state as the queue reports it); NotFoundError if there is none with that id."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(jobs_select(conn.dialect.name).where(sc.Job.id == job_id)).first()
            if row is None:
                raise NotFoundError(f"no job {job_id}")
            return job_info(row)

    def refit_candidates(self) -> list[RefitCandidate]:
        """Return the machines whose current model predates finished campaigns of theirs, with what to refit.

        A candidate's campaigns are the current model's sources plus every finished campaign started
        after the newest of them (campaigns the model left out on purpose stay out); ``params`` are
        those of the fit job that made the current model, when one did.
        """
        self.ensure_schema()
        out: list[RefitCandidate] = []
        with self.engine.connect() as conn, conn.begin():
            models = conn.execute(
                select(sc.ModelVersion.machine_id, sc.ModelVersion.version, sc.ModelVersion.source_campaigns)
                .where(sc.ModelVersion.status == "current")
                .order_by(sc.ModelVersion.machine_id)
            ).all()
            for m in models:
                sources = [int(c) for c in (m.source_campaigns or [])]
                if not sources:
                    continue
                done = conn.execute(
                    select(sc.Campaign.id, sc.Campaign.started_at)
                    .where(sc.Campaign.machine_id == m.machine_id, sc.Campaign.status == "done")
                    .order_by(sc.Campaign.started_at, sc.Campaign.id)
                ).all()
                started = {int(c.id): c.started_at for c in done}
                newest = max((started[c] for c in sources if c in started), default=None)
                if newest is None:
                    continue
                new = [c for c, at in started.items() if c not in sources and at > newest]
                if not new:
                    continue
                fits = conn.execute(
                    select(sc.Job.params, sc.Job.result)
                    .where(sc.Job.machine_id == m.machine_id, sc.Job.kind == "fit", sc.Job.state == "done")
                    .order_by(sc.Job.id.desc())
                ).all()
                params = next(
                    (dict(f.params or {}) for f in fits if (f.result or {}).get("model_version") == m.version), {}
                )
                out.append(
                    RefitCandidate(m.machine_id, int(m.version), [c for c in sources if c in started] + new, params)
                )
        return out

    # ------------------------------------------------------------------ on-line state

    def online_state(self, machine_id: str) -> OnlineStateInfo | None:
        """Return the machine's on-line state row (whatever model version it belongs to), or None."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(select(sc.OnlineState.__table__).where(sc.OnlineState.machine_id == machine_id)).first()
            return None if row is None else _online(row)

    def save_online_state(
        self,
        machine_id: str,
        seen_version: int | None,
        *,
        model_version_id: int | None,
        model_version: int,
        lam: float,
        n_updates: int,
        theta: dict[str, Any],
        p: dict[str, Any],
        probes: Sequence[dict[str, Any]] = (),
    ) -> tuple[OnlineStateInfo, list[int]]:
        """Write a new on-line state and its probe measurements in one transaction; return it and the probe ids.

        ``seen_version`` is the state's version the update was computed from (None: there was none).
        If the row has moved on meanwhile nothing is written and ``StaleOnlineState`` is raised (the
        caller recomputes from the new state). Each probe is a ``probe_measurements`` row
        (measured_at, x, y, z, a_deg, b_deg, dx, dy, dz, temperatures); a machine's second probing
        at the same time is refused (ConflictError) and nothing is written.
        """
        self.ensure_schema()
        now = sc.utcnow()
        values = {
            "model_version_id": model_version_id,
            "model_version": int(model_version),
            "lam": float(lam),
            "n_updates": int(n_updates),
            "theta": theta,
            "p": p,
            "updated_at": now,
        }
        with db.write_transaction(self.engine) as conn:
            lock = select(sc.Machine.id).where(sc.Machine.id == machine_id)
            if conn.dialect.name == "postgresql":
                lock = lock.with_for_update()  # serialises the state writers of one machine
            if conn.execute(lock).first() is None:
                raise NotFoundError(f"no machine {machine_id!r}")
            st = sc.OnlineState
            current = conn.execute(select(st.version).where(st.machine_id == machine_id)).scalar()
            if current != seen_version:
                raise StaleOnlineState(
                    f"machine {machine_id!r}: the on-line state moved on (version {current}, "
                    f"computed from {seen_version}); retry"
                )
            if seen_version is None:
                conn.execute(insert(st).values(machine_id=machine_id, version=1, **values))
            else:
                n = conn.execute(
                    update(st)
                    .where(st.machine_id == machine_id, st.version == seen_version)
                    .values(version=seen_version + 1, **values)
                ).rowcount
                if n != 1:  # pragma: no cover - the machine lock (or SQLite's writer lock) rules this out
                    raise StaleOnlineState(f"machine {machine_id!r}: the on-line state moved on; retry")
            ids = []
            for pr in probes:
                clash = conn.execute(
                    select(sc.ProbeMeasurement.id).where(
                        sc.ProbeMeasurement.machine_id == machine_id,
                        sc.ProbeMeasurement.measured_at == pr["measured_at"],
                    )
                ).first()
                if clash is not None:
                    raise ConflictError(
                        f"machine {machine_id!r} already has a probe measurement at {pr['measured_at'].isoformat()}"
                    )
                ids.append(
                    int(
                        conn.execute(
                            insert(sc.ProbeMeasurement)
                            .values(machine_id=machine_id, model_version_id=model_version_id, **pr)
                            .returning(sc.ProbeMeasurement.id)
                        ).scalar_one()
                    )
                )
            row = conn.execute(select(st.__table__).where(st.machine_id == machine_id)).one()
            return _online(row), ids

    # ------------------------------------------------------------------ acquisition progress

    def save_progress(
        self,
        campaign_id: int,
        stage_ordinal: int,
        sweep: int,
        last_sample_time_s: float | None,
        cursor: dict[str, Any] | None = None,
    ) -> None:
        """Record the scheduler's resume point of a campaign (insert or update)."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            values = {
                "stage_ordinal": stage_ordinal,
                "sweep": sweep,
                "last_sample_time_s": last_sample_time_s,
                "cursor": cursor,
                "updated_at": sc.utcnow(),
            }
            n = conn.execute(
                update(sc.AcquisitionProgress).where(sc.AcquisitionProgress.campaign_id == campaign_id).values(**values)
            ).rowcount
            if not n:
                conn.execute(insert(sc.AcquisitionProgress).values(campaign_id=campaign_id, **values))

    def progress(self, campaign_id: int) -> ProgressInfo | None:
        """Return the scheduler's resume point of a campaign, or None before its first commit."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(
                select(sc.AcquisitionProgress.__table__).where(sc.AcquisitionProgress.campaign_id == campaign_id)
            ).first()
            if row is None:
                return None
            return ProgressInfo(
                row.campaign_id, row.stage_ordinal, row.sweep, row.last_sample_time_s, row.cursor, row.updated_at
            )

    def check_writable(self) -> None:
        """Raise StoreError unless the store is at the head schema and accepts a write now.

        The probe rewrites the schema revision with itself inside a transaction that is rolled
        back: a read-only file, directory, mount or PostgreSQL role fails here, before a daemon
        starts its instruments, rather than at its first commit.
        """
        from sqlalchemy.exc import DBAPIError

        try:
            self.ensure_schema()
            with self.engine.connect() as conn:
                conn = conn.execution_options(driftlab_write=True)
                trans = conn.begin()
                try:
                    conn.execute(text("UPDATE alembic_version SET version_num = version_num"))
                finally:
                    trans.rollback()
        except (DBAPIError, OSError) as exc:
            orig = getattr(exc, "orig", None) or exc
            first = next((ln.strip() for ln in str(orig).splitlines() if ln.strip()), type(orig).__name__)
            raise db.StoreError(f"cannot write to the store at {self.url}: {first[:300]}") from None

    def ping(self) -> bool:
        """Return True when the database answers."""
        with self.engine.connect() as conn:
            return conn.execute(text("SELECT 1")).scalar() == 1


def connect(url: str | None = None, auto_upgrade: bool = True) -> Store:
    """Return a Store on ``url`` (default: DRIFTLAB_DB_URL or the embedded SQLite file)."""
    if url is None:
        from driftlab.config import Settings

        url = Settings().resolved_db_url()
    return Store(db.make_engine(url), auto_upgrade=auto_upgrade)
