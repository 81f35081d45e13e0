"""Fixtures of the dashboard's browser tests: a real stack (``ra2vipas up``: Zenoh router,
orchestrator with its SQLite file, learner, two rigs; with an API token) and a headless
Chromium driven by Playwright.

The browser is the system's (Debian package ``chromium``, which ``make test`` installs when it
is missing), never one Playwright downloads; ``RA2VIPAS_CHROMIUM`` names another executable.
Every page a test opens records its console errors, uncaught exceptions, failed requests and
every URL it requests, and the test fails on any error, or on any request to another host
or port than the orchestrator's; screenshots go to a temporary directory (printed).
"""

from __future__ import annotations

import os
from pathlib import Path

import httpx
import pytest

from tests.integration.conftest import Procs, start_stack, stop_stack

CHROMIUM = os.environ.get("RA2VIPAS_CHROMIUM", "/usr/bin/chromium")
TOKEN = "web-test-token-5f0c"
WIDE = {"width": 1280, "height": 800}
PHONE = {"width": 390, "height": 844}


@pytest.fixture(scope="session")
def screenshots(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("dashboard-screenshots")
    print(f"\ndashboard screenshots: {path}")
    return path


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """``ra2vipas up`` with two rigs and ``RA2VIPAS_TOKEN`` set: changes need the token."""
    registry = Procs()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RA2VIPAS_TOKEN", TOKEN)
        state = start_stack(registry, tmp_path_factory.mktemp("web-stack"), rigs=2)
    state["token"] = TOKEN
    try:
        yield state
    finally:
        stop_stack(registry, state["up"])


@pytest.fixture(scope="module")
def api(stack):
    with httpx.Client(base_url=stack["api"], timeout=30, headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        yield client


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: `make test` installs the Debian package chromium (or set RA2VIPAS_CHROMIUM)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        try:
            yield b
        finally:
            b.close()


class Watched:
    """A page with what went wrong in it: console errors, uncaught exceptions, failed
    requests (4xx/5xx other than those a test expects), and every URL it requested."""

    def __init__(self, page, expected_statuses: set[int]) -> None:
        self.page = page
        self.problems: list[str] = []
        self.urls: list[str] = []
        self.expected = expected_statuses
        page.on("console", lambda m: self.problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: self.problems.append(f"page error: {e}"))
        page.on("request", lambda r: self.urls.append(r.url))
        page.on("response", self._response)

    def _response(self, response) -> None:
        if response.status >= 400 and response.status not in self.expected:
            self.problems.append(f"HTTP {response.status} for {response.request.method} {response.url}")


def _to_the_orchestrator(url: str, api: str) -> bool:
    """Whether a page's request stays on the orchestrator (its scheme, host and port), or needs
    no network at all (``data:``, ``blob:``, ``about:``): the dashboard works offline."""
    from urllib.parse import urlsplit

    u, own = urlsplit(url), urlsplit(api)
    return u.scheme in ("data", "blob", "about") or (u.scheme, u.netloc) == (own.scheme, own.netloc)


@pytest.fixture()
def watched(browser, stack, request):
    """``watched(viewport=WIDE, expect=())``: a new browser context and page on the stack's
    API; at teardown, the test fails if the page logged a console error, raised, got an
    unexpected error response, put the token in a URL, or requested anything from another host
    or port than the orchestrator's (every script, style, stream and fetch is served by it:
    offline by construction)."""
    opened: list[tuple] = []

    def open_page(viewport: dict = WIDE, expect: tuple[int, ...] = ()) -> Watched:
        context = browser.new_context(viewport=viewport, base_url=stack["api"])
        page = context.new_page()
        page.set_default_timeout(30_000)
        # the browser logs a console error for every 4xx/5xx; a test that expects one (a 422 the
        # form shows) says so, and the response handler still checks every other status
        w = Watched(page, set(expect))
        opened.append((context, w))
        return w

    yield open_page
    problems = []
    for context, w in opened:
        expected_console = [p for p in w.problems if p.startswith("console error: Failed to load resource")
                            and any(f"status of {s}" in p for s in w.expected)]
        problems += [p for p in w.problems if p not in expected_console]
        problems += [f"token in URL: {u}" for u in w.urls if TOKEN in u]
        problems += [f"a request that leaves the orchestrator: {u}" for u in w.urls if not _to_the_orchestrator(u, stack["api"])]
        context.close()
    assert not problems, "\n".join(problems)
