"""The live page: /live (HTML), /live/events (server-sent events) and /live/snapshot (JSON).

One ``LiveHub`` per application polls the store for commits (one small query every ``poll_s``,
whatever the number of open pages), reads what is new once, and hands the same encoded event
to every subscriber. A page that connects gets a snapshot read for it, then the shared updates.

Events (``text/event-stream``, each ``data:`` one JSON document):

* ``snapshot``: ``{"campaigns": [campaign...], "server_time"}``, sent first on every connection;
* ``campaign``: ``{"campaign": campaign}``, a campaign that appeared (or needs a full redraw);
* ``update``: ``{"campaign": header + new temperature buckets + new error readings}``;
* ``gone``: ``{"campaign_id"}``, no longer on show (deleted, or superseded by a newer run).

A slow subscriber whose queue fills is dropped; its browser reconnects and gets a new snapshot.
Everything here only reads: the page needs no token.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, JSONResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool

from driftlab.campaigns import live as q

if TYPE_CHECKING:
    from driftlab.campaigns.live import ChannelRow

log = logging.getLogger(__name__)

router = APIRouter(tags=["live"])

KEEPALIVE_S = 15.0
QUEUE_EVENTS = 64


def encode(event: str, data: dict[str, Any]) -> bytes:
    """Return one server-sent event (``event:`` and one ``data:`` line of compact JSON)."""
    body = json.dumps(data, separators=(",", ":"), allow_nan=False, default=str)
    return f"event: {event}\ndata: {body}\n\n".encode()


@dataclass
class _Tracked:
    """What the hub has already sent of one campaign."""

    status: str
    updated_at: str | None
    channels: list[ChannelRow]
    after_s: float | None
    after_seq: int
    #: the daemon stopped beating (kill -9): pages are told once, when it happens
    stale: bool = False


@dataclass
class LiveHub:
    """Polls the store for new commits and fans one encoded event out to every subscribed page."""

    engine: Any
    poll_s: float = 0.5
    window_s: float = q.WINDOW_S
    max_points: int = q.MAX_POINTS
    subscribers: set[asyncio.Queue[bytes | None]] = field(default_factory=set)
    tracked: dict[int, _Tracked] = field(default_factory=dict)
    polls: int = 0
    _task: asyncio.Task[None] | None = None

    @property
    def width_s(self) -> float:
        """Return the temperature bucket width (s of campaign time)."""
        return q.bucket_width(self.window_s, self.max_points)

    def snapshot(self) -> dict[str, Any]:
        """Return every campaign on show, in full (blocking: call from a worker thread)."""
        out = []
        for cid in q.live_marks(self.engine):
            snap = q.snapshot(self.engine, cid, self.window_s, self.max_points)
            if snap is not None:
                out.append(snap)
        return {"campaigns": out, "server_time": _now()}

    async def subscribe(self) -> tuple[asyncio.Queue[bytes | None], bytes]:
        """Return a new subscriber's queue and its first event (a snapshot); starts polling if idle."""
        queue: asyncio.Queue[bytes | None] = asyncio.Queue(QUEUE_EVENTS)
        self.subscribers.add(queue)  # before the snapshot: an update read meanwhile overlaps it, none is lost
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run(), name="driftlab-live-hub")
        try:
            first = encode("snapshot", await run_in_threadpool(self.snapshot))
        except BaseException:
            self.subscribers.discard(queue)
            raise
        return queue, first

    def unsubscribe(self, queue: asyncio.Queue[bytes | None]) -> None:
        """Forget a subscriber; polling stops with the last one."""
        self.subscribers.discard(queue)
        if not self.subscribers and self._task is not None:
            self._task.cancel()
            self._task = None
            self.tracked.clear()

    async def stop(self) -> None:
        """Stop polling and end every subscriber's stream."""
        for queue in list(self.subscribers):
            _offer(queue, None)
        self.subscribers.clear()
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self._task = None

    async def _run(self) -> None:
        """Poll until cancelled; a failed poll (database away) is logged and retried."""
        while True:
            try:
                events = await run_in_threadpool(self.poll)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # the database may be restarting: keep the pages, try again
                log.warning("live: cannot read the store: %s", " ".join(str(exc).split())[:200])
                events = []
            self._broadcast(events)
            await asyncio.sleep(self.poll_s)

    def poll(self) -> list[bytes]:
        """Return the events of everything committed since the last poll (blocking: runs in a worker thread)."""
        self.polls += 1
        marks = q.live_marks(self.engine)
        events: list[bytes] = []
        for cid in [c for c in self.tracked if c not in marks]:
            del self.tracked[cid]
            events.append(encode("gone", {"campaign_id": cid}))
        for cid, mark in marks.items():
            tr = self.tracked.get(cid)
            if tr is None:
                # a campaign the hub starts following: pages get it whole (they replace what they had)
                seq = q.latest_seq(self.engine, cid)
                snap = q.snapshot(self.engine, cid, self.window_s, self.max_points)
                if snap is None:
                    continue
                temps, errs = snap["temperatures"], snap["errors"]
                self.tracked[cid] = _Tracked(
                    mark["status"],
                    mark["updated_at"],
                    q.channels(self.engine, cid),
                    max(temps["t"]) if temps["t"] else None,
                    max([seq, *errs["seq"]]),
                    mark["stale"],
                )
                events.append(encode("campaign", {"campaign": snap, "server_time": _now()}))
                continue
            if (mark["updated_at"], mark["status"], mark["stale"]) == (tr.updated_at, tr.status, tr.stale):
                continue
            upd = q.update(self.engine, cid, tr.channels, tr.after_s, tr.after_seq, self.width_s)
            if upd is None:
                continue
            tr.status, tr.updated_at, tr.stale = mark["status"], mark["updated_at"], mark["stale"]
            if upd["temperatures"]["t"]:
                tr.after_s = max(upd["temperatures"]["t"])
            if upd["errors"]["seq"]:
                tr.after_seq = max(upd["errors"]["seq"])
            events.append(encode("update", {"campaign": upd, "server_time": _now()}))
        return events

    def _broadcast(self, events: list[bytes]) -> None:
        """Queue the events for every subscriber; drop one whose queue is full (it reconnects)."""
        for ev in events:
            for queue in list(self.subscribers):
                if not _offer(queue, ev):
                    log.info("live: a page fell behind; it will reconnect")
                    self.subscribers.discard(queue)
                    _offer(queue, None, force=True)


def _offer(queue: asyncio.Queue[bytes | None], item: bytes | None, force: bool = False) -> bool:
    """Put without waiting; with ``force`` make room by dropping the oldest. Return False when full."""
    try:
        queue.put_nowait(item)
        return True
    except asyncio.QueueFull:
        if force:
            queue.get_nowait()
            queue.put_nowait(item)
        return False


def _now() -> str:
    """Return the server's time, ISO 8601 UTC (pages show how old the latest commit is)."""
    return datetime.now(UTC).isoformat().replace("+00:00", "Z")


def hub(request: Request) -> LiveHub:
    """Return the application's live hub."""
    return request.app.state.live_hub


@router.get("/live", include_in_schema=False, response_class=HTMLResponse)
def live_page() -> HTMLResponse:
    """Return the live page (no token needed: it only reads)."""
    page = resources.files("driftlab.api").joinpath("static/live.html").read_text(encoding="utf-8")
    return HTMLResponse(page, headers={"Cache-Control": "no-cache"})


@router.get("/live/events", include_in_schema=False)
async def live_events(request: Request) -> StreamingResponse:
    """Stream server-sent events: a snapshot of every campaign on show, then its updates as they are committed."""
    h = hub(request)
    queue, first = await h.subscribe()

    async def stream() -> AsyncIterator[bytes]:
        """Yield the snapshot, then each shared update; a comment line keeps idle connections open."""
        try:
            yield b"retry: 2000\n\n" + first
            last = time.monotonic()
            while True:
                try:
                    item = await asyncio.wait_for(queue.get(), timeout=KEEPALIVE_S)
                except TimeoutError:
                    if await request.is_disconnected():
                        return
                    yield b": keep-alive\n\n"
                    continue
                if item is None:
                    return
                yield item
                if time.monotonic() - last > KEEPALIVE_S and await request.is_disconnected():
                    return
                last = time.monotonic()
        finally:
            h.unsubscribe(queue)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )


@router.get(
    "/live/snapshot",
    summary="Running campaigns as the live page shows them",
    response_description="every daemon campaign on show: stage, progress, latest scan, "
    "temperature buckets of the last hours, recent error readings, instrument health",
)
async def live_snapshot(request: Request) -> JSONResponse:
    """Return the same document as the first event of /live/events (for scripts; the page uses the stream)."""
    return JSONResponse(await run_in_threadpool(hub(request).snapshot))
