"""What a running campaign looks like in the store: the queries behind /live and `campaign status --watch`.

Every function reads what the daemon has committed (campaign, stages, channels, the cursor in
``acquisition_progress``, temperature and error samples) and returns plain JSON-ready dicts.

Cost is bounded whatever the campaign's length:

* ``live_marks`` (polled twice a second by the API's live hub) reads one row per daemon campaign;
* temperatures are read per channel over a time window (the primary key
  ``(campaign_id, channel_id, time_s)`` makes each a range seek) and averaged in buckets, so
  a snapshot holds at most ``max_points`` points per channel and an update only the new buckets;
* error readings are read by ``seq`` (the primary key's order) after the last one sent.

Temperature points carry their bucket number ``b`` (``floor(time_s / width)``): an update may
repeat the last bucket of the previous one with more scans in it, and the reader replaces it.
Error rows carry ``seq``: a reader skips any it already has. Both make overlapping reads harmless.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from typing import Any, TypedDict, cast

from sqlalchemy import Engine, and_, func, or_, select
from sqlalchemy.orm import Session

from driftlab.campaigns import schema as sc
from driftlab.campaigns.status import stale_since

WINDOW_S = 4 * 3600.0  #: the strip charts show the last four hours of campaign time
MAX_POINTS = 240  #: at most this many points per channel and chart
MAX_ERRORS = 4000  #: at most this many error readings in a snapshot (the latest)
TIMEOUT_WORDS = ("timeout", "timed out", "no reply", "no complete reply")


def bucket_width(window_s: float = WINDOW_S, max_points: int = MAX_POINTS) -> float:
    """Return the width (s) of the temperature buckets: the window over the most points, whole seconds."""
    return float(max(1, math.ceil(window_s / max_points)))


class LiveMark(TypedDict):
    """A daemon campaign on show: its status, last commit and staleness (what the live hub compares)."""

    status: str
    updated_at: str | None
    time_s: float | None
    stale: bool


class ChannelRow(TypedDict):
    """A campaign's thermocouple as the live page lists it."""

    id: int
    name: str
    location: str
    structure: str  # "unspecified" when the campaign names none
    room: bool


class TemperatureBuckets(TypedDict):
    """Mean temperatures per bucket of ``width_s``: bucket numbers, latest scan times, per channel values."""

    width_s: float
    b: list[int]
    t: list[float]
    values: dict[str, list[float | None]]  # None where every reading was missing


class ErrorColumns(TypedDict):
    """Error readings column by column, in ``seq`` order (mm or rad; positions deg for A, B)."""

    seq: list[int]
    t: list[float]
    axis: list[str]
    term: list[str]
    position: list[float]
    direction: list[int]
    value: list[float]
    sweep: list[int]


def live_marks(engine: Engine, recent_done: bool = True) -> dict[int, LiveMark]:
    """Return, per daemon campaign on show, its status, last commit and staleness (change detection).

    On show: every running campaign and, with ``recent_done``, the latest daemon campaign whatever
    its status (so that a page opened after a run shows how it ended).
    """
    with Session(engine) as s:
        latest = s.execute(select(func.max(sc.Campaign.id)).where(sc.Campaign.source == "daemon")).scalar()
        cond = sc.Campaign.status == "running"
        if recent_done and latest is not None:
            cond = or_(cond, sc.Campaign.id == latest)
        rows = s.execute(
            select(
                sc.Campaign.id,
                sc.Campaign.status,
                sc.AcquisitionProgress.updated_at,
                sc.AcquisitionProgress.last_sample_time_s,
                sc.AcquisitionProgress.heartbeat_at,
            )
            .join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
            .where(and_(sc.Campaign.source == "daemon", cond))
            .order_by(sc.Campaign.id)
        ).all()
    return {
        r.id: {
            "status": r.status,
            "updated_at": _iso(r.updated_at),
            "time_s": r.last_sample_time_s,
            # a campaign whose daemon stopped beating changes its mark, so the page is told
            "stale": stale_since(r.status, r.heartbeat_at, r.updated_at) is not None,
        }
        for r in rows
    }


def find_campaign(engine: Engine, campaign: str | int) -> int | None:
    """Return the id of a daemon campaign given by id or name (the latest of that name), None if absent."""
    with Session(engine) as s:
        q = select(sc.Campaign.id).join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
        if isinstance(campaign, int) or str(campaign).isdigit():
            q = q.where(sc.Campaign.id == int(campaign))
        else:
            q = q.where(sc.Campaign.name == str(campaign)).order_by(sc.Campaign.id.desc())
        return s.execute(q.limit(1)).scalar()


def header(engine: Engine, campaign_id: int) -> dict[str, Any] | None:
    """Return a campaign's state as stored: stages, current stage and setup, progress, time left, latest scan,
    health."""
    with Session(engine) as s:
        row = s.execute(
            select(sc.Campaign, sc.AcquisitionProgress)
            .join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
            .where(sc.Campaign.id == campaign_id)
        ).first()
        if row is None:
            return None
        camp, prog = row
        stages = (
            s.execute(select(sc.Stage).where(sc.Stage.campaign_id == campaign_id).order_by(sc.Stage.ordinal))
            .scalars()
            .all()
        )
        return _header(camp, prog, list(stages))


def _header(camp: sc.Campaign, prog: sc.AcquisitionProgress, stages: list[sc.Stage]) -> dict[str, Any]:
    """Return the header dict of one campaign (see :func:`header`)."""
    cur = dict(prog.cursor or {})
    meta = dict(camp.meta or {})
    origin = dict(cur.get("origin") or {})
    meta_stages = list(meta.get("stages") or [])
    setups = dict(meta.get("setups") or {})
    last_scan = cur.get("last_scan")
    t = _latest_time(prog, last_scan)
    n_scans, n_points = int(cur.get("n_scans", 0)), int(cur.get("n_points", 0))
    scans, points = int(cur.get("next_scan", 0)), int(cur.get("next_point", 0))
    total_s = cur.get("total_s") or (max((st.end_s or 0.0) for st in stages) if stages else None)
    stage_rows = [_stage_row(st, meta_stages, setups) for st in stages]
    current = next((r for r in stage_rows if r["ordinal"] == prog.stage_ordinal), None)
    # simulated campaigns run at `speed` campaign seconds per wall second; real ones at 1
    speed = origin.get("speed") if origin.get("mode") == "sim" else 1.0
    stage_left = stage_frac = None
    if current is not None and current["end_s"] is not None and t is not None:
        c_start, c_end = float(current["start_s"]), float(current["end_s"])
        span = max(c_end - c_start, 1e-9)
        stage_frac = min(max((t - c_start) / span, 0.0), 1.0)
        stage_left = max(c_end - t, 0.0)
    total_left = max(float(total_s) - t, 0.0) if total_s is not None and t is not None else None
    fraction = round((scans + points) / (n_scans + n_points), 6) if n_scans + n_points else 0.0
    stale = stale_since(camp.status, prog.heartbeat_at, prog.updated_at)
    if camp.status == "done":  # finished: all of it, nothing left (not the last commit's 97 %)
        stage_left = total_left = 0.0
        stage_frac = fraction = 1.0
    elif camp.status != "running" or stale is not None:  # nobody runs it: no time is "left"
        stage_left = total_left = None
    started = camp.started_at
    return {
        "campaign_id": camp.id,
        "name": camp.name,
        "machine": camp.machine_id,
        "status": camp.status,
        "stale_since": _iso(stale),
        "heartbeat_at": _iso(prog.heartbeat_at),
        "mode": origin.get("mode"),
        "speed": speed,
        "scenario": origin.get("scenario"),
        "started_at": _iso(started),
        "updated_at": _iso(prog.updated_at),
        "stages": stage_rows,
        "stage": current,
        "progress": {
            "scans": scans,
            "n_scans": n_scans,
            "points": points,
            "n_points": n_points,
            "fraction": fraction,
            "time_s": t,
            "total_s": total_s,
            "stage_fraction": stage_frac,
            "stage_left_s": stage_left,
            "total_left_s": total_left,
            "stage_left_wall_s": None if stage_left is None or not speed else stage_left / speed,
            "total_left_wall_s": None if total_left is None or not speed else total_left / speed,
        },
        "latest": _latest(started, last_scan),
        "last_point": cur.get("last_point"),
        "health": _health(cur, last_scan),
    }


def _stage_row(st: sc.Stage, meta_stages: list[Any], setups: dict[str, Any]) -> dict[str, Any]:
    """Return a stage of the header: its row, with the setup its campaign.json entry names."""
    extra = meta_stages[st.ordinal] if st.ordinal < len(meta_stages) else {}
    return {
        "ordinal": st.ordinal,
        "name": st.name,
        "heat_source": st.heat_source,
        "axis": st.axis,
        "spindle_rpm": st.spindle_rpm,
        "feed_mm_min": st.feed_mm_min,
        "start_s": st.start_s,
        "end_s": st.end_s,
        "status": st.status,
        "setup": _setup(extra.get("setup"), setups),
    }


def _latest(started: datetime | None, last_scan: dict[str, Any] | None) -> dict[str, Any] | None:
    """Return the header's latest scan (its campaign time, values and wall-clock time), None before one."""
    if not last_scan:
        return None
    at = None
    if started and last_scan.get("t_s") is not None:
        at = _iso(started + timedelta(seconds=float(last_scan["t_s"])))
    return {"time_s": last_scan.get("t_s"), "values": dict(last_scan.get("values") or {}), "at": at}


def _latest_time(prog: sc.AcquisitionProgress, last_scan: dict[str, Any] | None) -> float | None:
    """Return the campaign time of the latest committed reading."""
    times = [v for v in (prog.last_sample_time_s, (last_scan or {}).get("t_s")) if v is not None]
    return float(max(times)) if times else None


def _setup(setup: Any, setups: dict[str, Any]) -> dict[str, Any] | None:
    """Return the stage's instrument setup as stored in campaign.json (by id or inline), None when not named."""
    if setup is None:
        return None
    if isinstance(setup, str):
        found = setups.get(setup)
        return {"id": setup, **found} if isinstance(found, dict) else {"id": setup}
    return dict(setup) if isinstance(setup, dict) else {"id": str(setup)}


def _health(cur: dict[str, Any], last_scan: dict[str, Any] | None) -> dict[str, Any]:
    """Return the instruments' health from the cursor: faults by instrument, timeouts, retries, open thermocouples.

    The cursor keeps the total fault count and the last 20 faults; counts by instrument and
    timeouts are over those. Retries that succeeded are counted only if the daemon records them
    (``cursor["retries"]``, per instrument); None otherwise.
    """
    recent = list(cur.get("recent_faults") or [])
    by_inst: dict[str, int] = {}
    timeouts = 0
    for f in recent:
        by_inst[f.get("instrument", "?")] = by_inst.get(f.get("instrument", "?"), 0) + 1
        timeouts += any(w in str(f.get("message", "")).lower() for w in TIMEOUT_WORDS)
    values = (last_scan or {}).get("values") or {}
    open_tc = sorted((k for k, v in values.items() if v is None), key=_natural)
    return {
        "faults": int(cur.get("faults", 0)),
        "by_instrument": by_inst,
        "timeouts": timeouts,
        "counted_over": len(recent),
        "retries": cur.get("retries"),
        "open": open_tc,
        "recent": recent[-5:],
    }


def channels(engine: Engine, campaign_id: int) -> list[ChannelRow]:
    """Return the campaign's thermocouples in scan order: name, location, structure, room flag, id."""
    with Session(engine) as s:
        rows = (
            s.execute(select(sc.Channel).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal))
            .scalars()
            .all()
        )
        return [
            {
                "id": c.id,
                "name": c.name,
                "location": c.location,
                "structure": c.structure or "unspecified",
                "room": bool(c.is_room),
            }
            for c in rows
        ]


def temperature_buckets(
    engine: Engine, campaign_id: int, chans: Sequence[ChannelRow], after_s: float | None, width_s: float
) -> TemperatureBuckets:
    """Return the mean temperature of each channel per bucket of ``width_s`` after ``after_s`` (None: all).

    ``{"width_s", "b": [...], "t": [...], "values": {channel: [...]}}`` with buckets in time order;
    ``t`` is the latest scan in the bucket; a value is None where every reading was missing.
    """
    ids = {c["id"]: c["name"] for c in chans}
    out: TemperatureBuckets = {"width_s": width_s, "b": [], "t": [], "values": {c["name"]: [] for c in chans}}
    if not ids:
        return out
    ts = sc.TemperatureSample
    b = func.floor(ts.time_s / width_s)
    q = select(ts.channel_id, b.label("b"), func.max(ts.time_s), func.avg(ts.value)).where(
        ts.campaign_id == campaign_id, ts.channel_id.in_(list(ids))
    )
    if after_s is not None:
        q = q.where(ts.time_s > after_s)
    q = q.group_by(ts.channel_id, b)
    with Session(engine) as s:
        rows = s.execute(q).all()
    cells: dict[int, dict[str, float | None]] = {}
    times: dict[int, float] = {}
    for ch, bk, tmax, avg in rows:
        k = int(bk)
        cells.setdefault(k, {})[ids[ch]] = None if avg is None else round(float(avg), 4)
        times[k] = max(times.get(k, -math.inf), float(tmax))
    for k in sorted(cells):
        out["b"].append(k)
        out["t"].append(times[k])
        for name in out["values"]:
            out["values"][name].append(cells[k].get(name))
    return out


def error_readings(
    engine: Engine,
    campaign_id: int,
    after_seq: int | None = None,
    since_s: float | None = None,
    limit: int = MAX_ERRORS,
) -> ErrorColumns:
    """Return the error readings after ``after_seq`` (or from campaign time ``since_s``), at most ``limit``,
    latest kept.

    Columns: seq, t (s), axis, term, position (mm; deg for A, B), direction, value (mm or rad), sweep.
    """
    es = sc.ErrorSample
    q = select(es.seq, es.time_s, es.axis, es.term, es.position, es.direction, es.value, es.sweep).where(
        es.campaign_id == campaign_id
    )
    if after_seq is not None:
        q = q.where(es.seq > after_seq)
    if since_s is not None:
        q = q.where(es.time_s >= since_s)
    q = q.order_by(es.seq.desc()).limit(limit)
    with Session(engine) as s:
        rows = s.execute(q).all()[::-1]
    keys = ("seq", "t", "axis", "term", "position", "direction", "value", "sweep")
    return cast("ErrorColumns", {k: [r[i] for r in rows] for i, k in enumerate(keys)})


def latest_seq(engine: Engine, campaign_id: int) -> int:
    """Return the last error reading's seq (-1 when none)."""
    with Session(engine) as s:
        v = s.execute(select(func.max(sc.ErrorSample.seq)).where(sc.ErrorSample.campaign_id == campaign_id)).scalar()
    return -1 if v is None else int(v)


def snapshot(
    engine: Engine, campaign_id: int, window_s: float = WINDOW_S, max_points: int = MAX_POINTS
) -> dict[str, Any] | None:
    """Return everything the live page draws for one campaign: header, channels, the strip-chart window, errors."""
    head = header(engine, campaign_id)
    if head is None:
        return None
    chans = channels(engine, campaign_id)
    width = bucket_width(window_s, max_points)
    t = head["progress"]["time_s"]
    since = None if t is None else t - window_s
    # whole buckets only: the first bucket is not cut in half by the window's edge
    after = None if since is None or since <= 0 else math.floor(since / width) * width - 1e-9
    temps = temperature_buckets(engine, campaign_id, chans, after, width)
    errors = error_readings(engine, campaign_id, since_s=since)
    return {
        **head,
        "window_s": window_s,
        "channels": [{k: c[k] for k in ("name", "location", "structure", "room")} for c in chans],
        "temperatures": temps,
        "errors": errors,
    }


def update(
    engine: Engine, campaign_id: int, chans: Sequence[ChannelRow], after_s: float | None, after_seq: int, width_s: float
) -> dict[str, Any] | None:
    """Return a campaign's header with the temperature buckets from the one holding ``after_s`` and errors
    after ``after_seq``."""
    head = header(engine, campaign_id)
    if head is None:
        return None
    # re-read the last bucket already sent (it may have gained scans): the reader replaces it
    start = None if after_s is None else math.floor(after_s / width_s) * width_s - 1e-9
    return {
        **head,
        "temperatures": temperature_buckets(engine, campaign_id, chans, start, width_s),
        "errors": error_readings(engine, campaign_id, after_seq=after_seq),
    }


def _iso(t: datetime | None) -> str | None:
    """Return an aware datetime as ISO 8601 UTC with a Z, None for None."""
    if t is None:
        return None
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


def _natural(name: str) -> tuple[Any, ...]:
    """Return a sort key that orders T2 before T10."""
    head = name.rstrip("0123456789")
    tail = name[len(head) :]
    return (head, int(tail) if tail else -1)


def campaign_meta(engine: Engine, campaign_id: int) -> dict[str, Any] | None:
    """Return a stored campaign's campaign.json document (None when absent); no samples are read."""
    with Session(engine) as s:
        meta = s.execute(select(sc.Campaign.meta).where(sc.Campaign.id == campaign_id)).scalar()
    return None if meta is None else dict(meta)
