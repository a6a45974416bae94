"""Time partitions of the reading tables on PostgreSQL: one partition per month of campaign start.

The three reading tables (``temperature_samples``, ``condition_samples``, ``error_samples``) are
range-partitioned on ``campaign_start_day``: the UTC day of the campaign's start, as days since
1970-01-01, written into every reading (on SQLite too, where the tables stay unpartitioned: one
logical schema). Why the campaign's start and not each reading's absolute time:

- every read of readings is per campaign (drift, histories, export, a fit's load) and already knows
  the campaign's start from its ``campaigns`` row, so ``campaign_start_day = :day`` prunes to
  exactly one partition; an absolute reading time would need the campaign's end to prune as well;
- a campaign never straddles two partitions: an import or a live batch writes into one partition,
  a campaign is deleted (or a month archived with DETACH) whole, and the per-campaign key order
  of the primary key is unchanged inside the partition;
- the key is constant per campaign, so it costs one int4 per row and no expression per query.

A partition holds the campaigns *started* in its month; their readings may run past the month's
end by the campaign's length (days), which is why queries prune by the campaign's key and never
by a reading's time.

Partitions are created ahead, never by the writer's own transaction: ``ensure_partitions`` (an
import before its write, the daemon when it opens a campaign) and ``ensure_ahead`` (the workers'
periodic task, ``driftlab db partitions``, the migration) create the missing ones in a short
transaction of their own. Each is created as a plain table and then ATTACHed, which locks the
parent only in SHARE UPDATE EXCLUSIVE mode (readers and writers go on; ``CREATE TABLE ...
PARTITION OF`` would take ACCESS EXCLUSIVE and wait behind every running query). Creators are
serialised by a transaction-level advisory lock and look again once they hold it, so two
importers reaching a new month at once both succeed and one partition is made. There is no
DEFAULT partition: a row for a month nobody prepared fails loudly instead of landing in a
catch-all that every later CREATE would have to scan.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, date, datetime, timedelta
from typing import TypedDict

from sqlalchemy import Connection, Engine, text

from driftlab.campaigns.db import PARTITIONED_TABLES, write_transaction

log = logging.getLogger(__name__)

#: the range-partitioned tables (PostgreSQL: ``db.PARTITIONED_TABLES``) and their partition key column
PARTITION_KEY = "campaign_start_day"
#: months created ahead of the current one by ``ensure_ahead``
MONTHS_AHEAD = 2

_EPOCH = date(1970, 1, 1)
#: pg_advisory_xact_lock key of partition DDL (db.upgrade serialises itself on 727271)
_LOCK_KEY = 727272
_BOUND = re.compile(r"FOR VALUES FROM \((-?\d+)\) TO \((-?\d+)\)")


def start_day(started_at: datetime) -> int:
    """Return a campaign's partition key: the UTC day of its start, as days since 1970-01-01."""
    if started_at.tzinfo is None:
        raise ValueError("started_at must be timezone-aware")
    return (started_at.astimezone(UTC).date() - _EPOCH).days


def day_date(day: int) -> date:
    """Return the date of a partition-key day."""
    return _EPOCH + timedelta(days=int(day))


def _day(d: date) -> int:
    return (d - _EPOCH).days


def month_range(day: int) -> tuple[int, int]:
    """Return the [first, next month's first) days of the month holding ``day``."""
    d = day_date(day)
    first = d.replace(day=1)
    nxt = date(first.year + first.month // 12, first.month % 12 + 1, 1)
    return _day(first), _day(nxt)


@dataclass(frozen=True)
class Partition:
    """One partition of a reading table: its name and the [lo, hi) days of campaign start it holds."""

    table: str
    name: str
    lo: int | None  # None: the DEFAULT partition (not made by driftlab, but honoured when present)
    hi: int | None

    def covers(self, day: int) -> bool:
        """Return True when a campaign started on ``day`` is routed here."""
        return self.lo is None or (self.lo <= day and (self.hi is None or day < self.hi))


def partitions(conn: Connection, table: str) -> list[Partition]:
    """Return the partitions of a reading table (PostgreSQL), ordered by their lower bound."""
    rows = conn.execute(
        text(
            "SELECT c.relname, pg_get_expr(c.relpartbound, c.oid) FROM pg_inherits i "
            "JOIN pg_class c ON c.oid = i.inhrelid WHERE i.inhparent = to_regclass(:t)"
        ),
        {"t": table},
    ).all()
    out = []
    for name, bound in rows:
        m = _BOUND.search(bound or "")
        if m:
            out.append(Partition(table, name, int(m.group(1)), int(m.group(2))))
        elif "DEFAULT" in (bound or ""):
            out.append(Partition(table, name, None, None))
        # MINVALUE/MAXVALUE bounds (made by hand) are read as not covering: a CREATE would then
        # fail on the overlap rather than be skipped silently
    return sorted(out, key=lambda p: (p.lo is not None, p.lo or 0))


def _gap(existing: list[Partition], table: str, day: int) -> Partition | None:
    """Return the partition to create so that ``day`` is covered (None when it is): its month, cut
    short where a partition made by other means already covers part of that month."""
    if any(p.covers(day) for p in existing):
        return None
    lo, hi = month_range(day)
    for p in existing:
        if p.lo is None or p.hi is None:
            continue
        if p.hi <= day:
            lo = max(lo, p.hi)
        elif p.lo > day:
            hi = min(hi, p.lo)
    d = day_date(lo)
    name = f"{table}_p{d.year:04d}_{d.month:02d}" + ("" if d.day == 1 else f"_{d.day:02d}")
    return Partition(table, name, lo, hi)


def missing(conn: Connection, days: Iterable[int], tables: Iterable[str] = PARTITIONED_TABLES) -> list[Partition]:
    """Return the partitions that must be created before readings of campaigns started on ``days`` are written."""
    out = []
    for table in tables:
        existing = partitions(conn, table)
        for day in sorted(set(int(d) for d in days)):
            gap = _gap(existing, table, day)
            if gap is not None:
                existing.append(gap)
                out.append(gap)
    return out


def create_partitions(conn: Connection, days: Iterable[int], tables: Iterable[str] = PARTITIONED_TABLES) -> list[str]:
    """Create, in the caller's transaction, the partitions missing for ``days``; return their names.

    Takes the partition advisory lock (held until the caller's transaction ends) and looks again
    under it, so a concurrent creator's partitions are found, not made twice. No-op on SQLite.
    """
    if conn.dialect.name != "postgresql":
        return []
    days = list(days)
    conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _LOCK_KEY})
    made = []
    for p in missing(conn, days, tables):
        # a plain table first, then ATTACH: SHARE UPDATE EXCLUSIVE on the parent instead of the
        # ACCESS EXCLUSIVE of CREATE TABLE ... PARTITION OF (which would queue behind every reader)
        conn.execute(
            text(f"CREATE TABLE {p.name} (LIKE {p.table} INCLUDING DEFAULTS INCLUDING CONSTRAINTS INCLUDING STORAGE)")
        )
        conn.execute(text(f"ALTER TABLE {p.table} ATTACH PARTITION {p.name} FOR VALUES FROM ({p.lo}) TO ({p.hi})"))
        made.append(p.name)
    if made:
        log.info("created partitions %s", ", ".join(made))
    return made


def ensure_partitions(engine: Engine, days: Iterable[int]) -> list[str]:
    """Make sure readings of campaigns started on ``days`` have a partition to go to; return those created.

    Runs in a short transaction of its own, committed before the caller writes (never inside an
    import's transaction: the new partition is visible to every session at once, and no lock of
    the DDL is held through a long write). Cheap when nothing is missing: one catalog read, no lock.
    """
    if engine.dialect.name != "postgresql":
        return []
    days = sorted(set(int(d) for d in days))
    if not days:
        return []
    with engine.connect() as conn:
        if not missing(conn, days):
            conn.rollback()
            return []
        conn.rollback()
    with write_transaction(engine) as conn:
        return create_partitions(conn, days)


def months_ahead(today: date | None = None, months: int = MONTHS_AHEAD) -> list[int]:
    """Return the first day of the current month and of the ``months`` after it."""
    d = (today or datetime.now(UTC).date()).replace(day=1)
    out = []
    for _ in range(months + 1):
        out.append(_day(d))
        d = date(d.year + d.month // 12, d.month % 12 + 1, 1)
    return out


def ensure_ahead(engine: Engine, months: int = MONTHS_AHEAD, today: date | None = None) -> list[str]:
    """Create the partitions of the current month and the ``months`` after it when missing; return those created."""
    return ensure_partitions(engine, months_ahead(today, months))


def analyze_new(conn: Connection, tables: Iterable[str]) -> list[str]:
    """ANALYZE those of ``tables`` that have never been analysed; return them.

    For a month's new partitions, where the planner reads statistics once it has pruned to them:
    without any, the first drift queries of the month could plan on an empty-table guess until
    autovacuum's next nap. Later growth is autovacuum's (it analyses a partition once a tenth of
    its rows changed), off the import's clock: a synchronous ANALYZE costs a tenth of a second
    or more per partition of a fleet, and re-analysing after every import would cost that each time.
    """
    if conn.dialect.name != "postgresql":
        return []
    names = list(tables)
    if not names:
        return []
    fresh = set(
        conn.execute(
            text(
                "SELECT relname FROM pg_stat_user_tables WHERE relname = ANY(:names) "
                "AND last_analyze IS NULL AND last_autoanalyze IS NULL"
            ),
            {"names": names},
        ).scalars()
    )
    todo = [n for n in names if n in fresh]
    if todo:
        conn.execute(text(f"ANALYZE {', '.join(todo)}"))
    return todo


def leaf(conn: Connection, table: str, day: int) -> str | None:
    """Return the name of the partition of ``table`` holding campaigns started on ``day`` (None: none)."""
    return next((p.name for p in partitions(conn, table) if p.covers(day)), None)


#: one partition of a reading table: its range of campaign-start dates (None: unbounded, the default
#: partition) and its size (the functional form, since ``from`` is a keyword)
PartitionRow = TypedDict(
    "PartitionRow", {"table": str, "partition": str, "from": str | None, "to": str | None, "bytes": int}
)


def describe(conn: Connection) -> list[PartitionRow]:
    """Return every partition of the reading tables with its range of campaign-start dates and its size."""
    out: list[PartitionRow] = []
    for table in PARTITIONED_TABLES:
        for p in partitions(conn, table):
            size = conn.execute(text("SELECT pg_total_relation_size(to_regclass(:n))"), {"n": p.name}).scalar()
            out.append(
                {
                    "table": table,
                    "partition": p.name,
                    "from": None if p.lo is None else day_date(p.lo).isoformat(),
                    "to": None if p.hi is None else day_date(p.hi).isoformat(),
                    "bytes": int(size or 0),
                }
            )
    return out
