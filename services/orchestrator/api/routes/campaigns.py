"""/campaigns: create, show, results."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Response, status

from services.orchestrator.api.deps import Authorized, SchedulerDep, StoreDep
from services.orchestrator.api.schemas import CampaignCreate, CampaignPublic, campaign_public
from services.protocol.scenario import ScenarioError, build_scenario

router = APIRouter(prefix="/campaigns", tags=["campaigns"])

NOT_FOUND = {404: {"description": "no campaign with this id"}}


def _get(store, campaign_id: str) -> dict[str, Any]:
    row = store.campaign(campaign_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign_id!r}")
    return row


@router.post("", status_code=status.HTTP_201_CREATED, response_model=CampaignPublic, dependencies=[Authorized],
             responses={422: {"description": "invalid preset, override or field"}})
def create_campaign(body: CampaignCreate, response: Response, store: StoreDep, scheduler: SchedulerDep) -> CampaignPublic:
    """Store a campaign and queue its tests x algorithms episodes on the live rigs."""
    try:
        scenario = build_scenario(body.preset, body.overrides)
    except ScenarioError as err:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, str(err)) from None
    algorithms = list(dict.fromkeys(body.algorithms))
    cid = store.create_campaign(
        preset=body.preset, overrides=body.overrides, scenario=scenario.model_dump(mode="json"), algorithms=algorithms,
        tests=body.tests, seed=body.seed, mode=body.mode, name=body.name,
    )
    scheduler.submit(cid)
    response.headers["Location"] = f"/campaigns/{cid}"
    return campaign_public(_get(store, cid))


@router.get("/{campaign_id}", response_model=CampaignPublic, responses=NOT_FOUND)
def show_campaign(campaign_id: str, store: StoreDep) -> CampaignPublic:
    """Status, progress, timings, the resolved scenario and the POD fit of one campaign."""
    return campaign_public(_get(store, campaign_id))


@router.get("/{campaign_id}/results", responses={**NOT_FOUND, 409: {"description": "the campaign has not finished"}})
def campaign_results(campaign_id: str, store: StoreDep) -> dict[str, Any]:
    """The results object: the same as ``ra2vipas simulate --json`` for the same preset, overrides and seed."""
    row = _get(store, campaign_id)
    if row["status"] != "done" or row["results"] is None:
        p = row["progress"]
        raise HTTPException(status.HTTP_409_CONFLICT, f"campaign {campaign_id} is {row['status']} ({p['done']}/{p['total']} episodes done)")
    return row["results"]
