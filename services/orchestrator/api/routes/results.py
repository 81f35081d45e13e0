"""/campaigns/{id}/results (JSON or CSV) and the campaign-level figures: DR curves (paper
Fig. 4) and the learned POD (paper Fig. 3), drawn by the renderer processes and cached
(``ra2vipas.services.orchestrator.api.render``)."""

from __future__ import annotations

from typing import Annotated, Any, Optional

from fastapi import APIRouter, HTTPException, Query, Request, Response, status

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.orchestrator.api.deps import CampaignDep, get_campaign
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.export import Table, write_results_csv
from ra2vipas.services.orchestrator.api.negotiate import ImageFormat, ResultsFormat, image_format, results_format
from ra2vipas.services.orchestrator.api.render import FigureSource, PlotKey, plot_responses, serve_figure
from ra2vipas.services.orchestrator.api.schemas import ResultsPublic

router = APIRouter(prefix="/campaigns/{campaign_id}", tags=["results"])

NOT_DONE = "the campaign is still queued or running (or stopped before any episode was recorded): no results yet"


def finished_results(campaign: dict[str, Any], store: Any = None) -> dict[str, Any]:
    """The stored results object of a done campaign; for a cancelled or failed one (with a
    ``store``), the reduction of the episodes it recorded, marked ``partial`` with
    ``tests_recorded``; 409 while it runs or if nothing was recorded."""
    if campaign["status"] == "done" and campaign["results"] is not None:
        return _with_id(campaign, _with_overrides(campaign["results"]))
    p = campaign["progress"]
    if store is not None and campaign["status"] in ("cancelled", "failed") and p["done"]:
        from ra2vipas.services.orchestrator.study_store import point_results

        results, tests, _ = point_results(store, campaign)
        if results is not None:
            return _with_id(campaign, {**_with_overrides(results), "partial": True, "tests_recorded": tests})
    raise HTTPException(status.HTTP_409_CONFLICT,
                        f"campaign {campaign['id']} is {campaign['status']} ({p['done']}/{p['total']} episodes done): no results"
                        + (" yet" if campaign["status"] in ("queued", "training", "running") else ""))


def _with_id(campaign: dict[str, Any], results: dict[str, Any]) -> dict[str, Any]:
    """The results object led by the id of the campaign it is of (null in this process)."""
    return {"id": campaign["id"], **{k: v for k, v in results.items() if k != "id"}}


def _with_overrides(results: dict[str, Any]) -> dict[str, Any]:
    """Results stored before they carried their ``overrides`` get them from their scenario."""
    if "overrides" in results:
        return results
    from ra2vipas.services.orchestrator.envelope import overrides_of

    return {"preset": results["preset"], "overrides": overrides_of(results["preset"], results["scenario"]), **results}


@router.get("/results", response_model=ResultsPublic, response_model_exclude_unset=True,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}},
                             "description": "the results object (JSON), or as CSV with `?format=csv` or `Accept: text/csv`"},
                       **responses(404, 409, 422, e409=NOT_DONE)})
def campaign_results(campaign: CampaignDep, request: Request,
                     fmt: Annotated[Optional[ResultsFormat], Query(alias="format", description="json (default) or csv")] = None,
                     table: Annotated[Table, Query(description="with CSV: dr (one row per algorithm x step, default) or summary "
                                                               "(one row per algorithm)")] = "dr") -> Any:
    """Per algorithm: the DR curve with Wilson 95 % bands, the final DR, the time to DR ≥ 0.9 and
    the in-FoV rate, with the preset, the full scenario and the seed (the same object as
    ``ra2vipas simulate --json``), with ``overrides``: the parameters that differ from the
    preset. The CSV is a tidy table (``?table=dr``: one row per algorithm x step;
    ``?table=summary``: one row per algorithm), each row led by the campaign's id, name, preset,
    seed, tests and one column per override.
    A cancelled or failed campaign's results are those of the episodes it recorded, with
    ``partial: true`` and ``tests_recorded``."""
    results = finished_results(campaign, request.app.state.store)
    if results_format(request, fmt) == "csv":
        suffix = "" if table == "dr" else f"-{table}"
        return Response(write_results_csv(results, campaign["id"], campaign["name"], table), media_type="text/csv",
                        headers={"Content-Disposition": f'inline; filename="campaign-{campaign["id"]}{suffix}.csv"'})
    return results


@router.get("/plots/dr", response_class=Response, responses=plot_responses(NOT_DONE))
async def dr_plot(campaign_id: str, request: Request,
                  fmt: Annotated[Optional[ImageFormat], Query(alias="format", description="png (default) or svg")] = None) -> Response:
    """DR_t of every algorithm with its Wilson 95 % band against time (paper Fig. 4).

    Drawn once per format by a renderer process and then served from the cache (a done
    campaign never changes); 503 with ``Retry-After`` while every renderer is busy."""
    kind = image_format(request, fmt)
    store = request.app.state.store

    def read() -> FigureSource:
        campaign = get_campaign(campaign_id, store)
        results = finished_results(campaign, store)
        return FigureSource(plots.PlotJob("dr", kind, {"results": results, "name": campaign["name"]}),
                            cacheable=not results.get("partial"))  # partial: an episode in flight may still land

    return await serve_figure(request, PlotKey(campaign_id, "dr", kind), read)


@router.get("/plots/reliability", response_class=Response, responses=plot_responses(NOT_DONE))
async def reliability_plot(campaign_id: str, request: Request,
                           fmt: Annotated[Optional[ImageFormat], Query(alias="format", description="png (default) or svg")] = None
                           ) -> Response:
    """Reliability diagram of every algorithm's final confidence: the share of final answers
    that were the Tx against the confidence given to them (10 bins), ECE in the legend."""
    kind = image_format(request, fmt)
    store = request.app.state.store

    def read() -> FigureSource:
        campaign = get_campaign(campaign_id, store)
        results = finished_results(campaign, store)
        return FigureSource(plots.PlotJob("reliability", kind, {"results": results, "name": campaign["name"]}),
                            cacheable=not results.get("partial"))  # partial: an episode in flight may still land

    return await serve_figure(request, PlotKey(campaign_id, "reliability", kind), read)


@router.get("/plots/pod", response_class=Response, responses=plot_responses("the POD model is not trained yet (or was not kept)"))
async def pod_plot(campaign_id: str, request: Request,
                   fmt: Annotated[Optional[ImageFormat], Query(alias="format", description="png (default) or svg")] = None) -> Response:
    """The learned POD p̂_D(r) (mean ± 2 std) against the true p_D(r), with the truth at every
    training sample (paper Fig. 3). The noisy labels the learner fitted are not kept by the
    orchestrator, so the points are the true p_D at each sample's true RSSI.

    Cached once the model is stored (it never changes after); 503 with ``Retry-After`` while
    every renderer is busy."""
    kind = image_format(request, fmt)
    store = request.app.state.store

    def read() -> FigureSource:
        # the model first: once it is stored, the campaign row read after it carries its R² and pod_job
        artifacts = store.pod_artifacts(campaign_id)
        campaign = get_campaign(campaign_id, store)
        if not artifacts or artifacts["model"] is None:
            raise HTTPException(status.HTTP_409_CONFLICT,
                                f"campaign {campaign['id']} has no POD model yet ({campaign['status']})")
        r2 = campaign["pod_r2"]
        what = campaign["preset"] + "".join(f", {k}={v}" for k, v in (campaign["overrides"] or {}).items())
        title = (f"POD regression, {campaign['name'] + ' — ' if campaign['name'] else ''}{what}, seed {campaign['seed']}"
                 + ("" if r2 is None else f": R² {r2:.3f}"))
        job = plots.PlotJob("pod", kind, {"scenario": campaign["scenario"], "model": artifacts["model"],
                                          "truth": artifacts["truth"], "title": title})
        return FigureSource(job, cacheable=campaign["pod_job"] is not None)

    return await serve_figure(request, PlotKey(campaign_id, "pod", kind), read)
