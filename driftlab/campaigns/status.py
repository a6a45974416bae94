"""Status of the daemon's campaigns as stored: stage, progress, last readings, faults, and whether a daemon runs them.

A running daemon writes a heartbeat (``beat``, every ``HEARTBEAT_S`` seconds, waiting or not). A
campaign that reads ``running`` but whose heartbeat (or, for rows written before the heartbeat, last
commit) is older than ``STALE_AFTER_S`` has lost its daemon (kill -9, a host that went down): status,
/live and ``--watch`` then say "stale since ...", never a running campaign.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, TypedDict

from driftlab.labels import display_unit

if TYPE_CHECKING:
    from sqlalchemy import Engine

#: how often a running daemon writes its heartbeat (s)
HEARTBEAT_S = 10.0
#: a running campaign without a heartbeat for this long (s) is stale (DRIFTLAB_STALE_AFTER_S overrides)
STALE_AFTER_S = 60.0


def stale_after_s() -> float:
    """Return the staleness threshold in seconds (DRIFTLAB_STALE_AFTER_S, else ``STALE_AFTER_S``)."""
    try:
        value = float(os.environ.get("DRIFTLAB_STALE_AFTER_S", STALE_AFTER_S))
    except ValueError:
        return STALE_AFTER_S
    return value if math.isfinite(value) and value > 0 else STALE_AFTER_S


def beat(engine: Any, campaign_id: int, at: datetime | None = None) -> None:
    """Write the daemon's heartbeat of a campaign (one small transaction)."""
    # lazy: the store (SQLAlchemy) adds 0.15 s to this module, whose status files are read without it (measured)
    from sqlalchemy import update

    from driftlab.campaigns import schema as sc
    from driftlab.campaigns.db import write_transaction

    with write_transaction(engine) as conn:
        conn.execute(
            update(sc.AcquisitionProgress.__table__)
            .where(sc.AcquisitionProgress.__table__.c.campaign_id == campaign_id)
            .values(heartbeat_at=at or datetime.now(UTC))
        )


def stale_since(
    status: str, heartbeat_at: datetime | None, updated_at: datetime | None, now: datetime | None = None
) -> datetime | None:
    """Return when a ``running`` campaign's daemon last showed life, if that is too long ago (else None)."""
    if status != "running":
        return None
    last = heartbeat_at or updated_at
    if last is None:
        return None
    now = now or datetime.now(UTC)
    return last if (now - last).total_seconds() > stale_after_s() else None


def _iso(t: datetime | None) -> str | None:
    """Return an aware time as ISO 8601 UTC with a Z (None stays None)."""
    return None if t is None else t.astimezone(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


class StageStatus(TypedDict):
    """The stage a daemon campaign is in."""

    ordinal: int
    name: str
    heat_source: str
    start_s: float
    end_s: float | None
    status: str


class AcquisitionCount(TypedDict):
    """How far a daemon campaign got: scans and sweep points stored of those planned, campaign time."""

    scans: int
    n_scans: int
    points: int
    n_points: int
    fraction: float
    time_s: float | None
    total_s: float | None


class LastScan(TypedDict):
    """The latest thermocouple scan a campaign stored (None where a channel was open or flagged)."""

    t_s: float
    values: dict[str, float | None]


class LastPoint(TypedDict):
    """The latest error sweep point a campaign stored, per term (None where the reading failed)."""

    t_s: float
    axis: str
    position: float
    direction: int
    values: dict[str, float | None]


class Fault(TypedDict):
    """An instrument fault the daemon recorded."""

    t_s: float
    step: str
    instrument: str
    message: str


class Faults(TypedDict):
    """How many faults a campaign had, and the last few."""

    count: int
    recent: list[Fault]


class CampaignStatus(TypedDict):
    """The status of one daemon campaign (``driftlab daemon status``)."""

    campaign_id: int
    name: str
    machine: str
    status: str
    mode: str | None  # "sim" or "instruments"
    stage: StageStatus | None
    stages: int
    progress: AcquisitionCount
    last_scan: LastScan | None
    last_point: LastPoint | None
    faults: Faults
    updated_at: str | None
    heartbeat_at: str | None
    stale_since: str | None


def campaign_status(engine: Engine, campaign: str | int | None = None) -> list[CampaignStatus]:
    """Return the status of daemon campaigns (all, or one by id or name): stage, progress, last readings, faults."""
    # lazy: the store (SQLAlchemy) adds 0.15 s to this module, whose status files are read without it (measured)
    from sqlalchemy import select

    from driftlab.campaigns import schema as sc

    q = (
        select(sc.Campaign, sc.AcquisitionProgress)
        .join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
        .order_by(sc.Campaign.id)
    )
    if isinstance(campaign, int) or (isinstance(campaign, str) and campaign.isdigit()):
        q = q.where(sc.Campaign.id == int(campaign))
    elif campaign:
        q = q.where(sc.Campaign.name == campaign)
    # lazy: the store (SQLAlchemy) adds 0.15 s to this module, whose status files are read without it (measured)
    from sqlalchemy.orm import Session

    out: list[CampaignStatus] = []
    with Session(engine) as conn:
        rows = conn.execute(q).all()
        for camp, prog in rows:
            stages = conn.execute(
                select(
                    sc.Stage.ordinal,
                    sc.Stage.name,
                    sc.Stage.heat_source,
                    sc.Stage.start_s,
                    sc.Stage.end_s,
                    sc.Stage.status,
                )
                .where(sc.Stage.campaign_id == camp.id)
                .order_by(sc.Stage.ordinal)
            ).all()
            cur = dict(prog.cursor or {})
            n_scans, n_points = int(cur.get("n_scans", 0)), int(cur.get("n_points", 0))
            done = int(cur.get("next_scan", 0)) + int(cur.get("next_point", 0))
            total = n_scans + n_points
            stage = next((s for s in stages if s.ordinal == prog.stage_ordinal), None)
            out.append(
                {
                    "campaign_id": camp.id,
                    "name": camp.name,
                    "machine": camp.machine_id,
                    "status": camp.status,
                    "mode": (cur.get("origin") or {}).get("mode"),
                    "stage": None
                    if stage is None
                    else {
                        "ordinal": stage.ordinal,
                        "name": stage.name,
                        "heat_source": stage.heat_source,
                        "start_s": stage.start_s,
                        "end_s": stage.end_s,
                        "status": stage.status,
                    },
                    "stages": len(stages),
                    "progress": {
                        "scans": int(cur.get("next_scan", 0)),
                        "n_scans": n_scans,
                        "points": int(cur.get("next_point", 0)),
                        "n_points": n_points,
                        "fraction": round(done / total, 6) if total else 0.0,
                        "time_s": prog.last_sample_time_s,
                        "total_s": cur.get("total_s"),
                    },
                    "last_scan": cur.get("last_scan"),
                    "last_point": cur.get("last_point"),
                    "faults": {"count": int(cur.get("faults", 0)), "recent": list(cur.get("recent_faults", []))[-5:]},
                    "updated_at": prog.updated_at.isoformat() if prog.updated_at else None,
                    "heartbeat_at": _iso(prog.heartbeat_at),
                    "stale_since": _iso(stale_since(camp.status, prog.heartbeat_at, prog.updated_at)),
                }
            )
    return out


def format_status(rows: Sequence[CampaignStatus]) -> str:
    """Return the status rows as a few human-readable lines per campaign."""
    if not rows:
        return "no daemon campaigns in the store"
    lines = []
    for r in rows:
        p = r["progress"]
        st = r["stage"]
        state = r["status"] if not r.get("stale_since") else f"running, stale since {r['stale_since']}: no daemon"
        lines.append(
            f"{r['campaign_id']:>4}  {r['name']}  [{state}]  machine {r['machine']}  "
            f"{100 * p['fraction']:.1f}%  scans {p['scans']}/{p['n_scans']}  points {p['points']}/{p['n_points']}"
        )
        if st:
            lines.append(
                f"      stage {st['ordinal'] + 1}/{r['stages']} {st['name']} ({st['heat_source']}) "
                f"{st['start_s']:.0f}-{st['end_s']:.0f} s, at t={p['time_s'] or 0:.0f} s"
            )
        if r["last_scan"]:
            vals = r["last_scan"]["values"]
            shown = ", ".join(
                f"{k} {v:.2f}" if isinstance(v, (int, float)) and math.isfinite(v) else f"{k} -"
                for k, v in list(vals.items())[:6]
            )
            more = f" (+{len(vals) - 6} more)" if len(vals) > 6 else ""
            lines.append(f"      last scan t={r['last_scan']['t_s']:.0f} s: {shown}{more} °C")
        if r["last_point"]:
            lp = r["last_point"]
            terms = ", ".join(
                f"{k} {v * display_unit(k)[0]:.2f} {display_unit(k)[1]}" if v is not None else f"{k} -"
                for k, v in lp["values"].items()
            )
            lines.append(
                f"      last point t={lp['t_s']:.0f} s {lp['axis']}={lp['position']:g} "
                f"dir {lp['direction']:+d}: {terms}"
            )
        f = r["faults"]
        if f["count"]:
            last = f["recent"][-1]
            lines.append(
                f"      faults {f['count']}, last at t={last['t_s']:.0f} s: {last['instrument']}: {last['message']}"
            )
    return "\n".join(lines)
