"""The readings' repository: drift across campaigns, histories and their pages, the latest scan.

A machine's drift is read across its campaigns; a campaign's temperature, machine-state and error
histories raw or downsampled in SQL, or a page at a time.

Every reading table is keyed by campaign and partitioned by the campaign's start day
(``partitions``): each query names that key, so on PostgreSQL it reads one partition. Pages are
keyset pages on the tables' primary keys (``HistoryPage.after``), so a page costs one range scan
whatever its offset in the history.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from sqlalchemy import Connection, func, select, text

from driftlab.campaigns import schema as sc
from driftlab.campaigns.ingest import CONDITION_VALUE_COLUMNS, ROLLUP_S
from driftlab.campaigns.partitions import start_day
from driftlab.campaigns.repository import Repository, campaign_day, campaign_row, machine_exists, time_window
from driftlab.errors import BadRequestError, NotFoundError, ValidationError
from driftlab.vocabulary import AXES, TERMS

if TYPE_CHECKING:
    from collections.abc import Sequence
    from datetime import datetime


@dataclass(frozen=True)
class DriftQuery:
    """What a drift query asks: (axis, term) of a machine, at a position (nearest measured, or
    interpolated along position within each sweep) or at every position, one direction or both,
    between two wall-clock times."""

    machine_id: str
    axis: str
    term: str
    position: float | None = None
    direction: int | None = None
    start: datetime | None = None
    end: datetime | None = None
    interpolate: bool = False

    def check(self) -> None:
        """Raise ValidationError / BadRequestError for an unknown axis or term, a bad direction, or
        interpolation without a position."""
        if self.axis not in AXES:
            raise ValidationError(f"unknown axis {self.axis!r}: expected one of {' '.join(AXES)}")
        if self.term not in TERMS:
            raise ValidationError(f"unknown term {self.term!r}: expected one of {' '.join(TERMS)}")
        if self.direction not in (None, 1, -1):
            raise ValidationError(f"direction must be +1 or -1, not {self.direction}")
        if self.interpolate and self.position is None:
            raise BadRequestError("interpolation needs a position")


@dataclass(frozen=True)
class HistoryPage:
    """A page of a raw history: a time range, the keyset position to start after (a time, or an
    error sample's seq), rows to skip and the page size."""

    start_s: float | None = None
    end_s: float | None = None
    after: float | None = None
    offset: int = 0
    limit: int = 1000


@dataclass(frozen=True)
class ErrorFilter:
    """Which error samples a page holds: of one axis, term and direction (None: any)."""

    axis: str | None = None
    term: str | None = None
    direction: int | None = None


@dataclass(frozen=True)
class LatestScan:
    """A machine's latest thermocouple scan: its campaign, the campaign's start, the scan's time and
    the value per channel (None where the reading is missing)."""

    campaign_id: int
    started_at: datetime
    time_s: float
    values: dict[str, float | None]


DRIFT_COLUMNS = ["campaign_id", "time", "time_s", "position", "direction", "sweep", "value"]

# Nearest measured position and its readings, one statement per campaign: the position nearest P
# (the lower one on a tie) of the largest <= P and the smallest >= P of each direction, each a
# single seek in the unique index (campaign_id, axis, term, direction, position, ...), then the
# readings at that position, one seek per direction in the same index (direction IN (...), not
# left open: the index is ordered by direction before position). campaign_start_day = :day keeps
# every part of it in the campaign's partition (PostgreSQL).
_CAMPAIGN_TERM = "campaign_id = :c AND campaign_start_day = :day AND axis = :axis AND term = :term"
_NEAREST_CANDIDATES = """
      SELECT x FROM (SELECT position AS x FROM error_samples WHERE {where} AND direction = {d}
                     AND position {op} :p ORDER BY position {order} LIMIT 1) AS {alias}"""


def nearest_sql(directions: list[int]) -> str:
    """Return the statement of the drift at the nearest measured position, for these directions (+1/-1)."""
    candidates = "\n      UNION ALL".join(
        _NEAREST_CANDIDATES.format(where=_CAMPAIGN_TERM, d=int(d), op=op, order=order, alias=f"{alias}{k}")
        for k, d in enumerate(directions)
        for op, order, alias in (("<=", "DESC", "below"), (">=", "", "above"))
    )
    return f"""
SELECT time_s, position, direction, sweep, value FROM error_samples
WHERE {_CAMPAIGN_TERM} AND direction IN ({", ".join(str(int(d)) for d in directions)})
  AND time_s >= :t0 AND time_s <= :t1
  AND position = (
    SELECT x FROM ({candidates}
    ) AS candidates
    ORDER BY ABS(x - :p), x LIMIT 1)
"""


_ALL_POSITIONS_SQL = """
SELECT time_s, position, direction, sweep, value FROM error_samples
WHERE campaign_id = :c AND campaign_start_day = :day AND axis = :axis AND term = :term {dir}
  AND time_s >= :t0 AND time_s <= :t1
ORDER BY time_s, position, direction
"""

# Linear interpolation along position inside each sweep. First the positions bracketing P in every
# sweep of one direction (one pass over ix_error_samples_sweep, in index order on SQLite)...
_BRACKETS_SQL = """
SELECT sweep, MAX(CASE WHEN position <= :p THEN position END) AS lo,
       MIN(CASE WHEN position >= :p THEN position END) AS hi
FROM error_samples
WHERE campaign_id = :c AND campaign_start_day = :day AND axis = :axis AND term = :term AND direction = :d
GROUP BY sweep
"""
# ... then the rows at each of those few positions (a seek in the unique index on ... direction, position).
_ROWS_AT_SQL = """
SELECT sweep, position, time_s, value FROM error_samples
WHERE campaign_id = :c AND campaign_start_day = :day AND axis = :axis AND term = :term AND direction = :d
  AND position = :pos
"""


def _directions(conn: Connection, params: dict[str, Any], direction: int | None) -> list[int]:
    if direction is not None:
        return [direction]
    # direction is +1 or -1 (a check constraint): two index probes instead of a DISTINCT scan
    probe = text(
        "SELECT 1 FROM error_samples WHERE campaign_id = :c AND campaign_start_day = :day AND axis = :axis "
        "AND term = :term AND direction = :d LIMIT 1"
    )
    return [d for d in (-1, 1) if conn.execute(probe, {**params, "d": d}).first() is not None]


def _drift(conn: Connection, q: DriftQuery) -> pd.DataFrame:
    """Return the error history of (axis, term) on a machine across its campaigns, in wall-clock time.

    With a position the history is taken at the nearest measured position of each campaign, or
    (``interpolate``) linearly interpolated along position within each sweep; without it every
    measured position is returned. Columns: campaign_id, time (UTC), time_s, position, direction,
    sweep, value.
    """
    q.check()
    machine_exists(conn, q.machine_id)
    campaigns = conn.execute(
        select(sc.Campaign.id, sc.Campaign.started_at)
        .where(sc.Campaign.machine_id == q.machine_id)
        .order_by(sc.Campaign.started_at, sc.Campaign.id)
    ).all()
    frames = []
    for cid, started in campaigns:
        t0 = -np.inf if q.start is None else (q.start - started).total_seconds()
        t1 = np.inf if q.end is None else (q.end - started).total_seconds()
        if t1 < 0:
            continue
        params: dict[str, Any] = {
            "c": cid,
            "day": start_day(started),
            "axis": q.axis,
            "term": q.term,
            "d": q.direction,
            "t0": max(t0, -1e300),
            "t1": min(t1, 1e300),
        }
        rows: Sequence[Sequence[Any]]
        if q.position is None:
            dir_sql = "" if q.direction is None else "AND direction = :d"
            rows = conn.execute(text(_ALL_POSITIONS_SQL.format(dir=dir_sql)), params).all()
        elif q.interpolate:
            rows = _interpolated(conn, {**params, "p": float(q.position)}, q.direction, (t0, t1))
        else:
            dirs = [-1, 1] if q.direction is None else [q.direction]
            rows = conn.execute(text(nearest_sql(dirs)), {**params, "p": float(q.position)}).all()
        if rows:
            frames.append((int(pd.Timestamp(started).value), [(cid, *r) for r in rows]))
    return _drift_frame(frames)


def _interpolated(
    conn: Connection, params: dict[str, Any], direction: int | None, span: tuple[float, float]
) -> list[tuple[Any, ...]]:
    """Return one campaign's (time_s, position, direction, sweep, value) rows interpolated at ``params["p"]``
    along position within each sweep, kept to the campaign's time span."""
    p = params["p"]
    out: list[tuple[Any, ...]] = []
    for d in _directions(conn, params, direction):
        q = {**params, "d": d}
        brackets = [r for r in conn.execute(text(_BRACKETS_SQL), q).all() if r[1] is not None and r[2] is not None]
        if not brackets:
            continue
        wanted = sorted({r[1] for r in brackets} | {r[2] for r in brackets})
        at = {(sw, pos): (t, v) for w in wanted for sw, pos, t, v in conn.execute(text(_ROWS_AT_SQL), {**q, "pos": w})}
        for sweep, lo, hi in brackets:
            (ta, va), (th, vh) = at[(sweep, lo)], at[(sweep, hi)]
            f = 0.0 if hi == lo else (p - lo) / (hi - lo)
            t = ta + (th - ta) * f
            if span[0] <= t <= span[1]:
                out.append((t, p, d, sweep, va + (vh - va) * f))
    return out


def _drift_frame(parts: list[tuple[int, list[tuple[Any, ...]]]]) -> pd.DataFrame:
    """Return the drift rows as one DataFrame: campaigns in start order, then time, position, direction."""
    rows = [(k, offset, *r) for k, (offset, data) in enumerate(parts) for r in data]
    if not rows:
        return pd.DataFrame(
            {
                "campaign_id": np.array([], dtype="i8"),
                "time": pd.DatetimeIndex([], tz="UTC"),
                "time_s": np.array([], dtype="f8"),
                "position": np.array([], dtype="f8"),
                "direction": np.array([], dtype="i8"),
                "sweep": np.array([], dtype="i8"),
                "value": np.array([], dtype="f8"),
            }
        )
    k, offset, cid, t, p, d, sw, v = (np.asarray(col) for col in zip(*rows, strict=True))
    t, p, v = t.astype("f8"), p.astype("f8"), v.astype("f8")
    order = np.lexsort((d, p, t, k))
    ns = offset.astype("i8")[order] + np.round(t[order] * 1e9).astype("i8")
    return pd.DataFrame(
        {
            "campaign_id": cid.astype("i8")[order],
            "time": pd.DatetimeIndex(ns.astype("datetime64[ns]")).tz_localize("UTC"),
            "time_s": t[order],
            "position": p[order],
            "direction": d.astype("i8")[order],
            "sweep": sw.astype("i8")[order],
            "value": v[order],
        }
    )


# ----------------------------------------------------------------------------- histories


def _channel_id(conn: Connection, campaign_id: int, channel: str) -> tuple[int, int]:
    """Return a campaign's channel id and the campaign's partition key (start day)."""
    row = conn.execute(
        select(sc.Channel.id, sc.Campaign.started_at)
        .join(sc.Campaign, sc.Campaign.id == sc.Channel.campaign_id)
        .where(sc.Channel.campaign_id == campaign_id, sc.Channel.name == channel)
    ).first()
    if row is None:
        campaign_row(conn, campaign_id)
        raise NotFoundError(f"campaign {campaign_id} has no channel {channel!r}")
    return int(row[0]), start_day(row[1])


def _range(conn: Connection, table: str, where: str, params: dict[str, Any]) -> tuple[float, float] | None:
    # two statements: each is a single seek at one end of the key range (SQLite optimises a lone
    # MIN or MAX, but scans the range for both in one statement)
    lo = conn.execute(text(f"SELECT MIN(time_s) FROM {table} WHERE {where}"), params).scalar()
    if lo is None:
        return None
    hi = conn.execute(text(f"SELECT MAX(time_s) FROM {table} WHERE {where}"), params).scalar()
    return float(lo), float(lo if hi is None else hi)


def _history(
    conn: Connection,
    table: str,
    where: str,
    params: dict[str, Any],
    columns: list[str],
    start_s: float | None,
    end_s: float | None,
    buckets: int | None,
) -> pd.DataFrame:
    """Return raw samples, or min/mean/max per equal-width time bucket computed in SQL."""
    span = _range(conn, table, where, params)
    if span is None:
        cols = (
            ["time_s", *columns]
            if not buckets
            else ["time_s", "t_end_s", "n"] + [f"{c}_{s}" for c in columns for s in ("min", "mean", "max")]
        )
        return pd.DataFrame({c: pd.Series(dtype="f8") for c in cols})
    t0 = span[0] if start_s is None else float(start_s)
    t1 = span[1] if end_s is None else float(end_s)
    if t1 < t0:
        raise ValidationError(f"time range ends ({t1}) before it starts ({t0})")
    params = {**params, "t0": t0, "t1": t1}
    if not buckets:
        sql = (
            f"SELECT time_s, {', '.join(columns)} FROM {table} WHERE {where} "
            "AND time_s >= :t0 AND time_s <= :t1 ORDER BY time_s"
        )
        rows = conn.execute(text(sql), params).all()
        arr = np.array([[np.nan if v is None else v for v in r] for r in rows], dtype="f8").reshape(
            len(rows), len(columns) + 1
        )
        return pd.DataFrame(arr, columns=["time_s", *columns])
    if buckets < 1:
        raise ValidationError("buckets must be at least 1")
    width = (t1 - t0) / buckets if t1 > t0 else 1.0
    # Bucket k holds t0 + k*w <= time_s < t0 + (k+1)*w; the last one also holds time_s = t1.
    params.update(w=width, nb=buckets, t1x=math.nextafter(t1, math.inf))
    aggs = ", ".join(f"MIN({c}), AVG({c}), MAX({c})" for c in columns)
    bounds = "time_s >= :t0 + k.i * :w AND time_s < CASE WHEN k.i = :nb - 1 THEN :t1x ELSE :t0 + (k.i + 1) * :w END"
    if conn.dialect.name == "postgresql":
        # One range scan of the primary key, hash-aggregated by bucket (the same bucket bounds,
        # as an index). work_mem is raised for this transaction so the aggregate stays in memory.
        conn.execute(text("SET LOCAL work_mem = '64MB'"))
        sql = (
            f"SELECT LEAST(CAST(FLOOR((time_s - :t0) / :w) AS integer), :nb - 1) AS b, COUNT(*), {aggs} "
            f"FROM {table} WHERE {where} AND time_s >= :t0 AND time_s <= :t1 GROUP BY 1 ORDER BY 1"
        )
    else:
        # One primary-key range scan per bucket: no per-row bucket arithmetic, no sort of the samples.
        sql = (
            f"WITH RECURSIVE k(i) AS (SELECT 0 UNION ALL SELECT i + 1 FROM k WHERE i < :nb - 1) "
            f"SELECT k.i, COUNT(*), {aggs} FROM k JOIN {table} ON {where} AND {bounds} "
            "GROUP BY k.i ORDER BY k.i"
        )
    rows = conn.execute(text(sql), params).all()
    data = np.array([[np.nan if v is None else float(v) for v in r] for r in rows], dtype="f8").reshape(
        len(rows), 2 + 3 * len(columns)
    )
    b = data[:, 0]
    out = {"time_s": t0 + b * width, "t_end_s": t0 + (b + 1) * width, "n": data[:, 1].astype("i8")}
    for k, c in enumerate(columns):
        out[f"{c}_min"], out[f"{c}_mean"], out[f"{c}_max"] = data[:, 2 + 3 * k], data[:, 3 + 3 * k], data[:, 4 + 3 * k]
    return pd.DataFrame(out)


_ROLLUP_SQL = """
SELECT (minute - :m0) / :wm AS b, SUM(n), MIN(vmin),
       CASE WHEN SUM(n_values) > 0 THEN SUM(vsum) / SUM(n_values) END, MAX(vmax)
FROM temperature_rollups
WHERE campaign_id = :c AND channel_id = :ch AND minute >= :m0 AND minute <= :m1
GROUP BY 1 ORDER BY 1
"""


def _rollup_history(
    conn: Connection, campaign_id: int, channel_id: int, t0: float, t1: float, buckets: int
) -> pd.DataFrame | None:
    """Return buckets aggregated from the per-minute rollups (edges snapped out to whole minutes),
    or None when the buckets would be narrower than two minutes."""
    width = (t1 - t0) / buckets
    if width < 2 * ROLLUP_S:
        return None
    m0, m1 = math.floor(t0 / ROLLUP_S), math.floor(t1 / ROLLUP_S)
    wm = math.ceil(width / ROLLUP_S)
    rows = conn.execute(text(_ROLLUP_SQL), {"c": campaign_id, "ch": channel_id, "m0": m0, "m1": m1, "wm": wm}).all()
    data = np.array([[np.nan if v is None else float(v) for v in r] for r in rows], dtype="f8").reshape(len(rows), 5)
    start = m0 * ROLLUP_S + data[:, 0] * wm * ROLLUP_S
    return pd.DataFrame(
        {
            "time_s": start,
            "t_end_s": start + wm * ROLLUP_S,
            "n": data[:, 1].astype("i8"),
            "value_min": data[:, 2],
            "value_mean": data[:, 3],
            "value_max": data[:, 4],
        }
    )


class ReadingRepository(Repository):
    """The readings of the campaigns: drift across campaigns, histories, pages and the latest scan."""

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
        """Return the error history of (axis, term) across a machine's campaigns (see ``DriftQuery``).

        Columns: campaign_id, time (UTC), time_s, position, direction, sweep, value.
        """
        return self.query_drift(DriftQuery(machine_id, axis, term, position, direction, start, end, interpolate))

    def query_drift(self, query: DriftQuery) -> pd.DataFrame:
        """Return the drift a ``DriftQuery`` asks for (as ``drift``)."""
        with self.read() as conn:
            return _drift(conn, query)

    def temperature_history(
        self,
        campaign_id: int,
        channel: str,
        start_s: float | None = None,
        end_s: float | None = None,
        buckets: int | None = None,
        rollups: bool = True,
    ) -> pd.DataFrame:
        """Return a channel's readings (time_s, value) in a time range, or per bucket
        (time_s, t_end_s, n, value_min, value_mean, value_max) when ``buckets`` is given.

        Buckets of two minutes or more are aggregated from the per-minute rollups when the campaign has
        them (``rollups``): their edges are then snapped outward to whole minutes and time_s/t_end_s
        give the exact bounds each figure covers. Otherwise the edges are exactly
        t0 + k (t1 - t0) / buckets.
        """
        with self.read() as conn:
            channel_id, day = _channel_id(conn, campaign_id, channel)
            where = "campaign_id = :c AND channel_id = :ch AND campaign_start_day = :day"
            params = {"c": campaign_id, "ch": channel_id, "day": day}
            if buckets and rollups:
                if buckets < 1:
                    raise ValidationError("buckets must be at least 1")
                complete = conn.execute(
                    select(sc.Campaign.rollups_complete).where(sc.Campaign.id == campaign_id)
                ).scalar()
                span = _range(conn, "temperature_samples", where, params) if complete else None
                if span is not None:
                    t0 = span[0] if start_s is None else float(start_s)
                    t1 = span[1] if end_s is None else float(end_s)
                    if t1 < t0:
                        raise ValidationError(f"time range ends ({t1}) before it starts ({t0})")
                    if t1 > t0:
                        frame = _rollup_history(conn, campaign_id, channel_id, t0, t1, buckets)
                        if frame is not None:
                            return frame
            return _history(conn, "temperature_samples", where, params, ["value"], start_s, end_s, buckets)

    def condition_history(
        self,
        campaign_id: int,
        columns: list[str] | None = None,
        start_s: float | None = None,
        end_s: float | None = None,
        buckets: int | None = None,
    ) -> pd.DataFrame:
        """Return machine-state values, raw or min/mean/max per bucket computed in SQL."""
        with self.read() as conn:
            params = {"c": campaign_id, "day": campaign_day(conn, campaign_id)}
            cols = list(columns or CONDITION_VALUE_COLUMNS)
            for c in cols:
                if c not in CONDITION_VALUE_COLUMNS:
                    known = ", ".join(CONDITION_VALUE_COLUMNS)
                    raise ValidationError(f"unknown condition {c!r}: expected some of {known}")
            where = "campaign_id = :c AND campaign_start_day = :day"
            return _history(conn, "condition_samples", where, params, cols, start_s, end_s, buckets)

    def temperature_page(self, campaign_id: int, channel: str, page: HistoryPage) -> list[tuple[float, float | None]]:
        """Return up to ``page.limit`` (time_s, value) readings of a channel in time order, after ``page.after``."""
        t = sc.TemperatureSample
        with self.read() as conn:
            day = campaign_day(conn, campaign_id)
            ch = conn.execute(
                select(sc.Channel.id).where(sc.Channel.campaign_id == campaign_id, sc.Channel.name == channel)
            ).scalar()
            if ch is None:
                raise NotFoundError(f"campaign {campaign_id} has no channel {channel!r}")
            q = select(t.time_s, t.value).where(
                t.campaign_id == campaign_id, t.channel_id == ch, t.campaign_start_day == day
            )
            rows = conn.execute(_paged(q, t.time_s, page)).all()
            return [(float(a), None if b is None else float(b)) for a, b in rows]

    def condition_page(self, campaign_id: int, columns: list[str], page: HistoryPage) -> list[tuple[Any, ...]]:
        """Return up to ``page.limit`` rows (time_s, *columns) of the machine-state log in time order."""
        for c in columns:
            if c not in CONDITION_VALUE_COLUMNS:
                raise BadRequestError(f"unknown condition {c!r}: expected some of {', '.join(CONDITION_VALUE_COLUMNS)}")
        t = sc.ConditionSample
        with self.read() as conn:
            day = campaign_day(conn, campaign_id)
            q = select(t.time_s, *[getattr(t, c) for c in columns]).where(
                t.campaign_id == campaign_id, t.campaign_start_day == day
            )
            return [tuple(r) for r in conn.execute(_paged(q, t.time_s, page)).all()]

    def error_page(self, campaign_id: int, where: ErrorFilter, page: HistoryPage) -> list[Any]:
        """Return up to ``page.limit`` error samples in bundle order (seq) after the seq ``page.after``,
        filtered by axis, term, direction and time."""
        e = sc.ErrorSample
        with self.read() as conn:
            day = campaign_day(conn, campaign_id)
            q = select(e.seq, e.time_s, e.axis, e.term, e.position, e.direction, e.sweep, e.flags, e.value).where(
                e.campaign_id == campaign_id, e.campaign_start_day == day
            )
            if where.axis is not None:
                q = q.where(e.axis == where.axis)
            if where.term is not None:
                q = q.where(e.term == where.term)
            if where.direction is not None:
                q = q.where(e.direction == where.direction)
            q = time_window(q, e.time_s, page.start_s, page.end_s)
            if page.after is not None:
                q = q.where(e.seq > page.after)
            return list(conn.execute(q.order_by(e.seq).limit(page.limit).offset(page.offset)).all())

    def latest_scan(self, machine_id: str) -> LatestScan | None:
        """Return the machine's latest thermocouple scan, or None when it has no reading.

        The latest campaign of the machine that has readings, its last scan time (one primary-key seek
        per channel for the maximum, then one per channel for the value).
        """
        with self.read() as conn:
            machine_exists(conn, machine_id)
            campaigns = conn.execute(
                select(sc.Campaign.id, sc.Campaign.started_at)
                .where(sc.Campaign.machine_id == machine_id)
                .order_by(sc.Campaign.started_at.desc(), sc.Campaign.id.desc())
            ).all()
            for cid, started in campaigns:
                found = _last_scan(conn, int(cid), start_day(started))
                if found is not None:
                    return LatestScan(int(cid), started, *found)
            return None


def _paged(q: Any, time_col: Any, page: HistoryPage) -> Any:
    """Return a time-ordered history query kept to the page's time range, after its keyset position."""
    q = time_window(q, time_col, page.start_s, page.end_s, page.after)
    return q.order_by(time_col).limit(page.limit).offset(page.offset)


def _last_scan(conn: Connection, campaign_id: int, day: int) -> tuple[float, dict[str, float | None]] | None:
    """Return a campaign's last scan time and value per channel, or None when it has no reading."""
    t = sc.TemperatureSample
    channels = conn.execute(
        select(sc.Channel.id, sc.Channel.name).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal)
    ).all()
    key = (t.campaign_id == campaign_id, t.campaign_start_day == day)
    last = [conn.execute(select(func.max(t.time_s)).where(*key, t.channel_id == ch)).scalar() for ch, _ in channels]
    times = [x for x in last if x is not None]
    if not times:
        return None
    when = max(times)
    values: dict[str, float | None] = {}
    for ch, name in channels:
        v = conn.execute(select(t.value).where(*key, t.channel_id == ch, t.time_s == when)).scalar()
        values[name] = None if v is None else float(v)
    return float(when), values
