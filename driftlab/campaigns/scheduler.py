"""The resumable scheduler: runs a campaign plan against instruments and stores every reading as it arrives.

The plan compiles to a timeline of steps (`driftlab.campaigns.plan.steps`); the
scheduler waits for each step's time on its clock, performs it on the rig
(the instruments, real or simulated, through the DAQ protocols) and hands the
readings to a sink, which commits them *together with the cursor* (the next
scan and sweep point still to do) in one transaction. After any interruption,
``kill -9`` included, the stored cursor says exactly which readings are in the
store: a resumed run starts there, so no reading is lost or stored twice. On a
simulated machine the readings are a function of the step's simulated time, so
a resumed campaign ends with exactly the rows of one that was never interrupted.

Readings are committed as soon as the scheduler would otherwise wait for the
next step; when it runs behind (accelerated time) consecutive readings share a
transaction of at most ``max_batch`` scans or ``flush_s`` seconds of work, which
keeps transactions small while letting it catch up; a sweep is committed as soon
as its last point is measured.

Block mode (a card with a pacer and a scan buffer, on a fast simulated clock): a run
of consecutive scans is read as one buffered block (``FETC?``: one exchange and one
vectorised conversion for up to ``max_batch`` scans), and a writer thread commits each
batch while the next blocks are read; batches commit in order and, after a failed
one, nothing more is committed, so the stored cursor never skips a reading.

Interrupts (the lost/duplicated-rows reports of other acquisition tools after a
Ctrl-C): every write is one transaction (``db.write_transaction``: one BEGIN, a
rollback on any exception); SIGINT/SIGTERM only set a stop flag that the loop
reads between steps, so a signal never lands inside a write; and SIGKILL or a
crash can only lose a transaction that had not committed, whose readings the
stored cursor still lists as to do.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from itertools import chain, repeat
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from driftlab.campaigns.clock import Clock
from driftlab.campaigns.db import write_transaction
from driftlab.campaigns.plan import Cursor, Move, Plan, Scan, Stage, StageStart, SweepPoint, steps
from driftlab.daq.protocols import BlockScanner, Reading, ScanBlock, TemperatureScan, TemperatureScanner
from driftlab.errors import ConflictError, DriftlabError, InstrumentError

log = logging.getLogger(__name__)


# -- what the scheduler drives and where it writes -------------------------------------------------


class Rig(Protocol):
    """The instruments of one machine as the scheduler uses them (real or simulated)."""

    scanner: TemperatureScanner

    def apply_stage(self, stage: Stage, t_s: float) -> None:
        """Set the machine to the stage's conditions (spindle, oscillating axis, holding motor)."""

    def machine_state(self) -> dict[str, float]:
        """Return spindle_rpm, feed_mm_min and the axis positions x, y, z (mm), a, b (deg)."""

    def move_to(self, point: SweepPoint) -> None:
        """Command the move to a sweep point, arriving from its approach direction (does not wait)."""

    def measure_point(self, point: SweepPoint) -> dict[str, Reading]:
        """Return the error term measured at the point (the axis has been moved there)."""

    def take_datum(self) -> dict[str, Any] | None:
        """Return the laser datum set since the last call (to be stored with the batch), else None."""

    def close(self) -> None:
        """Release the instruments."""


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


# -- run statistics ---------------------------------------------------------------------------------


@dataclass
class RunStats:
    """What one run of the scheduler did, with the figures the benchmark reports."""

    scans: int = 0
    points: int = 0
    commits: int = 0
    faults: int = 0
    wall_s: float = 0.0
    sim_s: float = 0.0
    max_lag_s: float = 0.0
    # the most recent figures only: a campaign of days at 10 Hz must not grow the daemon's memory
    latencies_s: deque[float] = field(default_factory=lambda: deque(maxlen=200_000))
    commit_s: deque[float] = field(default_factory=lambda: deque(maxlen=200_000))
    finished: bool = False

    def p99_commit_s(self) -> float:
        """Return the 99th percentile of commit (write transaction) durations."""
        return percentile(self.commit_s, 99.0)

    def p99_latency_s(self) -> float:
        """Return the 99th percentile of reading-to-committed latency (0 when nothing was stored)."""
        return percentile(self.latencies_s, 99.0)

    def scans_per_s(self) -> float:
        """Return scans stored per wall-clock second."""
        return self.scans / self.wall_s if self.wall_s > 0 else 0.0


def percentile(values: Iterable[float], q: float) -> float:
    """Return the q-th percentile (nearest rank) of values, 0 for none."""
    if not values:
        return 0.0
    ordered = sorted(values)
    rank = max(0, min(len(ordered) - 1, math.ceil(q / 100.0 * len(ordered)) - 1))
    return ordered[rank]


# -- the steps --------------------------------------------------------------------------------------


def start_stage(rig: Rig, plan: Plan, step: StageStart) -> Stage:
    """Set the machine to the conditions of `step.stage` and return that stage."""
    stage = plan.stages[step.stage]
    log.info("stage %d %s (%s) at t=%.0f s", step.stage, stage.name, stage.heat_label(), step.t_s)
    rig.apply_stage(stage, step.t_s)
    return stage


def read_scan(rig: Rig) -> TemperatureScan:
    """Return one thermocouple scan of every channel."""
    return rig.scanner.scan()


def read_state(rig: Rig) -> dict[str, float]:
    """Return the machine state to log (spindle speed, feed, positions)."""
    return rig.machine_state()


def move_to_point(rig: Rig, point: SweepPoint) -> None:
    """Command the move to a sweep point ahead of its reading (returns at once)."""
    rig.move_to(point)


def measure_point(rig: Rig, point: SweepPoint) -> dict[str, Reading]:
    """Return the error terms measured at one sweep point."""
    return rig.measure_point(point)


# -- the engine -------------------------------------------------------------------------------------


class Scheduler:
    """Runs a plan from a cursor to the end (or until stopped), committing readings through a sink."""

    def __init__(
        self,
        plan: Plan,
        rig: Rig,
        sink: Sink,
        clock: Clock,
        cursor: Cursor = Cursor(),
        *,
        max_batch: int = 200,
        flush_s: float = 0.05,
        on_commit: Callable[[Batch, RunStats], None] | None = None,
        stop: threading.Event | None = None,
        pipeline: bool = True,
    ) -> None:
        self.plan = plan
        self.rig = rig
        self.sink = sink
        self.clock = clock
        self.cursor = cursor
        self.max_batch = max_batch
        self.flush_s = flush_s
        self.on_commit = on_commit
        self.stop = stop or threading.Event()
        self.points = plan.sweep_points()
        self.stats = RunStats()
        self._paced = False  # the card's pacer is started at the first block read
        self.pipeline = pipeline
        self._queue: queue.Queue[Batch | None] | None = None  # batches waiting for the writer thread
        self._writer_error: BaseException | None = None
        self._abandon = False
        self._stage = plan.stage_at(0.0)

    def _flush(self, batch: Batch) -> Batch:
        """Commit `batch` (readings + cursor), or hand it to the writer thread, and return a fresh one."""
        if batch.empty():
            return batch
        if self._queue is not None:
            self._raise_writer_error()
            self._queue.put(batch)  # blocks while the writer is two batches behind: back-pressure
            return Batch(cursor=batch.cursor, stage=batch.stage, t_s=batch.t_s)
        self._store(batch)
        return Batch(cursor=batch.cursor, stage=batch.stage, t_s=batch.t_s)

    def _raise_writer_error(self) -> None:
        """Re-raise, in the acquiring thread, the error that stopped the writer thread."""
        if self._writer_error is not None:
            raise self._writer_error

    def _writer(self) -> None:
        """Commit queued batches in order; after a failure commit nothing more (the cursor must not skip it)."""
        assert self._queue is not None
        while True:
            batch = self._queue.get()
            if batch is None:
                return
            if self._writer_error is not None or self._abandon:
                continue
            try:
                self._store(batch)
            except BaseException as exc:  # noqa: BLE001 - handed to the acquiring thread
                self._writer_error = exc

    def _store(self, batch: Batch) -> None:
        """Commit `batch` (with retries on an unreachable store) and account for it."""
        t0 = time.monotonic()
        self._commit_with_retry(batch)
        done = time.monotonic()
        self.stats.commits += 1
        self.stats.commit_s.append(done - t0)
        self.stats.latencies_s.extend([done - batch.first_wall] * max(1, batch.n_readings()))
        self.stats.scans += batch.n_scans()
        self.stats.points += len(batch.points)
        self.stats.faults += len(batch.faults)
        if self.on_commit is not None:
            self.on_commit(batch, self.stats)

    def _commit_with_retry(self, batch: Batch) -> None:
        """Commit the batch; a store that is unreachable for a moment is retried, anything else raised.

        A failed transaction stored nothing (the cursor did not move either), so committing the same
        batch again is safe; if it keeps failing the daemon stops and `--resume` continues later.
        """
        delays = (0.1, 0.5, 2.0, 5.0)
        for attempt in range(len(delays) + 1):
            try:
                self.sink.commit(batch)
                return
            except StoreUnavailable as exc:
                if attempt == len(delays):
                    raise
                log.warning("%s; retry %d in %.1f s", exc.one_line(), attempt + 1, delays[attempt])
                if self.stop.wait(delays[attempt]):
                    raise

    def _due(self, t_s: float) -> bool:
        """Return True when step time t_s is already due (no waiting needed before it)."""
        if self.clock.simulated:
            pace = getattr(self.clock, "pace_s", None)
            return pace is None or pace() >= t_s
        return self.clock.now() >= t_s

    def run(self) -> RunStats:
        """Run the remaining steps; return the statistics (``finished`` when the plan is complete)."""
        anchor = getattr(self.clock, "anchor", None)
        if anchor is not None:
            anchor()  # setting up the instruments is not time the campaign fell behind
        wall0 = time.monotonic()
        sim0 = None
        batch = Batch(cursor=self.cursor, stage=self._stage)
        block = self.block_scans()
        writer = None
        if block > 1 and self.pipeline:
            # acquisition and database writes overlap: blocks are read while the previous batch commits
            self._queue = queue.Queue(maxsize=2)
            writer = threading.Thread(target=self._writer, name="scheduler-writer", daemon=True)
            writer.start()
        clean = False
        try:
            it = _Lookahead(steps(self.plan, self.cursor, self.points))
            for step in it:
                if self.stop.is_set():
                    break
                run: list[Scan] = []
                if block > 1 and isinstance(step, Scan):
                    # a run of consecutive scans (nothing else due between them) is read as one block
                    run.append(step)
                    while len(run) < block and isinstance(it.peek(), Scan):
                        run.append(next(it))
                last = run[-1] if run else step
                if not self._due(last.t_s):
                    batch = self._flush(batch)  # idle ahead of time: store what we have now
                    if self._sleep_until(last.t_s):
                        break
                t = self.clock.wait_until(last.t_s)
                sim0 = (run[0].t_s if run else t) if sim0 is None else sim0
                if not batch.first_wall:
                    batch.first_wall = time.monotonic()
                if run:
                    self._do_block(run, t, batch)
                else:
                    self._do(step, t, batch)
                batch.t_s = t
                if (
                    batch.n_scans() >= self.max_batch
                    or self._sweep_ended(batch)
                    or time.monotonic() - batch.first_wall >= self.flush_s
                ):
                    batch = self._flush(batch)
            else:
                batch = self._flush(batch)
                self.stats.finished = True
            batch = self._flush(batch)
            clean = True
        finally:
            if writer is not None and self._queue is not None:
                self._abandon = not clean  # an error or a second interrupt: commit nothing more
                self._queue.put(None)
                writer.join()
                self._queue = None
            self.stats.wall_s = time.monotonic() - wall0
            self.stats.sim_s = (batch.t_s - sim0) if sim0 is not None else 0.0
            max_lag = getattr(self.clock, "max_lag_s", None)
            self.stats.max_lag_s = max_lag() if max_lag else 0.0
        if self._writer_error is not None:
            self.stats.finished = False
            raise self._writer_error
        self.cursor = batch.cursor
        return self.stats

    def _sweep_ended(self, batch: Batch) -> bool:
        """Return True when the batch holds the last point of a sweep (a finished sweep is committed at once)."""
        if not batch.points:
            return False
        p = batch.points[-1][0]
        nxt = p.index + 1
        return nxt >= len(self.points) or (self.points[nxt].stage, self.points[nxt].sweep) != (p.stage, p.sweep)

    def block_scans(self) -> int:
        """Return how many scans to read per block: 1 (scan by scan) unless the card buffers and time runs fast.

        On a simulated clock the card's pacer runs ahead of the host, so the host reads what
        `flush_s` of wall-clock time brings at once (at most `max_batch` scans); on a real clock
        at real scan rates scans are read one by one as they are taken.
        """
        if not (isinstance(self.rig.scanner, BlockScanner) and self.clock.simulated):
            return 1
        speed = getattr(self.clock, "speed", math.inf)
        per_flush = self.flush_s * speed / self.plan.scan_interval_s
        return int(max(1, min(self.max_batch, per_flush)))

    def _do_block(self, run: list[Scan], t_last: float, batch: Batch) -> None:
        """Read a run of consecutive scans as one buffered block (states at each scan's own time) into the batch."""
        for step in run:
            if step.log_state:
                self.clock.set(step.t_s)  # the controller answers for the scan's instant, as scan by scan
                try:
                    batch.states.append((step.t_s, read_state(self.rig)))
                except InstrumentError as exc:
                    batch.faults.append(Fault(step.t_s, f"state {step.index}", "machine_link", exc.one_line()))
        self.clock.set(t_last)
        first, n = run[0].index, len(run)
        scanner = self.rig.scanner
        try:
            if not self._paced:
                scanner.pace(self.plan.scan_interval_s)  # type: ignore[attr-defined]
                self._paced = True
            blk = scanner.scan_block(first, n)  # type: ignore[attr-defined]
            times = np.array([s.t_s for s in run])
            batch.blocks.append(ScanBlock(first, times, blk.channels, blk.values, blk.open))
        except InstrumentError as exc:
            what = f"scan {first}" if n == 1 else f"scans {first}-{first + n - 1}"
            batch.faults.append(Fault(run[0].t_s, what, "thermocouple", exc.one_line()))
        batch.cursor = Cursor(first + n, batch.cursor.next_point)

    def _sleep_until(self, t_s: float) -> bool:
        """Wait (interruptibly) until just before t_s is due; return True when asked to stop."""
        while not self._due(t_s):
            if self.clock.simulated:
                speed = getattr(self.clock, "speed", math.inf)
                remaining = (t_s - self.clock.pace_s()) / speed  # type: ignore[attr-defined]
            else:
                remaining = t_s - self.clock.now()
            if self.stop.wait(min(max(remaining, 0.0), 0.5)):
                return True
        return False

    def _do(self, step: StageStart | Scan | SweepPoint | Move, t: float, batch: Batch) -> None:
        """Perform one step and add its readings (or its fault) to the batch, advancing the cursor."""
        if isinstance(step, Move):
            try:
                move_to_point(self.rig, self.points[step.point])
            except InstrumentError as exc:
                batch.faults.append(Fault(t, f"move {step.point}", "machine_link", exc.one_line()))
            return
        if isinstance(step, StageStart):
            self._stage = step.stage
            batch.stage = step.stage
            try:
                start_stage(self.rig, self.plan, step)
            except InstrumentError as exc:
                batch.faults.append(Fault(t, f"stage {step.stage}", "machine_link", exc.one_line()))
            return
        if isinstance(step, Scan):
            try:
                scan = read_scan(self.rig)
                batch.scans.append((step.index, _at(scan, t)))
            except InstrumentError as exc:
                batch.faults.append(Fault(t, f"scan {step.index}", "thermocouple", exc.one_line()))
            if step.log_state:
                try:
                    batch.states.append((t, read_state(self.rig)))
                except InstrumentError as exc:
                    batch.faults.append(Fault(t, f"state {step.index}", "machine_link", exc.one_line()))
            batch.cursor = Cursor(step.index + 1, batch.cursor.next_point)
            return
        try:
            values = measure_point(self.rig, step)
            batch.points.append((step, t, values))
        except InstrumentError as exc:
            batch.faults.append(Fault(t, f"point {step.index}", "laser", exc.one_line()))
        datum = self.rig.take_datum()
        if datum is not None:
            batch.datum = datum
        batch.cursor = Cursor(batch.cursor.next_scan, step.index + 1)


class _Lookahead:
    """An iterator with a one-step peek (the scheduler groups consecutive scans into blocks)."""

    _END = object()

    def __init__(self, it: Iterable[Any]) -> None:
        self._it = iter(it)
        self._next: Any = self._END

    def __iter__(self) -> _Lookahead:
        return self

    def __next__(self) -> Any:
        if self._next is not self._END:
            item, self._next = self._next, self._END
            return item
        return next(self._it)

    def peek(self) -> Any:
        """Return the next step without consuming it (None at the end)."""
        if self._next is self._END:
            try:
                self._next = next(self._it)
            except StopIteration:
                return None
        return self._next


def _at(scan: TemperatureScan, t_s: float) -> TemperatureScan:
    """Return the scan stamped with the step's time (the clock's, not the driver's own)."""
    if scan.t_s == t_s:
        return scan
    return TemperatureScan(t_s=t_s, values=scan.values, flags=scan.flags)


def readings_mean(readings: list[Reading]) -> Reading:
    """Return the mean of the valid readings, or a missing reading flagged as the first fault."""
    ok = [r.value for r in readings if r.ok]
    if ok:
        return Reading(math.fsum(ok) / len(ok))
    flag = next((r.flag for r in readings if r.flag), "no_reading")
    return Reading.missing(flag)


def term_means(samples: list[Mapping[str, Reading]]) -> dict[str, Reading]:
    """Return per term the mean of repeated readings (ch. 5.5: ten readings per point, averaged)."""
    terms = sorted({k for s in samples for k in s})
    return {k: readings_mean([s[k] for s in samples if k in s]) for k in terms}


# -- the store side: campaigns opened by the daemon, batches committed with their cursor ------------

TERMS = ("alpha", "beta", "gamma", "dx", "dy", "dz")
STATE_KEYS = ("spindle_rpm", "feed_mm_min", "x", "y", "z", "a", "b")


@dataclass(frozen=True)
class CampaignHandle:
    """A campaign row the daemon writes into, with its channel ids and the cursor to resume from."""

    campaign_id: int
    cursor: Cursor
    channel_ids: dict[str, int]
    resumed: bool
    progress: dict[str, Any] = field(default_factory=dict)


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
    to resume one whose plan timeline has changed since it started.
    """
    from sqlalchemy import select

    from driftlab.campaigns import schema as sc

    fp = plan.fingerprint()
    with write_transaction(engine) as conn:
        row = conn.execute(
            select(sc.Campaign.id, sc.Campaign.status, sc.AcquisitionProgress.cursor)
            .join(sc.AcquisitionProgress, sc.AcquisitionProgress.campaign_id == sc.Campaign.id)
            .where(sc.Campaign.name == plan.name, sc.Campaign.source == "daemon")
            .order_by(sc.Campaign.id.desc())
        ).first()
        if row is not None and (row.status == "running" or (resume and row.status == "done")):
            cid, cur = row.id, dict(row.cursor or {})
            if not resume:
                raise ConflictError(
                    f"campaign {plan.name!r} (id {cid}) is unfinished: continue it with --resume"
                )
            if cur.get("fingerprint") != fp:
                raise ConflictError(
                    f"campaign {plan.name!r} (id {cid}) was started from a different plan timeline: "
                    "resume it with the plan it started with"
                )
            ids = dict(
                conn.execute(select(sc.Channel.name, sc.Channel.id).where(sc.Channel.campaign_id == cid)).all()
            )
            if row.status == "done":
                log.info("campaign %s (id %d) is already complete", plan.name, cid)
            return CampaignHandle(cid, Cursor(int(cur["next_scan"]), int(cur["next_point"])), ids, True, cur)
        if resume:
            log.info("no unfinished campaign %s: starting it", plan.name)
        if conn.execute(select(sc.Machine.id).where(sc.Machine.id == plan.machine.id)).first() is None:
            conn.execute(sc.Machine.__table__.insert().values(
            id=plan.machine.id, name=plan.machine.name or str((extra_meta or {}).get("machine", {}).get("name", ""))))
        started = sc.utcnow()
        meta = {
            "format": "driftlab-bundle/1",
            "machine": {"id": plan.machine.id, "name": plan.machine.name},
            "started_at": started.strftime("%Y-%m-%dT%H:%M:%SZ"),
            "channels": {k: dict(v) for k, v in channels.items()},
            "room_channels": list(room_channels),
            "stages": plan.bundle_stages(),
        }
        for key, value in (extra_meta or {}).items():
            meta.setdefault(key, value) if key != "machine" else meta["machine"].update(
                {k: v for k, v in value.items() if k != "id" and (k != "name" or not plan.machine.name)}
            )
        cid = conn.execute(
            sc.Campaign.__table__.insert().values(
                machine_id=plan.machine.id, name=plan.name, started_at=started, status="running",
                source="daemon", meta=meta, conditions_columns=["time_s", *STATE_KEYS],
            )
        ).inserted_primary_key[0]
        conn.execute(
            sc.Stage.__table__.insert(),
            [
                {"campaign_id": cid, "ordinal": i, "name": r["name"], "heat_source": r["heat_source"],
                 "axis": r["axis"], "spindle_rpm": r["spindle_rpm"], "feed_mm_min": r["feed_mm_min"],
                 "start_s": r["start_s"], "end_s": r["end_s"], "status": "planned"}
                for i, r in enumerate(plan.bundle_stages())
            ],
        )
        conn.execute(
            sc.Channel.__table__.insert(),
            [
                {"campaign_id": cid, "ordinal": i, "name": name, "location": info.get("location", ""),
                 "structure": info.get("structure", ""), "is_room": name in room_channels}
                for i, (name, info) in enumerate(channels.items())
            ],
        )
        cursor = {"next_scan": 0, "next_point": 0, "n_scans": plan.n_scans, "n_points": len(plan.sweep_points()),
                  "total_s": plan.total_s, "fingerprint": fp, "plan": plan.name,
                  "origin": dict(origin), "faults": 0, "recent_faults": []}
        conn.execute(
            sc.AcquisitionProgress.__table__.insert().values(
                campaign_id=cid, stage_ordinal=0, sweep=0, last_sample_time_s=None, cursor=cursor,
                updated_at=sc.utcnow(),
            )
        )
        ids = dict(conn.execute(select(sc.Channel.name, sc.Channel.id).where(sc.Channel.campaign_id == cid)).all())
    log.info("campaign %s created (id %d)", plan.name, cid)
    return CampaignHandle(cid, Cursor(), ids, False, cursor)


class StoreUnavailable(DriftlabError):
    """The store could not be reached or was locked for a write (worth retrying the same batch)."""

    http_status = 503


class StoreSink:
    """Commits a batch of readings and the campaign's cursor in one database transaction."""

    def __init__(self, engine: Any, plan: Plan, handle: CampaignHandle) -> None:
        from driftlab.campaigns import schema as sc

        self.engine = engine
        self.plan = plan
        self.cid = handle.campaign_id
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
        self._stage = -1

    def _temperature_rows(self, batch: Batch) -> list[tuple[int, int, float, float | None]]:
        """Return (campaign_id, channel_id, time_s, value) rows of the batch (None: flagged or non-finite)."""
        rows = []
        cid, ids, isfinite = self.cid, self.channel_ids, math.isfinite
        for _, scan in batch.scans:
            t, flags = scan.t_s, scan.flags
            for name, value in scan.values.items():
                ch = ids.get(name)
                if ch is not None:
                    rows.append((cid, ch, t, value if isfinite(value) and name not in flags else None))
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
        from driftlab.campaigns.ingest import bulk_insert, copy_temperatures_pg

        ids, names, times, values = arrays
        if conn.dialect.name == "postgresql":
            import pandas as pd

            frame = pd.DataFrame(values, columns=names)
            frame.insert(0, "time_s", times)
            copy_temperatures_pg(conn, self.cid, ids, frame)  # numpy-encoded binary COPY
            return
        # executemany over C-level zips: no Python frame per row (sqlite stores a bound NaN as NULL)
        n, t = len(times), times.tolist()
        rows = chain.from_iterable(
            zip(repeat(self.cid, n), repeat(ch, n), t, col) for ch, col in zip(ids, values.T.tolist())
        )
        bulk_insert(conn, "temperature_samples", ("campaign_id", "channel_id", "time_s", "value"),
                    ("int4", "int4", "float8", "float8"), rows)

    def _error_rows(self, batch: Batch) -> list[dict[str, Any]]:
        """Return the error rows of the batch; a flagged (missing) term is not stored (it is a fault)."""
        rows = []
        for p, t, values in batch.points:
            for term, r in values.items():
                if not r.ok:
                    continue
                rows.append({
                    "campaign_id": self.cid, "seq": p.index * len(TERMS) + TERMS.index(term), "time_s": t,
                    "axis": p.axis, "term": term, "position": p.position, "direction": p.direction,
                    "value": r.value, "sweep": self.sweeps[(p.stage, p.sweep)], "flags": 0,
                })
        return rows

    def commit(self, batch: Batch) -> None:
        """Insert the batch's rows and move the cursor, stage status and fault log, all in one transaction.

        Raises ConflictError when a reading of the batch is already stored (never a second copy) and
        StoreUnavailable when the database could not be reached; either way nothing was stored.
        """
        from sqlalchemy.exc import DBAPIError, IntegrityError

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
        from driftlab.campaigns.ingest import bulk_insert

        temps = self._temperature_rows(batch)
        wide = self._block_arrays(batch)
        errs = self._error_rows(batch)
        conds = [{"campaign_id": self.cid, "time_s": t, **{k: s.get(k) for k in STATE_KEYS}} for t, s in batch.states]
        missing = [
            Fault(t, f"point {p.index}", "laser", f"{term}: {r.flag}")
            for p, t, values in batch.points for term, r in values.items() if not r.ok
        ]
        faults = [*batch.faults, *missing]
        finished = batch.cursor.next_scan >= self.plan.n_scans and batch.cursor.next_point >= self.n_points
        with write_transaction(self.engine) as conn:
            if temps:
                bulk_insert(conn, "temperature_samples", ("campaign_id", "channel_id", "time_s", "value"),
                            ("int4", "int4", "float8", "float8"), temps)
            if wide is not None:
                self._insert_blocks(conn, wide)
            if conds:
                conn.execute(self._t_cond.insert(), conds)
            if errs:
                conn.execute(self._t_err.insert(), errs)
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
                prog["last_scan"] = {"t_s": last.t_s, "values": {
                    k: (v if k not in last.flags and math.isfinite(v) else None) for k, v in last.values.items()}}
            if batch.points:
                p, t, values = batch.points[-1]
                prog["last_point"] = {"t_s": t, "axis": p.axis, "position": p.position, "direction": p.direction,
                                      "values": {k: (r.value if r.ok else None) for k, r in values.items()}}
                prog["sweep"] = self.sweeps[(p.stage, p.sweep)]
            conn.execute(
                self._t_prog.update().where(self._t_prog.c.campaign_id == self.cid).values(
                    cursor=prog, stage_ordinal=batch.stage, sweep=int(prog.get("sweep", 0)),
                    last_sample_time_s=batch.t_s, updated_at=_utcnow(),
                )
            )
            if batch.stage != self._stage:
                conn.execute(self._t_stage.update().where(
                    self._t_stage.c.campaign_id == self.cid, self._t_stage.c.ordinal < batch.stage,
                    self._t_stage.c.status.in_(("planned", "running"))).values(status="done"))
                conn.execute(self._t_stage.update().where(
                    self._t_stage.c.campaign_id == self.cid, self._t_stage.c.ordinal == batch.stage).values(
                    status="running"))
                self._stage = batch.stage
            if finished:
                conn.execute(self._t_stage.update().where(
                    self._t_stage.c.campaign_id == self.cid, self._t_stage.c.status.in_(("planned", "running"))
                ).values(status="done"))
                conn.execute(self._t_camp.update().where(self._t_camp.c.id == self.cid).values(status="done"))
        self._prog = prog  # only once committed: a failed batch leaves the in-memory cursor where the store's is


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


def _utcnow() -> Any:
    """Return the current UTC time (the store's timestamp convention)."""
    from driftlab.campaigns.schema import utcnow

    return utcnow()


# -- the rig on real drivers (the same drivers talk to the simulated servers) ------------------------


def stage_program(stage: Stage) -> list[str]:
    """Return the motion code that sets a stage's spindle (the heat cycles run as the controller's own program)."""
    rpm = stage.spindle_rpm()
    return [f"(stage {stage.name}: {stage.heat_label()})", f"S{rpm:.0f} M03" if rpm > 0 else "M05"]


def approach_program(point: SweepPoint, overtravel: float = 2.0, feed_mm_min: float = 2000.0) -> list[str]:
    """Return the motion code that reaches a sweep point from its approach side (ch. 5.5: backlash)."""
    before = point.position - point.direction * overtravel
    return [
        f"G00 {point.axis}{before:.4f}",
        f"G01 {point.axis}{point.position:.4f} F{feed_mm_min:.0f}",
        "G04 P0.5 (settle before reading, ch. 5.5)",
    ]


class InstrumentRig:
    """A Rig on the DAQ drivers: thermocouple card, laser interferometer and the controller link.

    The laser is referenced (zeroed) once per set-up, at the first point it measures, so that every
    later reading refers to the state at the start of the test (ch. 5.5); the datum is stored with
    the readings. A resumed simulated run restores the simulated head's datum, as the real head keeps
    its count while the PC restarts; a real one whose head lost it is referenced afresh.
    """

    def __init__(
        self,
        plan: Plan,
        scanner: TemperatureScanner,
        laser: Any | None,
        link: Any | None,
        *,
        clock: Clock,
        datum: Mapping[str, Any] | None = None,
        laser_server: Any | None = None,
        closers: list[Callable[[], None]] | None = None,
        servers: Mapping[str, Any] | None = None,
    ) -> None:
        self.plan = plan
        self.servers = dict(servers or {})  # simulated instrument servers by role (fault injection in tests)
        self.scanner = scanner
        self.laser = laser
        self.link = link
        self.clock = clock
        self.laser_server = laser_server
        self._saved = dict(datum) if datum else None
        self._new_datum: dict[str, Any] | None = None
        self._closers = list(closers or [])
        self._stage: Stage | None = None
        # Axis positions read while the controller was known to be at rest: every block sent so far
        # executed, no heat cycle of the stage moving an axis. Nothing can move them until the rig
        # itself sends motion again, so the machine-state log need not ask for them at every scan.
        self._rest_positions: dict[str, float] | None = None
        self._at_rest = False

    def _moving(self) -> None:
        """Forget the positions at rest: motion (or a program) was just sent."""
        self._at_rest = False
        self._rest_positions = None

    def apply_stage(self, stage: Stage, t_s: float) -> None:
        """Send the stage's spindle command to the controller."""
        self._stage = stage
        self._moving()
        if self.link is not None:
            self.link.send_program(stage_program(stage), wait=False)

    def machine_state(self) -> dict[str, float]:
        """Return the commanded spindle speed and feed with the controller's axis positions."""
        stage = self._stage
        state = {"spindle_rpm": stage.spindle_rpm() if stage else 0.0,
                 "feed_mm_min": stage.feed_mm_min() if stage else 0.0}
        if self.link is not None:
            pos = self._rest_positions
            if pos is None:
                pos = {k.lower(): float(v) for k, v in self.link.position().items()}
                axis_heat = stage is not None and any(h.kind == "axis" for h in stage.heat)
                if self._at_rest and not axis_heat:
                    self._rest_positions = pos
            state.update(pos)
        return state

    def move_to(self, point: SweepPoint) -> None:
        """Queue the approach moves to the point on the controller."""
        self._moving()
        if self.link is not None:
            self.link.send_program(approach_program(point), wait=False)

    def _ensure_reference(self, point: SweepPoint) -> None:
        """Configure the optics for the point's term and make sure the head has its datum."""
        self.laser.configure(point.axis, point.term)
        if not self.laser.reference_lost:
            return
        saved = self._saved
        if saved is not None and (saved.get("axis"), saved.get("term")) == (point.axis, point.term) and (
            self.laser_server is not None and "error" in saved
        ):
            self.laser_server.restore_reference(saved["t_s"], saved["position"], saved["error"])
            self.laser.reference_lost = False
            self.laser.reference_position = float(saved["position"])
            self._saved = None
            return
        self.laser.reference(point.position)
        datum: dict[str, Any] = {"axis": point.axis, "term": point.term, "position": point.position,
                                 "t_s": self.clock.now()}
        ref = self.laser_server.datum() if self.laser_server is not None else None
        if ref is not None:
            datum.update(ref)
        self._saved = None
        self._new_datum = datum

    def measure_point(self, point: SweepPoint) -> dict[str, Reading]:
        """Wait for the move, then read the point's term with the laser (mean of `samples` readings)."""
        if self.laser is None:
            raise InstrumentError("no laser interferometer configured for error sweeps")
        if self.link is not None:
            self.link.wait_done()
            self._at_rest = True  # every block sent has executed
        self._ensure_reference(point)
        self.laser.readings_per_point = point.samples
        sample = self.laser.measure_error(point.axis, point.term, point.position, point.direction)
        return {point.term: Reading(sample.value, sample.flag)}

    def take_datum(self) -> dict[str, Any] | None:
        """Return the datum set since the last call, once."""
        datum, self._new_datum = self._new_datum, None
        return datum

    def close(self) -> None:
        """Close every instrument (and stop simulated servers)."""
        for close in reversed(self._closers):
            try:
                close()
            except Exception:  # noqa: BLE001 - closing must not mask the run's own outcome
                log.debug("error while closing an instrument", exc_info=True)


class MemoWorld:
    """The virtual machine behind a small cache: it is a pure function of its arguments, so asking twice is waste.

    A sweep point asks the world for the same error and room air a dozen times at one instant (the
    laser's settle polls and ten averaged readings); the cache answers the repeats exactly.
    """

    def __init__(self, world: Any, size: int = 64) -> None:
        from functools import lru_cache

        self.world = world
        self._temps = lru_cache(maxsize=size)(world.temperatures)
        self._errors = lru_cache(maxsize=size)(world.measure_error)

    def temperatures(self, t_s: float) -> dict[str, float]:
        """Return the world's thermocouple readings at t_s (a fresh dict each call)."""
        return dict(self._temps(float(t_s)))

    def measure_error(self, t_s: float, axis: str, position: float, direction: int) -> dict[str, float]:
        """Return the world's measured error terms at (t_s, axis, position, direction)."""
        return dict(self._errors(float(t_s), axis, float(position), int(direction)))

    def state(self, t_s: float) -> Any:
        """Return the world's machine state at t_s."""
        return self.world.state(t_s)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.world, name)


def _no_wait(_dt: float) -> None:
    """Do not wait: on a simulated clock time only moves between steps."""


def build_sim_rig(
    plan: Plan, scenario: Any, clock: Any, channels: list[str], datum: Mapping[str, Any] | None = None,
    world: Any | None = None, cursor: Cursor = Cursor(),
) -> InstrumentRig:
    """Return a rig whose real drivers talk to simulated servers reading the virtual machine at `clock`.

    On a resume the simulated hardware is put back as the real hardware would have stayed while the
    PC restarted: each axis where its last sweep point left it, the laser head on its datum.
    """
    import pyvisa

    from driftlab.daq.laser import LaserInterferometer
    from driftlab.daq.machine_link import SerialMachineLink
    from driftlab.daq.retry import RetryPolicy
    from driftlab.daq.sim.instruments import (
        SimController,
        SimLaser,
        SimThermocoupleCard,
        serial_url,
        visa_address,
    )
    from driftlab.daq.thermocouple import ThermocoupleCard
    from driftlab.daq.transport import LineChannel, VisaPort

    if world is None:
        from driftlab.daq.sim.machine import VirtualMachine

        world = MemoWorld(VirtualMachine(plan_scenario(plan, scenario)))
    card_map = dict(enumerate(channels))
    card = SimThermocoupleCard(world, clock, card_map).start()
    ctrl = SimController(world, clock)
    for axis, (pos, direction) in axis_positions(plan, cursor).items():
        ctrl.pos[axis], ctrl.direction[axis] = pos, direction
    ctrl.start()
    head = SimLaser(world, clock, ctrl).start()
    closers: list[Callable[[], None]] = [card.close, ctrl.close, head.close]
    try:
        rm = pyvisa.ResourceManager("@py")
        closers.append(rm.close)
        policy = RetryPolicy(attempts=3, base_delay_s=0.0)
        card_io = LineChannel(VisaPort.open(visa_address(card), resource_manager=rm), "thermocouple card",
                              policy, sleep=_no_wait)
        scanner = ThermocoupleCard(card_io, card_map, clock=clock.now)
        closers.append(card_io.close)
        laser_io = LineChannel(VisaPort.open(visa_address(head), resource_manager=rm), "laser", policy,
                               sleep=_no_wait)
        closers.append(laser_io.close)
        laser = LaserInterferometer(laser_io, sleep=_no_wait, max_settle_polls=20, burst=True)
        link = SerialMachineLink.open(serial_url(ctrl), sleep=_no_wait, max_idle_polls=2)
        closers.append(link.close)
    except Exception:
        for c in reversed(closers):
            c()
        raise
    return InstrumentRig(plan, scanner, laser, link, clock=clock, datum=datum, laser_server=head, closers=closers,
                         servers={"thermocouple": card, "laser": head, "controller": ctrl})


def axis_positions(plan: Plan, cursor: Cursor) -> dict[str, tuple[float, int]]:
    """Return where each swept axis was left (position, approach direction) before the cursor's next point."""
    out: dict[str, tuple[float, int]] = {}
    for p in plan.sweep_points()[: cursor.next_point]:
        out[p.axis] = (p.position, p.direction)
    return out


def build_real_rig(plan: Plan, channels: list[str], clock: Any) -> InstrumentRig:
    """Return a rig on the instruments named in the plan's `instruments:` section."""
    from driftlab.daq.laser import LaserInterferometer
    from driftlab.daq.machine_link import SerialMachineLink
    from driftlab.daq.thermocouple import ThermocoupleCard
    from driftlab.daq.transport import LineChannel, open_port
    from driftlab.errors import ValidationError

    inst = plan.instruments
    if not inst.thermocouple:
        raise ValidationError(f"plan {plan.name}: instruments.thermocouple is required without --sim")
    closers: list[Callable[[], None]] = []
    card_io = LineChannel(open_port(inst.thermocouple), "thermocouple card")
    closers.append(card_io.close)
    scanner = ThermocoupleCard(card_io, dict(enumerate(channels)), clock=clock.now)
    laser = link = None
    if inst.laser:
        laser_io = LineChannel(open_port(inst.laser), "laser")
        closers.append(laser_io.close)
        laser = LaserInterferometer(laser_io)
    if inst.machine_link:
        link = SerialMachineLink.open(inst.machine_link)
        closers.append(link.close)
    if any(s.sweep is not None for s in plan.stages) and laser is None:
        raise ValidationError(f"plan {plan.name}: sweeps need instruments.laser without --sim")
    return InstrumentRig(plan, scanner, laser, link, clock=clock, closers=closers)


# -- the daemon: everything wired together ----------------------------------------------------------


@dataclass
class DaemonResult:
    """The outcome of one daemon run."""

    campaign_id: int
    cursor: Cursor
    stats: RunStats
    resumed: bool


def store_engine(db_url: str | None) -> Any:
    """Return the SQLAlchemy engine of the campaign store at db_url (schema brought up to date)."""
    from driftlab.campaigns import db
    from driftlab.config import get_settings

    from sqlalchemy.exc import OperationalError

    url = db_url or get_settings().resolved_db_url()
    engine = db.make_engine(url)
    try:
        if db.current_revision(engine) != db.head_revision():
            db.upgrade(engine)
    except OperationalError as exc:
        where = engine.url.render_as_string(hide_password=True)
        raise db.StoreError(f"cannot open the store at {where}: {str(exc.orig).strip().splitlines()[0]}") from None
    return engine


def skip_missed(plan: Plan, cursor: Cursor, now_s: float) -> tuple[Cursor, int, int]:
    """Return the cursor moved past steps already in the past on a real clock, and how many were skipped."""
    points = plan.sweep_points()
    k = cursor.next_scan
    while k < plan.n_scans and plan.scan_time(k) < now_s:
        k += 1
    j = cursor.next_point
    while j < len(points) and points[j].t_s < now_s:
        j += 1
    return Cursor(k, j), k - cursor.next_scan, j - cursor.next_point


def sim_clock(plan: Plan, cursor: Cursor = Cursor(), speed: float = 3600.0) -> Any:
    """Return the simulated clock for running `plan` from `cursor`: it starts at the cursor's first step.

    Build it before the simulated rig: the servers take their starting time from it.
    """
    from driftlab.campaigns.clock import SimClock
    from driftlab.campaigns.plan import cursor_time

    return SimClock(speed=speed, start_s=cursor_time(plan, plan.sweep_points(), cursor))


def run_daemon(
    plan: Plan,
    *,
    db_url: str | None = None,
    scenario_path: Path | str | None = None,
    speed: float = 3600.0,
    resume: bool = False,
    stop: threading.Event | None = None,
    max_batch: int = 200,
    flush_s: float = 0.05,
    stop_after_commits: int | None = None,
    engine: Any | None = None,
    world: Any | None = None,
) -> DaemonResult:
    """Open (or resume) the plan's campaign in the store and run it on the simulated or real rig."""
    from driftlab.campaigns.clock import SimClock, WallClock
    from driftlab.campaigns.plan import cursor_time
    from driftlab.progress import progress

    engine = engine if engine is not None else store_engine(db_url)
    stop = stop or threading.Event()
    scenario = None
    if scenario_path is not None:
        from driftlab.daq.sim.scenario import load_scenario

        scenario = load_scenario(scenario_path)
    channels, rooms = resolve_channels(plan, scenario)
    origin = {"mode": "sim" if scenario is not None else "real",
              "scenario": str(scenario_path) if scenario_path is not None else None,
              "speed": None if math.isinf(speed) else speed}
    points = plan.sweep_points()
    if scenario is None:
        # open the instruments before touching the store: an unreachable instrument leaves no campaign behind
        clock: Any = WallClock()
        rig = build_real_rig(plan, list(channels), clock)
    extra = sim_meta(plan, scenario) if scenario is not None else None
    try:
        handle = open_campaign(engine, plan, channels, rooms, resume=resume, origin=origin, extra_meta=extra)
    except BaseException:
        if scenario is None:
            rig.close()
        raise
    cursor = handle.cursor
    if scenario is not None:
        clock = sim_clock(plan, cursor, speed)
        rig = build_sim_rig(plan, scenario, clock, list(channels), datum=handle.progress.get("datum"), world=world,
                            cursor=cursor)
    else:
        clock.started_epoch_s = _campaign_started_epoch(engine, handle.campaign_id)
        if handle.resumed:
            cursor, ns, np_ = skip_missed(plan, cursor, clock.now())
            if ns or np_:
                log.warning("skipped %d scans and %d sweep points missed while the daemon was down", ns, np_)
    sink = StoreSink(engine, plan, handle)
    total = plan.n_scans + len(points)
    commits = [0]
    try:
        with progress(f"{plan.name}", total=total) as bar:
            bar.advance(cursor.next_scan + cursor.next_point)

            def on_commit(batch: Batch, stats: RunStats) -> None:
                """Advance the progress bar; stop after the requested number of commits."""
                bar.advance(len(batch.scans) + len(batch.points))
                commits[0] += 1
                if stop_after_commits is not None and commits[0] >= stop_after_commits:
                    stop.set()

            sched = Scheduler(plan, rig, sink, clock, cursor, max_batch=max_batch, flush_s=flush_s,
                              on_commit=on_commit, stop=stop)
            stats = sched.run()
    finally:
        rig.close()
    if stats.finished:
        _summarise_finished(engine, handle.campaign_id)
    return DaemonResult(handle.campaign_id, sched.cursor, stats, handle.resumed)


def _summarise_finished(engine: Any, campaign_id: int) -> None:
    """Build the per-minute temperature rollups of a campaign that has just finished.

    Live campaigns are written scan by scan without rollups; once complete, the wide-bucket
    history queries (API, `driftlab drift`) read the rollups instead of every raw reading.
    """
    from driftlab.campaigns import ingest

    with write_transaction(engine) as conn:
        ingest.refresh_rollups(conn, campaign_id)


def _campaign_started_epoch(engine: Any, campaign_id: int) -> float:
    """Return the campaign's start as a Unix epoch (the origin of a real campaign's time_s)."""
    from sqlalchemy import select

    from driftlab.campaigns import schema as sc

    with engine.connect() as conn:
        started = conn.execute(select(sc.Campaign.started_at).where(sc.Campaign.id == campaign_id)).scalar_one()
    return started.timestamp()


def resolve_channels(plan: Plan, scenario: Any | None) -> tuple[dict[str, dict[str, str]], list[str]]:
    """Return the channel map (name -> location, structure) and room channels of the plan or scenario."""
    from driftlab.errors import ValidationError

    if isinstance(plan.machine.channels, dict):
        chans = {k: {"location": v.location, "structure": v.structure} for k, v in plan.machine.channels.items()}
        if scenario is not None:
            known = scenario_meta(scenario)["channels"]
            unknown = [k for k in chans if k not in known]
            if unknown:
                raise ValidationError(
                    f"plan {plan.name}: machine.channels: {', '.join(unknown[:5])} not on the virtual machine "
                    f"(it has {', '.join(list(known)[:3])} ... {list(known)[-1]})"
                )
        return chans, list(plan.machine.room_channels)
    if scenario is None:
        raise ValidationError(
            f"plan {plan.name}: machine.channels is 'from scenario' but no --sim scenario was given"
        )
    meta = scenario_meta(scenario)
    chans = {k: {"location": v.get("location", ""), "structure": v.get("structure", "")}
             for k, v in meta["channels"].items()}
    return chans, list(plan.machine.room_channels or meta.get("room_channels", []))


# -- status ------------------------------------------------------------------------------------------


def campaign_status(engine: Any, campaign: str | int | None = None) -> list[dict[str, Any]]:
    """Return the status of daemon campaigns (all, or one by id or name): stage, progress, last readings, faults."""
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
    from sqlalchemy.orm import Session

    out = []
    with Session(engine) as conn:
        rows = conn.execute(q).all()
        for camp, prog in rows:
            stages = conn.execute(
                select(sc.Stage.ordinal, sc.Stage.name, sc.Stage.heat_source, sc.Stage.start_s, sc.Stage.end_s,
                       sc.Stage.status).where(sc.Stage.campaign_id == camp.id).order_by(sc.Stage.ordinal)
            ).all()
            cur = dict(prog.cursor or {})
            n_scans, n_points = int(cur.get("n_scans", 0)), int(cur.get("n_points", 0))
            done = int(cur.get("next_scan", 0)) + int(cur.get("next_point", 0))
            total = n_scans + n_points
            stage = next((s for s in stages if s.ordinal == prog.stage_ordinal), None)
            out.append({
                "campaign_id": camp.id, "name": camp.name, "machine": camp.machine_id, "status": camp.status,
                "mode": (cur.get("origin") or {}).get("mode"),
                "stage": None if stage is None else {
                    "ordinal": stage.ordinal, "name": stage.name, "heat_source": stage.heat_source,
                    "start_s": stage.start_s, "end_s": stage.end_s, "status": stage.status,
                },
                "stages": len(stages),
                "progress": {
                    "scans": int(cur.get("next_scan", 0)), "n_scans": n_scans,
                    "points": int(cur.get("next_point", 0)), "n_points": n_points,
                    "fraction": round(done / total, 6) if total else 0.0,
                    "time_s": prog.last_sample_time_s, "total_s": cur.get("total_s"),
                },
                "last_scan": cur.get("last_scan"),
                "last_point": cur.get("last_point"),
                "faults": {"count": int(cur.get("faults", 0)), "recent": list(cur.get("recent_faults", []))[-5:]},
                "updated_at": prog.updated_at.isoformat() if prog.updated_at else None,
            })
    return out


def format_status(rows: list[dict[str, Any]]) -> str:
    """Return the status rows as a few human-readable lines per campaign."""
    if not rows:
        return "no daemon campaigns in the store"
    lines = []
    for r in rows:
        p = r["progress"]
        st = r["stage"] or {}
        lines.append(
            f"{r['campaign_id']:>4}  {r['name']}  [{r['status']}]  machine {r['machine']}  "
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
            lines.append(f"      last scan t={r['last_scan']['t_s']:.0f} s: {shown}{more} degC")
        if r["last_point"]:
            lp = r["last_point"]
            terms = ", ".join(f"{k} {v:.6g}" if v is not None else f"{k} -" for k, v in lp["values"].items())
            lines.append(f"      last point t={lp['t_s']:.0f} s {lp['axis']}={lp['position']:g} "
                         f"dir {lp['direction']:+d}: {terms}")
        f = r["faults"]
        if f["count"]:
            last = f["recent"][-1]
            lines.append(f"      faults {f['count']}, last at t={last['t_s']:.0f} s: {last['instrument']}: "
                         f"{last['message']}")
    return "\n".join(lines)


# -- simulated mode ----------------------------------------------------------------------------------


def scenario_stages(plan: Plan) -> list[dict[str, Any]]:
    """Return the plan's stages as virtual-machine scenario stages (the heat sources the world runs)."""
    from driftlab.errors import ValidationError

    out = []
    for stage, (start, end) in zip(plan.stages, plan.stage_bounds()):
        kinds = sorted(h.kind for h in stage.heat)
        if "motor_hold" in kinds:
            raise ValidationError(
                f"plan {plan.name}: stage {stage.name!r}: the virtual machine's scenarios have no "
                "motor_hold heat source; run this stage on the real machine"
            )
        axes = [h.axis for h in stage.heat if h.kind == "axis"]
        if len(axes) > 1:
            raise ValidationError(
                f"plan {plan.name}: stage {stage.name!r}: the virtual machine runs one oscillating axis at a time"
            )
        source = {(): "idle", ("spindle",): "spindle", ("axis",): "feed", ("axis", "spindle"): "combined"}[
            tuple(kinds)
        ]
        out.append({
            "name": stage.name, "start_s": start, "end_s": end, "heat_source": source,
            "axis": axes[0] if axes else (stage.axis if source == "spindle" else None),
            "spindle_rpm": stage.spindle_rpm(), "feed_mm_min": stage.feed_mm_min(),
        })
    return out


def check_travel(plan: Plan) -> None:
    """Refuse sweep positions or oscillations outside the virtual machine's travel (Tables A.3, A.4)."""
    from driftlab.daq.sim.truth import AXIS_RANGE
    from driftlab.errors import ValidationError

    for i, stage in enumerate(plan.stages):
        lo, hi = AXIS_RANGE[stage.axis]
        if stage.sweep is not None:
            out = [p for p in stage.sweep.positions if not lo - 1e-9 <= p <= hi + 1e-9]
            if out:
                raise ValidationError(
                    f"plan {plan.name}: stages[{i}].sweep.positions: {', '.join(f'{p:g}' for p in out)} outside "
                    f"the virtual machine's {stage.axis} travel {lo:g}..{hi:g}"
                )
        for h in stage.heat:
            if h.kind == "axis":
                a, b = AXIS_RANGE[h.axis]
                if not (a - 1e-9 <= min(h.from_pos, h.to_pos) and max(h.from_pos, h.to_pos) <= b + 1e-9):
                    raise ValidationError(
                        f"plan {plan.name}: stages[{i}].heat: {h.axis} oscillation {h.from_pos:g}..{h.to_pos:g} "
                        f"outside the virtual machine's travel {a:g}..{b:g}"
                    )


def plan_scenario(plan: Plan, scenario: Any) -> Any:
    """Return the scenario with the plan's stages and length (the daemon's plan drives the world)."""
    from driftlab.daq.sim.scenario import Scenario

    check_travel(plan)
    doc = scenario.model_dump()
    doc["stages"] = scenario_stages(plan)
    doc["hours"] = max(doc["hours"], math.ceil(plan.total_s / 60.0) / 60.0)
    doc["machine"] = {**doc["machine"], "id": plan.machine.id}
    return Scenario.model_validate(doc)


def scenario_meta(scenario: Any) -> dict[str, Any]:
    """Return the virtual machine's channel map and room channels (Table 5.1 sites)."""
    from driftlab.daq.sim.sites import ROOM_CHANNELS, channel_map

    return {"channels": channel_map(), "room_channels": list(ROOM_CHANNELS)}


def sim_meta(plan: Plan, scenario: Any) -> dict[str, Any]:
    """Return what the virtual machine adds to campaign.json: machine details, model channels, noise."""
    from driftlab.daq.sim.campaign import campaign_meta

    meta = campaign_meta(plan_scenario(plan, scenario))
    return {k: meta[k] for k in ("machine", "model_channels", "noise") if k in meta}
