"""/campaigns/{id}/events: a running campaign's progress as server-sent events.

Each change of status or progress is one ``event: progress`` whose ``data`` is a
``CampaignProgress`` JSON object; a comment line keeps an idle connection open; the stream
ends after the event that shows the campaign finished (done, failed or cancelled), or with
``event: deleted`` if it disappears.
"""

from __future__ import annotations

import json
from typing import Annotated, AsyncIterator, Callable

from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from starlette.background import BackgroundTask

from ra2vipas.services.orchestrator.api.deps import CampaignDep, StoreDep
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.schemas import CampaignProgress
from ra2vipas.services.orchestrator.api.sse import Changed, poll
from ra2vipas.services.orchestrator.api.views import campaign_progress
from ra2vipas.services.orchestrator.storage import FINISHED, Store

router = APIRouter(prefix="/campaigns/{campaign_id}", tags=["campaigns"])

MAX_STREAMS = 64  # open event streams per server
KEEPALIVE_S = 10.0


class _Streams:
    """Counts open streams so that many idle clients cannot pin the server. A stream's place
    is reserved by the route itself (no ``await`` between the check and the count, so the cap
    is exact) and released once, whichever ends first: the stream or the response."""

    def __init__(self) -> None:
        self.open = 0

    def reserve(self) -> "Callable[[], None] | None":
        """A release function for one more stream, or None if the cap is reached."""
        if self.open >= MAX_STREAMS:
            return None
        self.open += 1
        released = False

        def release() -> None:
            nonlocal released
            if not released:
                released = True
                self.open -= 1

        return release


def _streams(request: Request) -> _Streams:
    state = request.app.state
    if not hasattr(state, "event_streams"):
        state.event_streams = _Streams()
    return state.event_streams


def _event_schema() -> dict:
    """One server-sent event as OpenAPI describes it: its ``data`` is JSON, a
    ``CampaignProgress`` (``event: progress``) or ``{"id"}`` (``event: deleted``)."""
    progress = CampaignProgress.model_json_schema(ref_template="#/components/schemas/{model}")
    progress.pop("$defs", None)
    deleted = {"type": "object", "properties": {"id": {"type": "string"}}, "required": ["id"]}
    return {
        "type": "object",
        "required": ["data", "event"],
        "properties": {
            "event": {"type": "string", "enum": ["progress", "deleted"]},
            "id": {"type": "string"},
            "data": {"type": "string", "contentMediaType": "application/json", "contentSchema": {"anyOf": [progress, deleted]}},
        },
    }


@router.get("/events", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {"schema": _event_schema()}},
                             "description": "`event: progress` with a CampaignProgress as JSON data, at every change, until the "
                                            "campaign finishes"},
                       **responses(404, 422, 503)})
async def campaign_events(campaign: CampaignDep, request: Request, store: StoreDep,
                          interval: Annotated[float, Query(ge=0.05, le=10.0, description="seconds between checks")] = 0.5
                          ) -> StreamingResponse:
    """Progress of a campaign as server-sent events, until it finishes."""
    release = _streams(request).reserve()
    if release is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"too many open event streams ({MAX_STREAMS}); poll GET /campaigns/{{id}}",
                            headers={"Retry-After": "5"})
    return StreamingResponse(_events(store, campaign["id"], interval, release), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}, background=BackgroundTask(release))


async def _events(store: Store, cid: str, interval: float, release: Callable[[], None]) -> AsyncIterator[str]:
    changed, sent = Changed(), [0]

    async def step() -> tuple[list[str], bool]:
        row = await run_in_threadpool(store.campaign, cid)
        if row is None:
            return [f"event: deleted\ndata: {json.dumps({'id': cid})}\n\n"], True
        data = campaign_progress(row, store.fault).model_dump_json()
        chunks = []
        if changed(data):
            sent[0] += 1
            chunks.append(f"id: {sent[0]}\nevent: progress\ndata: {data}\n\n")
        return chunks, row["status"] in FINISHED

    try:
        async for chunk in poll(step, interval, KEEPALIVE_S):
            yield chunk
    finally:
        release()
