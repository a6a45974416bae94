"""Fleet scale: the reading tables partitioned by month of campaign start (PostgreSQL).

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-09 10:00:00

``temperature_samples``, ``condition_samples`` and ``error_samples`` get ``campaign_start_day``
(the UTC day of their campaign's start, days since 1970-01-01; see driftlab/campaigns/partitions.py
for why the campaign's start and not each reading's time) as the last column of each unique key.
On PostgreSQL they become ``PARTITION BY RANGE (campaign_start_day)`` with one partition per month
(``<table>_pYYYY_MM``), made here for every month a stored campaign started in plus the current
month and the two after it. SQLite gets the same columns and keys, unpartitioned.

A table cannot be turned into a partitioned one in place: each is rebuilt (new table, rows copied
with their campaign's day, old table dropped, new one renamed, keys and indexes built once on the
loaded rows). Rows are preserved; a reading whose campaign no longer exists (which the store never
leaves behind: it deletes readings with their campaign) stops the migration, because it has no
partition to go to. The copy runs in the upgrade's transaction: on a large store, count on about
the time of a bulk load of the same rows, and twice the tables' size of free disk while it runs.

The downgrade rebuilds plain tables without the column, rows preserved.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, date, datetime, timedelta

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

KEY = "campaign_start_day"
TABLES = ("temperature_samples", "condition_samples", "error_samples")
MONTHS_AHEAD = 2
_EPOCH = date(1970, 1, 1)
# the day of a campaign's start as stored by this revision's writers (partitions.start_day)
_DAY_SQL = {
    "postgresql": "((c.started_at AT TIME ZONE 'UTC')::date - DATE '1970-01-01')",
    "sqlite": "CAST(julianday(date(c.started_at)) - 2440587.5 AS INTEGER)",
}


def _columns(table: str) -> list[sa.Column]:
    """Return the columns of a reading table as of revision 0007 (without the partition key)."""
    if table == "temperature_samples":
        return [
            sa.Column("campaign_id", sa.Integer(), nullable=False),
            sa.Column("channel_id", sa.Integer(), nullable=False),
            sa.Column("time_s", sa.Double(), nullable=False),
            sa.Column("value", sa.Double(), nullable=True),
        ]
    if table == "condition_samples":
        return [
            sa.Column("campaign_id", sa.Integer(), nullable=False),
            sa.Column("time_s", sa.Double(), nullable=False),
            *[
                sa.Column(c, sa.Double(), nullable=True)
                for c in ("spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")
            ],
        ]
    return [
        sa.Column("campaign_id", sa.Integer(), nullable=False),
        sa.Column("seq", sa.Integer(), nullable=False),
        sa.Column("time_s", sa.Double(), nullable=False),
        sa.Column("axis", sa.String(length=1), nullable=False),
        sa.Column("term", sa.String(length=5), nullable=False),
        sa.Column("position", sa.Double(), nullable=False),
        sa.Column("direction", sa.SmallInteger(), nullable=False),
        sa.Column("value", sa.Double(), nullable=False),
        sa.Column("sweep", sa.Integer(), nullable=False),
        sa.Column("flags", sa.Integer(), nullable=False),
        *[sa.Column(c, sa.Double(), nullable=True) for c in ("x", "y", "z", "a", "b")],
        sa.Column("setup", sa.String(length=64), nullable=True),
    ]


def _keys(table: str, partitioned: bool) -> tuple[list[str], list[str] | None]:
    """Return (primary key columns, unique key columns or None) of a reading table."""
    extra = [KEY] if partitioned else []
    if table == "temperature_samples":
        return ["campaign_id", "channel_id", "time_s", *extra], None
    if table == "condition_samples":
        return ["campaign_id", "time_s", *extra], None
    return (["campaign_id", "seq", *extra], ["campaign_id", "axis", "term", "direction", "position", "time_s", *extra])


def _uq_name(partitioned: bool) -> str:
    if partitioned:
        return "uq_error_samples_reading"
    return "uq_error_samples_campaign_id_axis_term_direction_position_time_s"  # 0001's (PostgreSQL shortens it)


def _checks(table: str) -> list[sa.CheckConstraint]:
    if table != "error_samples":
        return []
    return [
        sa.CheckConstraint("axis IN ('X', 'Y', 'Z', 'A', 'B')", name=op.f("ck_error_samples_axis")),
        sa.CheckConstraint("term IN ('alpha', 'beta', 'gamma', 'dx', 'dy', 'dz')", name=op.f("ck_error_samples_term")),
        sa.CheckConstraint("direction IN (-1, 1)", name=op.f("ck_error_samples_direction")),
    ]


def _month(d: date) -> date:
    return date(d.year + d.month // 12, d.month % 12 + 1, 1)


def _months(bind: sa.Connection) -> list[date]:
    """Return the first day of every month a campaign started in, of this month and the two after it."""
    sql = f"SELECT DISTINCT {_DAY_SQL['postgresql']} FROM campaigns c"
    starts = {
        (_EPOCH + timedelta(days=int(d))).replace(day=1) for d in bind.execute(sa.text(sql)).scalars() if d is not None
    }
    m = datetime.now(UTC).date().replace(day=1)
    for _ in range(MONTHS_AHEAD + 1):
        starts.add(m)
        m = _month(m)
    return sorted(starts)


def _rebuild(table: str, partitioned: bool) -> None:
    """Rebuild a reading table with (partitioned) or without the partition key, rows preserved."""
    bind = op.get_bind()
    dialect = bind.dialect.name
    pg = dialect == "postgresql"
    new = f"{table}_rebuilt"
    cols = _columns(table)
    names = ", ".join(c.name for c in cols)
    pk, uq = _keys(table, partitioned)
    # SQLite: WITHOUT ROWID needs its primary key at CREATE; PostgreSQL: keys are built after the copy
    keys: list[sa.Constraint] = [] if pg else [sa.PrimaryKeyConstraint(*pk, name=op.f(f"pk_{table}"))]
    if uq is not None and not pg:
        keys.append(sa.UniqueConstraint(*uq, name=op.f(_uq_name(partitioned))))
    kwargs: dict[str, str | bool] = {"sqlite_with_rowid": False}
    if partitioned and pg:
        kwargs["postgresql_partition_by"] = f"RANGE ({KEY})"
    op.create_table(
        new,
        *cols,
        *([sa.Column(KEY, sa.Integer(), nullable=False)] if partitioned else []),
        *keys,
        *_checks(table),
        **kwargs,
    )
    if partitioned and pg:
        for first in _months(bind):
            lo, hi = (first - _EPOCH).days, (_month(first) - _EPOCH).days
            op.execute(
                f"CREATE TABLE {table}_p{first.year:04d}_{first.month:02d} PARTITION OF {new} "
                f"FOR VALUES FROM ({lo}) TO ({hi})"
            )
    before = bind.execute(sa.text(f"SELECT COUNT(*) FROM {table}")).scalar_one()
    if partitioned:
        copied = bind.execute(
            sa.text(
                f"INSERT INTO {new} ({names}, {KEY}) "
                f"SELECT {', '.join('s.' + c.name for c in cols)}, {_DAY_SQL[dialect]} "
                f"FROM {table} s JOIN campaigns c ON c.id = s.campaign_id"
            )
        ).rowcount
    else:
        copied = bind.execute(sa.text(f"INSERT INTO {new} ({names}) SELECT {names} FROM {table}")).rowcount
    if copied != before:
        raise RuntimeError(
            f"{table}: {before - copied} of {before} rows belong to no stored campaign and have no partition to go "
            f"to; delete them (DELETE FROM {table} WHERE campaign_id NOT IN (SELECT id FROM campaigns)) "
            "and upgrade again"
        )
    if table == "error_samples":
        op.drop_index("ix_error_samples_sweep", table_name=table)
    op.drop_table(table)
    op.rename_table(new, table)
    if pg:
        op.create_primary_key(op.f(f"pk_{table}"), table, pk)
        if uq is not None:
            op.create_unique_constraint(op.f(_uq_name(partitioned)), table, uq)
    if table == "error_samples":
        op.create_index(
            "ix_error_samples_sweep", table, ["campaign_id", "axis", "term", "direction", "sweep", "position"]
        )


def upgrade() -> None:
    """Add the partition key to the reading tables; partition them by month of campaign start on PostgreSQL."""
    for table in TABLES:
        _rebuild(table, partitioned=True)
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ANALYZE temperature_samples, condition_samples, error_samples")


def downgrade() -> None:
    """Plain reading tables again, without the partition key (rows preserved)."""
    for table in TABLES:
        _rebuild(table, partitioned=False)
