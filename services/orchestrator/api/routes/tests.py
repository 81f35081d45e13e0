"""/campaigns/{id}/tests: the per-test outcome table, one test's trace and its figure."""

from __future__ import annotations

from typing import Annotated, Any, Optional

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.orchestrator.api.deps import CampaignDep, StoreDep, get_campaign
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.negotiate import ImageFormat, image_format
from ra2vipas.services.orchestrator.api.render import FigureSource, PlotKey, plot_responses, serve_figure
from ra2vipas.services.orchestrator.api.schemas import (
    MAX_OFFSET,
    MAX_PAGE,
    MAX_TESTS,
    AlgorithmName,
    EpisodeStatus,
    OutcomePage,
    TracePublic,
)
from ra2vipas.services.orchestrator.api.views import outcome_public, trace_public

router = APIRouter(prefix="/campaigns/{campaign_id}/tests", tags=["tests"])

TestIndex = Annotated[int, Path(ge=0, le=MAX_TESTS - 1, description="test index k")]
Algorithm = Annotated[AlgorithmName, Path(description="algorithm")]


@router.get("", response_model=OutcomePage, responses=responses(404, 422))
def list_outcomes(
    campaign: CampaignDep,
    store: StoreDep,
    algorithm: Annotated[Optional[AlgorithmName], Query(description="only this algorithm")] = None,
    status_: Annotated[Optional[EpisodeStatus], Query(alias="status", description="only tests in this state")] = None,
    hit: Annotated[Optional[bool], Query(description="only finished tests whose final choice was (true) or was not (false) the Tx")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
) -> OutcomePage:
    """One row per (test, algorithm), ordered by test index: the Tx's index, the final choice
    î, whether it hit, the hit rate over the test, the first hit and the time after which it
    stays on the Tx."""
    if algorithm is not None and algorithm not in campaign["algorithms"]:
        raise RequestValidationError([{"loc": ("query", "algorithm"), "type": "value_error",
                                       "msg": f"campaign {campaign['id']} ran {', '.join(campaign['algorithms'])}, not {algorithm!r}"}])
    rows, total = store.episode_page(campaign["id"], algorithm=algorithm, status=status_, hit=hit, limit=limit, offset=offset)
    period = campaign["scenario"]["rf_period_s"]
    return OutcomePage(items=[outcome_public(r, period) for r in rows], total=total, limit=limit, offset=offset)


def _finished_episode(store, campaign: dict[str, Any], test_index: int, algorithm: str) -> dict[str, Any]:
    row = store.episode(campaign["id"], test_index, algorithm)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"campaign {campaign['id']} has no test {test_index} of {algorithm} "
                            f"(tests 0..{campaign['tests'] - 1} of {', '.join(campaign['algorithms'])})")
    if row["status"] != "done":
        raise HTTPException(status.HTTP_409_CONFLICT, f"test {test_index} ({algorithm}) is {row['status']}: no trace yet")
    return row


@router.get("/{test_index}/{algorithm}", response_model=TracePublic,
            responses=responses(404, 409, 422, e409="the test has not finished"))
def test_trace(campaign: CampaignDep, store: StoreDep, test_index: TestIndex, algorithm: Algorithm) -> TracePublic:
    """Per step of one test: the pan angle s_t, the reward, the estimate γ̂_t, î_t and whether
    it hit; and the targets (bearing, range, which one is the Tx)."""
    row = _finished_episode(store, campaign, test_index, algorithm)
    return trace_public(row, campaign["scenario"]["rf_period_s"])


@router.get("/{test_index}/{algorithm}/plot", response_class=Response, responses=plot_responses("the test has not finished"))
async def test_plot(campaign_id: str, request: Request, test_index: TestIndex, algorithm: Algorithm,
                    fmt: Annotated[Optional[ImageFormat], Query(alias="format", description="png (default) or svg")] = None) -> Response:
    """One test's episode: the targets and the FoV at the final estimate seen from above, and
    the pan trajectory with its FoV and the estimate γ̂_t against time.

    Cached once drawn (a finished test never changes, even while its campaign runs); 503 with
    ``Retry-After`` while every renderer is busy."""
    kind = image_format(request, fmt)
    store = request.app.state.store

    def read() -> FigureSource:
        campaign = get_campaign(campaign_id, store)
        row = _finished_episode(store, campaign, test_index, algorithm)
        return FigureSource(plots.PlotJob("episode", kind, {"scenario": campaign["scenario"], "episode": row}))

    return await serve_figure(request, PlotKey(campaign_id, "episode", kind, (test_index, algorithm)), read)
