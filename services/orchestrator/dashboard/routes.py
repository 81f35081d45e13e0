"""The dashboard's pages (``/`` and ``/ui/...``), their htmx fragments and event streams.

Read-only: every page and stream reads the store and the scheduler like the REST API's GET
routes (the studies pages are in ``studies.py``); creating, cancelling and deleting campaigns is done by the page's script through the
REST API itself (``POST /campaigns``, ``POST /campaigns/{id}/cancel``, ``DELETE
/campaigns/{id}``), with the bearer token the user typed once (kept in the tab's
sessionStorage, never in a URL). None of these routes is in the OpenAPI schema.

Streams (``text/event-stream``) poll the database on the server, like
``/campaigns/{id}/events``, and share its cap on open streams.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import time
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, AsyncIterator, Awaitable, Callable, Literal, Optional

from cachetools import LRUCache
from fastapi import APIRouter, FastAPI, HTTPException, Query, Request, status
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse, StreamingResponse
from fastapi.templating import Jinja2Templates
from starlette.background import BackgroundTask
from starlette.middleware.gzip import GZipMiddleware
from starlette.routing import NoMatchFound
from starlette.staticfiles import StaticFiles

from ra2vipas.services.controller import registry
from ra2vipas.services.orchestrator.api.deps import get_campaign
from ra2vipas.services.orchestrator.api.routes.events import MAX_STREAMS, _streams
from ra2vipas.services.orchestrator.api.schemas import MAX_TESTS
from ra2vipas.services.orchestrator.api.sse import Changed, poll
from ra2vipas.services.orchestrator.api.views import campaign_progress, campaign_public, rigs_public, supervised_services
from ra2vipas.services.orchestrator.dashboard import data
from ra2vipas.services.orchestrator.storage import ACTIVE, FINISHED, Store
from ra2vipas.services.protocol.scenario import PRESET_DESCRIPTIONS, PRESETS

HERE = Path(str(resources.files(__package__)))
STATIC = HERE / "static"
PAGE = 50            # campaigns per page, tests per page
TICK_S = 0.5         # how often a stream looks at the database
CURVES_EVERY_S = 1.0  # at most one DR update per second per stream
KEEPALIVE_S = 15.0

router = APIRouter(include_in_schema=False)
templates = Jinja2Templates(directory=str(HERE / "templates"))  # autoescapes .html


def _asset_version() -> str:
    """A digest of every static file: part of their URLs, so a browser may cache them for good."""
    h = hashlib.sha256()
    for path in sorted(STATIC.rglob("*")):
        if path.is_file():
            h.update(path.name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:10]


ASSET_VERSION = _asset_version()


def asset(name: str) -> str:
    return f"/ui/static/{name}?v={ASSET_VERSION}"


def _when(epoch: float | None) -> str:
    return "—" if not epoch else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(epoch))


templates.env.globals.update(asset=asset, label=data.label, fmt=data.fmt, when=_when, json=lambda v: json.dumps(v, separators=(",", ":")))


class CachedStatic(StaticFiles):
    """Static files with a long cache lifetime (their URLs carry ``ASSET_VERSION``)."""

    def file_response(self, *args: Any, **kwargs: Any):
        response = super().file_response(*args, **kwargs)
        response.headers["Cache-Control"] = "public, max-age=31536000, immutable"
        return response


def mount(app: FastAPI) -> None:
    """Add the dashboard to ``app``: its routes and its static files (gzip-compressed)."""
    from ra2vipas.services.orchestrator.dashboard import studies  # its routes use this module's helpers

    app.include_router(router)
    app.include_router(studies.router)
    app.mount("/ui/static", GZipMiddleware(CachedStatic(directory=str(STATIC)), minimum_size=1024), name="dashboard-static")


# -- helpers -------------------------------------------------------------------------------------

def _store(request: Request) -> Store:
    return request.app.state.store


def _has_studies(request: Request) -> bool:
    """Whether the navigation shows "Studies" (``/ui/studies``): when the REST API serves
    ``/studies`` (an app built without the studies router has no such pages)."""
    state = request.app.state
    if not hasattr(state, "dashboard_has_studies"):
        try:  # FastAPI includes routers lazily: ask the app to build the URL rather than scan app.routes
            request.app.url_path_for("list_studies")
            state.dashboard_has_studies = True
        except NoMatchFound:
            state.dashboard_has_studies = False
    return state.dashboard_has_studies


def _html(request: Request, text: str) -> HTMLResponse:
    """An HTML response, gzip-compressed when the client takes it (a campaign page's long tables
    compress well). Only the dashboard's pages: the REST API's responses are unchanged."""
    body = text.encode()
    if len(body) >= 1024 and "gzip" in request.headers.get("accept-encoding", ""):
        return HTMLResponse(gzip.compress(body, compresslevel=6), headers={"Content-Encoding": "gzip", "Vary": "Accept-Encoding"})
    return HTMLResponse(body, headers={"Vary": "Accept-Encoding"})


def _page(request: Request, template: str, title: str, nav: str, **context: Any) -> HTMLResponse:
    settings = request.app.state.settings
    return _html(request, templates.get_template(template).render(
        request=request, title=title, nav=nav, auth_required=bool(settings.token), has_studies=_has_studies(request), **context))


def _not_found(request: Request, err: HTTPException) -> HTMLResponse:
    """A page (not JSON) for a person who followed a stale link."""
    response = _page(request, "error.html", "Not found", "", message=err.detail)
    response.status_code = err.status_code
    return response


def _fragment(request: Request, template: str, **context: Any) -> str:
    return templates.get_template(template).render(request=request, **context)


def _sse(event: str, payload: str) -> str:
    lines = payload.splitlines() or [""]
    return f"event: {event}\n" + "".join(f"data: {line}\n" for line in lines) + "\n"


def _stream(request: Request, body: Callable[[Callable[[], None]], AsyncIterator[str]]) -> StreamingResponse:
    """An event stream counted against the server's cap on open streams (shared with
    ``/campaigns/{id}/events``)."""
    release = _streams(request).reserve()
    if release is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"too many open event streams ({MAX_STREAMS})",
                            headers={"Retry-After": "5"})
    return StreamingResponse(body(release), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}, background=BackgroundTask(release))


def _poll(request: Request, step: Callable[[], Awaitable[tuple[list[str], bool]]]) -> Callable[[Callable[[], None]], AsyncIterator[str]]:
    """A stream's body: ``sse.poll`` every TICK_S while the browser is connected."""
    async def connected() -> bool:
        return not await request.is_disconnected()

    async def body(release: Callable[[], None]) -> AsyncIterator[str]:
        try:
            async for chunk in poll(step, TICK_S, KEEPALIVE_S, connected):
                yield chunk
        finally:
            release()

    return body


def _stream_changes(request: Request, event: str, html: Callable[[], Awaitable[str]]) -> StreamingResponse:
    """A stream of one HTML fragment (``event: EVENT``) whenever it changes."""
    changed = Changed()

    async def step() -> tuple[list[str], bool]:
        fragment = await html()
        return ([_sse(event, fragment)] if changed(fragment) else []), False

    return _stream(request, _poll(request, step))


def _pages(total: int, offset: int, size: int = PAGE) -> dict[str, Any]:
    return {"total": total, "offset": offset, "size": size, "first": offset + 1 if total else 0, "last": min(total, offset + size),
            "prev": max(0, offset - size) if offset > 0 else None, "next": offset + size if offset + size < total else None}


# -- campaigns (home) ----------------------------------------------------------------------------

StatusFilter = Optional[Literal["", "queued", "training", "running", "done", "failed", "cancelled"]]  # "": any


_FINALS: LRUCache = LRUCache(maxsize=4096)  # campaign id -> what its row shows of its results (a done campaign's never change)


def _final(store: Store, cid: str) -> dict[str, Any]:
    """What the home page shows of a done campaign's results: Ra²ViPAS's final DR and interval
    (``dr`` None without Ra²ViPAS), its warnings, and whether some episodes were scored under
    the scenario's assumptions (undescribed rigs)."""
    if cid not in _FINALS:
        results = (store.campaign(cid) or {}).get("results") or {}
        block = results.get("algorithms", {}).get("ra2vipas")
        _FINALS[cid] = {"dr": None if block is None else block["dr_final"], "ci": None if block is None else block["ci95"],
                        "warnings": list(results.get("warnings") or []), "assumptions": bool(results.get("assumptions"))}
    return _FINALS[cid]


PointsFilter = Optional[Literal["", "show"]]  # the points of studies: hidden ("") or shown


def _campaign_list(store: Store, status_: str | None, preset: str | None, offset: int, points: bool = False) -> dict[str, Any]:
    """One page of the home table: campaigns newest first, a study's points only when asked
    (they are listed, in grid order, on their study's page); and how many points are hidden."""
    rows, total = store.campaigns(status=status_, preset=preset or None, limit=PAGE, offset=offset, standalone=not points)
    hidden = 0 if points else store.campaigns(status=status_, preset=preset or None, limit=0)[1] - total
    items = []
    for row in rows:
        c = campaign_public(row, storage_fault=store.fault)
        items.append({"c": c, "final": _final(store, c.id) if c.status == "done" else None})
    return {"items": items, "pages": _pages(total, offset), "hidden_points": hidden}


@router.get("/", response_class=HTMLResponse)
def home(request: Request, status_: Annotated[StatusFilter, Query(alias="status")] = None,
         preset: Annotated[Optional[str], Query(max_length=64)] = None,
         offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
         points: Annotated[PointsFilter, Query(description="show: list the points of studies too")] = None) -> HTMLResponse:
    listing = _campaign_list(_store(request), status_, preset, offset, points == "show")
    query = {"status": status_ or "", "preset": preset or "", "offset": offset, "points": points or ""}
    return _page(request, "home.html", "Campaigns", "campaigns", presets=list(PRESETS), query=query,
                 statuses=["queued", "training", "running", "done", "failed", "cancelled"], **listing)


@router.get("/ui/streams/campaigns")
async def campaigns_stream(request: Request, status_: Annotated[StatusFilter, Query(alias="status")] = None,
                           preset: Annotated[Optional[str], Query(max_length=64)] = None,
                           offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
                           points: Annotated[PointsFilter, Query()] = None) -> StreamingResponse:
    """The home page's table body (``event: rows``, HTML) whenever it changes."""
    store = _store(request)

    async def html() -> str:
        listing = await run_in_threadpool(_campaign_list, store, status_, preset, offset, points == "show")
        return _fragment(request, "_campaign_rows.html", **listing)

    return _stream_changes(request, "rows", html)


# -- one campaign --------------------------------------------------------------------------------

SortKey = Literal["test", "confidence"]


def _live(request: Request, campaign: dict[str, Any]) -> data.LiveDR:
    """The campaign's growing DR curves, shared by every viewer (a small LRU of campaigns)."""
    state = request.app.state
    if not hasattr(state, "dashboard_live"):
        state.dashboard_live = LRUCache(maxsize=16)
    live = state.dashboard_live.get(campaign["id"])
    if live is None:
        live = data.LiveDR(campaign["id"], campaign["algorithms"], campaign["scenario"]["steps"], campaign["scenario"]["rf_period_s"])
        state.dashboard_live[campaign["id"]] = live
    return live


def _tests_context(store: Store, campaign: dict[str, Any], missed: bool, sort: str, sort_algorithm: Optional[str], order: str,
                   offset: int) -> dict[str, Any]:
    algorithms = campaign["algorithms"]
    can_miss = "ra2vipas" in algorithms
    sort_algorithm = sort_algorithm if sort_algorithm in algorithms else ("ra2vipas" if can_miss else algorithms[0])
    rows, total = store.test_page(campaign["id"], missed_by="ra2vipas" if missed and can_miss else None, sort=sort,
                                  sort_algorithm=sort_algorithm, descending=order == "desc", limit=PAGE, offset=offset)
    return {"tests": data.test_rows(rows, algorithms, campaign["scenario"]["rf_period_s"]), "algorithms": algorithms,
            "tq": {"missed": missed and can_miss, "sort": sort, "sort_algorithm": sort_algorithm, "order": order, "offset": offset},
            "can_miss": can_miss, "tpages": _pages(total, offset)}


def _membership(store: Store, cid: str) -> dict[str, Any] | None:
    """The study a campaign is a point of (its id and the point's index), else None."""
    from ra2vipas.services.orchestrator.study_store import StudyStore

    found = StudyStore(store).membership(cid)
    return None if found is None else {"id": found[0], "point": found[1]}


def _campaign_or_404(store: Store, cid: str) -> dict[str, Any]:
    return get_campaign(cid, store)


CampaignId = Annotated[str, PathParam(min_length=1, max_length=64)]


@router.get("/ui/campaigns/{campaign_id}", response_class=HTMLResponse)
def campaign_page(request: Request, campaign_id: CampaignId, missed: bool = False, sort: SortKey = "test",
                  sort_algorithm: Annotated[Optional[str], Query(max_length=16)] = None, order: Literal["asc", "desc"] = "asc",
                  offset: Annotated[int, Query(ge=0, le=MAX_TESTS * 4)] = 0) -> HTMLResponse:
    store = _store(request)
    try:
        row = _campaign_or_404(store, campaign_id)
    except HTTPException as err:
        return _not_found(request, err)
    c = campaign_public(row, storage_fault=store.fault)
    results = row["results"] if row["status"] == "done" else None
    context: dict[str, Any] = {
        "c": c, "scenario": data.scenario_rows(row["preset"], row["scenario"], row["overrides"]),
        "changed": sum(1 for r in data.scenario_rows(row["preset"], row["scenario"], row["overrides"]) if r["changed"]),
        "active": row["status"] in ACTIVE, "finished": row["status"] in FINISHED, "results": results,
        "summary": data.summary_table(results) if results else None,
        "tags": data.tags_table(results) if results else None,
        "curves": data.dr_curves(results) if results else None,
        "has_reliability": bool(results) and any("calibration" in b for b in results["algorithms"].values()),
        "reliability": data.reliability_series(results) if results else None,
        "study": _membership(store, campaign_id),
        **_tests_context(store, row, missed, sort, sort_algorithm, order, offset),
    }
    name = c.name or f"campaign {c.id}"
    return _page(request, "campaign.html", name, "campaigns", **context)


@router.get("/ui/campaigns/{campaign_id}/tests", response_class=HTMLResponse)
def campaign_tests(request: Request, campaign_id: CampaignId, missed: bool = False, sort: SortKey = "test",
                   sort_algorithm: Annotated[Optional[str], Query(max_length=16)] = None, order: Literal["asc", "desc"] = "asc",
                   offset: Annotated[int, Query(ge=0, le=MAX_TESTS * 4)] = 0) -> HTMLResponse:
    """The per-test table alone (htmx swaps it when the filter, sort or page changes)."""
    store = _store(request)
    row = _campaign_or_404(store, campaign_id)
    ctx = _tests_context(store, row, missed, sort, sort_algorithm, order, offset)
    return _html(request, _fragment(request, "_tests.html", c=campaign_public(row), **ctx))


@router.get("/ui/campaigns/{campaign_id}/live")
async def campaign_live(request: Request, campaign_id: CampaignId) -> StreamingResponse:
    """``event: progress`` (a CampaignProgress, JSON) at every change and ``event: curves``
    (the DR curves over the tests finished so far, JSON) at most once a second while they
    change; ends after the event that shows the campaign finished (``event: deleted`` if it
    disappears)."""
    store = _store(request)
    row = await run_in_threadpool(_campaign_or_404, store, campaign_id)
    live = _live(request, row)

    changed, curves = Changed(), {"done": -1, "at": 0.0}

    async def step() -> tuple[list[str], bool]:
        current = await run_in_threadpool(store.campaign, campaign_id)
        if current is None:
            return [_sse("deleted", json.dumps({"id": campaign_id}))], True
        chunks = []
        finished = current["status"] in FINISHED
        done = current["progress"]["done"]
        if done != curves["done"] and (finished or time.monotonic() - curves["at"] >= CURVES_EVERY_S):
            await run_in_threadpool(live.update, store)
            chunks.append(_sse("curves", json.dumps(live.snapshot(), separators=(",", ":"))))
            curves.update(done=done, at=time.monotonic())
        progress = campaign_progress(current, store.fault).model_dump_json()
        if changed(progress):
            chunks.append(_sse("progress", progress))
        return chunks, finished

    return _stream(request, _poll(request, step))


@router.get("/ui/campaigns/{campaign_id}/pod.json")
def campaign_pod(request: Request, campaign_id: CampaignId) -> JSONResponse:
    """The POD figure's data (``data.pod_series``, ``ready: true``), or ``{"ready": false}``
    until the learned model is stored (the page asks again when the campaign moves on)."""
    store = _store(request)
    artifacts = store.pod_artifacts(campaign_id)
    row = _campaign_or_404(store, campaign_id)
    if not artifacts or artifacts["model"] is None:
        return JSONResponse({"ready": False, "status": row["status"]})
    series = data.pod_series(row["scenario"], artifacts["model"], artifacts["truth"])
    return JSONResponse({"ready": True, **series, "r2": row["pod_r2"]})


@router.get("/ui/campaigns/{campaign_id}/tests/{test_index}/{algorithm}", response_class=HTMLResponse)
def episode_page(request: Request, campaign_id: CampaignId, test_index: Annotated[int, PathParam(ge=0, le=MAX_TESTS - 1)],
                 algorithm: Annotated[str, PathParam(max_length=64)]) -> HTMLResponse:
    store = _store(request)
    try:
        row = _campaign_or_404(store, campaign_id)
        if algorithm not in row["algorithms"] or test_index >= row["tests"]:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"campaign {campaign_id} has no test {test_index} of {algorithm}")
    except HTTPException as err:
        return _not_found(request, err)
    episode = store.episode(campaign_id, test_index, algorithm)
    ready = episode is not None and episode["status"] == "done"
    return _page(request, "episode.html", f"test {test_index}, {data.label(algorithm)}", "campaigns",
                 c=campaign_public(row), test_index=test_index, algorithm=algorithm, others=row["algorithms"],
                 ep=data.episode_data(episode, row["scenario"]) if ready else None,
                 episode_status=episode["status"] if episode else "missing")


# -- rigs ----------------------------------------------------------------------------------------

def _rigs_context(request: Request) -> dict[str, Any]:
    snapshot = request.app.state.scheduler.status()
    public = rigs_public(snapshot, supervised_services(request.app.state.settings.supervisor_status))
    since = {name: st.get("since") for name, st in snapshot["rigs"].items()}
    return {"rigs": [{"r": r, "since": since.get(r.name)} for r in public.rigs], "learners": public.learners,
            "services": public.services}


@router.get("/ui/rigs", response_class=HTMLResponse)
def rigs_page(request: Request) -> HTMLResponse:
    return _page(request, "rigs.html", "Rigs", "rigs", **_rigs_context(request))


@router.get("/ui/streams/rigs")
async def rigs_stream(request: Request) -> StreamingResponse:
    """The rigs table (``event: rigs``, HTML) whenever Zenoh liveliness changes it."""

    async def html() -> str:
        return _fragment(request, "_rigs.html", **_rigs_context(request))

    return _stream_changes(request, "rigs", html)


# -- new campaign --------------------------------------------------------------------------------

def _preset_or_default(preset: Optional[str]) -> str:
    return preset if preset in PRESETS else "paper"


@router.get("/ui/new", response_class=HTMLResponse)
def new_campaign(request: Request, preset: Annotated[Optional[str], Query(max_length=64)] = None) -> HTMLResponse:
    name = _preset_or_default(preset)
    return _page(request, "new.html", "New campaign", "new", presets=PRESET_DESCRIPTIONS, preset=name,
                 parameters=data.parameter_inputs(name), description=PRESET_DESCRIPTIONS[name], algorithms=list(registry.names()),
                 builtins=registry.BUILTINS, max_tests=MAX_TESTS)


@router.get("/ui/new/parameters", response_class=HTMLResponse)
def new_campaign_parameters(request: Request, preset: Annotated[Optional[str], Query(max_length=64)] = None) -> HTMLResponse:
    """The parameter inputs of a preset (htmx swaps them when the preset changes)."""
    name = _preset_or_default(preset)
    return _html(request, _fragment(request, "_parameters.html", preset=name, parameters=data.parameter_inputs(name),
                                  description=PRESET_DESCRIPTIONS[name]))
