"""Acquisition records and where the daemon writes them: batches, faults, the campaign row and its cursor.

A batch of readings is committed *together with the cursor* (the next scan and sweep point still
to do) in one transaction (``StoreSink``), so the stored cursor always says exactly which readings
are in the store: a run resumed after ``kill -9`` starts there and nothing is lost or stored twice.
The run loop that fills the batches lives in ``driftlab.daemon``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pandas as pd
from sqlalchemy import Connection, bindparam, select
from sqlalchemy.exc import DBAPIError, IntegrityError

from driftlab.campaigns import schema as sc
from driftlab.campaigns.db import write_transaction
from driftlab.campaigns.ingest import (
    TEMPERATURE_COLUMNS,
    TEMPERATURE_TYPES,
    bulk_insert,
    copy_temperatures_pg,
    insert_flat_sqlite,
    insert_ignoring_duplicates,
)
from driftlab.campaigns.partitions import ensure_partitions, start_day
from driftlab.campaigns.plan import Cursor, Plan, SweepPoint
from driftlab.campaigns.status import beat
from driftlab.errors import ConflictError, DriftlabError, ValidationError
from driftlab.physics.geometry import Geometry
from driftlab.readings import Reading, ScanBlock, TemperatureScan
from driftlab.vocabulary import TERMS

if TYPE_CHECKING:
    from sqlalchemy import Insert

    from driftlab.campaigns.ingest import SqlValue

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Fault:
    """An instrument fault met while running a step (the step's readings are missing)."""

    t_s: float
    step: str
    instrument: str
    message: str


@dataclass
class Batch:
    """Readings to commit in one transaction together with the cursor that follows them."""

    scans: list[tuple[int, TemperatureScan]] = field(default_factory=list)
    blocks: list[ScanBlock] = field(default_factory=list)  # buffered scans read in blocks (block mode)
    states: list[tuple[float, dict[str, float]]] = field(default_factory=list)
    points: list[tuple[SweepPoint, float, dict[str, Reading]]] = field(default_factory=list)
    faults: list[Fault] = field(default_factory=list)
    cursor: Cursor = field(default_factory=Cursor)
    stage: int = 0
    t_s: float = 0.0
    first_wall: float = 0.0
    datum: dict[str, Any] | None = None

    def empty(self) -> bool:
        """Return True when there is nothing to commit (not even a cursor move)."""
        return not (self.scans or self.blocks or self.states or self.points or self.faults)

    def n_scans(self) -> int:
        """Return the number of scans in the batch (single and block-read)."""
        return len(self.scans) + sum(len(b) for b in self.blocks)

    def n_readings(self) -> int:
        """Return the number of scans and sweep points in the batch."""
        return self.n_scans() + len(self.points)


class Sink(Protocol):
    """Where the scheduler's readings go: commits a batch and its cursor atomically."""

    def commit(self, batch: Batch) -> None:
        """Store every reading of the batch and move the campaign's cursor, all or nothing."""


# -- the store side: campaigns opened by the daemon, batches committed with their cursor ------------

STATE_KEYS = ("spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")


@dataclass(frozen=True)
class CampaignHandle:
    """A campaign row the daemon writes into, with its channel ids and the cursor to resume from."""

    campaign_id: int
    cursor: Cursor
    channel_ids: dict[str, int]
    resumed: bool
    progress: dict[str, Any] = field(default_factory=dict)
    #: the campaign's partition key (``partitions.start_day`` of its start), written into every reading
    start_day: int = 0


def _sweep_numbers(plan: Plan) -> dict[tuple[int, int], int]:
    """Return the campaign-wide number of each (stage, sweep-in-stage) pair, in time order."""
    out: dict[tuple[int, int], int] = {}
    for p in plan.sweep_points():
        out.setdefault((p.stage, p.sweep), len(out))
    return out


def open_campaign(
    engine: Any,
    plan: Plan,
    channels: Mapping[str, Mapping[str, str]],
    room_channels: list[str],
    *,
    resume: bool,
    origin: Mapping[str, Any],
    extra_meta: Mapping[str, Any] | None = None,
) -> CampaignHandle:
    """Create the daemon's campaign for `plan`, or with `resume` continue its latest one from its cursor.

    With `resume` and no campaign of this plan yet (the daemon died before creating it), the
    campaign is created; a complete one is returned with its final cursor (nothing left to do).
    Refuses (ConflictError) to start a second copy of an unfinished campaign without `resume`, and
    to resume one whose plan timeline has changed since it started. On PostgreSQL the partition of
    the campaign's start is made (if missing) before the handle is returned: before any reading.
    """
    fp = plan.fingerprint()
    with write_transaction(engine) as conn:
        handle = _resumable(conn, plan, fp, resume)
        if handle is None:
            if resume:
                log.info("no unfinished campaign %s: starting it", plan.name)
            started = sc.utcnow()
            meta = _campaign_document(plan, channels, room_channels, started, extra_meta)
            handle = _create_campaign(conn, plan, meta, started, origin, fp)
    if not handle.resumed:
        log.info("campaign %s created (id %d)", plan.name, handle.campaign_id)
    ensure_partitions(engine, [handle.start_day])
    return handle


def _create_campaign(
    conn: Connection, plan: Plan, meta: dict[str, Any], started: datetime, origin: Mapping[str, Any], fp: str
) -> CampaignHandle:
    """Insert a new daemon campaign (its machine when new, stages, channels, first cursor); return its handle."""
    if conn.execute(select(sc.Machine.id).where(sc.Machine.id == plan.machine.id)).first() is None:
        conn.execute(
            insert_ignoring_duplicates(conn, sc.Machine.__table__, ["id"]).values(
                id=plan.machine.id, name=plan.machine.name or str(meta["machine"].get("name") or "")
            )
        )
    cid = _insert_campaign(conn, plan, meta, started)
    room = set(meta["room_channels"])
    conn.execute(
        sc.Channel.__table__.insert(),
        [
            {
                "campaign_id": cid,
                "ordinal": i,
                "name": name,
                "location": info.get("location", ""),
                "structure": info.get("structure", ""),
                "is_room": name in room,
            }
            for i, (name, info) in enumerate(meta["channels"].items())
        ],
    )
    cursor = {
        "next_scan": 0,
        "next_point": 0,
        "n_scans": plan.n_scans,
        "n_points": len(plan.sweep_points()),
        "total_s": plan.total_s,
        "fingerprint": fp,
        "plan": plan.name,
        "origin": dict(origin),
        "faults": 0,
        "recent_faults": [],
    }
    conn.execute(
        sc.AcquisitionProgress.__table__.insert().values(
            campaign_id=cid, stage_ordinal=0, sweep=0, last_sample_time_s=None, cursor=cursor, updated_at=sc.utcnow()
        )
    )
    ids = dict(conn.execute(select(sc.Channel.name, sc.Channel.id).where(sc.Channel.campaign_id == cid)).all())
    return CampaignHandle(cid, Cursor(), ids, False, cursor, start_day(started))


def _resumable(conn: Connection, plan: Plan, fp: str, resume: bool) -> CampaignHandle | None:
    """Return the handle of the plan's latest campaign to continue (None: a new one is to be made).

    A running campaign is continued only with ``resume`` (ConflictError without) and only from the
    same plan timeline; with ``resume`` a complete one is returned with its final cursor.
    """
    row = conn.execute(
        select(sc.Campaign.id, sc.Campaign.status, sc.AcquisitionProgress.cursor, sc.Campaign.started_at)
        .join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
        .where(sc.Campaign.name == plan.name, sc.Campaign.source == "daemon")
        .order_by(sc.Campaign.id.desc())
    ).first()
    if row is None or not (row.status == "running" or (resume and row.status == "done")):
        return None
    cid, cur = row.id, dict(row.cursor or {})
    if not resume:
        raise ConflictError(f"campaign {plan.name!r} (id {cid}) is unfinished: continue it with --resume")
    if cur.get("fingerprint") != fp:
        raise ConflictError(
            f"campaign {plan.name!r} (id {cid}) was started from a different plan timeline: "
            "resume it with the plan it started with"
        )
    ids = dict(conn.execute(select(sc.Channel.name, sc.Channel.id).where(sc.Channel.campaign_id == cid)).all())
    if row.status == "done":
        log.info("campaign %s (id %d) is already complete", plan.name, cid)
    return CampaignHandle(
        cid, Cursor(int(cur["next_scan"]), int(cur["next_point"])), ids, True, cur, start_day(row.started_at)
    )


def _campaign_document(
    plan: Plan,
    channels: Mapping[str, Mapping[str, str]],
    room_channels: list[str],
    started: datetime,
    extra_meta: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """Return the campaign.json (bundle v2) of a new daemon campaign, with the scenario's ``extra_meta``
    merged in (its machine entries complete the plan's; ValidationError when both state a geometry)."""
    machine: dict[str, Any] = {
        "id": plan.machine.id,
        "name": plan.machine.name,
        **({"geometry": plan.machine.geometry.document()} if plan.machine.geometry else {}),
        # the plan's travel goes with the campaign, so a model fitted on it carries its machine's limits
        **(
            {"travel": {a: [float(lo), float(hi)] for a, (lo, hi) in plan.machine.travel.items()}}
            if plan.machine.travel
            else {}
        ),
    }
    meta: dict[str, Any] = {  # campaign.json of the bundle
        # bundle v2: every reading is stored with its commanded pose and the setup that made it
        "format": "driftlab-bundle/2",
        "setups": {k: v.bundle_entry() for k, v in plan.used_setups().items()},
        "machine": machine,
        "started_at": started.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "channels": {k: dict(v) for k, v in channels.items()},
        "room_channels": list(room_channels),
        "stages": plan.bundle_stages(),
    }
    for key, value in (extra_meta or {}).items():
        if (
            key == "machine"
            and "geometry" in value
            and "geometry" in machine
            and Geometry.model_validate(value["geometry"]) != plan.machine.geometry
        ):
            raise ValidationError(
                f"plan {plan.name!r} and the scenario state different geometries of machine "
                f"{plan.machine.id!r}: state it once"
            )
        # the plan's own name and travel win over the scenario's (the virtual machine's travel fills in
        # only when the plan states none, so a simulated campaign always carries one)
        meta.setdefault(key, value) if key != "machine" else machine.update(
            {
                k: v
                for k, v in value.items()
                if k != "id" and (k != "name" or not plan.machine.name) and (k != "travel" or not plan.machine.travel)
            }
        )
    return meta


def _insert_campaign(conn: Connection, plan: Plan, meta: dict[str, Any], started: datetime) -> int:
    """Insert a running daemon campaign and its planned stages; return its id."""
    inserted = conn.execute(
        sc.Campaign.__table__.insert().values(
            machine_id=plan.machine.id,
            name=plan.name,
            started_at=started,
            status="running",
            source="daemon",
            meta=meta,
            conditions_columns=["time_s", *STATE_KEYS],
        )
    ).inserted_primary_key
    assert inserted is not None  # a single-row insert of a table with a primary key
    cid = inserted[0]
    conn.execute(
        sc.Stage.__table__.insert(),
        [
            {
                "campaign_id": cid,
                "ordinal": i,
                "name": r["name"],
                "heat_source": r["heat_source"],
                "axis": r["axis"],
                "spindle_rpm": r["spindle_rpm"],
                "feed_mm_min": r["feed_mm_min"],
                "start_s": r["start_s"],
                "end_s": r["end_s"],
                "status": "planned",
            }
            for i, r in enumerate(plan.bundle_stages())
        ],
    )
    return int(cid)


class StoreUnavailable(DriftlabError):
    """The store could not be reached or was locked for a write (worth retrying the same batch)."""

    http_status = 503


class StoreSink:
    """Commits a batch of readings and the campaign's cursor in one database transaction."""

    def __init__(self, engine: Any, plan: Plan, handle: CampaignHandle) -> None:
        self.engine = engine
        self.plan = plan
        self.cid = handle.campaign_id
        self.day = handle.start_day
        self.channel_ids = handle.channel_ids
        self.sweeps = _sweep_numbers(plan)
        self.n_points = len(plan.sweep_points())
        self._prog: dict[str, Any] = dict(handle.progress)
        self._t_temp = sc.TemperatureSample.__table__
        self._t_cond = sc.ConditionSample.__table__
        self._t_err = sc.ErrorSample.__table__
        self._t_prog = sc.AcquisitionProgress.__table__
        self._t_stage = sc.Stage.__table__
        self._t_camp = sc.Campaign.__table__
        # built once, not per batch: a statement built per commit cost its construction and cache key each time
        self._ins_cond = self._t_cond.insert()
        self._ins_err = self._t_err.insert()
        self._upd_prog = self._t_prog.update().where(self._t_prog.c.campaign_id == bindparam("_campaign_id"))
        self._ins_scan_head = f"INSERT INTO temperature_samples ({', '.join(TEMPERATURE_COLUMNS)}) VALUES "
        self._ins_scan_row = f"({int(self.cid)}, ?, ?, ?, {int(self.day)})"  # the campaign and day as literals
        self._stage = -1
        self._setups = plan.used_setups()  # bundle v2: every reading is stored with its pose and setup

    def _temperature_rows(self, batch: Batch) -> list[tuple[int, int, float, float | None, int]]:
        """Return (campaign_id, channel_id, time_s, value, start day) rows of the batch (value None: flagged or
        non-finite)."""
        rows = []
        cid, ids, isfinite, day = self.cid, self.channel_ids, math.isfinite, self.day
        for _, scan in batch.scans:
            t, flags = scan.t_s, scan.flags
            for name, value in scan.values.items():
                ch = ids.get(name)
                if ch is not None:
                    rows.append((cid, ch, t, value if isfinite(value) and name not in flags else None, day))
        return rows

    def _block_arrays(self, batch: Batch) -> tuple[list[int], list[str], np.ndarray, np.ndarray] | None:
        """Return (channel ids, names, times (n,), values (n, c)) of the batch's blocks; NaN where open."""
        if not batch.blocks:
            return None
        channels = batch.blocks[0].channels
        if any(b.channels != channels for b in batch.blocks):
            raise ValueError("blocks of one batch must share their channels")
        cols = [i for i, c in enumerate(channels) if c in self.channel_ids]
        values = np.concatenate([b.values for b in batch.blocks])[:, cols]
        times = np.concatenate([b.t_s for b in batch.blocks])
        names = [channels[i] for i in cols]
        return [self.channel_ids[c] for c in names], names, times, values

    def _insert_blocks(self, conn: Any, arrays: tuple[list[int], list[str], np.ndarray, np.ndarray]) -> None:
        """Insert block readings with the store's bulk path, channel by channel (key order); NaN stored as NULL."""
        ids, names, times, values = arrays
        if conn.dialect.name == "postgresql":
            frame = pd.DataFrame(values, columns=names)
            frame.insert(0, "time_s", times)
            copy_temperatures_pg(conn, self.cid, ids, frame, self.day)  # numpy-encoded binary COPY
            return
        # the rows (channel, time, value) of each channel laid into one flat run of parameters by slice
        # assignment, in key order (sqlite stores a bound NaN as NULL): no tuple a row to build and flatten
        # again in the writer thread, which holds the interpreter lock meanwhile (0.9 -> 0.35 ms a block
        # of 200 scans x 50 channels); the rows and their order as before, channel by channel in key order
        n, t = len(times), times.tolist()
        width = 3 * n
        flat: list[SqlValue] = [None] * (width * len(ids))
        for k, (ch, col) in enumerate(zip(ids, values.T.tolist(), strict=True)):
            at = k * width
            flat[at : at + width : 3] = [ch] * n
            flat[at + 1 : at + width : 3] = t
            flat[at + 2 : at + width : 3] = col
        cur = conn.connection.driver_connection.cursor()
        try:
            insert_flat_sqlite(cur, self._ins_scan_head, self._ins_scan_row, 3, flat)
        finally:
            cur.close()

    def _error_rows(self, batch: Batch) -> list[dict[str, Any]]:
        """Return the error rows of the batch; a flagged (missing) term is not stored (it is a fault)."""
        rows = []
        for p, t, values in batch.points:
            for term, r in values.items():
                if not r.ok:
                    continue
                row = {
                    "campaign_id": self.cid,
                    "seq": p.index * len(TERMS) + TERMS.index(term),
                    "time_s": t,
                    "axis": p.axis,
                    "term": term,
                    "position": p.position,
                    "direction": p.direction,
                    "value": r.value,
                    "sweep": self.sweeps[(p.stage, p.sweep)],
                    "flags": 0,
                    "campaign_start_day": self.day,
                }
                row.update(self._setups[p.setup].full_pose(p.position))
                row["setup"] = p.setup
                rows.append(row)
        return rows

    def beat(self) -> None:
        """Write the daemon's heartbeat of this campaign (``campaigns.status.beat``)."""
        beat(self.engine, self.cid)

    def commit(self, batch: Batch) -> None:
        """Insert the batch's rows and move the cursor, stage status and fault log, all in one transaction.

        Raises ConflictError when a reading of the batch is already stored (never a second copy) and
        StoreUnavailable when the database could not be reached; either way nothing was stored.
        """
        dbapi = self.engine.dialect.dbapi
        try:
            self._commit(batch)
        except (IntegrityError, dbapi.IntegrityError) as exc:
            raise ConflictError(
                f"the store already holds a reading of this batch (t = {batch.t_s:g} s): {_first_line(exc)}"
            ) from None
        except (DBAPIError, dbapi.OperationalError, dbapi.InterfaceError) as exc:
            if isinstance(exc, DBAPIError) and not (
                exc.connection_invalidated or isinstance(exc.orig, (dbapi.OperationalError, dbapi.InterfaceError))
            ):
                raise
            raise StoreUnavailable(f"cannot store readings at t = {batch.t_s:g} s: {_first_line(exc)}") from None

    def _commit(self, batch: Batch) -> None:
        """Write the batch (see commit)."""
        temps = self._temperature_rows(batch)
        wide = self._block_arrays(batch)
        errs = self._error_rows(batch)
        conds = [
            {"campaign_id": self.cid, "time_s": t, **{k: s.get(k) for k in STATE_KEYS}, "campaign_start_day": self.day}
            for t, s in batch.states
        ]
        missing = [
            Fault(t, f"point {p.index}", "laser", f"{term}: {r.flag}")
            for p, t, values in batch.points
            for term, r in values.items()
            if not r.ok
        ]
        finished = batch.cursor.next_scan >= self.plan.n_scans and batch.cursor.next_point >= self.n_points
        with write_transaction(self.engine) as conn:
            if temps:
                bulk_insert(conn, "temperature_samples", TEMPERATURE_COLUMNS, TEMPERATURE_TYPES, temps)
            if wide is not None:
                self._insert_blocks(conn, wide)
            _insert_rows(conn, self._ins_cond, conds)
            _insert_rows(conn, self._ins_err, errs)
            prog, progress = self._progress(batch, [*batch.faults, *missing])
            conn.execute(self._upd_prog, {"_campaign_id": self.cid, **progress})
            self._advance_stages(conn, batch.stage, finished)
        self._prog = prog  # only once committed: a failed batch leaves the in-memory cursor where the store's is

    def _progress(self, batch: Batch, faults: list[Fault]) -> tuple[dict[str, Any], dict[str, Any]]:
        """Return the campaign's cursor document after the batch and its acquisition_progress values."""
        prog = dict(self._prog)  # this sink is the campaign's only writer: no read-back needed
        prog["next_scan"], prog["next_point"] = batch.cursor.next_scan, batch.cursor.next_point
        if faults:
            prog["faults"] = int(prog.get("faults", 0)) + len(faults)
            recent = list(prog.get("recent_faults", [])) + [
                {"t_s": f.t_s, "step": f.step, "instrument": f.instrument, "message": f.message} for f in faults
            ]
            prog["recent_faults"] = recent[-20:]
        if batch.datum is not None:
            prog["datum"] = batch.datum
        last = _last_scan(batch)
        if last is not None:
            prog["last_scan"] = {
                "t_s": last.t_s,
                "values": {
                    k: (v if k not in last.flags and math.isfinite(v) else None) for k, v in last.values.items()
                },
            }
        if batch.points:
            p, t, values = batch.points[-1]
            prog["last_point"] = {
                "t_s": t,
                "axis": p.axis,
                "position": p.position,
                "direction": p.direction,
                "values": {k: (r.value if r.ok else None) for k, r in values.items()},
            }
            prog["sweep"] = self.sweeps[(p.stage, p.sweep)]
        progress = {
            "cursor": prog,
            "stage_ordinal": batch.stage,
            "sweep": int(prog.get("sweep", 0)),
            "updated_at": _utcnow(),
        }
        t_read = last_reading_s(batch)
        if t_read is not None:  # a batch of moves and faults alone stores no sample: the time stays
            progress["last_sample_time_s"] = t_read
        return prog, progress

    def _advance_stages(self, conn: Connection, stage: int, finished: bool) -> None:
        """Mark the stages before ``stage`` done and it running (once per stage); all done when ``finished``."""
        st = self._t_stage
        if stage != self._stage:
            conn.execute(
                st.update()
                .where(st.c.campaign_id == self.cid, st.c.ordinal < stage, st.c.status.in_(("planned", "running")))
                .values(status="done")
            )
            conn.execute(
                st.update().where(st.c.campaign_id == self.cid, st.c.ordinal == stage).values(status="running")
            )
            self._stage = stage
        if finished:
            conn.execute(
                st.update()
                .where(st.c.campaign_id == self.cid, st.c.status.in_(("planned", "running")))
                .values(status="done")
            )
            conn.execute(self._t_camp.update().where(self._t_camp.c.id == self.cid).values(status="done"))


def _insert_rows(conn: Connection, insert: Insert, rows: list[dict[str, Any]]) -> None:
    """Insert rows sharing their keys with ``insert`` (executemany); on SQLite in multi-row INSERTs instead.

    On SQLite each value goes through its column type's bind processor, as in SQLAlchemy's
    executemany (so the same values reach sqlite3), but the batch's rows go in a few multi-row
    statements (``insert_flat_sqlite``) instead of one step a row: the daemon's writer thread gives up
    the interpreter lock, and waits to get it back from the acquiring thread, a few times, not once a row.
    """
    if not rows:
        return
    if conn.dialect.name != "sqlite":
        conn.execute(insert, rows)
        return
    cols, dialect = list(rows[0]), conn.dialect
    table = insert.table
    procs = [(c, table.c[c].type.dialect_impl(dialect).bind_processor(dialect)) for c in cols]
    flat: list[Any] = []
    for r in rows:
        flat.extend(r[c] if p is None else p(r[c]) for c, p in procs)
    cur = conn.connection.driver_connection.cursor()  # type: ignore[union-attr]
    try:
        head = f"INSERT INTO {table.name} ({', '.join(cols)}) VALUES "
        insert_flat_sqlite(cur, head, f"({', '.join('?' * len(cols))})", len(cols), flat)
    finally:
        cur.close()


def last_reading_s(batch: Batch) -> float | None:
    """Return the time of the batch's latest stored sample (scan, state or error reading), None without one.

    The batch's own ``t_s`` is the time of its last step, which may be a move command that stores nothing.
    """
    times = [scan.t_s for _, scan in batch.scans] + [t for t, _ in batch.states]
    times += [float(b.t_s[-1]) for b in batch.blocks if len(b)]
    times += [t for _, t, values in batch.points if any(r.ok for r in values.values())]
    return max(times) if times else None


def _last_scan(batch: Batch) -> TemperatureScan | None:
    """Return the latest scan of the batch (single or block-read), None when it has none."""
    cands = []
    if batch.scans:
        cands.append(batch.scans[-1][1])
    if batch.blocks and len(batch.blocks[-1]):
        blk = batch.blocks[-1]
        cands.append(blk.scan(len(blk) - 1))
    return max(cands, key=lambda s: s.t_s) if cands else None


def _first_line(exc: BaseException) -> str:
    """Return the first line of a database error's own message."""
    orig = getattr(exc, "orig", None) or exc
    text = str(orig).strip()
    return text.splitlines()[0] if text else type(orig).__name__


def _utcnow() -> datetime:
    """Return the current UTC time (the store's timestamp convention)."""
    return sc.utcnow()
