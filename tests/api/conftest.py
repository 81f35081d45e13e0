"""Fixtures of the API tests: live servers (see ``live.py``) and a finished campaign."""

from __future__ import annotations

import pytest

from tests.api.live import SMALL, LiveAPI

TOKEN = "s3cret-token"


@pytest.fixture(scope="session")
def live(tmp_path_factory):
    """One rig and a learner on an in-memory bus; the API on a real port and SQLite file."""
    server = LiveAPI(tmp_path_factory.mktemp("api") / "api.db").start()
    yield server
    server.stop()


@pytest.fixture(scope="session")
def done_campaign(live):
    """A small finished campaign: 3 tests of ra2vipas and rapas, seed 3."""
    body = {"preset": "paper", "overrides": SMALL, "algorithms": ["ra2vipas", "rapas"], "tests": 3, "seed": 3, "name": "fixture"}
    with live.client() as http:
        r = http.post("/campaigns", json=body)
    assert r.status_code == 201, r.text
    c = live.wait(r.json()["id"])
    assert c["status"] == "done", c
    return c


@pytest.fixture()
def http(live):
    with live.client() as client:
        yield client


@pytest.fixture(scope="module")
def guarded(tmp_path_factory):
    """A server with a token configured (no rigs: nothing runs)."""
    server = LiveAPI(tmp_path_factory.mktemp("token") / "token.db", rigs=(), learner=False, token=TOKEN).start()
    yield server
    server.stop()
