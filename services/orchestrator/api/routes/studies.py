"""/studies: parameter studies (issue 10). A study is a grid of points, each an ordinary campaign
with the same seed (``study.py`` the domain, ``study_store.py`` the storage); the scheduler
serves a study's points interleaved, test by test."""

from __future__ import annotations

from typing import Annotated, Any, Optional

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.exceptions import RequestValidationError

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.orchestrator.api.deps import Authorized, SchedulerDep, StoreDep
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.negotiate import ImageFormat, ResultsFormat, image_format, results_format
from ra2vipas.services.orchestrator.api.render import FigureSource, PlotKey, plot_responses, serve_figure
from ra2vipas.services.orchestrator.api.routes.catalog import check_policies
from ra2vipas.services.orchestrator.api.schemas import MAX_OFFSET, MAX_PAGE, CampaignStatus
from ra2vipas.services.orchestrator.api.study_schemas import StudyCreate, StudyPage, StudyPublic, StudyResults
from ra2vipas.services.orchestrator.api.views import study_public
from ra2vipas.services.orchestrator.rigcheck import TargetingError, resolve_targeting
from ra2vipas.services.orchestrator.storage import ACTIVE, CampaignActiveError, Store
from ra2vipas.services.orchestrator.study import StudyError, check_size, expand, metrics_of, study_results, write_study_csv
from ra2vipas.services.orchestrator.study_store import StudyStore, point_results
from ra2vipas.services.protocol.versions import campaign_features

router = APIRouter(prefix="/studies", tags=["studies"])

StudyId = Annotated[str, Path(max_length=64, description="study id")]
NO_ROWS = "no point of the study has a recorded test yet"


def _studies(store: Store) -> StudyStore:
    return StudyStore(store)


def _get(store: Store, sid: str) -> dict[str, Any]:
    s = _studies(store).study(sid)
    if s is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no study {sid!r}")
    return s


def _invalid(err: StudyError) -> RequestValidationError:
    loc: tuple = ("body", err.where) + ((err.name,) if err.name and err.where in ("vary", "overrides") else ())
    return RequestValidationError([{"loc": loc, "msg": str(err), "type": "value_error"}])


@router.post("", status_code=status.HTTP_201_CREATED, response_model=StudyPublic, dependencies=[Authorized],
             responses={201: {"headers": {"Location": {"description": "the new study's URL", "schema": {"type": "string"}}}},
                        **responses(401, 413, 422)})
def create_study(body: StudyCreate, response: Response, store: StoreDep, scheduler: SchedulerDep) -> StudyPublic:
    """Store a study, one campaign per point of its grid (the product of the ``vary`` values, at
    most 256 points), all with the study's seed, and queue them; the scheduler interleaves the
    points so every point gets its first tests before any point gets its last.

    Every point's scenario is resolved first: an unknown preset or parameter, a value out of its
    range, a parameter both overridden and varied, or a grid too large is a 422 naming the
    parameter, the value and what it accepts, and nothing is stored. A study that uses a
    protocol feature (``stop_confidence``) no live rig speaks is a 422 naming the rigs.
    """
    algorithms = list(dict.fromkeys(body.algorithms))
    check_policies(algorithms, scheduler.served())
    try:
        grid = expand(body.preset, body.overrides, body.vary)
        check_size(len(grid), body.tests, len(algorithms))
    except StudyError as err:
        raise _invalid(err) from None
    live = set(scheduler.live_rigs())
    try:  # a study runs on the live rigs that speak what it needs (docs/protocol.md, "Compatibility")
        resolve_targeting(grid[0][1], body.mode, None, None, False, dict.fromkeys(live), features=campaign_features(body.stop_confidence, body.algorithms, grid[0][1]),
                          protocols={name: v for name, v in scheduler.protocols().items() if name in live})
    except TargetingError as err:
        raise RequestValidationError([{"loc": ("body", *where.split(".")), "msg": msg, "type": "value_error"}
                                      for where, msg in err.errors]) from None
    base = grid[0][1].model_dump(mode="json")
    overrides = {name: base[name] for name in body.overrides}  # stored with the scenario's types (3 -> 3.0)
    points = [({**overrides, **values}, scenario.model_dump(mode="json")) for values, scenario in grid]
    vary = {n: list(dict.fromkeys(values[n] for values, _ in grid)) for n in body.vary}
    sid, cids = _studies(store).create(preset=body.preset, overrides=overrides, vary=vary, points=points, algorithms=algorithms,
                                       tests=body.tests, seed=body.seed, mode=body.mode, name=body.name,
                                       stop_confidence=body.stop_confidence)
    for cid in cids:
        scheduler.submit(cid)
    response.headers["Location"] = f"/studies/{sid}"
    return study_public(_get(store, sid))


@router.get("", response_model=StudyPage, responses=responses(422))
def list_studies(
    store: StoreDep,
    status_: Annotated[Optional[CampaignStatus], Query(alias="status", description="only studies in this state")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description="page size")] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="studies to skip")] = 0,
) -> StudyPage:
    """Studies, newest first, one page at a time (without their points)."""
    rows, total = _studies(store).studies(status=status_, limit=limit, offset=offset)
    return StudyPage(items=[study_public(r) for r in rows], total=total, limit=limit, offset=offset)


@router.get("/{study_id}", response_model=StudyPublic, responses=responses(404))
def show_study(study_id: StudyId, store: StoreDep) -> StudyPublic:
    """Status, progress over every point, timings, and each point's values, campaign, status,
    progress and POD fit."""
    return study_public(_get(store, study_id))


@router.post("/{study_id}/cancel", response_model=StudyPublic, dependencies=[Authorized],
             responses=responses(401, 404, 409, e409="the study has already finished"))
def cancel_study(study_id: StudyId, store: StoreDep, scheduler: SchedulerDep) -> StudyPublic:
    """Cancel every unfinished point: in-flight episodes are stopped on the rigs, the tests
    recorded so far are kept (``/results`` then shows them, partial). 409 if it has finished."""
    s = _get(store, study_id)
    cids = _studies(store).cancel(study_id)
    if not cids:
        raise HTTPException(status.HTTP_409_CONFLICT, f"study {study_id} has already finished ({s['status']})")
    for cid in cids:
        scheduler.cancel(cid)
    return study_public(_get(store, study_id))


@router.delete("/{study_id}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response, dependencies=[Authorized],
               responses=responses(401, 404, 409, e409="the study is still running; cancel it first"))
def delete_study(study_id: StudyId, store: StoreDep, request: Request) -> Response:
    """Delete a finished (done, failed or cancelled) study, its points' campaigns and every
    test they recorded."""
    try:
        cids = _studies(store).delete(study_id)
    except CampaignActiveError as err:
        raise HTTPException(status.HTTP_409_CONFLICT, str(err)) from None
    if cids is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no study {study_id!r}")
    renderer = request.app.state.renderer
    for key in (study_id, *cids):
        renderer.invalidate(key)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def study_results_of(store: Store, study_id: str) -> dict[str, Any]:
    """The study's results object: each done point's stored results, and for an unfinished
    one the tests recorded so far (``partial``); 404 if there is no such study."""
    s = _get(store, study_id)
    shown = []
    partial = s["status"] != "done"
    where = {p["campaign_id"]: p for p in s["points"]}
    for c in _studies(store).points(study_id):
        results, tests, part = point_results(store, c)
        partial = partial or (part and results is not None)
        p = where[c["id"]]
        shown.append({"point": p["point"], "values": p["values"], "campaign_id": c["id"], "status": c["status"], "results": results,
                      "tests": tests})
    sps = None
    if s["status"] == "done" and not s["stop_confidence"] and s["started_at"] and s["finished_at"] and s["finished_at"] > s["started_at"]:
        steps = sum(c["results"]["scenario"]["steps"] * c["results"]["tests"] * len(c["results"]["algorithms"])
                    for c in (p for p in shown) if c["results"])
        sps = steps / (s["finished_at"] - s["started_at"])
    return study_results(s, shown, sps, partial=partial)


@router.get("/{study_id}/results", response_model=StudyResults,
            responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}},
                             "description": "the results object (JSON), or as CSV with `?format=csv` or `Accept: text/csv`"},
                       **responses(404, 422)})
def get_study_results(study_id: StudyId, store: StoreDep, request: Request,
                      fmt: Annotated[Optional[ResultsFormat], Query(alias="format", description="json (default) or csv")] = None
                      ) -> Any:
    """One row per point x algorithm: the varied values, the final DR with its Wilson 95 %
    interval, t90, in-FoV, POD R², and every calibration and decision field the points'
    campaigns report (flattened: ``calibration_ece_final``, ``decision_accuracy``, ...). While
    the study runs, the rows rest on the tests recorded so far (``partial``; ``tests`` per row)."""
    results = study_results_of(store, study_id)
    if results_format(request, fmt) == "csv":
        return Response(write_study_csv(results), media_type="text/csv",
                        headers={"Content-Disposition": f'inline; filename="study-{study_id}.csv"'})
    return results


@router.get("/{study_id}/plots/{metric}", response_class=Response,
            responses=plot_responses(NO_ROWS))
async def study_plot(study_id: StudyId, metric: Annotated[str, Path(max_length=64, description="a numeric field of the results "
                                                                                   "rows: dr_final, time_to_dr90_s, in_fov_final, pod_r2, calibration_ece_final, ...")],
                     request: Request,
                     fmt: Annotated[Optional[ImageFormat], Query(alias="format", description="png (default) or svg")] = None) -> Response:
    """The metric against the varied parameter, one line per algorithm with its 95 % band where
    the metric has one (the final DR: Wilson); a heat map per algorithm when two parameters
    vary. 422 for a field the rows do not have or a study varying more than two parameters;
    409 while no test is recorded. Cached once the study has finished."""
    kind = image_format(request, fmt)
    store = request.app.state.store

    def read() -> FigureSource:
        results = study_results_of(store, study_id)
        params = results["parameters"]
        if len(params) > 2:
            raise RequestValidationError([{"loc": ("path", "study_id"), "type": "value_error",
                                           "msg": f"a study figure shows one or two varied parameters; this study varies {len(params)}"}])
        if not results["rows"]:
            raise HTTPException(status.HTTP_409_CONFLICT, f"study {study_id} is {results['status']}: {NO_ROWS}")
        known = metrics_of(results["rows"], params)
        if metric not in known:
            raise RequestValidationError([{"loc": ("path", "metric"), "type": "value_error",
                                           "msg": f"unknown metric {metric!r}; this study's rows have {', '.join(known)}"}])
        job = plots.PlotJob("study", kind, {"results": results, "metric": metric})
        return FigureSource(job, cacheable=results["status"] not in ACTIVE)

    return await serve_figure(request, PlotKey(study_id, "study", kind, (metric,)), read)
