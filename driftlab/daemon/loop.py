"""The resumable run loop: runs a campaign plan against instruments and stores every reading as it arrives.

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

Block mode (a card with a pacer and a scan buffer, on a fast simulated clock): the scans are
read from the card's buffer as blocks (``FETC?``/``DATA:REMove?``: one exchange and one
vectorised conversion for up to ``max_batch`` scans). The steps between scans (moves, sweep
points, stage starts, each scan's machine state) are still done in order at their own times;
the scans themselves wait in the card's buffer and are read together when the batch is
committed, so a sweep's interleaved moves and points do not cut them into small exchanges. A
writer thread commits each batch while the next blocks are read; batches commit in order and,
after a failed one, nothing more is committed, so the stored cursor never skips a reading.

The run's states (idle, running, paced, stopping, finished, stopped, aborting, aborted, failed)
and the transitions allowed between them are `driftlab.daemon.runstate`'s; the clock is narrowed
once, when the scheduler is built, to the complete protocols of `driftlab.daemon.clocks`.

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
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from driftlab.campaigns.acquisition import Batch, Fault, Sink, StoreUnavailable
from driftlab.campaigns.clock import Clock
from driftlab.campaigns.plan import Cursor, Move, Plan, Scan, Stage, StageStart, SweepPoint, steps
from driftlab.campaigns.status import HEARTBEAT_S
from driftlab.daemon.clocks import narrow_clock
from driftlab.daemon.runstate import RunState, RunStateMachine
from driftlab.daq.protocols import BlockScanner, Reading, ScanBlock, TemperatureScan, TemperatureScanner
from driftlab.errors import InstrumentError

log = logging.getLogger(__name__)


# -- what the loop drives -----------------------------------------------------------------------------


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


@dataclass(frozen=True)
class SchedulerOptions:
    """How the scheduler batches, pipelines and reports (the defaults are the daemon's).

    ``max_batch`` scans or ``flush_s`` seconds of work at most per transaction; ``pipeline``: commit
    in a writer thread while the next blocks are read (block mode), at most ``pipeline_depth``
    batches waiting for it (back-pressure beyond: a sweep's slow stretch of acquisition and a fast
    stretch of commits even out within that depth), the interpreter's thread switch interval set to
    ``switch_interval_s`` meanwhile (None: left as it is); ``on_commit(batch, stats)``
    after each commit; ``stop`` ends the run between steps; ``heartbeat`` (default: the sink's
    ``beat``) is called every ``heartbeat_s`` while the run lasts.
    """

    max_batch: int = 200
    flush_s: float = 0.05
    on_commit: Callable[[Batch, RunStats], None] | None = None
    stop: threading.Event | None = None
    pipeline: bool = True
    pipeline_depth: int = 8
    # The writer's bulk insert gives the GIL back for every row it steps, and waits for it again
    # while the acquiring thread (and an in-process simulated instrument) runs Python: up to the
    # interpreter's switch interval (5 ms) each time. 1 ms: flat out on the virtual machine, median
    # 7,325 against 6,785 scans/s at 5 ms and 6,788 at 0.3 ms (8 alternating runs each, one process).
    switch_interval_s: float | None = 0.001
    heartbeat: Callable[[], None] | None = None
    heartbeat_s: float = HEARTBEAT_S


class Scheduler:
    """Runs a plan from a cursor to the end (or until stopped), committing readings through a sink.

    The run goes through the states of `driftlab.daemon.runstate` (idle, running, paced, stopping,
    finished, stopped, aborting, aborted, failed); the clock is narrowed once, here, to the
    protocols of `driftlab.daemon.clocks` (TypeError naming what it lacks).
    """

    def __init__(
        self,
        plan: Plan,
        rig: Rig,
        sink: Sink,
        clock: Clock,
        cursor: Cursor = Cursor(),
        options: SchedulerOptions = SchedulerOptions(),
    ) -> None:
        self.plan = plan
        self.rig = rig
        self.sink = sink
        self.clock, self._paced_clock = narrow_clock(clock)
        self.cursor = cursor
        self.max_batch = options.max_batch
        self.flush_s = options.flush_s
        self.on_commit = options.on_commit
        self.stop = options.stop or threading.Event()
        self.pipeline = options.pipeline
        self.pipeline_depth = options.pipeline_depth
        self.switch_interval_s = options.switch_interval_s
        self.points = plan.sweep_points()
        self.stats = RunStats()
        self.state = RunStateMachine()
        scanner = rig.scanner
        self._block_scanner = scanner if isinstance(scanner, BlockScanner) else None
        self._queue: queue.Queue[Batch | None] | None = None  # batches waiting for the writer thread
        self._pending: list[Scan] = []  # scans taken by the card's pacer, their block not read yet
        self._block = 1  # scans per block (block_scans(), fixed when the run starts)
        self._stage = plan.stage_at(0.0)
        # the daemon's sign of life while it runs, waiting or not (``campaigns.status``): the sink's by default
        self.heartbeat = options.heartbeat if options.heartbeat is not None else getattr(sink, "beat", None)
        self.heartbeat_s = options.heartbeat_s

    # -- committing

    def _flush(self, batch: Batch) -> Batch:
        """Commit `batch` (readings + cursor), or hand it to the writer thread, and return a fresh one."""
        self._read_pending(batch)
        if batch.empty():
            return batch
        if self._queue is not None:
            self.state.raise_failure()
            self._queue.put(batch)  # blocks while the writer is pipeline_depth batches behind: back-pressure
        else:
            self._store(batch)
        return Batch(cursor=batch.cursor, stage=batch.stage, t_s=batch.t_s)

    def _writer(self) -> None:
        """Commit queued batches in order; after a failure or an abort commit nothing more (the cursor never skips)."""
        assert self._queue is not None
        while True:
            batch = self._queue.get()
            if batch is None:
                return
            if not self.state.committing:
                continue
            try:
                self._store(batch)
            except BaseException as exc:  # noqa: BLE001 - kept by the failed state, raised in the acquiring thread
                self.state.fail(exc)  # a commit's own failure is already kept; this keeps an on_commit error too

    def _store(self, batch: Batch) -> None:
        """Commit `batch` (with retries on an unreachable store) and account for it; a failure fails the run."""
        t0 = time.monotonic()
        try:
            self._commit_with_retry(batch)
        except BaseException as exc:
            self.state.fail(exc)
            raise
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

    # -- time

    def _due(self, t_s: float) -> bool:
        """Return True when step time t_s is already due (no waiting needed before it)."""
        paced = self._paced_clock
        if paced is not None:
            return paced.pace_s() >= t_s
        return self.clock.now() >= t_s

    def _sleep_until(self, t_s: float) -> bool:
        """Wait (interruptibly) until just before t_s is due; return True when asked to stop."""
        paced = self._paced_clock
        while not self._due(t_s):
            if paced is not None:
                remaining = (t_s - paced.pace_s()) / paced.speed
            else:
                remaining = t_s - self.clock.now()
            if self.stop.wait(min(max(remaining, 0.0), 0.5)):
                return True
        return False

    # -- the run

    def run(self) -> RunStats:
        """Run the remaining steps; return the statistics (``finished`` when the plan is complete).

        Raises the error of a failed commit (nothing after it was committed), or the loop's own
        error (the batches read before it were committed, nothing after).
        """
        self.state.to(RunState.RUNNING)
        if self._paced_clock is not None:
            self._paced_clock.anchor()  # setting up the instruments is not time the campaign fell behind
        wall0 = time.monotonic()
        batch = Batch(cursor=self.cursor, stage=self._stage)
        span = _SimSpan()
        switch = sys.getswitchinterval()
        writer = self._start_writer()
        beating = self._start_heartbeat()
        try:
            batch = self._steps(batch, span)
        except BaseException:
            self.state.abort()  # an error or a second interrupt: the writer commits nothing more
            raise
        finally:
            if beating is not None:
                beating.set()
            if writer is not None and self._queue is not None:
                self._queue.put(None)
                writer.join()
                self._queue = None
                ours = self.switch_interval_s
                if ours is not None and math.isclose(sys.getswitchinterval(), ours):  # unless changed since
                    sys.setswitchinterval(switch)
            self.state.settle()
            self.stats.finished = self.state.state is RunState.FINISHED
            self.stats.wall_s = time.monotonic() - wall0
            self.stats.sim_s = span.length()
            self.stats.max_lag_s = self.clock.max_lag_s()
        self.state.raise_failure()
        self.cursor = batch.cursor
        return self.stats

    def _start_writer(self) -> threading.Thread | None:
        """Start the writer thread in block mode (acquisition and database writes overlap); None otherwise."""
        if not (self.block_scans() > 1 and self.pipeline):
            return None
        self._queue = queue.Queue(maxsize=self.pipeline_depth)
        if self.switch_interval_s is not None:
            sys.setswitchinterval(self.switch_interval_s)
        writer = threading.Thread(target=self._writer, name="scheduler-writer", daemon=True)
        writer.start()
        return writer

    def _steps(self, batch: Batch, span: _SimSpan) -> Batch:
        """Perform the steps from the cursor on (until stopped), committing as they go; return the last batch."""
        block = self._block = self.block_scans()
        it = _Lookahead(steps(self.plan, self.cursor, self.points))
        for step in it:
            if self.stop.is_set():
                self.state.to(RunState.STOPPING)
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
                    self.state.to(RunState.STOPPING)
                    break
            t = self.clock.wait_until(last.t_s)
            span.note(run[0].t_s if run else t, t)
            if not batch.first_wall:
                batch.first_wall = time.monotonic()
            if run:
                self._do_block(run, t, batch)
            else:
                self._do(step, t, batch)
            batch.t_s = t
            if (
                batch.n_scans() + len(self._pending) >= self.max_batch
                or self._sweep_ended(batch)
                or time.monotonic() - batch.first_wall >= self.flush_s
            ):
                batch = self._flush(batch)
        return self._flush(batch)

    def _start_heartbeat(self) -> threading.Event | None:
        """Start beating (at once, then every ``heartbeat_s``) in a thread; return the event that stops it."""
        beat = self.heartbeat
        if beat is None:
            return None
        done = threading.Event()

        def run() -> None:
            failing = False
            while True:
                try:
                    beat()
                    if failing:
                        log.warning("heartbeat: written again")
                    failing = False
                except Exception as exc:  # the store may be away for a while: the readings' commits retry
                    if not failing:
                        log.warning("heartbeat: cannot write it (%s)", " ".join(str(exc).split())[:200])
                    failing = True
                if done.wait(self.heartbeat_s):
                    return

        threading.Thread(target=run, name="scheduler-heartbeat", daemon=True).start()
        return done

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
        paced = self._paced_clock
        if paced is None or self._block_scanner is None:
            return 1
        per_flush = self.flush_s * paced.speed / self.plan.scan_interval_s
        return int(max(1, min(self.max_batch, per_flush)))

    def _do_block(self, run: list[Scan], t_last: float, batch: Batch) -> None:
        """Take a run of consecutive scans from the card's buffer (states at each scan's own time) into the batch.

        The scans themselves are read later, with the next runs, in one block exchange (``FETC?``/
        ``DATA:REMove?``): when the batch is committed or a block's worth is waiting. The card holds
        them meanwhile, and what it returns for a scan does not depend on when it is read; the steps
        between (moves, sweep points, stage starts) go on in order, at their own times.
        """
        clock = self.clock  # blocks are only formed on a simulated clock, which the loop sets
        for step in run:
            if step.log_state:
                clock.set(step.t_s)  # the controller answers for the scan's instant, as scan by scan
                try:
                    batch.states.append((step.t_s, read_state(self.rig)))
                except InstrumentError as exc:
                    batch.faults.append(Fault(step.t_s, f"state {step.index}", "machine_link", exc.one_line()))
        clock.set(t_last)
        batch.cursor = Cursor(run[-1].index + 1, batch.cursor.next_point)
        if not self.state.paced:
            try:
                self._start_pacer(run[0].t_s, t_last)
            except InstrumentError as exc:
                batch.faults.append(Fault(run[0].t_s, _scans_what(run), "thermocouple", exc.one_line()))
                return
        self._pending.extend(run)
        if len(self._pending) >= self._block:
            self._read_pending(batch)

    def _start_pacer(self, t_first: float, t_last: float) -> None:
        """Start the card's pacer with the first scan it is to take (a timer scan's sweep 0 is taken at INIT)."""
        scanner = self._block_scanner
        if scanner is None:  # block_scans() forms no block then
            raise RuntimeError("buffered scan blocks need a BlockScanner")
        self.clock.set(t_first)
        try:
            scanner.pace(self.plan.scan_interval_s)
        finally:
            self.clock.set(t_last)
        self.state.to(RunState.PACED)

    def _read_pending(self, batch: Batch) -> None:
        """Read the scans waiting in the card's buffer as one block into the batch (a failure is their fault)."""
        run, self._pending = self._pending, []
        if not run:
            return
        scanner = self._block_scanner
        assert scanner is not None  # scans are only pending once the pacer of a BlockScanner started
        first, n = run[0].index, len(run)
        try:
            blk = scanner.scan_block(first, n)
        except InstrumentError as exc:
            batch.faults.append(Fault(run[0].t_s, _scans_what(run), "thermocouple", exc.one_line()))
            return
        times = np.array([s.t_s for s in run])
        batch.blocks.append(ScanBlock(first, times, blk.channels, blk.values, blk.open))

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


class _SimSpan:
    """The simulated time a run covered: from its first step's time to its last."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.last = 0.0

    def note(self, first_s: float, last_s: float) -> None:
        """Note a step that began at `first_s` (its first scan) and was recorded at `last_s`."""
        if self.first is None:
            self.first = first_s
        self.last = last_s

    def length(self) -> float:
        """Return the simulated seconds from the first step to the last (0 when no step ran)."""
        return self.last - self.first if self.first is not None else 0.0


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


def _scans_what(run: list[Scan]) -> str:
    """Return how a fault names a run of scans (``scan 7``, ``scans 7-26``)."""
    first, n = run[0].index, len(run)
    return f"scan {first}" if n == 1 else f"scans {first}-{first + n - 1}"


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
