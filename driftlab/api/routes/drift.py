"""Drift: the error history of one axis and term across a machine's campaigns, in wall-clock time."""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Depends, Query

from driftlab.api.deps import get_store
from driftlab.api.routes.machines import MachineId
from driftlab.api.schemas import DriftOut, DriftPoint
from driftlab.api.strict import StrictJsonRoute
from driftlab.campaigns.readings_repo import DriftQuery
from driftlab.campaigns.store import Store
from driftlab.errors import BadRequestError
from driftlab.vocabulary import Axis, Term

router = APIRouter(tags=["drift"], route_class=StrictJsonRoute)


def _aware(dt: datetime | None) -> datetime | None:
    """Return a timezone-aware datetime (naive ones are UTC)."""
    if dt is None:
        return None
    return dt if dt.tzinfo else dt.replace(tzinfo=UTC)


@dataclass(frozen=True)
class DriftOptions:
    """Where and when a drift request reads: the position, direction, time range and interpolation."""

    position: float | None
    direction: int | None
    start: datetime | None
    end: datetime | None
    interpolate: bool


def drift_options(
    position: Annotated[float | None, Query(ge=-1e6, le=1e6, description="at this position (mm or deg)")] = None,
    direction: Annotated[int | None, Query(ge=-1, le=1, description="+1 or -1 (default both)")] = None,
    start: Annotated[datetime | None, Query(description="from this UTC time")] = None,
    end: Annotated[datetime | None, Query(description="up to this UTC time")] = None,
    interpolate: Annotated[bool, Query(description="interpolate along position within each sweep")] = False,
) -> DriftOptions:
    """Return the request's DriftOptions (checked in the route, after FastAPI's own validation)."""
    return DriftOptions(position, direction, start, end, interpolate)


@router.get("/machines/{machine_id}/drift", response_model=DriftOut, summary="Drift of an axis/term across campaigns")
def drift(
    machine_id: MachineId,
    axis: Axis,
    term: Term,
    store: Annotated[Store, Depends(get_store)],
    options: Annotated[DriftOptions, Depends(drift_options)],
) -> DriftOut:
    """Return the measured values of (axis, term) over a machine's campaigns (nearest or interpolated position)."""
    o = options
    if o.direction == 0:
        raise BadRequestError("direction must be +1 or -1")
    frame = store.readings.query_drift(
        DriftQuery(machine_id, axis, term, o.position, o.direction, _aware(o.start), _aware(o.end), o.interpolate)
    )
    points = [
        DriftPoint(
            campaign_id=int(r.campaign_id),
            time=r.time.to_pydatetime(),
            time_s=float(r.time_s),
            position=float(r.position),
            direction=int(r.direction),
            sweep=int(r.sweep),
            value=float(r.value),
        )
        for r in frame.itertuples(index=False)
        if math.isfinite(r.value) and math.isfinite(r.time_s)
    ]
    return DriftOut(
        machine_id=machine_id,
        axis=axis,
        term=term,
        position=o.position,
        direction=o.direction,
        interpolate=o.interpolate,
        points=points,
    )
