"""Record and replay: a campaign recorded as it runs (every message, JSON Schemas embedded in the
MCAP file) re-scores to the results it recorded, and the current controller re-run on the
recorded measurements takes every recorded pan and gives the recorded estimates; a campaign
recorded afterwards from the store re-scores the same but cannot be re-run."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import httpx
import pytest
from mcap.reader import make_reader

from ra2vipas.cli.client import Client
from ra2vipas.cli.record import save_recording
from ra2vipas.services.rigs.recording import Recorder, RecordingError, read_mcap, replay_scores, rerun, rerun_summary
from tests.api.live import SMALL, LiveAPI
from tests.conftest import untimed
from tests.integration.conftest import ROOT
from tests.rigs.conftest import cli


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("record")
    server = LiveAPI(tmp / "rec.db", rigs=("rig-1", "rig-2")).start()
    recorder = Recorder(server.bus)
    try:
        with server.client() as http:
            r = http.post("/campaigns", json={"preset": "dynamic", "overrides": {**SMALL, "walking_fraction": 0.25}, "tests": 3,
                                              "seed": 6, "algorithms": ["ra2vipas", "rapas", "sweep"], "stop_confidence": 0.97})
        assert r.status_code == 201, r.text
        done = server.wait(r.json()["id"])
        assert done["status"] == "done", done["error"]
        server.settle()
        recorder.stop()
        client = Client(server.url, None)
        live, store = tmp / "live.mcap", tmp / "store.mcap"
        save_recording(client, done["id"], live, recorder, server.bus)
        save_recording(client, done["id"], store, None, None)
        results = client.request("GET", f"/campaigns/{done['id']}/results")
        yield {"live": live, "store": store, "results": results, "id": done["id"]}
    finally:
        server.stop()


def test_the_file_is_mcap_with_json_schemas_embedded(recorded):
    with open(recorded["live"], "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {s.name: s for s in summary.schemas.values()}
    assert {"EpisodeControl", "Command", "Measurement", "EpisodeResult", "EpisodeTruth", "RigDescriptor", "PODResponse"} <= set(schemas)
    assert all(s.encoding == "jsonschema" for s in schemas.values())
    assert json.loads(schemas["Measurement"].data)["title"] == "Measurement"
    topics = {c.topic for c in summary.channels.values()}
    assert "ra2vipas/v1/data/rig-1/measurement" in topics or "ra2vipas/v1/data/rig-2/measurement" in topics
    assert all(c.message_encoding == "json" for c in summary.channels.values())


def test_replay_reproduces_the_recorded_results(recorded):
    rec = read_mcap(recorded["live"])
    assert rec.source == "live" and rec.pod is not None and set(rec.descriptors) == {"rig-1", "rig-2"}
    assert untimed(replay_scores(rec)) == untimed(recorded["results"])
    store = read_mcap(recorded["store"])
    assert store.source == "store"
    assert untimed(replay_scores(store)) == untimed(recorded["results"])


def test_the_same_controller_rerun_takes_every_recorded_pan(recorded):
    rec = read_mcap(recorded["live"])
    runs = rerun(rec)
    assert runs and all(r.matched == r.steps and r.same_estimates for r in runs), [(r.episode_id, r.matched, r.steps) for r in runs]
    summary = rerun_summary(runs)
    for name in ("ra2vipas", "rapas", "sweep"):
        assert summary[name]["episodes_matched"] == summary[name]["same_estimates"] == 3
        assert summary[name]["dr_final_matched"] == recorded["results"]["algorithms"][name]["dr_final"]
        assert summary[name]["stopped_other_pan"] == summary[name]["stopped_missing_measurement"] == 0
    # another algorithm on the same measurements follows the recorded pans only while it asks for them
    other = rerun_summary(rerun(rec, "rapas"))["rapas"]
    assert other["episodes"] == 9 and other["steps_matched"] < 1.0
    assert other["stopped_other_pan"] >= 1 and other["stopped_missing_measurement"] == 0


def test_a_rerun_says_where_the_recording_lacks_a_measurement(recorded):
    """A measurement lost while recording stops that episode's rerun there, and the summary says
    it was the recording, not the controller, that stopped it."""
    rec = read_mcap(recorded["live"])
    episode = next(ep for ep in rec.recorded() if ep.start.algorithm == "ra2vipas" and len(ep.result.estimates_rad) > 5)
    del episode.measurements[5]
    runs = {r.episode_id: r for r in rerun(rec)}
    lost = runs[episode.episode_id]
    assert (lost.stopped, lost.matched) == ("missing", 5)
    assert all(r.stopped is None for eid, r in runs.items() if eid != episode.episode_id)
    summary = rerun_summary(list(runs.values()))["ra2vipas"]
    assert (summary["stopped_missing_measurement"], summary["stopped_other_pan"], summary["episodes_matched"]) == (1, 0, 2)


def test_a_recording_from_the_store_cannot_be_rerun(recorded):
    with pytest.raises(RecordingError, match="no measurements"):
        rerun(read_mcap(recorded["store"]))
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "replay", str(recorded["store"]), "--rerun", "same"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and out.stderr.startswith("error: the recording holds no measurements")
    out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "replay", str(ROOT / "pyproject.toml")], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and out.stderr.count("\n") == 1 and "not a readable ra2vipas recording" in out.stderr


def test_campaign_start_record_then_replay_through_real_processes(local_stack, tmp_path):
    """The commands as a user runs them: an insecure local stack, `campaign start --record`,
    `replay` (re-score and re-run)."""
    api, env = local_stack["api"], local_stack["env"]
    file = tmp_path / "c.mcap"
    args = ["--preset", "paper", "--tests", "2", "--seed", "3", "-a", "ra2vipas,rapas", "--set", "steps=20", "--set", "n_train=200",
            "--set", "n_targets=8"]
    started = cli("campaign", "start", "--api", api, *args, "--record", str(file), "--json", env=env, timeout=300)
    assert started.returncode == 0, started.stderr
    results = json.loads(started.stdout.strip().splitlines()[-1])
    replayed = cli("replay", str(file), "--json")
    assert replayed.returncode == 0, replayed.stderr
    body = json.loads(replayed.stdout.strip().splitlines()[-1])
    assert body["source"] == "live" and body["matches_recorded_results"] is True
    assert untimed(body["results"]) == untimed(results)
    again = cli("replay", str(file), "--rerun", "same", "--json")
    assert again.returncode == 0, again.stderr
    rerun_body = json.loads(again.stdout.strip().splitlines()[-1])["rerun"]
    assert {a: (s["episodes_matched"], s["same_estimates"]) for a, s in rerun_body.items()} == {"ra2vipas": (2, 2), "rapas": (2, 2)}


def test_record_a_running_campaign_then_the_finished_one_with_the_command(local_stack, tmp_path):
    """`ra2vipas record --campaign ID`: on a running campaign (realtime: it runs for 4 s at least)
    it records live until the campaign finishes; on the finished one, from what the orchestrator
    kept plus the POD model from the learner. Both re-score to the campaign's results."""
    api, env = local_stack["api"], local_stack["env"]
    with httpx.Client(base_url=api, timeout=30) as http:
        r = http.post("/campaigns", json={"overrides": {"steps": 20, "rf_period_s": 0.05, "n_train": 200, "n_targets": 6}, "tests": 4, "seed": 5,
                                          "algorithms": ["rapas"], "mode": "realtime"})
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        live = cli("record", "--campaign", cid, "-o", str(tmp_path / "live.mcap"), "--api", api, env=env, timeout=300)
        assert live.returncode == 0, live.stderr
        assert f"recording campaign {cid} live until it finishes" in live.stderr  # it was still running
        assert re.fullmatch(rf"wrote \d+ messages of campaign {cid} to .*live\.mcap", live.stdout.strip()), live.stdout
        done = http.get(f"/campaigns/{cid}").json()
        assert done["status"] == "done", done
        results = http.get(f"/campaigns/{cid}/results").json()
    rec = read_mcap(tmp_path / "live.mcap")
    assert rec.source in ("live", "live+store") and rec.campaign["id"] == cid and rec.campaign["mode"] == "realtime"
    assert any(ep.measurements for ep in rec.episodes.values()), "no measurement recorded live"
    assert untimed(replay_scores(rec)) == untimed(results)
    kept = cli("record", "--campaign", cid, "--output", str(tmp_path / "kept.mcap"), "--api", api, env=env)
    assert kept.returncode == 0 and "live" not in kept.stderr, kept.stderr
    rec = read_mcap(tmp_path / "kept.mcap")
    assert rec.source == "store" and rec.pod is not None and set(rec.descriptors) == {"rig-1"}
    assert untimed(replay_scores(rec)) == untimed(results)
