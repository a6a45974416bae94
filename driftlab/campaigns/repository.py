"""What every repository of the store shares, and the SQL that belongs to no one aggregate.

A ``Store`` (``campaigns.store``) is one engine and one repository per aggregate: campaigns and
their readings (``campaign_repo``, ``readings_repo``), the model registry (``model_repo``), job
records (``job_repo``) and the machines' on-line state (``online_repo``). They share the engine, the
schema gate (the schema is brought to head once, on first use, whichever repository comes first),
one way to read (``Repository.read``: one transaction, one snapshot) and one way to write
(``db.write_transaction``: committed whole or rolled back).

The store-wide SQL lives here once: a machine's existence and its row lock, a campaign's row and
partition key, the time window of a history query, table counts, the planner statistics, and the
liveness and writability probes.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from sqlalchemy import Connection, Engine, Row, Select, func, select, text
from sqlalchemy.exc import DBAPIError

from driftlab.campaigns import db, partitions
from driftlab.campaigns import schema as sc
from driftlab.errors import NotFoundError

if TYPE_CHECKING:
    from collections.abc import Iterator

    from sqlalchemy.orm import InstrumentedAttribute
    from sqlalchemy.sql.elements import ColumnElement

S = TypeVar("S", bound=Select)


class SchemaGate:
    """One engine and whether its schema is at head yet: shared by the repositories of one store."""

    def __init__(self, engine: Engine, auto_upgrade: bool = True) -> None:
        """Wrap an engine; with ``auto_upgrade`` the schema is upgraded on first use."""
        self.engine = engine
        self.ready = not auto_upgrade

    def upgrade(self, revision: str = "head") -> str:
        """Bring the schema to ``revision`` (head by default) and return the revision reached."""
        reached = db.upgrade(self.engine, revision)
        self.ready = True
        return reached

    def ensure(self) -> None:
        """Upgrade the schema to head if it is not there yet (done once per gate)."""
        if self.ready:
            return
        if db.current_revision(self.engine) != db.head_revision():
            self.upgrade()
        self.ready = True


class Repository:
    """The base of every repository: the shared engine and schema gate, one read and one write path."""

    def __init__(self, gate: SchemaGate) -> None:
        """Share ``gate`` (and its engine) with the store's other repositories."""
        self.gate = gate
        self.engine = gate.engine

    @contextmanager
    def read(self) -> Iterator[Connection]:
        """Yield a connection in one read transaction (one snapshot), closed on exit."""
        self.gate.ensure()
        with self.engine.connect() as conn, conn.begin():
            yield conn

    @contextmanager
    def write(self) -> Iterator[Connection]:
        """Yield a connection in one write transaction (``db.write_transaction``)."""
        self.gate.ensure()
        with db.write_transaction(self.engine) as conn:
            yield conn


@dataclass(frozen=True)
class Page:
    """A page of a listing: at most ``limit`` rows (None: all) after skipping ``offset``."""

    limit: int | None = None
    offset: int = 0

    def apply(self, q: S) -> S:
        """Return the query limited to this page."""
        return q.limit(self.limit).offset(self.offset) if self.limit is not None else q.offset(self.offset)


# ----------------------------------------------------------------------------- machines and campaigns


def machine_exists(conn: Connection, machine_id: str) -> None:
    """Raise NotFoundError unless the machine is stored."""
    if conn.execute(select(sc.Machine.id).where(sc.Machine.id == machine_id)).first() is None:
        raise NotFoundError(f"no machine {machine_id!r}")


def lock_machine(conn: Connection, machine_id: str) -> None:
    """Take the machine's row lock (PostgreSQL; SQLite's BEGIN IMMEDIATE already serialises writers).

    Serialises the writers of one machine's registry and on-line state; NotFoundError when there is
    no such machine.
    """
    q = select(sc.Machine.id).where(sc.Machine.id == machine_id)
    if conn.dialect.name == "postgresql":
        q = q.with_for_update()
    if conn.execute(q).first() is None:
        raise NotFoundError(f"no machine {machine_id!r}")


def campaign_row(conn: Connection, campaign_id: int) -> Row[Any]:
    """Return a campaign's row; NotFoundError when there is no such campaign."""
    row = conn.execute(select(sc.Campaign.__table__).where(sc.Campaign.id == campaign_id)).first()
    if row is None:
        raise NotFoundError(f"no campaign {campaign_id}")
    return row


def campaign_day(conn: Connection, campaign_id: int) -> int:
    """Return the campaign's partition key (start day); NotFoundError when there is no such campaign."""
    started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == campaign_id)).scalar()
    if started is None:
        raise NotFoundError(f"no campaign {campaign_id}")
    return partitions.start_day(started)


def time_window(
    q: S,
    col: ColumnElement[Any] | InstrumentedAttribute[Any],
    start_s: float | None,
    end_s: float | None,
    after: float | None = None,
) -> S:
    """Return the query kept to ``start_s <= col <= end_s`` and ``col > after`` (each when given)."""
    if start_s is not None:
        q = q.where(col >= start_s)
    if end_s is not None:
        q = q.where(col <= end_s)
    if after is not None:
        q = q.where(col > after)
    return q


# ----------------------------------------------------------------------------- the whole store


def table_counts(conn: Connection) -> dict[str, int]:
    """Return the row count of every table of the schema (used to prove a failed write changed nothing)."""
    return {
        name: int(conn.execute(select(func.count()).select_from(table)).scalar_one())
        for name, table in sorted(sc.metadata.tables.items())
    }


def analyze(engine: Engine, start_day: int | None = None) -> None:
    """Refresh the planner statistics of the sample tables (after a bulk load or a campaign's end).

    Without them both planners may scan a campaign's error samples instead of seeking the
    drift indexes. SQLite samples a bounded number of rows per index (fast on any size). On
    PostgreSQL, with ``start_day``, only the partitions of that day's month (and the rollups) that
    were never analysed are, now (the planner reads a partition's own statistics once it has
    pruned to it); their growth is left to autovacuum. A whole-table ANALYZE samples every
    partition, a cost that grows with the fleet.
    """
    with engine.connect() as conn:
        if conn.dialect.name == "postgresql":
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


def ping(engine: Engine) -> bool:
    """Return True when the database answers."""
    with engine.connect() as conn:
        return conn.execute(text("SELECT 1")).scalar() == 1


def check_writable(gate: SchemaGate) -> None:
    """Raise StoreError unless the store is at the head schema and accepts a write now.

    The probe rewrites the schema revision with itself inside a transaction that is rolled
    back: a read-only file, directory, mount or PostgreSQL role fails here, before a daemon
    starts its instruments, rather than at its first commit.
    """
    engine = gate.engine
    try:
        gate.ensure()
        with engine.connect() as conn:
            conn = conn.execution_options(driftlab_write=True)
            trans = conn.begin()
            try:
                conn.execute(text("UPDATE alembic_version SET version_num = version_num"))
            finally:
                trans.rollback()
    except (DBAPIError, OSError) as exc:
        orig = getattr(exc, "orig", None) or exc
        first = next((ln.strip() for ln in str(orig).splitlines() if ln.strip()), type(orig).__name__)
        where = engine.url.render_as_string(hide_password=True)
        raise db.StoreError(f"cannot write to the store at {where}: {first[:300]}") from None
