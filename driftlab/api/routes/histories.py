"""Temperature, condition and error histories of a campaign: time range, filters, paging, downsampling.

Raw histories are paged by ``limit`` with either ``offset`` or an opaque ``cursor`` (keyset paging:
the next page starts after the last row of this one, one range scan of the primary key). With
``buckets`` the store computes min/mean/max per equal-width time bucket in SQL (no paging).
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import timedelta
from operator import attrgetter, itemgetter
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query

from driftlab.api.deps import get_store
from driftlab.api.routes.machines import MachineId
from driftlab.api.schemas import (
    ID_PATTERN,
    Bucket,
    Condition,
    ConditionBucket,
    ConditionHistory,
    ConditionRow,
    ErrorHistory,
    ErrorSampleOut,
    LatestTemperatures,
    TemperatureHistory,
    TemperaturePoint,
)
from driftlab.api.strict import Buckets, CampaignId, RowLimit, RowOffset, StrictJsonRoute
from driftlab.campaigns.ingest import CONDITION_VALUE_COLUMNS
from driftlab.campaigns.readings_repo import ErrorFilter, HistoryPage
from driftlab.campaigns.store import Store
from driftlab.errors import BadRequestError, NotFoundError
from driftlab.jsonsafe import finite_or_none
from driftlab.vocabulary import Axis, Term

router = APIRouter(tags=["histories"], route_class=StrictJsonRoute)

Limit = RowLimit
Offset = RowOffset
Cursor = Annotated[str | None, Query(max_length=200, description="next_cursor of the previous page")]
StartS = Annotated[float | None, Query(ge=-1e12, le=1e12, description="from this time (s since start)")]
EndS = Annotated[float | None, Query(ge=-1e12, le=1e12, description="up to this time (s since start)")]


def encode_cursor(kind: str, last: float | int) -> str:
    """Return an opaque cursor naming the last row of a page."""
    raw = json.dumps({"k": kind, "after": last}, separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def decode_cursor(cursor: str | None, kind: str) -> float | int | None:
    """Return the position a cursor names; BadRequestError (400) when it is not one of ours."""
    if cursor is None:
        return None
    try:
        raw = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4))
        data = json.loads(raw)
        after = data["after"]
        if data["k"] != kind or isinstance(after, bool) or not isinstance(after, (int, float)):
            raise ValueError
        if kind == "error":  # a sequence number: an integer the database's BIGINT can hold
            if not isinstance(after, int) or not 0 <= after < 2**63:
                raise ValueError
        else:  # a time in seconds (within the range start_s/end_s accept), compared as a float
            after = float(after)
            if not (math.isfinite(after) and abs(after) <= 1e12):
                raise ValueError
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError):
        raise BadRequestError(f"not a valid {kind} cursor: {cursor[:60]!r}") from None
    return after


@dataclass(frozen=True)
class Window:
    """The time range and page of a history request, checked once for every history endpoint."""

    start_s: float | None
    end_s: float | None
    limit: int
    offset: int
    cursor: str | None

    def page(self, kind: str) -> HistoryPage:
        """Return the store's page of this window for a ``kind`` of history (its cursor decoded)."""
        return HistoryPage(self.start_s, self.end_s, decode_cursor(self.cursor, kind), self.offset, self.limit)


def window(
    start_s: StartS = None, end_s: EndS = None, limit: Limit = 1000, offset: Offset = 0, cursor: Cursor = None
) -> Window:
    """Return the request's Window; BadRequestError (400) for a reversed range or offset with cursor."""
    if start_s is not None and end_s is not None and end_s < start_s:
        raise BadRequestError(f"time range ends ({end_s}) before it starts ({start_s})")
    if cursor is not None and offset:
        raise BadRequestError("give either offset or cursor, not both")
    return Window(start_s, end_s, limit, offset, cursor)


Paging = Annotated[Window, Depends(window)]


def _bucket(time_s: float, t_end_s: float, n: Any, lo: Any, mean: Any, hi: Any) -> Bucket:
    return Bucket(
        time_s=time_s,
        t_end_s=t_end_s,
        n=int(n),
        min=finite_or_none(lo),
        mean=finite_or_none(mean),
        max=finite_or_none(hi),
    )


def _next(kind: str, rows: Sequence[Any], page: Window, key: Callable[[Any], float | int]) -> str | None:
    """Return the cursor of the page after a full one (its last row's ``key``), None after the last page."""
    return encode_cursor(kind, key(rows[-1])) if rows and len(rows) == page.limit else None


@router.get(
    "/campaigns/{campaign_id}/temperatures/{channel}",
    response_model=TemperatureHistory,
    response_model_exclude_unset=True,
    summary="Temperature history of a channel",
)
def temperatures(
    campaign_id: CampaignId,
    channel: Annotated[str, Path(pattern=ID_PATTERN, description="channel name, e.g. T9")],
    store: Annotated[Store, Depends(get_store)],
    page: Paging,
    buckets: Buckets = None,
) -> TemperatureHistory:
    """Return a channel's readings in a time range (paged), or min/mean/max per time bucket."""
    if buckets:
        frame = store.readings.temperature_history(campaign_id, channel, page.start_s, page.end_s, buckets)
        out = [
            _bucket(r.time_s, r.t_end_s, r.n, r.value_min, r.value_mean, r.value_max)
            for r in frame.itertuples(index=False)
        ]
        return TemperatureHistory(campaign_id=campaign_id, channel=channel, buckets=out)
    rows = store.readings.temperature_page(campaign_id, channel, page.page("temperature"))
    points = [TemperaturePoint(time_s=t, value=finite_or_none(v)) for t, v in rows]
    nxt = _next("temperature", rows, page, itemgetter(0))
    return TemperatureHistory(campaign_id=campaign_id, channel=channel, points=points, next_cursor=nxt)


@router.get(
    "/campaigns/{campaign_id}/conditions",
    response_model=ConditionHistory,
    response_model_exclude_unset=True,
    summary="Machine-state history",
)
def conditions(
    campaign_id: CampaignId,
    store: Annotated[Store, Depends(get_store)],
    page: Paging,
    column: Annotated[list[Condition] | None, Query(max_length=7, description="columns (default all seven)")] = None,
    buckets: Buckets = None,
) -> ConditionHistory:
    """Return spindle, feed and axis positions over a time range (paged), or min/mean/max per bucket."""
    cols: list[str] = list(dict.fromkeys(column)) if column else list(CONDITION_VALUE_COLUMNS)
    if buckets:
        frame = store.readings.condition_history(campaign_id, cols, page.start_s, page.end_s, buckets)
        out = []
        for r in frame.to_dict("records"):
            span = (r["time_s"], r["t_end_s"], r["n"])
            values = {c: _bucket(*span, r[f"{c}_min"], r[f"{c}_mean"], r[f"{c}_max"]) for c in cols}
            out.append(ConditionBucket(time_s=r["time_s"], t_end_s=r["t_end_s"], n=int(r["n"]), values=values))
        return ConditionHistory(campaign_id=campaign_id, columns=cols, buckets=out)
    rows = store.readings.condition_page(campaign_id, cols, page.page("condition"))
    points = [ConditionRow(time_s=r[0], **{c: finite_or_none(v) for c, v in zip(cols, r[1:])}) for r in rows]
    nxt = _next("condition", rows, page, itemgetter(0))
    return ConditionHistory(campaign_id=campaign_id, columns=cols, points=points, next_cursor=nxt)


@router.get(
    "/campaigns/{campaign_id}/errors",
    response_model=ErrorHistory,
    response_model_exclude_unset=True,
    summary="Measured error samples of a campaign",
)
def errors(
    campaign_id: CampaignId,
    store: Annotated[Store, Depends(get_store)],
    page: Paging,
    axis: Axis | None = None,
    term: Term | None = None,
    direction: Annotated[int | None, Query(ge=-1, le=1, description="+1 or -1")] = None,
) -> ErrorHistory:
    """Return a page of error samples in measurement order, filtered by axis, term, direction and time."""
    if direction == 0:
        raise BadRequestError("direction must be +1 or -1")
    rows = store.readings.error_page(campaign_id, ErrorFilter(axis, term, direction), page.page("error"))
    items = [
        ErrorSampleOut(
            seq=r.seq,
            time_s=r.time_s,
            axis=r.axis,
            term=r.term,
            position=r.position,
            direction=r.direction,
            sweep=r.sweep,
            flags=r.flags,
            value=r.value,
        )
        for r in rows
    ]
    nxt = _next("error", rows, page, attrgetter("seq"))
    return ErrorHistory(campaign_id=campaign_id, items=items, next_cursor=nxt)


@router.get(
    "/machines/{machine_id}/temperatures/latest",
    response_model=LatestTemperatures,
    summary="The machine's latest thermocouple scan",
)
def latest_temperatures(machine_id: MachineId, store: Annotated[Store, Depends(get_store)]) -> LatestTemperatures:
    """Return the last scan of the machine's latest campaign with readings (degC per channel)."""
    found = store.readings.latest_scan(machine_id)
    if found is None:
        raise NotFoundError(f"machine {machine_id!r} has no temperature readings")
    return LatestTemperatures(
        machine_id=machine_id,
        campaign_id=found.campaign_id,
        time_s=found.time_s,
        time=found.started_at + timedelta(seconds=found.time_s),
        temperatures={c: finite_or_none(v) for c, v in found.values.items()},
    )
