"""Surveys of a scene with several tags (issue 21, protocol 1.4): the recorder keeps every tag's
RF evidence (``rf_tags`` with the paper's radio) and the carrier of each tag (the layout's
``tx_indices``); the survey rig serves them back, and a campaign with several tags on it is
scored per tag against the layout's carriers."""

from __future__ import annotations

import queue

import numpy as np
import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.orchestrator.metrics import score_episode
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, EpisodeResult, EpisodeStart, EpisodeTruth, Measurement, decode, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.rigs.survey import Layout, Survey, SurveyNode, SurveySample, load, record_survey, save
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus
from tests.api.live import LiveAPI

SCENE = {"n_targets": 6, "n_tags": 2}
SEED = 4
PANS, PASSES = 36, 2
STEPS = 30


@pytest.fixture(scope="module")
def survey(tmp_path_factory) -> Survey:
    bus = MemoryBus()
    node = SensorsNode(bus, "sim-1")
    try:
        recorded = record_survey(bus, "sim-1", pans=PANS, passes=PASSES, n_train=100, seed=SEED, scenario=build_scenario("paper", SCENE))
    finally:
        node.close()
        bus.close()
    path = tmp_path_factory.mktemp("survey-tags") / "two-tags.json"
    save(recorded, path)
    return load(path)


def test_the_recorder_keeps_every_tags_pair_and_carrier(survey):
    lay = survey.layout
    assert len(lay.tx_indices) == 2 and lay.tx_indices[0] == lay.tx_index and lay.tx_indices[1] != lay.tx_index
    assert len(lay.tag_addresses) == 2 and len(set(lay.tag_addresses)) == 2
    for one in survey.passes:
        for sample in one:
            assert sample.rf is not None and sample.rf.tag == 0
            assert [p.tag for p in sample.rf_tags] == [1]
    # the recorded pairs are the simulator's: tag 1's pair differs from tag 0's (its own carrier, its own noise)
    assert any(s.rf_tags[0].dir_rssi_dbm != s.rf.dir_rssi_dbm for s in survey.passes[0])


def test_a_single_tag_survey_sample_and_layout_hold_no_tag_fields():
    """What 1.3 wrote is still what is written (``dump`` leaves unused 1.4 fields out), and
    rf_tags need rf, tx_indices start with tx_index."""
    from ra2vipas.services.protocol.measurements import CameraFrame, RFSample

    sample = SurveySample(rf=RFSample(iso_rssi_dbm=-50.0, dir_rssi_dbm=-52.0), frames=(CameraFrame(),))
    assert b"rf_tags" not in dump(sample)
    assert b"tx_indices" not in dump(Layout(bearings_rad=(0.1, 0.2), tx_index=1))
    with pytest.raises(ValueError, match="rf_tags need rf"):
        SurveySample(frames=(CameraFrame(),), rf_tags=(RFSample(iso_rssi_dbm=-50.0, dir_rssi_dbm=-52.0, tag=1),))
    with pytest.raises(ValueError, match="tx_indices must start with tx_index"):
        Layout(bearings_rad=(0.1, 0.2), tx_index=1, tx_indices=(0, 1))


def test_the_survey_rig_serves_every_tags_pair_and_the_carriers(survey):
    bus = MemoryBus()
    node = SurveyNode(bus, "survey-1", survey)
    got: queue.Queue = queue.Queue()
    bus.subscribe(keys.measurement("survey-1"), lambda _k, p: got.put(decode(Measurement, p)[0]))
    bus.subscribe(keys.episode_truth("survey-1"), lambda _k, p: got.put(decode(EpisodeTruth, p)[0]))
    try:
        sc = build_scenario("paper", {**SCENE, "steps": 4})
        bus.publish(keys.episode_control("survey-1"), dump(EpisodeStart(episode_id="e.0.ra2vipas.1.x", campaign_id="e", test_index=0,
                                                                          algorithm="ra2vipas", seed=1, scenario=sc)))
        bus.publish(keys.command("survey-1"), dump(Command(episode_id="e.0.ra2vipas.1.x", step=0, pan_rad=survey.pans_rad[5])))
        first, second = got.get(timeout=10), got.get(timeout=10)
    finally:
        node.close()
        bus.close()
    truth = first if isinstance(first, EpisodeTruth) else second
    m = second if truth is first else first
    assert truth.tx_indices == survey.layout.tx_indices and truth.tag_addresses == survey.layout.tag_addresses
    assert m.pan_rad == survey.pans_rad[5] and [p.tag for p in m.pairs()] == [0, 1]
    assert any(m.rf_tags == one[5].rf_tags and m.rf == one[5].rf for one in survey.passes)


def test_a_two_tag_campaign_on_the_survey_rig_is_scored_per_tag_against_the_layout(tmp_path, survey):
    server = LiveAPI(tmp_path / "survey-tags.db", rigs=())
    server.nodes += [SurveyNode(server.bus, "survey-1", survey), ControllerNode(server.bus, "survey-1")]
    server.start()
    try:
        server.settle()
        with server.client() as http:
            r = http.post("/campaigns", json={"preset": "paper", "overrides": {**SCENE, "steps": STEPS, "n_train": 100}, "tests": 3,
                                              "seed": SEED, "algorithms": ["ra2vipas"], "rig_kind": "survey", "use_rig_values": True})
            assert r.status_code == 201, r.text
        done = server.wait(r.json()["id"], timeout=300)
        assert done["status"] == "done", done["error"]
        with server.client() as http:
            results = http.get(f"/campaigns/{done['id']}/results").json()
        sent = [EpisodeResult.model_validate_json(p) for k, p in server.bus.published if k == keys.episode_result("survey-1")]
    finally:
        server.stop()
    per_tag = results["algorithms"]["ra2vipas"]["tags"]["per_tag"]
    assert len(per_tag) == 2 and len(sent) == 3 and all(sorted(t.tag for t in r.tags) == [0, 1] for r in sent)
    # tag k's DR is eq. 11 against the layout's carrier of tag k, not tag 0's
    bearings = np.asarray(survey.layout.bearings_rad)
    fov = build_scenario("paper", SCENE).fov_half_angle_rad
    for k in range(2):
        finals = [score_episode(np.asarray(next(t for t in r.tags if t.tag == k).estimates_rad), bearings, survey.layout.tx_indices[k],
                                fov, STEPS)[0][-1] for r in sent]
        assert per_tag[k]["dr_final"] == pytest.approx(sum(bool(h) for h in finals) / 3)
