"""Store-side queries the REST API needs beyond ``store``/``queries``: machines, paged histories,
model promotion and retirement and job lists.

Every function takes a ``Store`` and runs in one transaction of its own (writes through
``db.write_transaction``). Paging is keyset paging on the tables' primary keys, so a page costs one
range scan whatever its offset in the history.

The on-line (RLS) state is the store's ``online_states`` table (``Store.online_state`` and
``Store.save_online_state``, used through ``driftlab.jobs.online.store_update``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, func, select, text, update

from driftlab.campaigns import db
from driftlab.campaigns import schema as sc
from driftlab.campaigns.ingest import CONDITION_VALUE_COLUMNS
from driftlab.campaigns.partitions import start_day
from driftlab.campaigns.store import JobInfo, Store, job_info, jobs_select
from driftlab.errors import BadRequestError, ConflictError, NotFoundError, ValidationError


@dataclass(frozen=True)
class MachineInfo:
    """A machine with the size of its history and its current model version."""

    id: str
    name: str
    resolution_mm: float | None
    resolution_deg: float | None
    created_at: datetime
    campaigns: int
    current_model_version: int | None


@dataclass(frozen=True)
class ModelRow:
    """A model registry row as the API serves it."""

    id: int
    machine_id: str
    version: int
    status: str
    created_at: datetime
    retired_at: datetime | None
    source_campaigns: list[int]
    document: dict[str, Any]


def _model_row(r: Any) -> ModelRow:
    return ModelRow(
        r.id,
        r.machine_id,
        r.version,
        r.status,
        r.created_at,
        r.retired_at,
        list(r.source_campaigns or []),
        dict(r.document or {}),
    )


@contextmanager
def _read(store: Store) -> Iterator[Connection]:
    """Yield a connection in one read transaction (one snapshot), closed on exit."""
    store.ensure_schema()
    with store.engine.connect() as conn, conn.begin():
        yield conn


def _machine_exists(conn: Connection, machine_id: str) -> None:
    if conn.execute(select(sc.Machine.id).where(sc.Machine.id == machine_id)).first() is None:
        raise NotFoundError(f"no machine {machine_id!r}")


def _campaign_exists(conn: Connection, campaign_id: int) -> int:
    """Return the campaign's partition key (start day); NotFoundError when there is no such campaign."""
    started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == campaign_id)).scalar()
    if started is None:
        raise NotFoundError(f"no campaign {campaign_id}")
    return start_day(started)


# ----------------------------------------------------------------------------- machines


def list_machines(store: Store, limit: int = 100, offset: int = 0) -> list[MachineInfo]:
    """Return machines ordered by id with their campaign count and current model version."""
    with _read(store) as conn:
        return _machines(conn, None, limit, offset)


def get_machine(store: Store, machine_id: str) -> MachineInfo:
    """Return one machine; NotFoundError when it does not exist."""
    with _read(store) as conn:
        rows = _machines(conn, machine_id, 1, 0)
    if not rows:
        raise NotFoundError(f"no machine {machine_id!r}")
    return rows[0]


def _machines(conn: Connection, machine_id: str | None, limit: int, offset: int) -> list[MachineInfo]:
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
    rows = conn.execute(q.limit(limit).offset(offset)).all()
    return [MachineInfo(r.id, r.name, r.resolution_mm, r.resolution_deg, r.created_at, int(r.n), r.cur) for r in rows]


# ----------------------------------------------------------------------------- campaigns


def campaign_detail(store: Store, campaign_id: int) -> tuple[Any, list[Any], list[Any]]:
    """Return a campaign's row, its stages and its channels (in plan and card order)."""
    with _read(store) as conn:
        row = conn.execute(select(sc.Campaign.__table__).where(sc.Campaign.id == campaign_id)).first()
        if row is None:
            raise NotFoundError(f"no campaign {campaign_id}")
        stages = conn.execute(
            select(sc.Stage.__table__).where(sc.Stage.campaign_id == campaign_id).order_by(sc.Stage.ordinal)
        ).all()
        channels = conn.execute(
            select(sc.Channel.__table__).where(sc.Channel.campaign_id == campaign_id).order_by(sc.Channel.ordinal)
        ).all()
        return row, list(stages), list(channels)


def temperature_page(
    store: Store,
    campaign_id: int,
    channel: str,
    start_s: float | None,
    end_s: float | None,
    after_s: float | None,
    offset: int,
    limit: int,
) -> list[tuple[float, float | None]]:
    """Return up to ``limit`` (time_s, value) readings of a channel in time order, after ``after_s``."""
    with _read(store) as conn:
        day = _campaign_exists(conn, campaign_id)
        ch = conn.execute(
            select(sc.Channel.id).where(sc.Channel.campaign_id == campaign_id, sc.Channel.name == channel)
        ).scalar()
        if ch is None:
            raise NotFoundError(f"campaign {campaign_id} has no channel {channel!r}")
        t = sc.TemperatureSample
        q = select(t.time_s, t.value).where(
            t.campaign_id == campaign_id, t.channel_id == ch, t.campaign_start_day == day
        )
        q = _time_window(q, t.time_s, start_s, end_s, after_s)
        rows = conn.execute(q.order_by(t.time_s).limit(limit).offset(offset)).all()
        return [(float(a), None if b is None else float(b)) for a, b in rows]


def latest_scan(store: Store, machine_id: str) -> tuple[int, datetime, float, dict[str, float | None]] | None:
    """Return the machine's latest thermocouple scan: (campaign id, campaign start, time_s, value per channel).

    The latest campaign of the machine that has readings, its last scan time (one primary-key seek
    per channel for the maximum, then one per channel for the value); None when there is no reading.
    """
    t = sc.TemperatureSample
    with _read(store) as conn:
        _machine_exists(conn, machine_id)
        campaigns = conn.execute(
            select(sc.Campaign.id, sc.Campaign.started_at)
            .where(sc.Campaign.machine_id == machine_id)
            .order_by(sc.Campaign.started_at.desc(), sc.Campaign.id.desc())
        ).all()
        for cid, started in campaigns:
            day = start_day(started)
            channels = conn.execute(
                select(sc.Channel.id, sc.Channel.name).where(sc.Channel.campaign_id == cid).order_by(sc.Channel.ordinal)
            ).all()
            last = [
                conn.execute(
                    select(func.max(t.time_s)).where(
                        t.campaign_id == cid, t.channel_id == ch, t.campaign_start_day == day
                    )
                ).scalar()
                for ch, _ in channels
            ]
            times = [x for x in last if x is not None]
            if not times:
                continue
            when = max(times)
            values: dict[str, float | None] = {}
            for ch, name in channels:
                v = conn.execute(
                    select(t.value).where(
                        t.campaign_id == cid, t.channel_id == ch, t.time_s == when, t.campaign_start_day == day
                    )
                ).scalar()
                values[name] = None if v is None else float(v)
            return int(cid), started, float(when), values
        return None


def condition_page(
    store: Store,
    campaign_id: int,
    columns: list[str],
    start_s: float | None,
    end_s: float | None,
    after_s: float | None,
    offset: int,
    limit: int,
) -> list[tuple[Any, ...]]:
    """Return up to ``limit`` rows (time_s, *columns) of the machine-state log in time order."""
    for c in columns:
        if c not in CONDITION_VALUE_COLUMNS:
            raise BadRequestError(f"unknown condition {c!r}: expected some of {', '.join(CONDITION_VALUE_COLUMNS)}")
    with _read(store) as conn:
        day = _campaign_exists(conn, campaign_id)
        t = sc.ConditionSample
        q = select(t.time_s, *[getattr(t, c) for c in columns]).where(
            t.campaign_id == campaign_id, t.campaign_start_day == day
        )
        q = _time_window(q, t.time_s, start_s, end_s, after_s)
        return [tuple(r) for r in conn.execute(q.order_by(t.time_s).limit(limit).offset(offset)).all()]


def error_page(
    store: Store,
    campaign_id: int,
    axis: str | None,
    term: str | None,
    direction: int | None,
    start_s: float | None,
    end_s: float | None,
    after_seq: int | None,
    offset: int,
    limit: int,
) -> list[Any]:
    """Return up to ``limit`` error samples in bundle order (seq), filtered by axis/term/direction/time."""
    with _read(store) as conn:
        day = _campaign_exists(conn, campaign_id)
        e = sc.ErrorSample
        q = select(e.seq, e.time_s, e.axis, e.term, e.position, e.direction, e.sweep, e.flags, e.value).where(
            e.campaign_id == campaign_id, e.campaign_start_day == day
        )
        if axis is not None:
            q = q.where(e.axis == axis)
        if term is not None:
            q = q.where(e.term == term)
        if direction is not None:
            q = q.where(e.direction == direction)
        q = _time_window(q, e.time_s, start_s, end_s, None)
        if after_seq is not None:
            q = q.where(e.seq > after_seq)
        return list(conn.execute(q.order_by(e.seq).limit(limit).offset(offset)).all())


def _time_window(q: Any, col: Any, start_s: float | None, end_s: float | None, after_s: float | None) -> Any:
    if start_s is not None:
        q = q.where(col >= start_s)
    if end_s is not None:
        q = q.where(col <= end_s)
    if after_s is not None:
        q = q.where(col > after_s)
    return q


# ----------------------------------------------------------------------------- model registry


def current_model(store: Store, machine_id: str) -> ModelRow | None:
    """Return the machine's current model row, or None when it has none."""
    with _read(store) as conn:
        r = conn.execute(
            select(sc.ModelVersion.__table__).where(
                sc.ModelVersion.machine_id == machine_id, sc.ModelVersion.status == "current"
            )
        ).first()
        return None if r is None else _model_row(r)


def model_version(store: Store, machine_id: str, version: int) -> ModelRow:
    """Return one model version of a machine; NotFoundError when there is no such version."""
    with _read(store) as conn:
        r = conn.execute(
            select(sc.ModelVersion.__table__).where(
                sc.ModelVersion.machine_id == machine_id, sc.ModelVersion.version == version
            )
        ).first()
        if r is None:
            raise NotFoundError(f"no model version {version} for machine {machine_id!r}")
        return _model_row(r)


def model_versions(store: Store, machine_id: str | None, status: str | None, limit: int, offset: int) -> list[ModelRow]:
    """Return model versions (of one machine, of one status) ordered by machine then version."""
    with _read(store) as conn:
        if machine_id is not None:
            _machine_exists(conn, machine_id)
        q = select(sc.ModelVersion.__table__).order_by(sc.ModelVersion.machine_id, sc.ModelVersion.version)
        if machine_id is not None:
            q = q.where(sc.ModelVersion.machine_id == machine_id)
        if status is not None:
            q = q.where(sc.ModelVersion.status == status)
        return [_model_row(r) for r in conn.execute(q.limit(limit).offset(offset)).all()]


def _lock_machine(conn: Connection, machine_id: str) -> None:
    q = select(sc.Machine.id).where(sc.Machine.id == machine_id)
    if conn.dialect.name == "postgresql":
        q = q.with_for_update()  # serialises registry changes of one machine
    if conn.execute(q).first() is None:
        raise NotFoundError(f"no machine {machine_id!r}")


def _version_row(conn: Any, machine_id: str, version: int) -> Any:
    """Return (id, status) of a machine's model version, or raise NotFoundError."""
    mv = sc.ModelVersion
    row = conn.execute(select(mv.id, mv.status).where(mv.machine_id == machine_id, mv.version == version)).first()
    if row is None:
        raise NotFoundError(f"no model version {version} for machine {machine_id!r}")
    return row


def promote_model(store: Store, machine_id: str, version: int) -> ModelRow:
    """Make a version the machine's current one (retiring the previous current) and return it."""
    store.ensure_schema()
    with db.write_transaction(store.engine) as conn:
        _lock_machine(conn, machine_id)
        mv = sc.ModelVersion
        target = _version_row(conn, machine_id, version)
        if target.status != "current":
            now = sc.utcnow()
            # retire first: the partial unique index allows one current version per machine
            conn.execute(
                update(mv)
                .where(mv.machine_id == machine_id, mv.status == "current")
                .values(status="retired", retired_at=now)
            )
            conn.execute(update(mv).where(mv.id == target.id).values(status="current", retired_at=None))
        return _model_row(conn.execute(select(mv.__table__).where(mv.id == target.id)).one())


def retire_model(store: Store, machine_id: str, version: int) -> ModelRow:
    """Retire a version (the machine has no current model if it was the current one) and return it."""
    store.ensure_schema()
    with db.write_transaction(store.engine) as conn:
        _lock_machine(conn, machine_id)
        mv = sc.ModelVersion
        target = _version_row(conn, machine_id, version)
        if target.status == "retired":
            raise ConflictError(f"model version {version} of machine {machine_id!r} is already retired")
        conn.execute(update(mv).where(mv.id == target.id).values(status="retired", retired_at=sc.utcnow()))
        return _model_row(conn.execute(select(mv.__table__).where(mv.id == target.id)).one())


# ----------------------------------------------------------------------------- jobs


def list_jobs(
    store: Store,
    state: str | None,
    kind: str | None,
    machine_id: str | None,
    limit: int,
    offset: int,
    kinds: tuple[str, ...] | None = None,
) -> list[JobInfo]:
    """Return jobs (newest first), filtered by state (as reported), kind (or set of kinds) and machine."""
    with _read(store) as conn:
        jobs = jobs_select(conn.dialect.name).subquery()
        q = select(jobs).order_by(jobs.c.id.desc())
        if kinds:
            q = q.where(jobs.c.kind.in_(kinds))
        if state is not None:
            q = q.where(jobs.c.state == state)
        if kind is not None:
            q = q.where(jobs.c.kind == kind)
        if machine_id is not None:
            q = q.where(jobs.c.machine_id == machine_id)
        return [job_info(r) for r in conn.execute(q.limit(limit).offset(offset)).all()]


def check_job_targets(store: Store, machine_id: str | None, campaign_ids: list[int]) -> list[int]:
    """Check a job's machine and campaigns exist (and belong together); return the campaigns to use.

    With a machine and no campaigns, every campaign of the machine is returned (oldest first).
    """
    with _read(store) as conn:
        if machine_id is not None:
            _machine_exists(conn, machine_id)
        rows = (
            {
                r.id: r.machine_id
                for r in conn.execute(
                    select(sc.Campaign.id, sc.Campaign.machine_id).where(sc.Campaign.id.in_(campaign_ids))
                ).all()
            }
            if campaign_ids
            else {}
        )
        for c in campaign_ids:
            if c not in rows:
                raise NotFoundError(f"no campaign {c}")
            if machine_id is not None and rows[c] != machine_id:
                raise ValidationError(f"campaign {c} is of machine {rows[c]!r}, not {machine_id!r}")
        if campaign_ids:
            return list(campaign_ids)
        if machine_id is None:
            return []
        return [
            int(c)
            for c in conn.execute(
                select(sc.Campaign.id)
                .where(sc.Campaign.machine_id == machine_id)
                .order_by(sc.Campaign.started_at, sc.Campaign.id)
            )
            .scalars()
            .all()
        ]


def ping(store: Store) -> bool:
    """Return True when the database answers."""
    with store.engine.connect() as conn:
        return conn.execute(text("SELECT 1")).scalar() == 1
