"""/campaigns: create, list, show, cancel, delete."""

from __future__ import annotations

from typing import Annotated, Optional

from fastapi import APIRouter, HTTPException, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError

from ra2vipas.services.orchestrator.api.deps import Authorized, CampaignDep, SchedulerDep, StoreDep
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.routes.catalog import check_policies
from ra2vipas.services.orchestrator.api.schemas import (
    MAX_OFFSET,
    MAX_PAGE,
    CampaignCreate,
    CampaignPage,
    CampaignPublic,
    CampaignStatus,
)
from ra2vipas.services.orchestrator.api.views import campaign_public
from ra2vipas.services.orchestrator.rigcheck import TargetingError, resolve_targeting
from ra2vipas.services.orchestrator.storage import CampaignActiveError, CampaignInStudyError
from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario
from ra2vipas.services.protocol.versions import campaign_features

router = APIRouter(prefix="/campaigns", tags=["campaigns"])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=CampaignPublic, dependencies=[Authorized],
             responses={201: {"headers": {"Location": {"description": "the new campaign's URL", "schema": {"type": "string"}}}},
                        **responses(401, 413, 422)})
def create_campaign(body: CampaignCreate, response: Response, store: StoreDep, scheduler: SchedulerDep) -> CampaignPublic:
    """Store a campaign and queue its tests x algorithms episodes on the live rigs.

    The preset and overrides are resolved into the full scenario first: an unknown preset or
    parameter, or a value out of its range, is a 422 naming it and what it accepts, and
    nothing is stored.

    Then it is checked against the rigs it targets (``rigs``, ``rig_kind``, or every live rig):
    a scenario parameter (or the mode) that contradicts a targeted rig's descriptor is a 422
    naming the field, the rig and both values, unless ``use_rig_values`` takes the rig's values
    into the scenario (docs/protocol.md, "Rig descriptor"). A campaign that uses a protocol
    feature newer than a targeted rig speaks (``stop_confidence`` on a rig that serves no
    descriptor: protocol 1.0) is a 422 naming the rig, the feature and both versions
    (docs/protocol.md, "Compatibility"). A policy that no live controller among the targeted
    rigs serves is a 422 listing the ones they serve (with no such rig live yet: a policy not
    installed here).
    """
    try:
        scenario = build_scenario(body.preset, body.overrides)
    except ScenarioError as err:
        loc = ["body", "preset"] if str(err).startswith("unknown preset") else ["body", "overrides"]
        raise RequestValidationError([{"loc": tuple(loc), "msg": str(err), "type": "value_error"}]) from None
    live = set(scheduler.live_rigs())
    descriptors = {name: d for name, d in scheduler.descriptors().items() if name in live}
    try:
        scenario, targeting = resolve_targeting(scenario, body.mode, body.rigs, body.rig_kind, body.use_rig_values, descriptors,
                                                features=campaign_features(body.stop_confidence, body.algorithms, scenario),
                                                protocols={name: v for name, v in scheduler.protocols().items() if name in live})
    except TargetingError as err:
        raise RequestValidationError([{"loc": ("body", *where.split(".")), "msg": msg, "type": "value_error"}
                                      for where, msg in err.errors]) from None
    algorithms = list(dict.fromkeys(body.algorithms))
    check_policies(algorithms, {name: served for name, served in scheduler.served().items()
                                if name in live and _targets(name, body.rigs, body.rig_kind, descriptors)})
    resolved = scenario.model_dump(mode="json")
    taken = list((targeting or {}).get("rig_values", {}))  # the rigs' values count as overrides of the preset
    overrides = {name: resolved[name] for name in [*body.overrides, *taken]}  # stored with the scenario's types (3 -> 3.0)
    cid = store.create_campaign(
        preset=body.preset, overrides=overrides, scenario=resolved, algorithms=algorithms,
        tests=body.tests, seed=body.seed, mode=body.mode, name=body.name, stop_confidence=body.stop_confidence,
        targeting=targeting,
    )
    scheduler.submit(cid)
    response.headers["Location"] = f"/campaigns/{cid}"
    row = store.campaign(cid)
    assert row is not None
    return campaign_public(row, storage_fault=store.fault)


def _targets(rig: str, rigs: list[str] | None, rig_kind: str | None, descriptors: dict) -> bool:
    """Whether a campaign that targets ``rigs`` / ``rig_kind`` may run on live rig ``rig``."""
    if rigs and rig not in rigs:
        return False
    if rig_kind:
        descriptor = descriptors.get(rig)
        return descriptor is not None and descriptor.kind == rig_kind
    return True


@router.get("", response_model=CampaignPage, responses=responses(422))
def list_campaigns(
    store: StoreDep,
    status_: Annotated[Optional[CampaignStatus], Query(alias="status", description="only campaigns in this state")] = None,
    preset: Annotated[Optional[str], Query(max_length=64, description="only campaigns of this preset")] = None,
    name: Annotated[Optional[str], Query(max_length=200, description="only campaigns with exactly this name")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description="page size")] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="campaigns to skip")] = 0,
) -> CampaignPage:
    """Campaigns, newest first, one page at a time."""
    rows, total = store.campaigns(status=status_, preset=preset, name=name, limit=limit, offset=offset)
    return CampaignPage(items=[campaign_public(r, storage_fault=store.fault) for r in rows], total=total, limit=limit, offset=offset)


@router.get("/{campaign_id}", response_model=CampaignPublic, responses=responses(404))
def show_campaign(campaign: CampaignDep, store: StoreDep) -> CampaignPublic:
    """Status, progress, timings, the resolved scenario (every parameter) and the POD fit (R²)."""
    return campaign_public(campaign, storage_fault=store.fault)


@router.post("/{campaign_id}/cancel", response_model=CampaignPublic, dependencies=[Authorized],
             responses=responses(401, 404, 409, e409="the campaign has already finished"))
def cancel_campaign(campaign: CampaignDep, store: StoreDep, scheduler: SchedulerDep) -> CampaignPublic:
    """Cancel a queued, training or running campaign: its in-flight episodes are stopped on the
    rigs and it keeps the tests recorded so far. 409 if it has already finished."""
    cid = campaign["id"]
    if not store.cancel_campaign(cid):
        current = store.campaign(cid) or campaign
        raise HTTPException(status.HTTP_409_CONFLICT, f"campaign {cid} has already finished ({current['status']})")
    scheduler.cancel(cid)
    row = store.campaign(cid)
    if row is None:  # deleted in between
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {cid!r}")
    return campaign_public(row, storage_fault=store.fault)


@router.delete("/{campaign_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response, dependencies=[Authorized],
               responses=responses(401, 404, 409, e409="the campaign is still queued, training or running (cancel it first), or "
                                                         "is a point of a study (delete the study)"))
def delete_campaign(campaign: CampaignDep, store: StoreDep, request: Request) -> Response:
    """Delete a finished (done, failed or cancelled) campaign and every test it recorded."""
    try:
        deleted = store.delete_campaign(campaign["id"])
    except (CampaignActiveError, CampaignInStudyError) as err:
        raise HTTPException(status.HTTP_409_CONFLICT, str(err)) from None
    if not deleted:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign['id']!r}")
    request.app.state.renderer.invalidate(campaign["id"])  # its cached figures
    return Response(status_code=status.HTTP_204_NO_CONTENT)
