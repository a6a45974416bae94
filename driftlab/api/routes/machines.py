"""Machines: the list and one machine with its campaign count and current model version."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path

from driftlab.api.deps import get_store
from driftlab.api.schemas import ID_PATTERN, MachineList, MachineOut
from driftlab.api.strict import Limit, Offset, StrictJsonRoute
from driftlab.campaigns.repository import Page
from driftlab.campaigns.store import MachineInfo, Store

router = APIRouter(tags=["machines"], route_class=StrictJsonRoute)

MachineId = Annotated[str, Path(pattern=ID_PATTERN, description="machine id (the bundle's machine.id)")]


def _out(m: MachineInfo) -> MachineOut:
    """Return the response model of a machine (the same fields as the store's MachineInfo)."""
    return MachineOut(**dict(m))


@router.get("/machines", response_model=MachineList, summary="List machines")
def list_machines(
    store: Annotated[Store, Depends(get_store)],
    limit: Limit = 100,
    offset: Offset = 0,
) -> MachineList:
    """Return a page of machines ordered by id."""
    return MachineList(
        items=[_out(m) for m in store.campaigns.machines(Page(limit, offset))], limit=limit, offset=offset
    )


@router.get("/machines/{machine_id}", response_model=MachineOut, summary="Get a machine")
def get_machine(machine_id: MachineId, store: Annotated[Store, Depends(get_store)]) -> MachineOut:
    """Return one machine."""
    return _out(store.campaigns.machine(machine_id))
