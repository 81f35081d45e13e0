"""Policies through the API (issue 19): ``GET /rigs`` shows each rig's served policies; a
campaign naming a policy no live controller serves is a 422 listing the available ones; a
policy installed only on a controller (not on the orchestrator) runs there and only there."""

from __future__ import annotations

import pytest

from ra2vipas.services.controller import registry
from ra2vipas.services.controller.registry import BUILTINS
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
from tests.api.live import SMALL, LiveAPI
from tests.nodes.test_policy_mesh import SPIN


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """spin-1 serves only spin (a policy the orchestrator has not installed); all-1 serves every
    installed policy."""
    live = LiveAPI(tmp_path_factory.mktemp("policies") / "p.db", rigs=("spin-1", "all-1"), window=4,
                   controllers={"spin-1": {"policies": [SPIN]}}).start()
    live.settle()
    yield live
    live.stop()


def _start(server, **body):
    with server.client() as http:
        return http.post("/campaigns", json={"preset": "paper", "overrides": SMALL, "tests": 3, "seed": 4, **body})


def test_rigs_show_the_policies_their_controllers_serve(server):
    with server.client() as http:
        rigs = {r["name"]: r for r in http.get("/rigs").json()["rigs"]}
        page = http.get("/ui/rigs").text
    assert '<td class="policies">spin</td>' in page  # the dashboard's rigs page too
    assert rigs["spin-1"]["announced"] == "announced" and rigs["spin-1"]["controller_protocol"] == PROTOCOL_VERSION
    assert [p["name"] for p in rigs["spin-1"]["policies"]] == ["spin"]
    assert [p["name"] for p in rigs["all-1"]["policies"]][:4] == list(BUILTINS)
    assert rigs["all-1"]["policies"][0]["package"] == "ra2vipas"


def test_a_policy_no_live_controller_serves_is_a_422_listing_the_available_ones(server):
    r = _start(server, algorithms=["ra2vipas", "nope"])
    assert r.status_code == 422, r.text
    available = ", ".join([*registry.names(), "spin"])  # all-1 serves every installed policy (ra2vipas-seq too)
    assert r.json()["detail"] == f"algorithms: no live controller serves policy 'nope'; available: {available}"
    assert r.json()["errors"][0]["loc"] == ["body", "algorithms"]
    r = _start(server, algorithms=["rapas"], rigs=["spin-1"])  # only the targeted rigs' controllers count
    assert r.status_code == 422 and r.json()["detail"] == "algorithms: no live controller serves policy 'rapas'; available: spin", r.text


def test_a_policy_served_by_one_controller_runs_there_only(server):
    r = _start(server, algorithms=["spin", "rapas"])
    assert r.status_code == 201, r.text
    done = server.wait(r.json()["id"])
    assert done["status"] == "done", done["error"]
    with server.client() as http:
        tests = http.get(f"/campaigns/{done['id']}/tests", params={"limit": 200}).json()["items"]
    by_policy: dict[str, set[str]] = {}
    for t in tests:
        by_policy.setdefault(t["algorithm"], set()).add(t["rig"])
    assert by_policy["spin"] == {"spin-1"} and by_policy["rapas"] == {"all-1"}


def test_a_study_naming_a_policy_served_by_one_controller_runs_it_there_only(server):
    with server.client() as http:
        r = http.post("/studies", json={"preset": "paper", "overrides": SMALL, "vary": {"rf_noise_db": [2.0, 4.0]},
                                        "algorithms": ["rapas", "spin"], "tests": 2, "seed": 5})
        assert r.status_code == 201, r.text
        points = r.json()["points"]
        assert http.post("/studies", json={"preset": "paper", "overrides": SMALL, "vary": {"rf_noise_db": [2.0, 4.0]},
                                           "algorithms": ["nope"], "tests": 1, "seed": 5}).status_code == 422
    by_policy: dict[str, set[str]] = {}
    for point in points:
        done = server.wait(point["campaign_id"])
        assert done["status"] == "done", done["error"]
        with server.client() as http:
            for t in http.get(f"/campaigns/{point['campaign_id']}/tests", params={"limit": 200}).json()["items"]:
                by_policy.setdefault(t["algorithm"], set()).add(t["rig"])
    assert by_policy == {"spin": {"spin-1"}, "rapas": {"all-1"}}
