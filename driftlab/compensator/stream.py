"""Streaming compensation: corrected blocks fed to the controller as it asks for them (ch. 7.2).

The program is checked completely before anything is sent (a bad block stops it there), then
read again a piece at a time (``compensate.parse_pieces``, the second pass of the offline path):
the streamer holds only the pieces between the last line sent and the last line prepared, so its
memory does not grow with the program's length. Blocks are corrected lazily: ``Streamer.lines()``
is the iterable the machine link pulls from whenever the controller's buffer has drained to the
low-water mark, so every block leaves with the latest model and temperatures. The waiting time of
the link (``Streamer.idle``, given to the link as its sleep) is used to refresh the model and
temperatures and to correct the next blocks ahead, so a pull returns at once. A prepared block is
never sent once its correction is older than ``max_age_s`` (two minutes, ch. 7.2): it is corrected
again first. When the model's ETag changes (``GET {api}/machines/{id}/model/current`` with
``If-None-Match``), the blocks prepared with the old model are corrected again with the new one.
If the API goes away, the last good model and temperatures stay in use and a warning is logged.
"""

from __future__ import annotations

import logging
import random
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NotRequired, Protocol, TypedDict

import httpx
import numpy as np
from typing_extensions import Unpack

from driftlab.compensator.compensate import (
    Carry,
    Correction,
    ErrorModel,
    FirstPass,
    Grid,
    TemperatureTable,
    correct,
    with_options,
)
from driftlab.compensator.gcode import Points, Program, count_points, emit, subdivide
from driftlab.compensator.guard import Guard
from driftlab.daq.dnc import carries_code, unsendable
from driftlab.errors import InstrumentError, NotFoundError, ValidationError
from driftlab.physics.lag import LaggedReadings, LagState

if TYPE_CHECKING:
    from driftlab.daq.protocols import StreamReport

log = logging.getLogger(__name__)

#: ch. 7.2: "the code should never be allowed to wait more than two minutes before being updated"
MAX_AGE_S = 120.0


# ----------------------------------------------------------------------------- sources


class ModelSource(Protocol):
    """Where the current model comes from."""

    model: ErrorModel | None

    def refresh(self) -> bool:
        """Fetch the model if it changed; return True when it did."""


class TemperatureSource(Protocol):
    """Where the latest temperatures come from."""

    def read(self) -> dict[str, float]:
        """Return the latest reading of every channel (degC)."""


@dataclass
class StaticModel:
    """A model that never changes (``--model FILE``)."""

    model: ErrorModel | None

    def refresh(self) -> bool:
        """Return False: nothing to reload."""
        return False


@dataclass
class FixedTemperatures:
    """A fixed set of readings."""

    values: Mapping[str, float]

    def read(self) -> dict[str, float]:
        """Return the readings."""
        return dict(self.values)


@dataclass
class CsvTemperatures:
    """The latest row of a temperatures.csv that a logger keeps appending to (re-read on each call)."""

    path: Path

    def read(self) -> dict[str, float]:
        """Return the latest valid reading of every channel."""
        return TemperatureTable.read_csv(self.path).latest()


def _client(client: httpx.Client | None, timeout_s: float, token: str | None) -> httpx.Client:
    """Return the given client, or a new one with the timeout and bearer token."""
    if client is not None:
        return client
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(timeout=timeout_s, headers=headers)


class _ApiResource:
    """One resource of a machine on the driftlab API: ``{api}/machines/{machine}/{path}``, read with ``client``
    (default: a new one with the timeout and bearer token)."""

    path = ""

    def __init__(
        self,
        api: str,
        machine: str,
        client: httpx.Client | None = None,
        timeout_s: float = 5.0,
        token: str | None = None,
    ) -> None:
        self.url = f"{api.rstrip('/')}/machines/{machine}/{self.path}"
        self.machine = machine
        self.client = _client(client, timeout_s, token)


class ApiModel(_ApiResource):
    """The machine's current model from the driftlab API, reloaded when its ETag changes."""

    path = "model/current"
    #: the model in use, its ETag and document; whether the API answered last time; models loaded
    model: ErrorModel | None = None
    etag: str | None = None
    document: dict[str, Any] | None = None
    reachable = True
    reloads = 0

    def refresh(self) -> bool:
        """Fetch the model unless unchanged (304); keep the last good one when the API fails."""
        headers = {"If-None-Match": self.etag} if self.etag and self.model is not None else {}
        try:
            reply = self.client.get(self.url, headers=headers)
        except httpx.HTTPError as exc:
            return self._outage(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)
        if reply.status_code == 304:
            self._back()
            return False
        if reply.status_code == 404 and self.model is None:
            raise NotFoundError(f"no current model for machine {self.machine} at {self.url}")
        if reply.status_code != 200:
            return self._outage(f"HTTP {reply.status_code}")
        try:
            body = reply.json()
            doc = body.get("document", body) if isinstance(body, dict) else body
            model = ErrorModel.from_document(doc)
        except (ValueError, ValidationError) as exc:
            return self._outage(f"unusable model document ({' '.join(str(exc).split())[:120]})")
        self._back()
        etag = reply.headers.get("ETag")
        changed = self.model is None or etag is None or etag != self.etag
        self.model, self.etag, self.document = model, etag, doc
        if changed:
            self.reloads += 1
            log.info("model %s loaded (ETag %s)", model.label, etag)
        return changed

    def _outage(self, reason: str) -> bool:
        """Keep the last model (warn once per outage); fail when there has never been one."""
        if self.model is None:
            raise InstrumentError(f"cannot get the model from {self.url}: {reason}")
        if self.reachable:
            log.warning("model API unavailable (%s): keeping model %s", reason, self.model.label)
        self.reachable = False
        return False

    def _back(self) -> None:
        """Note that the API answers again."""
        if not self.reachable:
            log.warning("model API reachable again")
        self.reachable = True


class ApiTemperatures(_ApiResource):
    """The machine's latest scan from the driftlab API: ``GET {api}/machines/{id}/temperatures/latest``.

    Accepted replies: ``{"time_s": .., "temperatures": {channel: degC}}`` (also under ``values``
    or ``channels``), or a plain ``{channel: degC}`` object.
    """

    path = "temperatures/latest"

    def read(self) -> dict[str, float]:
        """Return the latest reading per channel; InstrumentError when the API cannot give one."""
        try:
            reply = self.client.get(self.url)
            reply.raise_for_status()
            body = reply.json()
        except (httpx.HTTPError, ValueError) as exc:
            raise InstrumentError(f"cannot read temperatures from {self.url}: {exc}") from None
        for key in ("temperatures", "values", "channels"):
            if isinstance(body, dict) and isinstance(body.get(key), dict):
                body = body[key]
                break
        try:
            return {str(c): float("nan") if v is None else float(v) for c, v in body.items() if c != "time_s"}
        except (AttributeError, TypeError, ValueError):
            raise InstrumentError(f"unexpected temperatures reply from {self.url}") from None


# ----------------------------------------------------------------------------- streamer


@dataclass(frozen=True)
class _Cursor:
    """Where preparation resumes: a program line, the next point of its block, the carried state."""

    line: int
    sub: int  # points of this line's block already prepared (0: the line itself is next)
    steps: np.ndarray
    sent: np.ndarray
    nominal: np.ndarray
    direction: np.ndarray | None


@dataclass(frozen=True)
class _Ready:
    """A prepared line for the controller and the cursor just after it."""

    text: str
    after: _Cursor
    made_at: float
    model: str


#: block latencies kept for the percentiles: every one up to this many, then a uniform sample of this size
LATENCY_SAMPLE = 100_000


class StreamSummary(TypedDict):
    """The JSON summary of a :class:`StreamResult`: blocks, recomputations, reloads and latency (ms)."""

    blocks_sent: int
    recomputed: int
    model_reloads: int
    latency_ms_p50: float
    latency_ms_p99: float
    latency_ms_max: float
    #: added by ``driftlab compensate --stream``: the channels read beyond their fitted range (``Guard.report``)
    extrapolated: NotRequired[dict[str, dict[str, float]]]
    #: added by ``driftlab compensate --link dnc``: characters sent, DC3s seen, time held (s)
    dnc: NotRequired[dict[str, float]]


@dataclass
class StreamResult:
    """What a streaming run did (in memory that does not grow with the program's length)."""

    blocks_sent: int = 0
    recomputed: int = 0
    reloads: int = 0
    #: per-block latency (s): all of them for up to LATENCY_SAMPLE blocks, then a uniform sample of them
    latency_s: list[float] = field(default_factory=list)
    latency_max_s: float = 0.0
    link_report: StreamReport | None = None
    warnings: list[str] = field(default_factory=list)
    _recorded: int = field(default=0, repr=False)
    _rng: random.Random = field(default_factory=lambda: random.Random(0), repr=False)

    def record(self, latency_s: float) -> None:
        """Count one block's latency: kept, or past LATENCY_SAMPLE blocks sampled (reservoir), the maximum exact."""
        self.latency_max_s = max(self.latency_max_s, latency_s)
        if len(self.latency_s) < LATENCY_SAMPLE:
            self.latency_s.append(latency_s)
        else:
            k = self._rng.randrange(self._recorded + 1)
            if k < LATENCY_SAMPLE:
                self.latency_s[k] = latency_s
        self._recorded += 1

    def latency_ms(self, pct: float) -> float:
        """Return a percentile of the per-block latency (ms), 0 when nothing was sent (100: the exact maximum)."""
        if not self.latency_s:
            return 0.0
        if pct >= 100:
            return self.latency_max_s * 1e3
        return float(np.percentile(self.latency_s, pct) * 1e3)

    def summary(self) -> StreamSummary:
        """Return a JSON-ready summary."""
        return {
            "blocks_sent": self.blocks_sent,
            "recomputed": self.recomputed,
            "model_reloads": self.reloads,
            "latency_ms_p50": round(self.latency_ms(50), 4),
            "latency_ms_p99": round(self.latency_ms(99), 4),
            "latency_ms_max": round(self.latency_ms(100), 4),
        }


def _rows(text: bytes) -> list[bytes]:
    """Return the lines of ``text`` without their terminators."""
    rows = text.split(b"\n")
    if rows and rows[-1] == b"":
        rows.pop()
    return [r[:-1] if r.endswith(b"\r") else r for r in rows]


def _sendable(text: str) -> bool:
    """Return True for a line that is a block for the controller: code once comments are out (``dnc.carries_code``;
    a line ``(note) G1 X1`` is a block, not a comment)."""
    return carries_code(text)


#: bytes a block may carry down a controller's line: printable 7-bit ASCII, tab, and the line ends
_LINE_OK = np.zeros(256, dtype=bool)
_LINE_OK[0x20:0x7F] = True
_LINE_OK[[0x09, 0x0A, 0x0D]] = True


def check_sendable(pieces: Iterable[tuple[int, bytes]], name: str) -> None:
    """Refuse, before the first byte is sent, a program with a block the line cannot carry (``dnc.unsendable``).

    ``pieces``: (lines before, text) of the program (``compensate.program_pieces``). Every line that
    will be sent (not blank, a comment line or ``%``) must be printable 7-bit ASCII without a ``%``: a
    Latin-1 comment, a control character (a DC3 in a comment would stop the line) or a ``%`` in a block
    is one line ``PROGRAM:LINE: ...; program not accepted``, never a failure in the middle of the part.
    """
    for before, text in pieces:
        buf = np.frombuffer(text, dtype=np.uint8)
        odd = np.flatnonzero(~_LINE_OK[buf] | (buf == 0x25))
        if odd.shape[0] == 0:
            continue
        nl = np.flatnonzero(buf == 10)
        for li in np.unique(np.searchsorted(nl, odd)).tolist():
            a = int(nl[li - 1]) + 1 if li > 0 else 0
            b = int(nl[li]) if li < nl.shape[0] else len(text)
            row = text[a:b].rstrip(b"\r")
            if not carries_code(row.decode("latin-1")):
                continue  # not sent
            why = unsendable(row)
            if why is not None:
                raise ValidationError(f"{name}:{before + li + 1}: {why}; program not accepted")


@dataclass(frozen=True)
class Pacing:
    """How far ahead blocks are prepared and how old they may get (ch. 7.2: two minutes at the most)."""

    max_age_s: float = MAX_AGE_S
    refresh_s: float = 30.0
    lookahead: int = 64
    batch_lines: int = 32
    inline_lines: int = 4


@dataclass(frozen=True)
class Clocks:
    """The streamer's time: ``clock`` (s, monotonic), ``sleep``, ``timer`` (latencies), and ``epoch_s``, the POSIX
    time at ``clock() == 0`` (None: now less ``time.monotonic()`` for the monotonic clock, else left to the model)."""

    clock: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep
    timer: Callable[[], float] = time.perf_counter
    epoch_s: float | None = None


@dataclass(frozen=True)
class StreamerSettings:
    """The options of a ``Streamer``: its grid, pacing and clocks, the envelope guard, the readings' lags.

    Pass one ``LagState`` (``lags``) to successive streamers of one run to keep its history across them.
    """

    grid: Grid = Grid()
    pacing: Pacing = Pacing()
    clocks: Clocks = Clocks()
    guard: Guard | None = None
    lags: LagState | None = None

    def with_keywords(self, keywords: StreamerKeywords) -> StreamerSettings:
        """Return these settings with the fields ``keywords`` names replaced (``StreamerKeywords``)."""
        return StreamerSettings(
            with_options(self.grid, keywords),
            with_options(self.pacing, keywords),
            with_options(self.clocks, keywords),
            keywords.get("guard", self.guard),
            keywords.get("lags", self.lags),
        )


class StreamerKeywords(TypedDict, total=False):
    """The keyword options of ``Streamer``: the fields of ``Grid``, ``Pacing``, ``Clocks``, the guard and lags."""

    resolution_mm: float
    resolution_deg: float
    hysteresis_steps: float
    max_segment_mm: float
    max_segment_deg: float
    max_age_s: float
    refresh_s: float
    lookahead: int
    batch_lines: int
    inline_lines: int
    clock: Callable[[], float]
    sleep: Callable[[float], None]
    timer: Callable[[], float]
    epoch_s: float | None
    guard: Guard | None
    lags: LagState | None


class Streamer:
    """Prepares corrected blocks just in time for the machine link (see module docstring)."""

    def __init__(
        self,
        program: Program | Iterable[Program],
        models: ModelSource,
        temperatures: TemperatureSource,
        settings: StreamerSettings | None = None,
        **keywords: Unpack[StreamerKeywords],
    ) -> None:
        """Stream ``program`` (a whole one, or its pieces in order) with ``settings`` (the ``keywords`` replacing
        the fields they name: ``StreamerKeywords``)."""
        opts = (settings or StreamerSettings()).with_keywords(keywords)
        pacing, clocks = opts.pacing, opts.clocks
        if not 0 < pacing.refresh_s <= pacing.max_age_s:
            raise ValidationError("refresh interval must be positive and no longer than the maximum age")
        # a whole program, or its pieces in order (``parse_pieces``), read only as preparation needs them
        self._source: Iterator[Program] = iter([program] if isinstance(program, Program) else program)
        # a whole program is checked against the guard's envelope in ``prime`` before anything is
        # prepared (pieces of a file were checked by the caller's first pass, ``scan_program``)
        self._whole = program if isinstance(program, Program) else None
        self._window: deque[Program] = deque()  # the pieces from the last line sent to the last prepared
        first = self._next_piece()
        self.models = models
        self.temperature_source = temperatures
        self.grid = opts.grid
        self.resolution = (opts.grid.resolution_mm, opts.grid.resolution_deg)
        self.segment = opts.grid.segment
        self.max_age_s = pacing.max_age_s
        self.refresh_s = pacing.refresh_s
        self.lookahead = max(1, pacing.lookahead)
        self.batch_lines = max(1, pacing.batch_lines)
        self.inline_lines = max(1, pacing.inline_lines)
        self.clock, self.sleep, self.timer = clocks.clock, clocks.sleep, clocks.timer
        # POSIX time at clock() == 0: each block is corrected for the time it is prepared, so that
        # time-dependent terms (drift, ch. 6.4.3) follow the program; None leaves it to the model (now)
        epoch_s = clocks.epoch_s
        if epoch_s is None and clocks.clock is time.monotonic:
            epoch_s = time.time() - time.monotonic()
        self.epoch_s = epoch_s
        self.guard = opts.guard
        zero = np.zeros(5, dtype=np.int64)
        pose = first.start_int.copy() if first is not None else zero
        start = _Cursor(first.first_line if first is not None else 0, 0, zero, pose, pose.copy(), None)
        self._taken = start  # just after the last line handed to the link
        self._made = start  # just after the last line prepared
        self._ready: deque[_Ready] = deque()
        self._temps: dict[str, float] | None = None
        # the lags of every reading (ch. 5.3) kept from scan to scan for the model's lagged terms;
        # pass one LagState to successive streamers of one run to keep its history across them
        self.lags = opts.lags if opts.lags is not None else LagState()
        self._temps_at = -np.inf
        self._temps_ok = True
        self._model_at = -np.inf
        self.result = StreamResult()

    # -- sources
    def refresh(self, due_s: float | None = None) -> None:
        """Refresh model and temperatures when older than ``due_s`` (default: the refresh interval)."""
        due = self.refresh_s if due_s is None else due_s
        now = self.clock()
        if now - self._model_at >= due:
            changed = self.models.refresh()
            self._model_at = now
            if self.models.model is None:
                raise ValidationError("no model to compensate with")
            if changed and self._ready:
                self._discard()  # prepared with the old model: prepare them again
            if changed:
                self.result.reloads += 1
        if now - self._temps_at >= due:
            try:
                temps = self.temperature_source.read()
            except (InstrumentError, ValidationError) as exc:
                if self._temps is None:
                    raise
                if self._temps_ok:  # once per outage
                    msg = f"temperatures unavailable ({exc.one_line()}): keeping the last reading"
                    log.warning(msg)
                    self.result.warnings.append(msg)
                self._temps_ok = False
                self._temps_at = now
                return
            if self.guard is not None:  # readings it refuses are never used: the run stops here
                self.guard.check_temperatures(temps)
            model = self.models.model
            if model is not None:
                self.lags.track(model.lag_taus)
            self.lags.update(now, temps)
            self._temps = LaggedReadings(temps, self.lags.values())
            self._temps_at = now
            if not self._temps_ok:
                log.warning("temperatures available again")
            self._temps_ok = True

    def _discard(self) -> None:
        """Drop the prepared lines; preparation restarts after the last line sent."""
        self.result.recomputed += len(self._ready)
        self._ready.clear()
        self._made = self._taken

    # -- pieces
    def _next_piece(self) -> Program | None:
        """Read the next piece of the program into the window (None at the end)."""
        for piece in self._source:
            if piece.n_lines:
                self._window.append(piece)
                return piece
        return None

    def _piece(self, line: int) -> Program | None:
        """Return the piece holding program line ``line``, reading on as far as it (None past the end)."""
        for piece in self._window:
            if piece.first_line <= line < piece.first_line + piece.n_lines:
                return piece
        while (read := self._next_piece()) is not None:
            if line < read.first_line + read.n_lines:
                return read
        return None

    def _release(self) -> None:
        """Drop the pieces whose every line has been sent (a discard restarts after the last line sent)."""
        while self._window and self._window[0].first_line + self._window[0].n_lines <= self._taken.line:
            self._window.popleft()

    # -- preparation
    def _prepare(self, n_lines: int | None = None) -> bool:
        """Prepare the next ``n_lines`` program lines (default: a batch, within one piece); False at the end."""
        cur = self._made
        p = self._piece(cur.line)
        if p is None:
            return False
        model = self.models.model
        assert model is not None and self._temps is not None
        made_at = self.clock()
        batch = self._batch(p, cur, n_lines or self.batch_lines, made_at)
        # rows in output order: (text, point carried or -1, program line)
        rows = batch.resumed_rows(cur)
        rows += batch.line_rows(cur, batch.l0 + 1 if batch.resumed() else batch.l0)
        for text, k, li in rows:
            after = batch.cursor_after(cur, k, li)
            self._ready.append(_Ready(text.decode("utf-8", "replace"), after, made_at, model.label))
        self._made = batch.end(cur)
        return True

    def _batch(self, p: Program, cur: _Cursor, n_lines: int, made_at: float) -> _Batch:
        """Return lines ``cur.line`` on (at most ``n_lines``, within piece ``p``) with their points corrected."""
        model = self.models.model
        assert model is not None and self._temps is not None
        l0 = cur.line - p.first_line  # cursors count lines over the whole program, the piece from its first
        l1 = min(p.n_lines, l0 + n_lines)
        b0, b1 = (int(x) for x in np.searchsorted(p.block_line, [l0, l1]))
        pts = subdivide(p, *self.segment, blocks=slice(b0, b1))
        skip = cur.sub if (b0 < b1 and p.block_line[b0] == l0) else 0
        pts = Points(pts.block[skip:], pts.nominal_int[skip:])
        corr = None
        if pts.n:
            at = None if self.epoch_s is None else self.epoch_s + made_at
            carry = Carry(cur.steps, cur.nominal, cur.direction)
            corr = correct(p, pts, model, self._temps, carry, self.grid, at)
            if self.guard is not None:  # nothing outside the envelope is ever queued for the link
                self.guard.check_sent(p, pts.block, pts.nominal_int, corr.sent_int)
        return _Batch(p, l0, l1, b0, skip, pts, corr)

    def _fill(self) -> None:
        """Prepare lines until the look-ahead is full or the program ends."""
        while len(self._ready) < self.lookahead and self._prepare():
            pass

    def prime(self) -> None:
        """Fetch model and temperatures, check a whole program, prepare the first lines (before streaming starts).

        With a ``guard`` and a whole ``Program``, every block is checked first (``compensate.FirstPass``:
        targets in the travel, subdivision, corrections with the first reading): a refusal raises here,
        before any line is prepared or sent.
        """
        self.refresh(due_s=0.0)
        if self.guard is not None and self._whole is not None:
            assert self.models.model is not None and self._temps is not None
            check = FirstPass(self.guard, self.models.model, self._temps, grid=self.grid)
            check.targets(self._whole)
            count_points(self._whole, *self.segment)
            check.corrections(self._whole)
            self._whole = None  # checked once; the lines then go through ``guard.check_sent`` as prepared
        self._fill()

    def idle(self, seconds: float) -> None:
        """Use the link's waiting time: refresh when due, renew stale lines, prepare ahead; then sleep."""
        t_end = self.clock() + seconds
        self.refresh()
        if self._ready and self.clock() - self._ready[0].made_at > self.max_age_s - self.refresh_s:
            self._discard()
        self._fill()
        rest = t_end - self.clock()
        if rest > 0:
            self.sleep(rest)

    def lines(self) -> Iterator[str]:
        """Yield corrected blocks for the machine link, each prepared at most ``max_age_s`` ago."""
        while True:
            t0 = self.timer()
            if self.clock() - min(self._model_at, self._temps_at) >= self.refresh_s:
                self.refresh()  # the link has not waited long enough for ``idle`` to do it
            while True:
                if not self._ready:
                    # the link caught up with the preparation: a short run keeps this wait short
                    while not self._ready and self._prepare(self.inline_lines):
                        pass
                    if not self._ready:
                        return
                item = self._ready[0]
                if self.clock() - item.made_at > self.max_age_s:
                    self._discard()
                    continue
                self._ready.popleft()
                self._taken = item.after
                self._release()
                if _sendable(item.text):
                    break
            self.result.record(self.timer() - t0)
            self.result.blocks_sent += 1
            yield item.text

    def run(self, link: Any, low_water: int = 4, high_water: int | None = None, wait: bool = True) -> StreamResult:
        """Stream the whole program over ``link`` (a ``daq.protocols.MachineLink``); return what happened."""
        if hasattr(link, "sleep"):
            link.sleep = self.idle
        self.prime()
        self.result.link_report = link.send_program(self.lines(), low_water=low_water, high_water=high_water, wait=wait)
        return self.result


@dataclass(frozen=True)
class _Batch:
    """Lines ``l0:l1`` of piece ``p`` being prepared: their points (after ``skip`` already prepared) corrected."""

    p: Program
    l0: int
    l1: int
    b0: int
    skip: int
    pts: Points
    corr: Correction | None

    @property
    def sent(self) -> np.ndarray:
        """Return (P, 5) the commanded points."""
        assert self.corr is not None
        return self.corr.sent_int

    def carried(self, cur: _Cursor) -> tuple[np.ndarray, np.ndarray]:
        """Return (P,) whether each point is its block's first (on the block's line) and whether it gets a line."""
        pts, sent = self.pts, self.sent
        prev = np.vstack([cur.sent[None, :], sent[:-1]])
        first = np.ones(pts.n, dtype=bool)
        first[1:] = pts.block[1:] != pts.block[:-1]
        first[0] = not self.skip
        extra = ~first & (sent != prev).any(axis=1)  # later points of a block that get a line
        return first, first | extra

    def resumed_rows(self, cur: _Cursor) -> list[tuple[bytes, int, int]]:
        """Return the rows of the rest of a block whose line was already sent: only its new lines."""
        if not (self.skip and self.pts.n):
            return []
        pts, sent, l0 = self.pts, self.sent, self.l0
        base = self.resumed()
        text = emit(
            self.p,
            Points(pts.block[:base], pts.nominal_int[:base]),
            sent[:base],
            prev_sent=cur.sent,
            lines=slice(l0 + 1, l0 + 1),
            resume=True,
        )
        # (a newline may lead them when the block's line ends the file without one)
        texts = [r for r in _rows(text) if r]
        first, lines = self.carried(cur)
        carried = np.flatnonzero((lines & ~first)[:base]).tolist()
        if len(texts) != len(carried):
            raise RuntimeError("emitted lines do not match the prepared points")
        return [(t, k, l0) for t, k in zip(texts, carried)]

    def resumed(self) -> int:
        """Return how many points continue a block whose line was already sent."""
        if not (self.skip and self.pts.n):
            return 0
        return int(np.searchsorted(self.pts.block, self.pts.block[0], side="right"))

    def line_rows(self, cur: _Cursor, start_line: int) -> list[tuple[bytes, int, int]]:
        """Return the rows of lines ``start_line:l1``: each line, and the new lines of its block's later points."""
        if start_line >= self.l1:
            return []
        pts, base = self.pts, self.resumed()
        carriers: dict[int, list[int]] = {}
        if pts.n > base:
            sent = self.sent
            part = Points(pts.block[base:], pts.nominal_int[base:])
            prev_sent = cur.sent if base == 0 else sent[base - 1]
            text = emit(self.p, part, sent[base:], prev_sent=prev_sent, lines=slice(start_line, self.l1))
            point_line = self.p.block_line[pts.block]
            for k in np.flatnonzero(self.carried(cur)[1][base:]).tolist():
                carriers.setdefault(int(point_line[base + k]), []).append(base + k)
        else:
            text = emit(self.p, None, lines=slice(start_line, self.l1))
        order = [(k, li) for li in range(start_line, self.l1) for k in carriers.get(li, [-1])]
        texts = _rows(text)
        if len(texts) != len(order):
            raise RuntimeError("emitted lines do not match the program lines")
        return [(t, k, li) for t, (k, li) in zip(texts, order)]

    def cursor_after(self, cur: _Cursor, k: int, li: int) -> _Cursor:
        """Return where to resume after a row: after point ``k`` (-1: after line ``li``), with the state of the
        last point before it."""
        pts, f = self.pts, self.p.first_line
        if k >= 0:
            assert self.corr is not None
            blk = pts.block[k]
            last = k + 1 >= pts.n or pts.block[k + 1] != blk
            done = k + 1 - int(np.searchsorted(pts.block, blk)) + (self.skip if blk == self.b0 else 0)
            return self._cursor(f + li + 1 if last else f + li, 0 if last else done, k)
        j = int(np.searchsorted(self.p.block_line[pts.block], li)) - 1 if pts.n else -1
        if j < 0:
            return _Cursor(f + li + 1, 0, cur.steps, cur.sent, cur.nominal, cur.direction)
        return self._cursor(f + li + 1, 0, j)

    def end(self, cur: _Cursor) -> _Cursor:
        """Return where to resume after the batch: its last line, with its last point's state."""
        line = self.p.first_line + self.l1
        if self.pts.n:
            return self._cursor(line, 0, self.pts.n - 1)
        return _Cursor(line, 0, cur.steps, cur.sent, cur.nominal, cur.direction)

    def _cursor(self, line: int, sub: int, k: int) -> _Cursor:
        """Return a cursor at ``line`` (``sub`` points of its block prepared) with point ``k``'s state."""
        corr = self.corr
        assert corr is not None
        return _Cursor(line, sub, corr.steps[k], corr.sent_int[k], self.pts.nominal_int[k], corr.direction[k])
