"""The CLI's HTTP client of the orchestrator API, with the CLI's error convention: an
unreachable API or an error response is one stderr line and exit code 1 (2 for a 422: the
input was wrong)."""

from __future__ import annotations

import json
import time
from typing import Annotated, Any, Iterator, Optional

import httpx
import typer

from ra2vipas.cli.output import EXIT_FAILED, EXIT_USAGE, fail

DEFAULT_API = "http://127.0.0.1:8080"

ApiOpt = Annotated[str, typer.Option("--api", envvar="RA2VIPAS_API", help="Base URL of the orchestrator API.")]
TokenOpt = Annotated[Optional[str], typer.Option("--token", envvar="RA2VIPAS_TOKEN", help="Bearer token, if the API requires one.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print JSON (one line; the last line of stdout) instead of tables.")]

FINISHED = ("done", "failed", "cancelled")


class Client:
    """HTTP calls; every failure ends the command with one stderr line."""

    def __init__(self, api: str, token: str | None) -> None:
        if not api.startswith(("http://", "https://")):
            fail(f"--api {api!r}: expected the API's URL with its scheme, e.g. http://{api or '127.0.0.1:8080'}", EXIT_USAGE)
        self.api = api.rstrip("/")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=self.api, headers=headers, timeout=30.0)

    def _unreachable(self, err: Exception) -> None:
        if isinstance(err, httpx.ProtocolError):  # something answered, but not in HTTP
            self._not_ours("it does not answer HTTP")
        fail(f"cannot reach the API at {self.api} ({type(err).__name__}); is `ra2vipas up` running? (--api / RA2VIPAS_API)")

    def _not_ours(self, why: str) -> None:
        fail(f"{self.api} is not a ra2vipas API ({why}); --api takes the orchestrator's base URL, e.g. {DEFAULT_API}",
             EXIT_FAILED)

    def response(self, method: str, path: str, **kw) -> httpx.Response:
        """The raw response of a successful request."""
        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as err:
            self._unreachable(err)
        if r.status_code >= 400:
            self._check_error(r, method, path)
            _raise_for(r, method, path)
        return r

    def _check_error(self, r: httpx.Response, method: str, path: str) -> None:
        """Every error of a ra2vipas API is JSON ``{"detail": ...}``, and a path it does not
        serve answers exactly ``Not Found``: anything else means --api points elsewhere."""
        try:
            body = r.json()
        except ValueError:
            self._not_ours(f"{method} {path} answered HTTP {r.status_code} with {r.headers.get('content-type') or 'no'} content")
        if not isinstance(body, dict) or "detail" not in body:
            self._not_ours(f"{method} {path} answered HTTP {r.status_code} without a detail")
        if r.status_code == 404 and body["detail"] == "Not Found":
            self._not_ours(f"it does not serve {method} {path}")

    def request(self, method: str, path: str, **kw) -> Any:
        """The decoded JSON body of a successful request (None for 204)."""
        r = self.response(method, path, **kw)
        if r.status_code == 204 or not r.content:
            return None
        try:
            return r.json()
        except ValueError:
            self._not_ours(f"{method} {path} answered {r.headers.get('content-type') or 'something'}, not JSON")

    def events(self, path: str) -> Iterator[tuple[str, dict]]:
        """Server-sent events of ``path`` as (event name, JSON data) until the server ends the stream."""
        try:
            with self.http.stream("GET", path, headers={"Accept": "text/event-stream"},
                                  timeout=httpx.Timeout(30.0, read=120.0)) as r:
                if r.status_code >= 400:
                    r.read()
                    self._check_error(r, "GET", path)
                    _raise_for(r, "GET", path)
                name, data = "message", []
                for line in r.iter_lines():
                    if not line:
                        if data:
                            yield name, json.loads("\n".join(data))
                        name, data = "message", []
                    elif line.startswith("event:"):
                        name = line[6:].strip()
                    elif line.startswith("data:"):
                        data.append(line[5:].strip())
        except httpx.HTTPError as err:
            self._unreachable(err)

    def follow(self, cid: str, on_update) -> dict:
        """Call ``on_update(progress)`` for each change of a campaign until it finishes; return
        its final state. Uses the event stream, and polls if the server has no stream to spare."""
        while True:
            try:
                for name, data in self.events(f"/campaigns/{cid}/events"):
                    if name == "deleted":
                        fail(f"campaign {cid} was deleted")
                    if name == "progress":
                        on_update(data)
                        if data["status"] in FINISHED:
                            return data
            except _Busy:
                pass
            c = self.request("GET", f"/campaigns/{cid}")  # the stream ended early: check, then resume
            on_update(c)
            if c["status"] in FINISHED:
                return c
            time.sleep(0.5)


class _Busy(Exception):
    """503 from the event stream: too many open streams."""


def _raise_for(r: httpx.Response, method: str, path: str) -> None:
    if r.status_code == 503 and path.endswith("/events"):
        raise _Busy()
    code = EXIT_USAGE if r.status_code == 422 else EXIT_FAILED
    fail(f"{detail_of(r)} ({method} {path}: HTTP {r.status_code})", code)


def detail_of(r: httpx.Response) -> str:
    """The one-line reason an error response gives."""
    try:
        body = r.json()
    except ValueError:
        return " ".join(r.text.split())[:300] or r.reason_phrase
    detail = body.get("detail", body) if isinstance(body, dict) else body
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):  # FastAPI's default shape
        first = detail[0]
        loc = ".".join(str(p) for p in first.get("loc", ())[1:])
        detail = f"{loc}: {first.get('msg', '')}" if loc else str(first.get("msg", ""))
    return " ".join(str(detail).split())
