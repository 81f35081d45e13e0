"""/campaigns against the live server: create, list, show, and every way a request can be
wrong (422 naming the field, 404, 413), none of which stores anything."""

from __future__ import annotations

import json
import re

import httpx
import pytest

from ra2vipas.services.controller.policy import ALGORITHMS
from ra2vipas.services.orchestrator.api.schemas import ALGORITHM_NAMES
from ra2vipas.services.protocol.scenario import Scenario, build_scenario
from tests.api.live import SMALL


def count(http: httpx.Client) -> int:
    return http.get("/campaigns", params={"limit": 1}).json()["total"]


def test_api_algorithm_names_are_the_controllers():
    assert ALGORITHM_NAMES == ALGORITHMS


def test_openapi_and_the_docs_page_are_served(http):
    spec = http.get("/openapi.json").json()
    paths = set(spec["paths"])
    assert {"/campaigns", "/campaigns/{campaign_id}", "/campaigns/{campaign_id}/cancel", "/campaigns/{campaign_id}/results",
            "/campaigns/{campaign_id}/events", "/campaigns/{campaign_id}/tests", "/campaigns/{campaign_id}/tests/{test_index}/{algorithm}",
            "/campaigns/{campaign_id}/plots/dr", "/campaigns/{campaign_id}/plots/pod", "/presets", "/presets/{name}", "/rigs",
            "/health"} <= paths
    assert "delete" in spec["paths"]["/campaigns/{campaign_id}"]
    docs = http.get("/docs")
    assert docs.status_code == 200 and "swagger" in docs.text.lower()


def test_create_answers_201_with_location_and_the_resolved_scenario(live, http):
    body = {"preset": "paper-uniform", "overrides": {**SMALL, "n_targets": 6, "rf_noise_db": 3}, "algorithms": ["rapas"],
            "tests": 1, "seed": 8, "name": "one"}
    r = http.post("/campaigns", json=body)
    assert r.status_code == 201, r.text
    c = r.json()
    assert r.headers["location"] == f"/campaigns/{c['id']}"
    assert re.fullmatch(r"[0-9a-f]{12}", c["id"])
    assert c["name"] == "one" and c["preset"] == "paper-uniform" and c["algorithms"] == ["rapas"]
    assert c["scenario"] == build_scenario("paper-uniform", {**SMALL, "n_targets": 6}).model_dump(mode="json")
    assert c["overrides"]["rf_noise_db"] == 3.0 and isinstance(c["overrides"]["rf_noise_db"], float)  # stored as the scenario types it
    assert set(c["scenario"]) == set(Scenario.model_fields)  # every parameter, not only the overrides
    assert c["progress"]["total"] == 1
    assert http.get(r.headers["location"]).json()["id"] == c["id"]
    assert live.wait(c["id"])["status"] == "done"


def test_show_gives_status_progress_timings_and_the_pod_fit(http, done_campaign):
    c = http.get(f"/campaigns/{done_campaign['id']}").json()
    assert c["status"] == "done"
    assert c["progress"] == {"done": 6, "running": 0, "pending": 0, "total": 6}
    assert c["created_at"] <= c["started_at"] <= c["finished_at"]
    assert c["elapsed_s"] == pytest.approx(c["finished_at"] - c["started_at"], abs=1e-3)
    assert 0.0 < c["pod"]["r2"] <= 1.0 and c["pod"]["train_seconds"] > 0
    assert c["steps_per_second"] > 0 and c["error"] is None


def test_list_paginates_newest_first_and_filters(live, http, done_campaign):
    ids = []
    for seed in (21, 22, 23):
        r = http.post("/campaigns", json={"overrides": SMALL, "algorithms": ["rapas"], "tests": 1, "seed": seed, "preset": "paper-uniform"})
        ids.append(r.json()["id"])
    for cid in ids:
        live.wait(cid)
    page = http.get("/campaigns", params={"limit": 2, "preset": "paper-uniform"}).json()
    assert page["limit"] == 2 and page["offset"] == 0 and page["total"] >= 3
    assert [c["id"] for c in page["items"]] == ids[::-1][:2]
    nxt = http.get("/campaigns", params={"limit": 2, "offset": 2, "preset": "paper-uniform"}).json()
    assert nxt["items"] and nxt["items"][0]["id"] not in {c["id"] for c in page["items"]}
    done = http.get("/campaigns", params={"status": "done", "limit": 200}).json()
    assert done_campaign["id"] in {c["id"] for c in done["items"]}
    assert all(c["status"] == "done" for c in done["items"])
    assert http.get("/campaigns", params={"preset": "no-such"}).json() == {"items": [], "total": 0, "limit": 50, "offset": 0}


@pytest.mark.parametrize("params, field", [
    ({"limit": 201}, "limit"), ({"limit": 0}, "limit"), ({"offset": -1}, "offset"), ({"status": "sleeping"}, "status"),
    ({"limit": "ten"}, "limit"),
])
def test_list_rejects_bad_query_parameters(http, params, field):
    r = http.get("/campaigns", params=params)
    assert r.status_code == 422
    assert r.json()["detail"].startswith(f"{field}: ")


BAD_BODIES = [
    ({"tests": 0}, "tests: Input should be greater than or equal to 1"),
    ({"tests": 10001}, "tests: Input should be less than or equal to 10000"),
    ({"algorithms": ["ra2vipas", "magic"]}, "algorithms: no live controller serves policy 'magic'; available: ra2vipas, rapas, ravipas, sweep"),
    ({"algorithms": ["Magic!"]}, "algorithms.0: String should match pattern"),
    ({"algorithms": []}, "algorithms: List should have at least 1 item"),
    ({"mode": "slow"}, "mode: Input should be 'fast' or 'realtime'"),
    ({"seed": -1}, "seed: Input should be greater than or equal to 0"),
    ({"name": "x" * 101}, "name: String should have at most 100 characters"),
    ({"colour": "red"}, "colour: Extra inputs are not permitted"),
    ({"preset": "moon"}, "preset: unknown preset 'moon'; choose one of paper, paper-uniform, dynamic, ble, ble-dynamic, ble-recorded, ward"),
    ({"overrides": {"n_targets": 0}}, "overrides: n_targets: expected an integer in [1, 500], got 0"),
    ({"overrides": {"placement": "circle"}}, "overrides: placement: expected one of reference|uniform"),
    ({"overrides": {"nope": 1}}, "overrides: unknown scenario parameter 'nope'"),
    ({"overrides": {"n_targets": [1, 2]}}, "overrides.n_targets"),
    ({"overrides": {f"p{i}": 1 for i in range(65)}}, "overrides: Dictionary should have at most 64 items"),
    ({"overrides": {"placement": "x" * 65}}, "overrides.placement"),
    # no coercion: strings and booleans are not numbers (issue 14's probes)
    ({"tests": "10"}, "tests: Input should be a valid integer"),
    ({"tests": True}, "tests: Input should be a valid integer"),
    ({"seed": "1"}, "seed: Input should be a valid integer"),
    ({"name": 5}, "name: Input should be a valid string"),
    ({"overrides": {"n_targets": True}}, "overrides: n_targets: expected an integer in [1, 500], got True"),
    ({"overrides": {"n_targets": "30"}}, "overrides: n_targets: expected an integer in [1, 500], got '30'"),
    ({"overrides": {"n_targets": 30.5}}, "overrides: n_targets: expected an integer in [1, 500], got 30.5"),
    ({"overrides": {"rf_noise_db": "3"}}, "overrides: rf_noise_db: expected a number in [0.0, 30.0], got '3'"),
    ({"overrides": {"rf_period_s": -0.0}}, "overrides: rf_period_s: expected a number in (0.0, 10.0], got"),
    ({"overrides": {"n_target": 30}}, "overrides: unknown scenario parameter 'n_target' (did you mean 'n_targets'?)"),
]


@pytest.mark.parametrize("body, needle", BAD_BODIES, ids=[n.split(":")[0] + str(i) for i, (_, n) in enumerate(BAD_BODIES)])
def test_bad_campaigns_are_422_naming_the_field_and_store_nothing(http, body, needle):
    before = count(http)
    r = http.post("/campaigns", json=body)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert needle in detail and "\n" not in detail
    assert r.json()["errors"] and all(e["loc"][0] == "body" for e in r.json()["errors"])
    assert count(http) == before


@pytest.mark.parametrize("content", [b"{not json", b"", b"[]", json.dumps({"tests": float("nan")}).encode()])
def test_malformed_bodies_are_rejected_and_store_nothing(http, content):
    before = count(http)
    r = http.post("/campaigns", content=content, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["detail"]
    assert count(http) == before


def test_a_body_over_the_limit_is_413_and_stores_nothing(http):
    before = count(http)
    big = json.dumps({"name": "x", "overrides": {"pad": "y" * 70_000}}).encode()
    r = http.post("/campaigns", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and "larger than 65536 bytes" in r.json()["detail"]

    def chunks():  # no Content-Length: the limit is enforced while reading
        yield b'{"name": "'
        for _ in range(100):
            yield b"z" * 1000
        yield b'"}'

    r = http.post("/campaigns", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert count(http) == before


@pytest.mark.parametrize("method, path", [
    ("GET", "/campaigns/{x}"), ("GET", "/campaigns/{x}/results"), ("GET", "/campaigns/{x}/tests"),
    ("GET", "/campaigns/{x}/tests/0/ra2vipas"), ("GET", "/campaigns/{x}/tests/0/ra2vipas/plot"), ("GET", "/campaigns/{x}/plots/dr"),
    ("GET", "/campaigns/{x}/plots/pod"), ("GET", "/campaigns/{x}/events"), ("POST", "/campaigns/{x}/cancel"), ("DELETE", "/campaigns/{x}"),
])
def test_unknown_campaign_ids_are_404(http, method, path):
    r = http.request(method, path.format(x="0123456789ab"))
    assert r.status_code == 404
    assert r.json()["detail"] == "no campaign '0123456789ab'"


def test_health_reports_the_api_the_database_and_zenoh(http):
    body = http.get("/health").json()
    assert body["status"] == "ok" and body["ready"] and body["database"] and body["zenoh"]
    assert body["rigs"] == ["rig-1"] and body["learners"] == ["learner"]
