"""The campaign store's tables (SQLAlchemy 2.0 typed declarative), the same on SQLite and PostgreSQL.

Shape of the sample tables (why long and narrow for temperatures):
a campaign has 16..50 thermocouples whose set differs between campaigns and machines, and the
drift/history queries read one channel over a time range. A long narrow table keyed by
(campaign_id, channel_id, time_s) makes that a single range scan of the primary key (clustered on
SQLite by WITHOUT ROWID; on PostgreSQL the rows arrive in key order from a bulk ingest, so the
index scan is near-sequential), needs no schema change when a channel is added, and makes a
re-inserted reading impossible by the key itself. A wide table (one column per channel) would be
faster to write but needs DDL per channel map and reads every channel to answer a one-channel
query. Conditions (a fixed set of seven machine-state values, always read together) stay wide.

No foreign keys on the three sample tables: a per-row referential check (a trigger per row on
PostgreSQL) would halve bulk COPY speed. The store writes samples only inside the transaction that
creates or locks their campaign and channels, and deletes them with the campaign.

Fleet scale: on PostgreSQL the three sample tables are range-partitioned by month of campaign
start on ``campaign_start_day`` (the UTC day of the campaign's start, days since 1970-01-01, the
same in every reading of a campaign; see ``partitions``). The key is the last column of each
unique key (a partitioned table's unique keys must hold it; being constant per campaign it changes
neither what they refuse nor the order of a campaign's rows). SQLite has the same columns and keys,
unpartitioned.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Double,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    SmallInteger,
    String,
    Table,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

JSONDoc = JSON().with_variant(JSONB(), "postgresql")

JOB_STATES = ("queued", "running", "done", "failed")
MODEL_STATUSES = ("current", "retired")
CAMPAIGN_STATUSES = ("planned", "running", "done", "aborted")
STAGE_STATUSES = ("planned", "running", "done", "aborted", "skipped")

# error_samples.flags bits
FLAG_BEAM_BREAK = 1  # the laser beam was interrupted during the reading
FLAG_REPEATED = 2  # the point was re-measured after a failed reading
FLAG_OUTLIER = 4  # marked by the operator or a screening step as not to be fitted


def utcnow() -> datetime:
    """Return the current time, timezone-aware in UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A timestamp stored in UTC and always returned timezone-aware (SQLite has no time zones)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Convert an aware datetime to UTC (naive on SQLite); refuse naive ones."""
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("timestamps must be timezone-aware")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Return the stored timestamp as an aware UTC datetime."""
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base with a constraint naming convention (needed by Alembic batch mode)."""

    metadata = MetaData(naming_convention=NAMING)
    # every mapping here is a plain Table (no mapping to a join or select), so say so to the type
    # checker: DeclarativeBase types __table__ as the general FromClause, which has no insert()/update()
    __table__: ClassVar[Table]


class Machine(Base):
    """A machine tool; its id is the bundle's machine.id (e.g. vmc-5ax-01)."""

    __tablename__ = "machines"

    # primary key: machine lookup by its bundle id (drift queries, registry, import)
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    resolution_mm: Mapped[float | None] = mapped_column(Double)
    resolution_deg: Mapped[float | None] = mapped_column(Double)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Campaign(Base):
    """A characterisation campaign: one run of a staged plan on one machine."""

    __tablename__ = "campaigns"
    __table_args__ = (
        CheckConstraint(f"status IN {CAMPAIGN_STATUSES}", name="status"),
        # drift queries: all campaigns of a machine, in time order
        Index("ix_campaigns_machine_started", "machine_id", "started_at"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id", ondelete="RESTRICT"))
    name: Mapped[str] = mapped_column(String(200))
    started_at: Mapped[datetime] = mapped_column(UTCDateTime)
    status: Mapped[str] = mapped_column(String(16), default="done")
    source: Mapped[str] = mapped_column(String(16), default="import")
    # SHA-256 of the bundle's values: importing the same data twice is refused by this constraint
    content_hash: Mapped[str | None] = mapped_column(String(64), unique=True)
    meta: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)
    conditions_columns: Mapped[list[str] | None] = mapped_column(JSONDoc)
    # temperature_rollups cover every stored reading of this campaign (set by import/refresh)
    rollups_complete: Mapped[bool] = mapped_column(Boolean, default=False, server_default=text("false"))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class Stage(Base):
    """One stage of a campaign's plan as run (heat source, spindle, feed, axis, start/end, status)."""

    __tablename__ = "stages"
    __table_args__ = (
        # a campaign's plan in order (WHERE campaign_id = ? ORDER BY ordinal); one stage per slot
        UniqueConstraint("campaign_id", "ordinal"),
        CheckConstraint(f"status IN {STAGE_STATUSES}", name="status"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    campaign_id: Mapped[int] = mapped_column(ForeignKey("campaigns.id", ondelete="CASCADE"))
    ordinal: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(200))
    heat_source: Mapped[str] = mapped_column(String(64))
    axis: Mapped[str | None] = mapped_column(String(1))
    spindle_rpm: Mapped[float] = mapped_column(Double, default=0.0)
    feed_mm_min: Mapped[float] = mapped_column(Double, default=0.0)
    start_s: Mapped[float] = mapped_column(Double)
    end_s: Mapped[float | None] = mapped_column(Double)
    status: Mapped[str] = mapped_column(String(16), default="done")


class Channel(Base):
    """A thermocouple site of a campaign: location, structure, calibration (T = slope * raw + offset)."""

    __tablename__ = "channels"
    __table_args__ = (
        # channel lookup by name within a campaign (history queries, import)
        UniqueConstraint("campaign_id", "name"),
        # a campaign's channels in temperatures.csv column order (export, scan counts)
        UniqueConstraint("campaign_id", "ordinal"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    campaign_id: Mapped[int] = mapped_column(ForeignKey("campaigns.id", ondelete="CASCADE"))
    ordinal: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(64))
    location: Mapped[str] = mapped_column(String(200), default="")
    structure: Mapped[str] = mapped_column(String(64), default="")
    is_room: Mapped[bool] = mapped_column(Boolean, default=False)
    calibration_slope: Mapped[float] = mapped_column(Double, default=1.0)
    calibration_offset: Mapped[float] = mapped_column(Double, default=0.0)


#: partitioning of the sample tables on PostgreSQL (partitions are made by ``partitions``)
PARTITION_BY = "RANGE (campaign_start_day)"


class TemperatureSample(Base):
    """One thermocouple reading (degC); value NULL = a missing reading (an empty bundle cell)."""

    __tablename__ = "temperature_samples"
    # The primary key serves the temperature history query (WHERE campaign_id = ? AND channel_id = ?
    # AND time_s BETWEEN ? AND ? AND campaign_start_day = ?) as one range scan of one partition,
    # and makes re-inserting the same reading impossible.
    __table_args__ = {"sqlite_with_rowid": False, "postgresql_partition_by": PARTITION_BY}

    campaign_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    channel_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    time_s: Mapped[float] = mapped_column(Double, primary_key=True)
    value: Mapped[float | None] = mapped_column(Double)
    # the campaign's start day (partitions.start_day): the partition key
    campaign_start_day: Mapped[int] = mapped_column(Integer, primary_key=True)


class TemperatureRollup(Base):
    """Per channel and minute of a campaign: count, min, sum and max of the readings.

    Long histories (a 1,000-bucket view of 70 hours reads 252,000 readings per channel) are
    aggregated from these rows instead, 60 times fewer, with bucket edges snapped to whole
    minutes so that every figure stays exact. Written with the samples by an import (and by
    ``store.campaigns.refresh_rollups`` for campaigns written live); ``campaigns.rollups_complete`` says
    they cover every stored reading.
    """

    __tablename__ = "temperature_rollups"
    # The primary key serves the bucketed history (WHERE campaign_id = ? AND channel_id = ?
    # AND minute BETWEEN ? AND ?) as one range scan.
    __table_args__ = {"sqlite_with_rowid": False}

    campaign_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    channel_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    minute: Mapped[int] = mapped_column(Integer, primary_key=True)  # floor(time_s / 60)
    n: Mapped[int] = mapped_column(Integer)  # scans in the minute, missing readings included
    n_values: Mapped[int] = mapped_column(Integer)  # readings present
    vmin: Mapped[float | None] = mapped_column(Double)
    vsum: Mapped[float | None] = mapped_column(Double)
    vmax: Mapped[float | None] = mapped_column(Double)


class ConditionSample(Base):
    """One line of the machine state log (wide: the seven values are always read together)."""

    __tablename__ = "condition_samples"
    # The primary key serves condition histories (WHERE campaign_id = ? AND time_s BETWEEN ? AND ?
    # AND campaign_start_day = ?) and refuses a second state record at the same time.
    __table_args__ = {"sqlite_with_rowid": False, "postgresql_partition_by": PARTITION_BY}

    campaign_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    time_s: Mapped[float] = mapped_column(Double, primary_key=True)
    spindle_rpm: Mapped[float | None] = mapped_column(Double)
    feed_mm_min: Mapped[float | None] = mapped_column(Double)
    x: Mapped[float | None] = mapped_column(Double)
    y: Mapped[float | None] = mapped_column(Double)
    z: Mapped[float | None] = mapped_column(Double)
    a: Mapped[float | None] = mapped_column(Double)
    b: Mapped[float | None] = mapped_column(Double)
    campaign_start_day: Mapped[int] = mapped_column(Integer, primary_key=True)  # the partition key


class ErrorSample(Base):
    """One measured work-space error: axis moved, error term, position, approach direction, value."""

    __tablename__ = "error_samples"
    __table_args__ = (
        # The unique key refuses a re-inserted reading and serves the drift query
        # (WHERE campaign_id = ? AND axis = ? AND term = ? [AND direction = ?] ORDER BY position/time;
        # with campaign_start_day = ? the query reads one partition).
        UniqueConstraint(
            "campaign_id",
            "axis",
            "term",
            "direction",
            "position",
            "time_s",
            "campaign_start_day",
            name="uq_error_samples_reading",
        ),
        # The interpolating drift query: per (direction, sweep) the positions bracketing P
        # (MAX(position) <= P, MIN(position) >= P) and their rows, each one seek.
        Index("ix_error_samples_sweep", "campaign_id", "axis", "term", "direction", "sweep", "position"),
        CheckConstraint("axis IN ('X', 'Y', 'Z', 'A', 'B')", name="axis"),
        CheckConstraint("term IN ('alpha', 'beta', 'gamma', 'dx', 'dy', 'dz')", name="term"),
        CheckConstraint("direction IN (-1, 1)", name="direction"),
        {"sqlite_with_rowid": False, "postgresql_partition_by": PARTITION_BY},
    )

    # (campaign_id, seq) keeps the bundle's row order for an exact export.
    campaign_id: Mapped[int] = mapped_column(Integer, primary_key=True)
    seq: Mapped[int] = mapped_column(Integer, primary_key=True)
    time_s: Mapped[float] = mapped_column(Double)
    axis: Mapped[str] = mapped_column(String(1))
    term: Mapped[str] = mapped_column(String(5))
    position: Mapped[float] = mapped_column(Double)
    direction: Mapped[int] = mapped_column(SmallInteger)
    value: Mapped[float] = mapped_column(Double)
    # sweep number within (axis, term, direction): a new sweep starts when the positions stop moving
    # one way; the interpolating drift query interpolates along position within one sweep.
    sweep: Mapped[int] = mapped_column(Integer, default=0)
    flags: Mapped[int] = mapped_column(Integer, default=0)
    # bundle v2: the full commanded pose at the reading (mm, degrees) and the instrument setup that made
    # it (an id of the campaign meta's ``setups``); NULL for readings imported from a v1 bundle
    x: Mapped[float | None] = mapped_column(Double, nullable=True)
    y: Mapped[float | None] = mapped_column(Double, nullable=True)
    z: Mapped[float | None] = mapped_column(Double, nullable=True)
    a: Mapped[float | None] = mapped_column(Double, nullable=True)
    b: Mapped[float | None] = mapped_column(Double, nullable=True)
    setup: Mapped[str | None] = mapped_column(String(64), nullable=True)
    campaign_start_day: Mapped[int] = mapped_column(Integer, primary_key=True)  # the partition key


class ProbeMeasurement(Base):
    """A touch-probe sphere-centre measurement at a pose, for the on-line model update (RLS)."""

    __tablename__ = "probe_measurements"
    # (machine_id, measured_at) unique: the on-line update reads a machine's probe history in time
    # order, and the same probing cannot be stored twice.
    __table_args__ = (UniqueConstraint("machine_id", "measured_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    campaign_id: Mapped[int | None] = mapped_column(ForeignKey("campaigns.id", ondelete="SET NULL"))
    measured_at: Mapped[datetime] = mapped_column(UTCDateTime)
    x: Mapped[float] = mapped_column(Double)
    y: Mapped[float] = mapped_column(Double)
    z: Mapped[float] = mapped_column(Double)
    a_deg: Mapped[float] = mapped_column(Double, default=0.0)
    b_deg: Mapped[float] = mapped_column(Double, default=0.0)
    dx: Mapped[float] = mapped_column(Double)
    dy: Mapped[float] = mapped_column(Double)
    dz: Mapped[float] = mapped_column(Double)
    model_version_id: Mapped[int | None] = mapped_column(ForeignKey("model_versions.id", ondelete="SET NULL"))
    # the readings (degC per channel) the on-line update was computed with
    temperatures: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)


class OnlineState(Base):
    """The on-line (RLS, eqs. 6.10-6.13) state of a machine: one row, rewritten by every probe update.

    ``theta`` and ``p`` hold one entry per probed term (dx, dy, dz). The state belongs to one model
    version (a new current model starts a new state). ``version`` is the optimistic-concurrency
    counter: an update is written only if the row still has the version it was computed from
    (``UPDATE ... WHERE version = :seen``), so two concurrent updates never lose one.
    """

    __tablename__ = "online_states"

    # primary key: the update's read and conditional write (WHERE machine_id = ?), one state per machine
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"), primary_key=True)
    model_version_id: Mapped[int | None] = mapped_column(ForeignKey("model_versions.id", ondelete="SET NULL"))
    model_version: Mapped[int] = mapped_column(Integer)
    lam: Mapped[float] = mapped_column(Double)
    n_updates: Mapped[int] = mapped_column(Integer, default=0)
    theta: Mapped[dict[str, Any]] = mapped_column(JSONDoc)
    p: Mapped[dict[str, Any]] = mapped_column(JSONDoc)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    version: Mapped[int] = mapped_column(Integer, default=1)


class ModelVersion(Base):
    """A versioned model document of a machine (the registry); exactly one current per machine."""

    __tablename__ = "model_versions"
    __table_args__ = (
        # version lookup (GET /models/{machine}/{version}) and monotonic numbering per machine
        UniqueConstraint("machine_id", "version"),
        CheckConstraint(f"status IN {MODEL_STATUSES}", name="status"),
        # at most one current version per machine (the store retires the old one in the same
        # transaction that registers the new one); also serves "current model of machine M"
        Index(
            "uq_model_versions_current",
            "machine_id",
            unique=True,
            sqlite_where=text("status = 'current'"),
            postgresql_where=text("status = 'current'"),
        ),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id", ondelete="CASCADE"))
    version: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    source_campaigns: Mapped[list[int]] = mapped_column(JSONDoc, default=list)
    document: Mapped[dict[str, Any]] = mapped_column(JSONDoc)
    status: Mapped[str] = mapped_column(String(16), default="current")
    retired_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class Job(Base):
    """The record of a fit or diagnosis job: what was asked, its state, and what came out.

    Not a queue: jobs are queued by procrastinate on PostgreSQL (``queue_job_id`` is the
    procrastinate_jobs row, whose state the API reports while the job is queued or running) and run
    in-process on SQLite. The record keeps what a queue does not: the result or the one-line error.
    """

    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(f"state IN {JOB_STATES}", name="state"),
        # a machine's jobs, newest first (GET /jobs?machine_id=..., and the refit looking up the
        # fit that made the current model: WHERE machine_id = ? AND kind = 'fit' ORDER BY id DESC)
        Index("ix_jobs_machine_id_id", "machine_id", "id"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), default="queued")
    params: Mapped[dict[str, Any]] = mapped_column(JSONDoc, default=dict)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)
    error: Mapped[str | None] = mapped_column(Text)
    # the worker that ran (or last tried) the job
    worker: Mapped[str | None] = mapped_column(String(128))
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    machine_id: Mapped[str | None] = mapped_column(ForeignKey("machines.id", ondelete="SET NULL"))
    campaign_id: Mapped[int | None] = mapped_column(ForeignKey("campaigns.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # procrastinate_jobs.id of the queued job (PostgreSQL); NULL on SQLite
    queue_job_id: Mapped[int | None] = mapped_column(BigInteger)


class AcquisitionProgress(Base):
    """Where the acquisition scheduler of a campaign has got to, so a daemon resumes idempotently."""

    __tablename__ = "acquisition_progress"

    # primary key: the daemon's resume lookup (WHERE campaign_id = ?), one resume point per campaign
    campaign_id: Mapped[int] = mapped_column(ForeignKey("campaigns.id", ondelete="CASCADE"), primary_key=True)
    stage_ordinal: Mapped[int] = mapped_column(Integer, default=0)
    sweep: Mapped[int] = mapped_column(Integer, default=0)
    # last sample time (s since started_at) committed for this campaign; samples at or before it
    # are already stored and are skipped on resume
    last_sample_time_s: Mapped[float | None] = mapped_column(Double)
    cursor: Mapped[dict[str, Any] | None] = mapped_column(JSONDoc)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)
    # the running daemon's last sign of life (every ``status.HEARTBEAT_S``, waiting or not): a running
    # campaign whose heartbeat is older than ``status.STALE_AFTER_S`` has lost its daemon (kill -9, host down)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


metadata = Base.metadata
