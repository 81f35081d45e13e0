"""Security: the API binds loopback by default; with a token configured, every request that
changes state needs ``Authorization: Bearer <token>`` (401 otherwise, and nothing changes),
while reads stay open."""

from __future__ import annotations

import pytest

from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from tests.api.conftest import TOKEN

BODY = {"overrides": {"steps": 10, "n_train": 100}, "algorithms": ["rapas"], "tests": 1}


def test_the_api_binds_loopback_by_default():
    assert OrchestratorSettings().host == "127.0.0.1"
    assert OrchestratorSettings.from_sources(env={}).host == "127.0.0.1"
    assert OrchestratorSettings.from_sources(env={"RA2VIPAS_TOKEN": "t"}).token == "t"


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": f"Basic {TOKEN}"},
                                     {"Authorization": TOKEN}, {"Authorization": f"Bearer {TOKEN}x"}])
def test_state_changes_without_the_token_are_401_and_change_nothing(guarded, headers):
    with guarded.client() as http:
        before = http.get("/campaigns").json()["total"]
        r = http.post("/campaigns", json=BODY, headers=headers)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert "bearer token" in r.json()["detail"]
        assert http.get("/campaigns").json()["total"] == before


def test_with_the_token_state_changes_go_through_and_reads_need_none(guarded):
    with guarded.client(token=TOKEN) as authed, guarded.client() as anonymous:
        r = authed.post("/campaigns", json=BODY)
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        for path in (f"/campaigns/{cid}", "/campaigns", "/presets", "/rigs", f"/campaigns/{cid}/tests", "/openapi.json"):
            assert anonymous.get(path).status_code == 200, path
        assert anonymous.post(f"/campaigns/{cid}/cancel").status_code == 401
        assert anonymous.delete(f"/campaigns/{cid}").status_code == 401
        assert anonymous.get(f"/campaigns/{cid}").json()["status"] != "cancelled"
        assert authed.post(f"/campaigns/{cid}/cancel").json()["status"] == "cancelled"
        assert anonymous.delete(f"/campaigns/{cid}").status_code == 401
        assert authed.delete(f"/campaigns/{cid}").status_code == 204


def test_the_token_is_checked_before_the_campaign_is_looked_up(guarded):
    with guarded.client() as anonymous:
        assert anonymous.post("/campaigns/0123456789ab/cancel").status_code == 401
        assert anonymous.delete("/campaigns/0123456789ab").status_code == 401


def test_openapi_declares_the_bearer_scheme_on_state_changing_operations(guarded):
    with guarded.client() as http:
        spec = http.get("/openapi.json").json()
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    assert spec["paths"]["/campaigns"]["post"]["security"] == [{"HTTPBearer": []}]
    assert "security" not in spec["paths"]["/campaigns"]["get"]
