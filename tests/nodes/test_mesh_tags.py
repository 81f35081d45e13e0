"""Several tags through the in-memory mesh (issue 21): the controller node searches every tag,
sends one ``TagResult`` per tag, ends the episode when all are decided, and the orchestrator
scores each tag against its carrier; the results equal ``simulate``'s value for value."""

from __future__ import annotations

import json

import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.scenario import build_scenario
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end

SMALL = {"steps": 40, "n_train": 200, "n_targets": 8, "n_tags": 3}


@pytest.mark.parametrize("stop_confidence", [0.0, 0.9])
def test_a_three_tag_campaign_over_the_bus_equals_simulate(mesh, stop_confidence):
    bus, store, scheduler = mesh()
    algorithms = ["ra2vipas", "ra2vipas-seq"]
    c = run_to_end(store, scheduler, "paper", SMALL, 3, 5, algorithms, stop_confidence=stop_confidence, timeout=240.0)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("paper", build_scenario("paper", SMALL), 3, 5, algorithms, stop_confidence=stop_confidence)
    got = untimed(c["results"])
    got.pop("warnings", None)
    expected.pop("warnings", None)
    assert got == untimed(expected)
    for name in algorithms:
        assert len(got["algorithms"][name]["tags"]["per_tag"]) == 3
    results = [json.loads(p) for k, p in bus.published if k == keys.episode_result("rig-1")]
    assert results and all(sorted(t["tag"] for t in r["tags"]) == [0, 1, 2] for r in results)
