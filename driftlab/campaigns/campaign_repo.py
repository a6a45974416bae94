"""The campaigns' repository: import, export, list, describe and delete campaigns; machines; resume points.

A campaign's readings are written by its import; the acquisition scheduler's resume point is kept
beside the campaign it belongs to.

An import is one transaction (``ingest.import_bundle`` inside ``Repository.write``): it lands whole
or leaves the database exactly as it was, whatever interrupts it. The readings' queries (drift,
histories, pages) are the same aggregate's, in ``readings_repo``.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from pydantic import BaseModel
from sqlalchemy import Connection, Row, delete, func, insert, select, update

from driftlab.campaigns import import_pipeline, ingest, partitions
from driftlab.campaigns import schema as sc
from driftlab.campaigns.bundle import CSV_BLOCK_BYTES, Bundle, CampaignMeta
from driftlab.campaigns.repository import Page, Repository, analyze, campaign_row, machine_exists
from driftlab.errors import NotFoundError, ValidationError

if TYPE_CHECKING:
    from pathlib import Path

    from driftlab.campaigns.import_pipeline import ImportedBundle
    from driftlab.campaigns.staging import StagedBundle


class CampaignSummary(BaseModel):
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
        return {**dict(self), "started_at": self.started_at.isoformat().replace("+00:00", "Z")}


@dataclass(frozen=True)
class CampaignDetail:
    """A campaign's row with its stages (plan order) and channels (card order)."""

    row: Row[Any]
    stages: list[Row[Any]]
    channels: list[Row[Any]]


class MachineInfo(BaseModel):
    """A machine tool with the size of its history and its current model version."""

    id: str
    name: str
    resolution_mm: float | None
    resolution_deg: float | None
    created_at: datetime
    campaigns: int
    current_model_version: int | None


@dataclass(frozen=True)
class ProgressInfo:
    """The acquisition scheduler's resume point of a campaign."""

    campaign_id: int
    stage_ordinal: int
    sweep: int
    last_sample_time_s: float | None
    cursor: dict[str, Any] | None
    updated_at: datetime


class CampaignRepository(Repository):
    """Campaigns and machines: import, export, list, describe, delete; the scheduler's resume point."""

    def import_bundle(self, bundle: Bundle | StagedBundle) -> int:
        """Store a validated bundle (in memory, or staged: ``staging.stage_bundle``) in one transaction.

        Returns its campaign id. Refused (ConflictError) when a campaign with the same content hash
        is already stored. A staged bundle's rows are written a chunk at a time.
        """
        self.gate.ensure()
        content_hash = bundle.content_hash()
        day = partitions.start_day(bundle.meta.started_at)
        # the month's partition, made (in a transaction of its own) before the import writes into it
        partitions.ensure_partitions(self.engine, [day])
        with ingest.concurrent_duplicate_refused(bundle.name), self.write() as conn:
            existing = conn.execute(select(sc.Campaign.id).where(sc.Campaign.content_hash == content_hash)).scalar()
            if existing is not None:
                raise ingest.already_stored(bundle.name, existing, content_hash)
            campaign_id = ingest.import_bundle(conn, bundle, content_hash)
        analyze(self.engine, day)
        return campaign_id

    def import_directory(
        self, path: str | Path, block_bytes: int = CSV_BLOCK_BYTES, directory: str | None = None
    ) -> ImportedBundle:
        """Validate and store the bundle in directory ``path`` in one transaction (``import_pipeline``).

        Returns the campaign id with the staged bundle (close it, or use it in a ``with``). On
        PostgreSQL the files are read while the server writes; on SQLite the bundle is staged first.
        BundleError for a bad bundle, ConflictError for one already stored: either way nothing stored.
        """
        return import_pipeline.import_directory(self, path, self.import_bundle, block_bytes, directory)

    def load(self, campaign_id: int) -> Bundle:
        """Return a stored campaign as a Bundle with exactly the values stored."""
        with self.read() as conn:
            return _load_campaign(conn, campaign_id)

    def machine_of(self, campaign_id: int) -> str:
        """Return the machine id of a campaign; NotFoundError if there is no such campaign."""
        with self.read() as conn:
            machine = conn.execute(select(sc.Campaign.machine_id).where(sc.Campaign.id == campaign_id)).scalar()
        if machine is None:
            raise NotFoundError(f"no campaign {campaign_id}")
        return str(machine)

    def summaries(self, machine_id: str | None = None) -> list[CampaignSummary]:
        """Return a summary of every campaign (optionally of one machine) with its sizes, oldest first."""
        with self.read() as conn:
            q = select(sc.Campaign.__table__).order_by(sc.Campaign.started_at, sc.Campaign.id)
            if machine_id is not None:
                q = q.where(sc.Campaign.machine_id == machine_id)
            return [_summary(conn, c) for c in conn.execute(q).all()]

    def detail(self, campaign_id: int) -> CampaignDetail:
        """Return a campaign's row, its stages and its channels (in plan and card order)."""
        with self.read() as conn:
            row = campaign_row(conn, campaign_id)
            stages = conn.execute(
                select(sc.Stage.__table__).where(sc.Stage.campaign_id == campaign_id).order_by(sc.Stage.ordinal)
            ).all()
            channels = conn.execute(
                select(sc.Channel.__table__).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal)
            ).all()
            return CampaignDetail(row, list(stages), list(channels))

    def delete(self, campaign_id: int) -> None:
        """Delete a campaign with all its samples, stages, channels and progress (one transaction)."""
        with self.write() as conn:
            # FOR UPDATE (PostgreSQL; SQLite's BEGIN IMMEDIATE already serialises writers): a concurrent
            # delete of the same campaign waits here, then finds no row and answers "no campaign"
            row = conn.execute(select(sc.Campaign.id).where(sc.Campaign.id == campaign_id).with_for_update()).first()
            if row is None:
                raise NotFoundError(f"no campaign {campaign_id}")
            # every partition is looked at (one index probe each), not just the campaign's: a delete
            # must not depend on the readings' key being what the campaign's start says
            for table in (sc.TemperatureSample, sc.TemperatureRollup, sc.ConditionSample, sc.ErrorSample):
                conn.execute(delete(table).where(table.campaign_id == campaign_id))
            gone = conn.execute(delete(sc.Campaign).where(sc.Campaign.id == campaign_id))
            if gone.rowcount != 1:  # pragma: no cover - the row lock above makes this unreachable
                raise NotFoundError(f"no campaign {campaign_id}")

    def refresh_rollups(self, campaign_id: int) -> int:
        """Recompute a campaign's per-minute temperature rollups (e.g. when a live campaign ends)."""
        with self.write() as conn:
            campaign_row(conn, campaign_id)
            return ingest.refresh_rollups(conn, campaign_id)

    # ------------------------------------------------------------------ machines

    def machines(self, page: Page = Page()) -> list[MachineInfo]:
        """Return machines ordered by id with their campaign count and current model version."""
        with self.read() as conn:
            return _machines(conn, None, page)

    def machine(self, machine_id: str) -> MachineInfo:
        """Return one machine; NotFoundError when it does not exist."""
        with self.read() as conn:
            rows = _machines(conn, machine_id, Page(1))
        if not rows:
            raise NotFoundError(f"no machine {machine_id!r}")
        return rows[0]

    def job_targets(self, machine_id: str | None, campaign_ids: list[int]) -> list[int]:
        """Check a job's machine and campaigns exist (and belong together); return the campaigns to use.

        With a machine and no campaigns, every campaign of the machine is returned (oldest first).
        """
        with self.read() as conn:
            if machine_id is not None:
                machine_exists(conn, machine_id)
            owner = {}
            if campaign_ids:
                q = select(sc.Campaign.id, sc.Campaign.machine_id).where(sc.Campaign.id.in_(campaign_ids))
                owner = {r.id: r.machine_id for r in conn.execute(q).all()}
            for c in campaign_ids:
                if c not in owner:
                    raise NotFoundError(f"no campaign {c}")
                if machine_id is not None and owner[c] != machine_id:
                    raise ValidationError(f"campaign {c} is of machine {owner[c]!r}, not {machine_id!r}")
            if campaign_ids or machine_id is None:
                return list(campaign_ids)
            mine = (
                select(sc.Campaign.id)
                .where(sc.Campaign.machine_id == machine_id)
                .order_by(sc.Campaign.started_at, sc.Campaign.id)
            )
            return [int(c) for c in conn.execute(mine).scalars().all()]

    # ------------------------------------------------------------------ acquisition progress

    def save_progress(
        self,
        campaign_id: int,
        stage_ordinal: int,
        sweep: int,
        last_sample_time_s: float | None,
        cursor: dict[str, Any] | None = None,
    ) -> None:
        """Record the scheduler's resume point of a campaign (insert or update)."""
        with self.write() as conn:
            values = {
                "stage_ordinal": stage_ordinal,
                "sweep": sweep,
                "last_sample_time_s": last_sample_time_s,
                "cursor": cursor,
                "updated_at": sc.utcnow(),
            }
            n = conn.execute(
                update(sc.AcquisitionProgress).where(sc.AcquisitionProgress.campaign_id == campaign_id).values(**values)
            ).rowcount
            if not n:
                conn.execute(insert(sc.AcquisitionProgress).values(campaign_id=campaign_id, **values))

    def progress(self, campaign_id: int) -> ProgressInfo | None:
        """Return the scheduler's resume point of a campaign, or None before its first commit."""
        with self.read() as conn:
            row = conn.execute(
                select(sc.AcquisitionProgress.__table__).where(sc.AcquisitionProgress.campaign_id == campaign_id)
            ).first()
            if row is None:
                return None
            return ProgressInfo(
                row.campaign_id, row.stage_ordinal, row.sweep, row.last_sample_time_s, row.cursor, row.updated_at
            )


# ----------------------------------------------------------------------------- listings


def _summary(conn: Connection, c: Any) -> CampaignSummary:
    """Return the summary of a campaign row: its channel, scan, error sample and stage counts."""
    day = partitions.start_day(c.started_at)
    channels = (
        conn.execute(select(sc.Channel.id).where(sc.Channel.campaign_id == c.id).order_by(sc.Channel.ordinal))
        .scalars()
        .all()
    )
    scans = 0
    if channels:
        # one channel's key range (primary key prefix) counts the scans without a table scan
        ts = sc.TemperatureSample
        scans = conn.execute(
            select(func.count())
            .select_from(ts)
            .where(ts.campaign_id == c.id, ts.channel_id == channels[0], ts.campaign_start_day == day)
        ).scalar_one()
    errors = conn.execute(
        select(func.count())
        .select_from(sc.ErrorSample)
        .where(sc.ErrorSample.campaign_id == c.id, sc.ErrorSample.campaign_start_day == day)
    ).scalar_one()
    stages = conn.execute(select(func.count()).select_from(sc.Stage).where(sc.Stage.campaign_id == c.id)).scalar_one()
    return CampaignSummary(
        id=c.id,
        machine_id=c.machine_id,
        name=c.name,
        started_at=c.started_at,
        status=c.status,
        source=c.source,
        channels=len(channels),
        scans=int(scans),
        error_samples=int(errors),
        stages=int(stages),
    )


def _machines(conn: Connection, machine_id: str | None, page: Page) -> list[MachineInfo]:
    n_campaigns = (
        select(func.count()).select_from(sc.Campaign).where(sc.Campaign.machine_id == sc.Machine.id).scalar_subquery()
    )
    current = (
        select(sc.ModelVersion.version)
        .where(sc.ModelVersion.machine_id == sc.Machine.id, sc.ModelVersion.status == "current")
        .limit(1)
        .scalar_subquery()
    )
    q = select(sc.Machine.__table__, n_campaigns.label("n"), current.label("cur")).order_by(sc.Machine.id)
    if machine_id is not None:
        q = q.where(sc.Machine.id == machine_id)
    rows = conn.execute(page.apply(q)).all()
    return [
        MachineInfo(
            id=r.id,
            name=r.name,
            resolution_mm=r.resolution_mm,
            resolution_deg=r.resolution_deg,
            created_at=r.created_at,
            campaigns=int(r.n),
            current_model_version=r.cur,
        )
        for r in rows
    ]


# ----------------------------------------------------------------------------- export


def _meta_from_tables(conn: Connection, campaign: Any) -> CampaignMeta:
    """Return campaign.json rebuilt from the tables (for campaigns stored without a document)."""
    machine = conn.execute(select(sc.Machine.__table__).where(sc.Machine.id == campaign.machine_id)).one()
    channels = conn.execute(
        select(sc.Channel.__table__).where(sc.Channel.campaign_id == campaign.id).order_by(sc.Channel.ordinal)
    ).all()
    stages = conn.execute(
        select(sc.Stage.__table__).where(sc.Stage.campaign_id == campaign.id).order_by(sc.Stage.ordinal)
    ).all()
    described = {
        "id": machine.id,
        "name": machine.name,
        "resolution_mm": machine.resolution_mm,
        "resolution_deg": machine.resolution_deg,
    }
    doc = {
        "format": "driftlab-bundle/1",
        "machine": {k: v for k, v in described.items() if v is not None},
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
    return CampaignMeta.model_validate(doc)


def _load_campaign(conn: Connection, campaign_id: int) -> Bundle:
    """Return a stored campaign as a Bundle (the exact values that were imported)."""
    campaign = campaign_row(conn, campaign_id)
    meta = CampaignMeta.model_validate(campaign.meta) if campaign.meta else _meta_from_tables(conn, campaign)
    day = partitions.start_day(campaign.started_at)
    conditions = None
    if campaign.conditions_columns is not None:
        conditions = _conditions_frame(
            conn, campaign_id, day, [c for c in campaign.conditions_columns if c != "time_s"]
        )
    return Bundle(
        name=campaign.name,
        meta=meta,
        temperatures=_temperatures_frame(conn, campaign_id, day),
        conditions=conditions,
        errors=_errors_frame(conn, campaign_id, day, meta.v2),
    )


def _temperatures_frame(conn: Connection, campaign_id: int, day: int) -> pd.DataFrame:
    """Return a campaign's readings as the bundle's wide table (time_s, one column per channel)."""
    channels = conn.execute(
        select(sc.Channel.id, sc.Channel.name).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal)
    ).all()
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
        return pd.DataFrame({"time_s": times, **{k: s.to_numpy() for k, s in series.items()}})
    wide = pd.DataFrame(series).sort_index()
    return pd.concat([pd.Series(wide.index.to_numpy(), name="time_s"), wide.reset_index(drop=True)], axis=1)


def _conditions_frame(conn: Connection, campaign_id: int, day: int, cols: list[str]) -> pd.DataFrame:
    """Return a campaign's machine-state log (time_s and the stored columns, NaN where NULL)."""
    cs = sc.ConditionSample
    rows = conn.execute(
        select(cs.time_s, *[getattr(cs, c) for c in cols])
        .where(cs.campaign_id == campaign_id, cs.campaign_start_day == day)
        .order_by(cs.time_s)
    ).all()
    arr = np.array([[np.nan if v is None else v for v in r] for r in rows], dtype="f8").reshape(
        len(rows), len(cols) + 1
    )
    return pd.DataFrame(arr, columns=["time_s", *cols])


def _errors_frame(conn: Connection, campaign_id: int, day: int, v2: bool) -> pd.DataFrame:
    """Return a campaign's error log in file order (bundle v2: with the commanded pose and setup)."""
    e = sc.ErrorSample
    pose_cols = [e.x, e.y, e.z, e.a, e.b, e.setup] if v2 else []
    rows = conn.execute(
        select(e.time_s, e.axis, e.term, e.position, e.direction, e.value, *pose_cols)
        .where(e.campaign_id == campaign_id, e.campaign_start_day == day)
        .order_by(e.seq)
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
    if v2:  # bundle v2: the commanded pose (mm, deg) and setup of every reading
        for k, name in enumerate(("x", "y", "z", "a", "b")):
            errors[name] = np.array([np.nan if r[6 + k] is None else r[6 + k] for r in rows], dtype="f8")
        errors["setup"] = pd.array([r[11] for r in rows], dtype="str")
    return errors
