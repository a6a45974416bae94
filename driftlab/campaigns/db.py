"""Engines and schema upgrades of the campaign store (SQLite embedded default, PostgreSQL production)."""

from __future__ import annotations

import logging
import re
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, Engine, create_engine, event, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

from driftlab.errors import DriftlabError, ValidationError
from driftlab.resources import migrations_dir

if TYPE_CHECKING:
    from alembic.config import Config

log = logging.getLogger(__name__)

#: the Alembic scripts, shipped in the package (driftlab.migrations; top-level migrations/ in the source tree)
MIGRATIONS_DIR = migrations_dir()


class StoreError(DriftlabError):
    """The store cannot be opened or brought to the current schema."""


#: SQLite's primary result code of a write to a read-only database (file, directory, mount, URI mode=ro)
SQLITE_READONLY = 8
#: PostgreSQL's SQLSTATE of a write in a read-only transaction (default_transaction_read_only, a hot standby)
PG_READ_ONLY_SQL_TRANSACTION = "25006"


def read_only_cause(exc: BaseException) -> str | None:
    """Return the driver's first line if ``exc`` (or what it wraps) is a write refused by a read-only store."""
    seen: BaseException | None = exc
    for _ in range(8):  # the driver's error, possibly under SQLAlchemy's or a queue library's wrapper
        if seen is None:
            return None
        orig = getattr(seen, "orig", None) or seen
        code = getattr(orig, "sqlite_errorcode", None)
        if (isinstance(code, int) and code & 0xFF == SQLITE_READONLY) or (
            getattr(orig, "sqlstate", None) == PG_READ_ONLY_SQL_TRANSACTION
        ):
            return next((ln.strip() for ln in str(orig).splitlines() if ln.strip()), type(orig).__name__)[:300]
        seen = seen.__cause__ or seen.__context__
    return None


def normalise_url(url: str) -> str:
    """Return the URL with PostgreSQL routed through psycopg 3; refuse unsupported databases."""
    try:
        parsed = make_url(url)
    except Exception as exc:  # sqlalchemy.exc.ArgumentError
        raise ValidationError(f"not a database URL: {url!r}") from exc
    backend = parsed.get_backend_name()
    if backend == "postgresql":
        if parsed.drivername in ("postgresql", "postgres", "postgresql+psycopg2"):
            parsed = parsed.set(drivername="postgresql+psycopg")
        return parsed.render_as_string(hide_password=False)
    if backend == "sqlite":
        return url
    raise ValidationError(f"unsupported database {backend!r}: use sqlite:///PATH or postgresql+psycopg://...")


def _sqlite_events(engine: Engine) -> None:
    """WAL, foreign keys and a busy timeout on every connection; BEGIN issued by SQLAlchemy."""

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        # Take transaction control away from the sqlite3 module so that BEGIN is emitted exactly
        # when SQLAlchemy begins (reads and writes of one transaction see one snapshot).
        dbapi_conn.isolation_level = None
        cur = dbapi_conn.cursor()
        cur.execute("PRAGMA journal_mode=WAL")
        cur.execute("PRAGMA foreign_keys=ON")
        cur.execute("PRAGMA synchronous=NORMAL")
        cur.execute("PRAGMA busy_timeout=60000")
        cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        # Writers take the write lock up front (BEGIN IMMEDIATE): a deferred transaction that
        # later writes could fail with SQLITE_BUSY after another writer committed.
        immediate = conn.get_execution_options().get("driftlab_write", False)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


def make_engine(url: str) -> Engine:
    """Return an engine for ``url`` (SQLite: parent directories created, WAL, foreign keys on)."""
    url = normalise_url(url)
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        database = parsed.database
        if database and database != ":memory:" and not database.startswith("file:"):
            Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 60})
        _sqlite_events(engine)
        return engine
    return create_engine(url, pool_pre_ping=True)


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold off Ctrl-C while the block runs (main thread only); deliver it right after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[Any] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


@contextmanager
def write_transaction(engine: Engine) -> Iterator[Connection]:
    """Yield a connection in one write transaction: committed at the end, rolled back on any error.

    An exception (Ctrl-C included) before the commit rolls everything back; the commit itself
    runs with Ctrl-C held off, so an interrupt never leaves the caller unsure whether it landed.
    """
    with engine.connect() as conn:
        conn = conn.execution_options(driftlab_write=True)
        trans = conn.begin()
        try:
            yield conn
        except BaseException:
            trans.rollback()
            raise
        with _sigint_deferred():
            trans.commit()


#: the job queue's tables (procrastinate, revision 0006): created from procrastinate's SQL, not the metadata
QUEUE_TABLE_PREFIX = "procrastinate_"
#: the range-partitioned reading tables on PostgreSQL (``campaigns.partitions`` makes their partitions)
PARTITIONED_TABLES = ("temperature_samples", "condition_samples", "error_samples")
_PARTITION_NAME = re.compile("^(" + "|".join(PARTITIONED_TABLES) + r")_p\d{4}_\d{2}(_\d{2})?$")


def is_partition_name(name: str | None) -> bool:
    """Return True for the name of one of our partitions (``<table>_pYYYY_MM[_DD]``)."""
    return bool(name and _PARTITION_NAME.match(name))


def include_name(name: str | None, type_: str, parent_names: Any) -> bool:
    """Return False for the job queue's tables and the reading tables' partitions (made at run time, not
    by a revision): Alembic's autogenerate compares the store's own declared schema only."""
    if type_ != "table":
        return True
    return not ((name or "").startswith(QUEUE_TABLE_PREFIX) or is_partition_name(name))


def alembic_config(connection: Connection | None = None) -> Config:
    """Return an Alembic Config pointing at the absolute migrations folder (no alembic.ini needed)."""
    # lazy: alembic adds 0.13 s to `import driftlab.campaigns.db`, which every store user pays (measured)
    from alembic.config import Config

    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise StoreError(f"migrations folder not found at {MIGRATIONS_DIR}")
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.attributes["configure_logger"] = False
    if connection is not None:
        cfg.attributes["connection"] = connection
    return cfg


def head_revision() -> str:
    """Return the head revision of the migration scripts."""
    # lazy: alembic adds 0.13 s to `import driftlab.campaigns.db`, which every store user pays (measured)
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:  # pragma: no cover - the repository always has revisions
        raise StoreError("no migration revisions found")
    return head


def current_revision(engine: Engine) -> str | None:
    """Return the database's schema revision (None for an empty database)."""
    # lazy: alembic adds 0.13 s to `import driftlab.campaigns.db`, which every store user pays (measured)
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: Engine, revision: str = "head") -> str:
    """Bring the database to ``revision`` in one locked transaction; return the revision reached."""
    # lazy: alembic adds 0.13 s to `import driftlab.campaigns.db`, which every store user pays (measured)
    from alembic import command

    with write_transaction(engine) as conn:
        if conn.dialect.name == "postgresql":
            # Serialise concurrent upgraders of the same database (two workers starting at once).
            conn.execute(text("SELECT pg_advisory_xact_lock(727271)"))
        command.upgrade(alembic_config(conn), revision)
    reached = current_revision(engine)
    log.info("database at revision %s", reached)
    return reached or ""


def store_engine(db_url: str | None) -> Engine:
    """Return the SQLAlchemy engine of the campaign store at db_url (schema brought up to date)."""
    # lazy: driftlab.config (pydantic-settings) adds 0.07 s to `import driftlab.campaigns.db` (measured)
    from driftlab.config import get_settings

    url = db_url or get_settings().resolved_db_url()
    engine = make_engine(url)
    try:
        if current_revision(engine) != head_revision():
            upgrade(engine)
    except OperationalError as exc:
        where = engine.url.render_as_string(hide_password=True)
        raise StoreError(f"cannot open the store at {where}: {str(exc.orig).strip().splitlines()[0]}") from None
    return engine
