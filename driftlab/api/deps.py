"""Shared state of the API (store, token, current-model cache, job runner) and its dependencies."""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, NotRequired, TypedDict

from fastapi import Request
from starlette.exceptions import HTTPException

from driftlab.api.guard import token_problem
from driftlab.campaigns.store import ModelVersionInfo, Store
from driftlab.jobs import Jobs

log = logging.getLogger(__name__)


def iso(dt: Any) -> str | None:
    """Return a datetime as ISO 8601 UTC with a Z (None stays None)."""
    return None if dt is None else dt.isoformat().replace("+00:00", "Z")


class ModelVersionJson(TypedDict):
    """The JSON form of a registry row: ``schemas.ModelVersionOut``, or ``ModelSummary`` without the document."""

    machine_id: str
    version: int
    status: str
    created_at: str | None  # ISO 8601 UTC with a Z
    retired_at: str | None
    source_campaigns: list[int]
    terms: int  # how many error-parameter models the document holds
    document: NotRequired[dict[str, object]]  # the model document, its version filled in


def model_out(row: ModelVersionInfo, with_document: bool = True) -> ModelVersionJson:
    """Return the JSON form of a registry row (ModelVersionOut, or ModelSummary without the document)."""
    out: ModelVersionJson = {
        "machine_id": row.machine_id,
        "version": row.version,
        "status": row.status,
        "created_at": iso(row.created_at),
        "retired_at": iso(row.retired_at),
        "source_campaigns": [int(c) for c in row.source_campaigns],
        "terms": len(row.document.get("terms", []) or []),
    }
    if with_document:
        # the registry keeps the version number in the row; compensators read it from the document
        out["document"] = {**row.document, "version": row.version}
    return out


def model_etag(row: ModelVersionInfo) -> str:
    """Return the strong ETag of a model version: a hash of its row id and canonical document."""
    h = hashlib.sha256(f"{row.id}\n".encode())
    h.update(json.dumps(row.document, sort_keys=True, separators=(",", ":")).encode())
    return f'"{h.hexdigest()[:32]}"'


@dataclass(frozen=True)
class CachedModel:
    """A machine's current model, serialised once: body bytes, ETag and version."""

    etag: str
    body: bytes
    version: int
    row: ModelVersionInfo


class ModelCache:
    """Current model per machine, served without a database read while fresh.

    Writes through this API invalidate at once (register, promote, retire, fit jobs); changes made by
    other processes are seen after at most ``ttl_s`` seconds (plus one refresh): an expired entry is
    still served while one background refresh runs (stale-while-revalidate), so pollers never queue
    behind the database. A generation counter keeps a load that raced with an invalidation from
    storing the stale answer.
    """

    def __init__(self, store: Store, ttl_s: float = 1.0) -> None:
        self.store = store
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[float, CachedModel | None]] = {}
        self._generation = 0
        self._lock = threading.Lock()
        self._refreshing: set[str] = set()
        self._tasks: set[Any] = set()
        self.loads = 0

    def fresh(self, machine_id: str) -> tuple[bool, CachedModel | None]:
        """Return (hit, entry): a hit is a cached answer (possibly "no model") younger than the TTL."""
        entry = self._entries.get(machine_id)
        if entry is None or time.monotonic() - entry[0] >= self.ttl_s:
            return False, None
        return True, entry[1]

    def servable(self, machine_id: str) -> CachedModel | None:
        """Return the cached model to answer with now (refreshing it in the background when expired).

        None means the caller must load (nothing cached, or the cached answer is "no model").
        Call from the event loop.
        """
        entry = self._entries.get(machine_id)
        if entry is None or entry[1] is None:
            return None
        if time.monotonic() - entry[0] >= self.ttl_s and machine_id not in self._refreshing:
            self._refreshing.add(machine_id)
            task = asyncio.get_running_loop().run_in_executor(None, self._refresh, machine_id)
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        return entry[1]

    def _refresh(self, machine_id: str) -> None:
        """Reload one machine's entry (a background refresh; errors keep the old entry)."""
        try:
            self.load(machine_id)
        except Exception:
            log.warning("model cache: refreshing %s failed; serving the previous answer", machine_id, exc_info=True)
        finally:
            self._refreshing.discard(machine_id)

    def load(self, machine_id: str) -> CachedModel | None:
        """Read the machine's current model from the store, cache it and return it (None: no current model)."""
        generation = self._generation
        row = self.store.models.current(machine_id)
        cached = None
        if row is not None:
            body = json.dumps(model_out(row), allow_nan=False, separators=(",", ":")).encode()
            cached = CachedModel(model_etag(row), body, row.version, row)
        with self._lock:
            self.loads += 1
            if generation == self._generation:
                self._entries[machine_id] = (time.monotonic(), cached)
        return cached

    def get(self, machine_id: str) -> CachedModel | None:
        """Return the current model, from the cache when fresh."""
        hit, entry = self.fresh(machine_id)
        return entry if hit else self.load(machine_id)

    def invalidate(self, machine_id: str | None = None) -> None:
        """Forget one machine's cached model (or all of them)."""
        with self._lock:
            self._generation += 1
            if machine_id is None:
                self._entries.clear()
            else:
                self._entries.pop(machine_id, None)


@dataclass
class ApiState:
    """Everything a request handler needs."""

    store: Store
    token: str
    models: ModelCache
    jobs: Jobs  # submits jobs; runs them in this process too unless the server was started with --no-jobs
    extra: dict[str, Any] = field(default_factory=dict)


def get_state(request: Request) -> ApiState:
    """Return the application's state."""
    return request.app.state.driftlab


def get_store(request: Request) -> Store:
    """Return the application's store."""
    return get_state(request).store


def require_token(request: Request) -> None:
    """Refuse a write without ``Authorization: Bearer <token>`` (401), or any write when no token is set (403).

    The front door (api.guard) has already checked this before the body was read; this dependency
    keeps every write route safe on its own and declares the requirement in the OpenAPI document.
    """
    refused = token_problem(get_state(request).token, request.headers.get("authorization"))
    if refused is not None:
        raise HTTPException(refused[0], refused[1], headers=refused[2] or None)
