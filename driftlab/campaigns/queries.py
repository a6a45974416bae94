"""Read queries of the campaign store: export, campaign list, drift and downsampled histories.

Every query's SQL lives here (callers such as the API and the CLI get DataFrames or dataclasses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

import numpy as np
import pandas as pd
from sqlalchemy import Connection, func, select, text

from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import Bundle, CampaignMeta
from driftlab.campaigns.ingest import CONDITION_VALUE_COLUMNS, ROLLUP_S
from driftlab.campaigns.partitions import start_day
from driftlab.errors import BadRequestError, NotFoundError, ValidationError
from driftlab.vocabulary import AXES, TERMS


@dataclass(frozen=True)
class CampaignSummary:
    """One line of the campaign list."""

    id: int
    machine_id: str
    name: str
    started_at: datetime
    status: str
    source: str
    channels: int
    scans: int
    error_samples: int
    stages: int

    def as_dict(self) -> dict[str, Any]:
        """Return the summary as a JSON-ready dict."""
        return {
            "id": self.id,
            "machine_id": self.machine_id,
            "name": self.name,
            "started_at": self.started_at.isoformat().replace("+00:00", "Z"),
            "status": self.status,
            "source": self.source,
            "channels": self.channels,
            "scans": self.scans,
            "error_samples": self.error_samples,
            "stages": self.stages,
        }


def _campaign_row(conn: Connection, campaign_id: int) -> Any:
    row = conn.execute(select(sc.Campaign.__table__).where(sc.Campaign.id == campaign_id)).first()
    if row is None:
        raise NotFoundError(f"no campaign {campaign_id}")
    return row


def list_campaigns(conn: Connection, machine_id: str | None = None) -> list[CampaignSummary]:
    """Return every campaign (optionally of one machine) with its sizes, oldest first."""
    q = select(sc.Campaign.__table__).order_by(sc.Campaign.started_at, sc.Campaign.id)
    if machine_id is not None:
        q = q.where(sc.Campaign.machine_id == machine_id)
    out = []
    for c in conn.execute(q).all():
        channels = (
            conn.execute(select(sc.Channel.id).where(sc.Channel.campaign_id == c.id).order_by(sc.Channel.ordinal))
            .scalars()
            .all()
        )
        scans = 0
        if channels:
            # one channel's key range (primary key prefix) counts the scans without a table scan
            scans = conn.execute(
                select(func.count())
                .select_from(sc.TemperatureSample)
                .where(
                    sc.TemperatureSample.campaign_id == c.id,
                    sc.TemperatureSample.channel_id == channels[0],
                    sc.TemperatureSample.campaign_start_day == start_day(c.started_at),
                )
            ).scalar_one()
        errors = conn.execute(
            select(func.count())
            .select_from(sc.ErrorSample)
            .where(sc.ErrorSample.campaign_id == c.id, sc.ErrorSample.campaign_start_day == start_day(c.started_at))
        ).scalar_one()
        stages = conn.execute(
            select(func.count()).select_from(sc.Stage).where(sc.Stage.campaign_id == c.id)
        ).scalar_one()
        out.append(
            CampaignSummary(
                c.id,
                c.machine_id,
                c.name,
                c.started_at,
                c.status,
                c.source,
                len(channels),
                int(scans),
                int(errors),
                int(stages),
            )
        )
    return out


def _meta_from_tables(conn: Connection, campaign: Any) -> CampaignMeta:
    """Return campaign.json rebuilt from the tables (for campaigns stored without a document)."""
    machine = conn.execute(select(sc.Machine.__table__).where(sc.Machine.id == campaign.machine_id)).one()
    channels = conn.execute(
        select(sc.Channel.__table__).where(sc.Channel.campaign_id == campaign.id).order_by(sc.Channel.ordinal)
    ).all()
    stages = conn.execute(
        select(sc.Stage.__table__).where(sc.Stage.campaign_id == campaign.id).order_by(sc.Stage.ordinal)
    ).all()
    doc = {
        "format": "driftlab-bundle/1",
        "machine": {
            "id": machine.id,
            "name": machine.name,
            "resolution_mm": machine.resolution_mm,
            "resolution_deg": machine.resolution_deg,
        },
        "started_at": campaign.started_at,
        "channels": {c.name: {"location": c.location, "structure": c.structure} for c in channels},
        "room_channels": [c.name for c in channels if c.is_room],
        "stages": [
            {
                "name": s.name,
                "start_s": s.start_s,
                "end_s": s.end_s if s.end_s is not None else s.start_s,
                "heat_source": s.heat_source,
                "axis": s.axis,
                "spindle_rpm": s.spindle_rpm,
                "feed_mm_min": s.feed_mm_min,
            }
            for s in stages
        ],
    }
    doc["machine"] = {k: v for k, v in doc["machine"].items() if v is not None}
    return CampaignMeta.model_validate(doc)


def load_campaign(conn: Connection, campaign_id: int) -> Bundle:
    """Return a stored campaign as a Bundle (the exact values that were imported)."""
    campaign = _campaign_row(conn, campaign_id)
    meta = CampaignMeta.model_validate(campaign.meta) if campaign.meta else _meta_from_tables(conn, campaign)
    channels = conn.execute(
        select(sc.Channel.id, sc.Channel.name).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal)
    ).all()
    day = start_day(campaign.started_at)
    raw = conn.connection.driver_connection
    placeholder = "%s" if conn.dialect.name == "postgresql" else "?"
    cur = raw.cursor()  # type: ignore[union-attr]
    try:
        series: dict[str, pd.Series] = {}
        for channel_id, name in channels:
            cur.execute(
                "SELECT time_s, value FROM temperature_samples WHERE campaign_id = "
                f"{placeholder} AND channel_id = {placeholder} AND campaign_start_day = {placeholder} ORDER BY time_s",
                (campaign_id, channel_id, day),
            )
            rows = cur.fetchall()
            t = np.fromiter((r[0] for r in rows), dtype="f8", count=len(rows))
            v = np.fromiter((np.nan if r[1] is None else r[1] for r in rows), dtype="f8", count=len(rows))
            series[name] = pd.Series(v, index=t)
    finally:
        cur.close()
    if series and all(s.index.equals(next(iter(series.values())).index) for s in series.values()):
        times = next(iter(series.values())).index.to_numpy()
        temps = pd.DataFrame({"time_s": times, **{k: s.to_numpy() for k, s in series.items()}})
    else:
        wide = pd.DataFrame(series).sort_index()
        temps = pd.concat([pd.Series(wide.index.to_numpy(), name="time_s"), wide.reset_index(drop=True)], axis=1)
    conditions = None
    if campaign.conditions_columns is not None:
        cols = [c for c in campaign.conditions_columns if c != "time_s"]
        rows = conn.execute(
            select(sc.ConditionSample.time_s, *[getattr(sc.ConditionSample, c) for c in cols])
            .where(sc.ConditionSample.campaign_id == campaign_id, sc.ConditionSample.campaign_start_day == day)
            .order_by(sc.ConditionSample.time_s)
        ).all()
        arr = np.array([[np.nan if v is None else v for v in r] for r in rows], dtype="f8").reshape(
            len(rows), len(cols) + 1
        )
        conditions = pd.DataFrame(arr, columns=["time_s", *cols])
    pose_cols = (
        [sc.ErrorSample.x, sc.ErrorSample.y, sc.ErrorSample.z, sc.ErrorSample.a, sc.ErrorSample.b, sc.ErrorSample.setup]
        if meta.v2
        else []
    )
    rows = conn.execute(
        select(
            sc.ErrorSample.time_s,
            sc.ErrorSample.axis,
            sc.ErrorSample.term,
            sc.ErrorSample.position,
            sc.ErrorSample.direction,
            sc.ErrorSample.value,
            *pose_cols,
        )
        .where(sc.ErrorSample.campaign_id == campaign_id, sc.ErrorSample.campaign_start_day == day)
        .order_by(sc.ErrorSample.seq)
    ).all()
    errors = pd.DataFrame(
        {
            "time_s": np.array([r[0] for r in rows], dtype="f8"),
            "axis": pd.array([r[1] for r in rows], dtype="str"),
            "term": pd.array([r[2] for r in rows], dtype="str"),
            "position": np.array([r[3] for r in rows], dtype="f8"),
            "direction": np.array([r[4] for r in rows], dtype="i8"),
            "value": np.array([r[5] for r in rows], dtype="f8"),
        }
    )
    if meta.v2:  # bundle v2: the commanded pose (mm, deg) and setup of every reading
        for k, name in enumerate(("x", "y", "z", "a", "b")):
            errors[name] = np.array([np.nan if r[6 + k] is None else r[6 + k] for r in rows], dtype="f8")
        errors["setup"] = pd.array([r[11] for r in rows], dtype="str")
    return Bundle(name=campaign.name, meta=meta, temperatures=temps, conditions=conditions, errors=errors)


# ----------------------------------------------------------------------------- drift


def _check_axis_term(axis: str, term: str) -> None:
    if axis not in AXES:
        raise ValidationError(f"unknown axis {axis!r}: expected one of {' '.join(AXES)}")
    if term not in TERMS:
        raise ValidationError(f"unknown term {term!r}: expected one of {' '.join(TERMS)}")


def _seconds(delta: timedelta) -> float:
    return delta.total_seconds()


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


def drift(
    conn: Connection,
    machine_id: str,
    axis: str,
    term: str,
    position: float | None = None,
    direction: int | None = None,
    start: datetime | None = None,
    end: datetime | None = None,
    interpolate: bool = False,
) -> pd.DataFrame:
    """Return the error history of (axis, term) on a machine across its campaigns, in wall-clock time.

    With ``position`` the history is taken at the nearest measured position of each campaign, or
    (``interpolate``) linearly interpolated along position within each sweep; without it every
    measured position is returned. Columns: campaign_id, time (UTC), time_s, position, direction,
    sweep, value.
    """
    _check_axis_term(axis, term)
    if direction not in (None, 1, -1):
        raise ValidationError(f"direction must be +1 or -1, not {direction}")
    if interpolate and position is None:
        raise BadRequestError("interpolation needs a position")
    if conn.execute(select(sc.Machine.id).where(sc.Machine.id == machine_id)).first() is None:
        raise NotFoundError(f"no machine {machine_id!r}")
    campaigns = conn.execute(
        select(sc.Campaign.id, sc.Campaign.started_at)
        .where(sc.Campaign.machine_id == machine_id)
        .order_by(sc.Campaign.started_at, sc.Campaign.id)
    ).all()
    dir_sql = "" if direction is None else "AND direction = :d"
    frames = []
    for cid, started in campaigns:
        t0 = -np.inf if start is None else _seconds(start - started)
        t1 = np.inf if end is None else _seconds(end - started)
        if t1 < 0:
            continue
        params: dict[str, Any] = {
            "c": cid,
            "day": start_day(started),
            "axis": axis,
            "term": term,
            "d": direction,
            "t0": max(t0, -1e300),
            "t1": min(t1, 1e300),
        }
        data: list[tuple[Any, ...]] = []
        if position is None:
            rows = conn.execute(text(_ALL_POSITIONS_SQL.format(dir=dir_sql)), params).all()
            data = [(cid, t, p, d, s, v) for t, p, d, s, v in rows]
        elif interpolate:
            params["p"] = p = float(position)
            for d in _directions(conn, params, direction):
                q = {**params, "d": d}
                brackets = [
                    r for r in conn.execute(text(_BRACKETS_SQL), q).all() if r[1] is not None and r[2] is not None
                ]
                if not brackets:
                    continue
                wanted = sorted({r[1] for r in brackets} | {r[2] for r in brackets})
                at = {
                    (sw, pos): (t, v)
                    for w in wanted
                    for sw, pos, t, v in conn.execute(text(_ROWS_AT_SQL), {**q, "pos": w})
                }
                for sweep, lo, hi in brackets:
                    (ta, va), (th, vh) = at[(sweep, lo)], at[(sweep, hi)]
                    f = 0.0 if hi == lo else (p - lo) / (hi - lo)
                    t = ta + (th - ta) * f
                    if t0 <= t <= t1:
                        data.append((cid, t, p, d, sweep, va + (vh - va) * f))
        else:
            params["p"] = float(position)
            dirs = [-1, 1] if direction is None else [direction]
            rows = conn.execute(text(nearest_sql(dirs)), params).all()
            data = [(cid, t, p, d, s, v) for t, p, d, s, v in rows]
        if data:
            offset_ns = int(pd.Timestamp(started).value)
            frames.append((offset_ns, data))
    return _drift_frame(frames)


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
        _campaign_row(conn, campaign_id)
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


def temperature_history(
    conn: Connection,
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
    channel_id, day = _channel_id(conn, campaign_id, channel)
    where, params = (
        "campaign_id = :c AND channel_id = :ch AND campaign_start_day = :day",
        {"c": campaign_id, "ch": channel_id, "day": day},
    )
    if buckets and rollups:
        if buckets < 1:
            raise ValidationError("buckets must be at least 1")
        complete = conn.execute(select(sc.Campaign.rollups_complete).where(sc.Campaign.id == campaign_id)).scalar()
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
    conn: Connection,
    campaign_id: int,
    columns: list[str] | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    buckets: int | None = None,
) -> pd.DataFrame:
    """Return machine-state values in a time range, raw or min/mean/max per bucket."""
    day = start_day(_campaign_row(conn, campaign_id).started_at)
    cols = list(columns or CONDITION_VALUE_COLUMNS)
    for c in cols:
        if c not in CONDITION_VALUE_COLUMNS:
            raise ValidationError(f"unknown condition {c!r}: expected some of {', '.join(CONDITION_VALUE_COLUMNS)}")
    return _history(
        conn,
        "condition_samples",
        "campaign_id = :c AND campaign_start_day = :day",
        {"c": campaign_id, "day": day},
        cols,
        start_s,
        end_s,
        buckets,
    )
