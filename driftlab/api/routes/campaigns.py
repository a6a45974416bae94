"""Campaigns and their stages and channels (read), and deleting a campaign (write)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response

from driftlab.api.deps import get_store, require_token
from driftlab.api.schemas import (
    ID_PATTERN,
    CampaignDetail,
    CampaignList,
    CampaignOut,
    ChannelOut,
    StageOut,
)
from driftlab.api.strict import CampaignId, Limit, Offset, StrictJsonRoute
from driftlab.campaigns.store import Store
from driftlab.errors import NotFoundError

router = APIRouter(tags=["campaigns"], route_class=StrictJsonRoute)


def _stage(s: object) -> StageOut:
    """Return the response model of a stage row (read by attribute)."""
    return StageOut.model_validate(s, from_attributes=True)


def _channel(c: object) -> ChannelOut:
    """Return the response model of a channel row (read by attribute)."""
    return ChannelOut.model_validate(c, from_attributes=True)


@router.get("/campaigns", response_model=CampaignList, summary="List campaigns")
def list_campaigns(
    store: Annotated[Store, Depends(get_store)],
    machine_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> CampaignList:
    """Return a page of campaigns (optionally of one machine), oldest first, with their sizes."""
    rows = store.campaigns.summaries(machine_id)[offset : offset + limit]
    return CampaignList(items=[CampaignOut(**dict(r)) for r in rows], limit=limit, offset=offset)


@router.get("/campaigns/{campaign_id}", response_model=CampaignDetail, summary="Get a campaign")
def get_campaign(campaign_id: CampaignId, store: Annotated[Store, Depends(get_store)]) -> CampaignDetail:
    """Return a campaign with its stages, channels and campaign.json document."""
    detail = store.campaigns.detail(campaign_id)
    summary = next((s for s in store.campaigns.summaries(detail.row.machine_id) if s.id == campaign_id), None)
    if summary is None:  # deleted between the two reads
        raise NotFoundError(f"no campaign {campaign_id}")
    return CampaignDetail(
        **dict(summary),
        stage_list=[_stage(s) for s in detail.stages],
        channel_list=[_channel(c) for c in detail.channels],
        meta=detail.row.meta,
    )


@router.get("/campaigns/{campaign_id}/stages", response_model=list[StageOut], summary="List a campaign's stages")
def get_stages(campaign_id: CampaignId, store: Annotated[Store, Depends(get_store)]) -> list[StageOut]:
    """Return the stages of a campaign in plan order."""
    return [_stage(s) for s in store.campaigns.detail(campaign_id).stages]


@router.get(
    "/campaigns/{campaign_id}/channels",
    response_model=list[ChannelOut],
    summary="List a campaign's thermocouple channels",
)
def get_channels(campaign_id: CampaignId, store: Annotated[Store, Depends(get_store)]) -> list[ChannelOut]:
    """Return the channels of a campaign in card order."""
    return [_channel(c) for c in store.campaigns.detail(campaign_id).channels]


@router.delete(
    "/campaigns/{campaign_id}",
    status_code=204,
    response_class=Response,
    dependencies=[Depends(require_token)],
    summary="Delete a campaign and all its samples",
)
def delete_campaign(campaign_id: CampaignId, store: Annotated[Store, Depends(get_store)]) -> Response:
    """Delete a campaign with its samples, stages and channels in one transaction."""
    store.campaigns.delete(campaign_id)
    return Response(status_code=204)
