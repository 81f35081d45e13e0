"""The dashboard's studies pages (``/ui/studies``, ``/ui/studies/{id}``), their fragments and
event streams: read-only like the campaign pages; cancelling and deleting a study is done by
the page's script through the REST API (``POST /studies/{id}/cancel``, ``DELETE
/studies/{id}``) with the token the user typed once."""

from __future__ import annotations

import json
import threading
import time
from typing import Annotated, Any

from cachetools import LRUCache
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, StreamingResponse

from ra2vipas.services.orchestrator.api.routes.studies import study_results_of
from ra2vipas.services.orchestrator.api.sse import Changed
from ra2vipas.services.orchestrator.api.views import study_public
from ra2vipas.services.orchestrator.dashboard import data
from ra2vipas.services.orchestrator.dashboard.routes import (
    PAGE,
    StatusFilter,
    _fragment,
    _not_found,
    _page,
    _pages,
    _poll,
    _sse,
    _store,
    _stream,
    _stream_changes,
)
from ra2vipas.services.orchestrator.storage import ACTIVE, FINISHED, Store
from ra2vipas.services.orchestrator.study_store import StudyStore

router = APIRouter(include_in_schema=False)
RESULTS_EVERY_S = 2.0  # a running study's rows (reduced from every recorded episode) at most this often per study
StudyId = Annotated[str, PathParam(min_length=1, max_length=64)]


# -- studies list --------------------------------------------------------------------------------

def _study_list(store: Store, status_: str | None, offset: int) -> dict[str, Any]:
    rows, total = StudyStore(store).studies(status=status_ or None, limit=PAGE, offset=offset)
    return {"items": [study_public(r) for r in rows], "pages": _pages(total, offset)}


@router.get("/ui/studies", response_class=HTMLResponse)
def studies_page(request: Request, status_: Annotated[StatusFilter, Query(alias="status")] = None,
                 offset: Annotated[int, Query(ge=0, le=10**9)] = 0) -> HTMLResponse:
    listing = _study_list(_store(request), status_, offset)
    return _page(request, "studies.html", "Studies", "studies", query={"status": status_ or "", "offset": offset},
                 statuses=["queued", "training", "running", "done", "failed", "cancelled"], **listing)


@router.get("/ui/streams/studies")
async def studies_stream(request: Request, status_: Annotated[StatusFilter, Query(alias="status")] = None,
                         offset: Annotated[int, Query(ge=0, le=10**9)] = 0) -> StreamingResponse:
    """The studies page's table body (``event: rows``, HTML) whenever it changes."""
    store = _store(request)

    async def html() -> str:
        listing = await run_in_threadpool(_study_list, store, status_, offset)
        return _fragment(request, "_study_rows.html", **listing)

    return _stream_changes(request, "rows", html)


# -- one study -----------------------------------------------------------------------------------

class _Results:
    """A study's results object, shared by every viewer of its page and recomputed at most every
    ``RESULTS_EVERY_S`` while it runs (a running point's rows are reduced from every episode it
    recorded), at once when the study finishes; never again once it has finished."""

    def __init__(self) -> None:
        self.cache: LRUCache = LRUCache(maxsize=32)  # study id -> (episodes done, status, when, results)
        self.lock = threading.Lock()

    def get(self, store: Store, study: dict[str, Any]) -> dict[str, Any]:
        sid, done, st = study["id"], study["progress"]["done"], study["status"]
        with self.lock:
            hit = self.cache.get(sid)
            if hit is not None:
                h_done, h_status, h_when, results = hit
                unchanged = h_done == done and h_status == st
                if unchanged or (st in ACTIVE and time.monotonic() - h_when < RESULTS_EVERY_S):
                    return results
            results = study_results_of(store, sid)
            self.cache[sid] = (done, st, time.monotonic(), results)
            return results


def _results(request: Request) -> _Results:
    state = request.app.state
    if not hasattr(state, "dashboard_study_results"):
        state.dashboard_study_results = _Results()
    return state.dashboard_study_results


def _study_context(request: Request, study: dict[str, Any]) -> dict[str, Any]:
    public = study_public(study)
    results = _results(request).get(_store(request), study)
    points = [p.model_dump() for p in public.points or []]
    chart = data.study_chart(results)
    return {"s": public, "chart": chart, "table": data.study_table(points, results), "has_rows": bool(results["rows"]),
            "active": study["status"] in ACTIVE, "finished": study["status"] in FINISHED}


def _study_or_404(store: Store, sid: str) -> dict[str, Any]:
    s = StudyStore(store).study(sid)
    if s is None:
        raise HTTPException(404, f"no study {sid!r}")
    return s


@router.get("/ui/studies/{study_id}", response_class=HTMLResponse)
def study_page(request: Request, study_id: StudyId) -> HTMLResponse:
    store = _store(request)
    try:
        study = _study_or_404(store, study_id)
    except HTTPException as err:
        return _not_found(request, err)
    context = _study_context(request, study)
    return _page(request, "study.html", study["name"] or f"study {study_id}", "studies", **context)


@router.get("/ui/studies/{study_id}/live")
async def study_live(request: Request, study_id: StudyId) -> StreamingResponse:
    """``event: progress`` (the study as ``GET /studies/{id}`` shows it, JSON) at every change
    and ``event: results`` (the plot's data and the results table, JSON: ``chart``, ``table``
    HTML) when the rows change, at most every ``RESULTS_EVERY_S``; ends after the events that
    show the study finished (``event: deleted`` if it disappears)."""
    store = _store(request)
    await run_in_threadpool(_study_or_404, store, study_id)
    shared = _results(request)

    changed, shown = Changed(), [None]  # shown: the results object sent last (a new object when they change)

    async def step() -> tuple[list[str], bool]:
        study = await run_in_threadpool(StudyStore(store).study, study_id)
        if study is None:
            return [_sse("deleted", json.dumps({"id": study_id}))], True
        chunks = []
        progress = study_public(study).model_dump_json()
        if changed(progress):
            chunks.append(_sse("progress", progress))
        results = await run_in_threadpool(shared.get, store, study)
        if results is not shown[0]:
            points = [p.model_dump() for p in study_public(study).points or []]
            table = _fragment(request, "_study_table.html", table=data.study_table(points, results), s=study_public(study))
            chunks.append(_sse("results", json.dumps({"chart": data.study_chart(results), "table": table}, separators=(",", ":"))))
            shown[0] = results
        return chunks, study["status"] in FINISHED

    return _stream(request, _poll(request, step))
