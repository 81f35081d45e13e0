"""Record and replay a campaign with several tags (issue 21): the recording re-scores to the
recorded results per tag too (each tag against its carrier), and the same policies re-run on the
recorded measurements (every tag's RF evidence, ``rf_tags``) take every recorded pan and give
every tag's recorded estimates."""

from __future__ import annotations

import pytest

from ra2vipas.cli.client import Client
from ra2vipas.cli.record import save_recording
from ra2vipas.services.rigs.recording import Recorder, read_mcap, replay_scores, rerun, rerun_summary
from tests.api.live import SMALL, LiveAPI
from tests.conftest import untimed

ALGORITHMS = ["ra2vipas", "ra2vipas-seq"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("record-tags")
    server = LiveAPI(tmp / "rec.db", rigs=("rig-1",)).start()
    recorder = Recorder(server.bus)
    try:
        with server.client() as http:
            r = http.post("/campaigns", json={"preset": "paper", "overrides": {**SMALL, "steps": 30, "n_tags": 2}, "tests": 3,
                                              "seed": 6, "algorithms": ALGORITHMS, "stop_confidence": 0.9})
        assert r.status_code == 201, r.text
        done = server.wait(r.json()["id"])
        assert done["status"] == "done", done["error"]
        server.settle()
        recorder.stop()
        client = Client(server.url, None)
        live = tmp / "live.mcap"
        save_recording(client, done["id"], live, recorder, server.bus)
        yield {"live": live, "results": client.request("GET", f"/campaigns/{done['id']}/results")}
    finally:
        server.stop()


def test_replay_reproduces_the_recorded_per_tag_results(recorded):
    results = recorded["results"]
    assert all(len(results["algorithms"][a]["tags"]["per_tag"]) == 2 for a in ALGORITHMS)
    rec = read_mcap(recorded["live"])
    assert any(m.rf_tags for ep in rec.recorded() for m in ep.measurements.values())
    assert untimed(replay_scores(rec)) == untimed(results)


def test_the_same_policies_rerun_give_every_tags_recorded_estimates(recorded):
    rec = read_mcap(recorded["live"])
    runs = rerun(rec)
    assert len(runs) == 6
    assert all(r.matched == r.steps and r.same_estimates and len(r.tag_estimates) == 2 for r in runs), [
        (r.episode_id, r.matched, r.steps, r.same_estimates) for r in runs]
    summary = rerun_summary(runs)
    for name in ALGORITHMS:
        assert summary[name]["same_estimates"] == summary[name]["episodes_matched"] == 3  # an early decision: matched to its end
        expected = [t["dr_final"] for t in recorded["results"]["algorithms"][name]["tags"]["per_tag"]]
        assert summary[name]["tag_dr_final_matched"] == expected
