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


def test_health_counts_the_result_and_truth_messages_it_dropped(live, http):
    """Defence in depth (issue 14): what the orchestrator drops on the result and truth planes is
    counted by reason and shown by /health: a payload that does not validate (malformed), an
    episode id that is not in flight (a guess or a replay), none of it recorded."""
    from ra2vipas.services.protocol import keys
    from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeTruth, dump

    before = http.get("/health").json()["rejected_messages"]
    assert set(before) == {"malformed", "not_in_flight", "wrong_rig"}
    guessed = "0123456789ab.0.ra2vipas.0"  # campaign.test.algorithm.attempt, no nonce
    live.bus.publish(keys.episode_result("rig-1"), dump(EpisodeResult(episode_id=guessed, rig="rig-1", estimates_rad=(0.0,),
                                                                       pans_rad=(0.0,), rewards=(0.0,))))
    live.bus.publish(keys.episode_truth("evil"), dump(EpisodeTruth(episode_id=guessed, bearings_rad=(0.0,), ranges_m=(1.0,), tx_index=0)))
    live.bus.publish(keys.episode_result("rig-1"), b'{"episode_id": 3}')
    live.settle()
    after = http.get("/health").json()["rejected_messages"]
    assert after["not_in_flight"] == before["not_in_flight"] + 2
    assert after["malformed"] == before["malformed"] + 1
    assert after["wrong_rig"] == before["wrong_rig"]
