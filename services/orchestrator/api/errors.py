"""Errors at the API's edge: every error body is ``ErrorPublic`` (``{"detail": "one line"}``).

* 422: a request that fails validation names the field and what it accepts, e.g.
  ``tests: Input should be less than or equal to 10000``, with every error in ``errors``;
* 400, 401, 404, 409, 413, 503: ``HTTPException`` with a one-line ``detail``.

``responses(...)`` documents those codes in the OpenAPI schema.
"""

from __future__ import annotations

from typing import Any

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from ra2vipas.services.orchestrator.api.schemas import ErrorPublic
from ra2vipas.services.orchestrator.storage import StorageFault

_WHERE = ("body", "query", "path", "header", "cookie")
MAX_LISTED = 5

_DESCRIPTIONS = {
    400: "the body could not be read (e.g. not UTF-8)",
    401: "a token is configured and the request lacks `Authorization: Bearer <token>`",
    404: "no such campaign, test or preset",
    409: "the campaign is not in a state that allows this",
    413: "the request body is too large",
    422: "invalid input: the field and what it accepts",
    503: "the database cannot take writes right now (retried by the server), or too many open event streams; retry later",
}


def responses(*codes: int, **descriptions: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI documentation of error responses, all with the ``ErrorPublic`` body."""
    out: dict[int | str, dict[str, Any]] = {}
    for code in codes:
        out[code] = {"model": ErrorPublic, "description": descriptions.get(f"e{code}", _DESCRIPTIONS[code])}
    return out


def _where(loc: tuple) -> str:
    parts = [str(p) for p in loc]
    if len(parts) > 1 and parts[0] in _WHERE:
        parts = parts[1:]
    return ".".join(parts) or "request"


async def storage_fault(_request: Request, exc: StorageFault) -> JSONResponse:
    """503 with a one-line reason when the database cannot be read or written (nothing was
    half-written; the orchestrator retries its own writes and recovers by itself)."""
    body = ErrorPublic(detail=f"database unavailable: {exc}; try again later")
    return JSONResponse(body.model_dump(exclude_none=True), status_code=503, headers={"Retry-After": "5"})


async def validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with one line naming each invalid field and what it accepts (the input is never echoed)."""
    items = [{"loc": [p if isinstance(p, int) else str(p) for p in e.get("loc", ())], "msg": str(e.get("msg", "")),
              "type": str(e.get("type", ""))} for e in exc.errors()]
    lines = [f"{_where(tuple(i['loc']))}: {i['msg']}" for i in items[:MAX_LISTED]]
    if len(items) > MAX_LISTED:
        lines.append(f"and {len(items) - MAX_LISTED} more")
    body = ErrorPublic(detail="; ".join(lines) or "invalid request", errors=items)
    return JSONResponse(body.model_dump(), status_code=422)
