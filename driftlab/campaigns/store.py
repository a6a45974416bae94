"""The campaign store: one object over SQLite or PostgreSQL for ingest, queries, registry and jobs.

Writes happen in one transaction each (``db.write_transaction``): an import either lands whole or
leaves the database exactly as it was, whatever interrupts it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

import pandas as pd
from sqlalchemy import Engine, func, insert, select, text, update
from sqlalchemy.exc import IntegrityError

from driftlab.campaigns import db, ingest, queries
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
    heartbeat_at: datetime | None
    finished_at: datetime | None


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
    return OnlineStateInfo(row.machine_id, row.model_version_id, int(row.model_version), float(row.lam),
                           int(row.n_updates), dict(row.theta or {}), dict(row.p or {}), row.updated_at,
                           int(row.version))


def _job(row: Any) -> JobInfo:
    return JobInfo(row.id, row.kind, row.state, row.params or {}, row.result, row.error, row.worker, row.attempts,
                   row.machine_id, row.campaign_id, row.created_at, row.started_at, row.heartbeat_at,
                   row.finished_at)


def _model(row: Any) -> ModelVersionInfo:
    return ModelVersionInfo(row.id, row.machine_id, row.version, row.created_at, list(row.source_campaigns or []),
                            row.document, row.status)


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
        try:
            with db.write_transaction(self.engine) as conn:
                existing = conn.execute(
                    select(sc.Campaign.id).where(sc.Campaign.content_hash == content_hash)
                ).scalar()
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
        self.analyze()
        return campaign_id

    def analyze(self) -> None:
        """Refresh the planner statistics of the sample tables (after a bulk load or a campaign's end).

        Without them both planners may scan a campaign's error samples instead of seeking the
        drift indexes. SQLite samples a bounded number of rows per index (fast on any size).
        """
        with self.engine.connect() as conn:
            if self.dialect == "postgresql":
                # temperature_samples is left to autovacuum: its queries are primary-key ranges whose
                # plan does not depend on statistics, and sampling 12 million rows costs a second
                conn.execute(text("ANALYZE temperature_rollups, condition_samples, error_samples"))
            else:
                conn.exec_driver_sql("PRAGMA analysis_limit=1000")
                conn.exec_driver_sql("ANALYZE")
            conn.commit()

    def load_campaign(self, campaign_id: int) -> Bundle:
        """Return a stored campaign as a Bundle with exactly the values stored."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.load_campaign(conn, campaign_id)

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
            for table in (sc.TemperatureSample, sc.TemperatureRollup, sc.ConditionSample, sc.ErrorSample):
                conn.execute(table.__table__.delete().where(table.__table__.c.campaign_id == campaign_id))
            gone = conn.execute(sc.Campaign.__table__.delete().where(sc.Campaign.__table__.c.id == campaign_id))
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

    def drift(self, machine_id: str, axis: str, term: str, position: float | None = None,
              direction: int | None = None, start: datetime | None = None, end: datetime | None = None,
              interpolate: bool = False) -> pd.DataFrame:
        """Return the error history of (axis, term) across a machine's campaigns (see queries.drift)."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.drift(conn, machine_id, axis, term, position, direction, start, end, interpolate)

    def temperature_history(self, campaign_id: int, channel: str, start_s: float | None = None,
                            end_s: float | None = None, buckets: int | None = None,
                            rollups: bool = True) -> pd.DataFrame:
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

    def condition_history(self, campaign_id: int, columns: list[str] | None = None, start_s: float | None = None,
                          end_s: float | None = None, buckets: int | None = None) -> pd.DataFrame:
        """Return machine-state values, raw or min/mean/max per bucket computed in SQL."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            return queries.condition_history(conn, campaign_id, columns, start_s, end_s, buckets)

    # ------------------------------------------------------------------ model registry

    def register_model(self, machine_id: str, document: dict[str, Any],
                       source_campaigns: list[int] | None = None) -> ModelVersionInfo:
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
                insert(sc.ModelVersion).values(
                    machine_id=machine_id, version=(last or 0) + 1, created_at=now,
                    source_campaigns=list(source_campaigns or []), document=document, status="current",
                ).returning(sc.ModelVersion.id)
            ).scalar_one()
            row = conn.execute(select(sc.ModelVersion.__table__).where(sc.ModelVersion.id == new_id)).one()
            return _model(row)

    def current_model(self, machine_id: str) -> ModelVersionInfo | None:
        """Return the machine's current model version, or None when it has none."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(
                select(sc.ModelVersion.__table__).where(sc.ModelVersion.machine_id == machine_id,
                                              sc.ModelVersion.status == "current")
            ).first()
            return None if row is None else _model(row)

    def model_versions(self, machine_id: str) -> list[ModelVersionInfo]:
        """Return every model version of a machine, oldest first."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            rows = conn.execute(
                select(sc.ModelVersion.__table__).where(sc.ModelVersion.machine_id == machine_id)
                .order_by(sc.ModelVersion.version)
            ).all()
            return [_model(r) for r in rows]

    # ------------------------------------------------------------------ jobs

    def submit_job(self, kind: str, params: dict[str, Any] | None = None, machine_id: str | None = None,
                   campaign_id: int | None = None) -> int:
        """Queue a job and return its id."""
        self.ensure_schema()
        if not kind:
            raise ValidationError("a job needs a kind")
        with db.write_transaction(self.engine) as conn:
            return int(conn.execute(
                insert(sc.Job).values(kind=kind, state="queued", params=params or {}, machine_id=machine_id,
                                      campaign_id=campaign_id, attempts=0, created_at=sc.utcnow())
                .returning(sc.Job.id)
            ).scalar_one())

    def claim_job(self, worker: str, kinds: list[str] | None = None) -> JobInfo | None:
        """Atomically take the oldest queued job (of ``kinds``) for ``worker``; None when there is none.

        PostgreSQL: SELECT ... FOR UPDATE SKIP LOCKED, so concurrent workers never take the same
        job nor wait on each other. SQLite: one conditional UPDATE (state still 'queued') under the
        database's single writer lock.
        """
        self.ensure_schema()
        now = sc.utcnow()
        with db.write_transaction(self.engine) as conn:
            pick = select(sc.Job.id).where(sc.Job.state == "queued").order_by(sc.Job.id).limit(1)
            if kinds:
                pick = pick.where(sc.Job.kind.in_(kinds))
            if conn.dialect.name == "postgresql":
                job_id = conn.execute(pick.with_for_update(skip_locked=True)).scalar()
                if job_id is None:
                    return None
                cond = sc.Job.id == job_id
            else:
                cond = sc.Job.id == pick.scalar_subquery()
            claimed = conn.execute(
                update(sc.Job).where(cond, sc.Job.state == "queued")
                .values(state="running", worker=worker, started_at=now, heartbeat_at=now,
                        attempts=sc.Job.attempts + 1)
                .returning(sc.Job.id)
            ).scalar()
            if claimed is None:
                return None
            return _job(conn.execute(select(sc.Job.__table__).where(sc.Job.id == claimed)).one())

    def heartbeat(self, job_id: int, worker: str) -> bool:
        """Record that ``worker`` is still running the job; False if the job is no longer its own."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            n = conn.execute(
                update(sc.Job).where(sc.Job.id == job_id, sc.Job.worker == worker, sc.Job.state == "running")
                .values(heartbeat_at=sc.utcnow())
            ).rowcount
            return bool(n)

    def finish_job(self, job_id: int, worker: str, result: dict[str, Any]) -> None:
        """Mark the worker's running job done with its result."""
        self._end_job(job_id, worker, "done", result=result)

    def fail_job(self, job_id: int, worker: str, error: str) -> None:
        """Mark the worker's running job failed with a one-line error."""
        self._end_job(job_id, worker, "failed", error=" ".join(error.split()))

    def _end_job(self, job_id: int, worker: str, state: str, result: dict[str, Any] | None = None,
                 error: str | None = None) -> None:
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            n = conn.execute(
                update(sc.Job).where(sc.Job.id == job_id, sc.Job.worker == worker, sc.Job.state == "running")
                .values(state=state, result=result, error=error, finished_at=sc.utcnow())
            ).rowcount
            if not n:
                raise ConflictError(f"job {job_id} is not running under worker {worker!r}")

    def requeue_stale(self, older_than_s: float) -> int:
        """Put back in the queue running jobs whose worker has not beaten for ``older_than_s``; return how many."""
        self.ensure_schema()
        cutoff = sc.utcnow() - timedelta(seconds=older_than_s)
        with db.write_transaction(self.engine) as conn:
            return int(conn.execute(
                update(sc.Job).where(sc.Job.state == "running", sc.Job.heartbeat_at < cutoff)
                .values(state="queued", worker=None)
            ).rowcount)

    def get_job(self, job_id: int) -> JobInfo:
        """Return a job; NotFoundError if there is none with that id."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(select(sc.Job.__table__).where(sc.Job.id == job_id)).first()
            if row is None:
                raise NotFoundError(f"no job {job_id}")
            return _job(row)

    # ------------------------------------------------------------------ on-line state

    def online_state(self, machine_id: str) -> OnlineStateInfo | None:
        """Return the machine's on-line state row (whatever model version it belongs to), or None."""
        self.ensure_schema()
        with self.engine.connect() as conn, conn.begin():
            row = conn.execute(
                select(sc.OnlineState.__table__).where(sc.OnlineState.machine_id == machine_id)
            ).first()
            return None if row is None else _online(row)

    def save_online_state(self, machine_id: str, seen_version: int | None, *, model_version_id: int | None,
                          model_version: int, lam: float, n_updates: int, theta: dict[str, Any], p: dict[str, Any],
                          probes: list[dict[str, Any]] = ()) -> tuple[OnlineStateInfo, list[int]]:
        """Write a new on-line state and its probe measurements in one transaction; return it and the probe ids.

        ``seen_version`` is the state's version the update was computed from (None: there was none).
        If the row has moved on meanwhile nothing is written and ``StaleOnlineState`` is raised (the
        caller recomputes from the new state). Each probe is a ``probe_measurements`` row
        (measured_at, x, y, z, a_deg, b_deg, dx, dy, dz, temperatures); a machine's second probing
        at the same time is refused (ConflictError) and nothing is written.
        """
        self.ensure_schema()
        now = sc.utcnow()
        values = {"model_version_id": model_version_id, "model_version": int(model_version), "lam": float(lam),
                  "n_updates": int(n_updates), "theta": theta, "p": p, "updated_at": now}
        with db.write_transaction(self.engine) as conn:
            lock = select(sc.Machine.id).where(sc.Machine.id == machine_id)
            if conn.dialect.name == "postgresql":
                lock = lock.with_for_update()  # serialises the state writers of one machine
            if conn.execute(lock).first() is None:
                raise NotFoundError(f"no machine {machine_id!r}")
            st = sc.OnlineState
            current = conn.execute(select(st.version).where(st.machine_id == machine_id)).scalar()
            if current != seen_version:
                raise StaleOnlineState(f"machine {machine_id!r}: the on-line state moved on (version {current}, "
                                       f"computed from {seen_version}); retry")
            if seen_version is None:
                conn.execute(insert(st).values(machine_id=machine_id, version=1, **values))
            else:
                n = conn.execute(update(st).where(st.machine_id == machine_id, st.version == seen_version)
                                 .values(version=seen_version + 1, **values)).rowcount
                if n != 1:  # pragma: no cover - the machine lock (or SQLite's writer lock) rules this out
                    raise StaleOnlineState(f"machine {machine_id!r}: the on-line state moved on; retry")
            ids = []
            for pr in probes:
                clash = conn.execute(select(sc.ProbeMeasurement.id).where(
                    sc.ProbeMeasurement.machine_id == machine_id,
                    sc.ProbeMeasurement.measured_at == pr["measured_at"])).first()
                if clash is not None:
                    raise ConflictError(f"machine {machine_id!r} already has a probe measurement at "
                                        f"{pr['measured_at'].isoformat()}")
                ids.append(int(conn.execute(insert(sc.ProbeMeasurement).values(
                    machine_id=machine_id, model_version_id=model_version_id, **pr)
                    .returning(sc.ProbeMeasurement.id)).scalar_one()))
            row = conn.execute(select(st.__table__).where(st.machine_id == machine_id)).one()
            return _online(row), ids

    # ------------------------------------------------------------------ acquisition progress

    def save_progress(self, campaign_id: int, stage_ordinal: int, sweep: int, last_sample_time_s: float | None,
                      cursor: dict[str, Any] | None = None) -> None:
        """Record the scheduler's resume point of a campaign (insert or update)."""
        self.ensure_schema()
        with db.write_transaction(self.engine) as conn:
            values = {"stage_ordinal": stage_ordinal, "sweep": sweep, "last_sample_time_s": last_sample_time_s,
                      "cursor": cursor, "updated_at": sc.utcnow()}
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
            return ProgressInfo(row.campaign_id, row.stage_ordinal, row.sweep, row.last_sample_time_s, row.cursor,
                                row.updated_at)

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
