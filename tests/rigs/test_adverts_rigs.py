"""Protocol 1.3 adverts through the rigs' kit (issue 20, 6): a survey whose samples hold
advertisements (some none) is served as a rig that passes the conformance kit, its steps
carrying the recorded adverts and never a made-up pair; our simulated sensors node puts the
world's adverts on the wire; a 1.2 node that sends adverts fails the rf-evidence rule."""

from __future__ import annotations

import json
import time

import pytest

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.measurements import Advertisement
from ra2vipas.services.protocol.messages import Command, EpisodeStart, Measurement, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.rigs.conformance import check_rig
from ra2vipas.services.rigs.survey import Survey, SurveyNode, SurveySample, load
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus

DATA = __import__("pathlib").Path(__file__).resolve().parent / "data" / "sim-survey.json"


def _advert_survey(protocol: str = "1.3") -> Survey:
    """The checked-in survey with every sample's pair replaced by adverts: whole-dBm iso and dir
    packets on two samples in three, none on the third."""
    survey = load(DATA)
    passes = []
    for p in survey.passes:
        row = []
        for j, sample in enumerate(p):
            adverts = () if j % 3 == 2 else (
                Advertisement(receiver="iso", rssi_dbm=round(sample.rf.iso_rssi_dbm), channel=37 + j % 3, offset_s=0.01 * (j % 7)),
                Advertisement(receiver="dir", rssi_dbm=round(sample.rf.dir_rssi_dbm), offset_s=0.01 * (j % 7) + 0.002))
            row.append(SurveySample(frames=sample.frames, adverts=adverts))
        passes.append(tuple(row))
    return survey.model_copy(update={"passes": tuple(passes), "rig": survey.rig.model_copy(update={"protocol": protocol})})


def _wait_for_steps(got: list, n: int, timeout: float = 60.0) -> None:
    """A node answers on its own event loop, after the bus has gone idle: wait (on a loaded
    machine, up to ``timeout``) until ``n`` measurements arrived."""
    deadline = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        time.sleep(0.01)


def test_a_survey_sample_holds_a_pair_or_adverts_not_both():
    sample = load(DATA).passes[0][0]
    with pytest.raises(ValueError):
        SurveySample(rf=sample.rf, frames=sample.frames, adverts=(Advertisement(receiver="iso", rssi_dbm=-50),))
    empty = SurveySample(frames=sample.frames)
    assert empty.rf is None and empty.adverts == ()
    again = Survey.model_validate_json(_advert_survey().model_dump_json())
    assert sum(1 for s in again.passes[0] if not s.adverts) == 60


def test_a_survey_of_adverts_passes_the_kit_and_serves_them():
    survey = _advert_survey()
    bus = MemoryBus()
    node = SurveyNode(bus, "survey-ble", survey)
    try:
        results = {r.rule: r for r in check_rig(bus, "survey-ble", timeout=3.0)}
        got: list[Measurement] = []
        bus.subscribe(keys.measurement("survey-ble"), lambda _k, payload: got.append(Measurement.model_validate_json(payload)))
        start = EpisodeStart(episode_id="s.0.ra2vipas.1", campaign_id="s", test_index=0, algorithm="ra2vipas", seed=1,
                             scenario=build_scenario("paper", {"steps": 3, "n_targets": len(survey.layout.bearings_rad)}))
        bus.publish(keys.episode_control("survey-ble"), dump(start))
        assert bus.wait_idle()
        for t, pan in enumerate((0.0, 0.5, 1.0)):
            bus.publish(keys.command("survey-ble"), dump(Command(episode_id=start.episode_id, step=t, pan_rad=pan)))
            _wait_for_steps(got, t + 1)
    finally:
        node.close()
        bus.close()
    assert {k: r.status for k, r in results.items() if not k.startswith("realtime")} == {**dict.fromkeys(
        [k for k in results if not k.startswith("realtime")], "pass"), "tags": "skip"}, results  # it says no number of tags
    assert results["rf-evidence"].detail.startswith("0 steps with an rf pair"), results["rf-evidence"].detail
    assert len(got) == 3 and all(m.rf is None for m in got)
    assert all(a.rssi_dbm == round(a.rssi_dbm) for m in got for a in m.adverts)


def test_a_node_that_speaks_1_2_may_not_send_adverts():
    bus = MemoryBus()
    node = SurveyNode(bus, "survey-old", _advert_survey(protocol="1.2"))
    try:
        results = {r.rule: r for r in check_rig(bus, "survey-old", timeout=3.0)}
    finally:
        node.close()
        bus.close()
    assert results["rf-evidence"].status == "fail" and "speaks protocol 1.2" in results["rf-evidence"].detail


def test_the_simulated_sensors_node_sends_the_worlds_adverts():
    bus = MemoryBus()
    node = SensorsNode(bus, "sim-ble")
    got: list[bytes] = []
    try:
        bus.subscribe(keys.measurement("sim-ble"), lambda _k, payload: got.append(payload))
        start = EpisodeStart(episode_id="b.0.ra2vipas.1", campaign_id="b", test_index=0, algorithm="ra2vipas", seed=3,
                             scenario=build_scenario("ble", {"steps": 40}))
        bus.publish(keys.episode_control("sim-ble"), dump(start))
        assert bus.wait_idle()
        for t in range(40):
            bus.publish(keys.command("sim-ble"), dump(Command(episode_id=start.episode_id, step=t, pan_rad=0.1 * t)))
            deadline = time.monotonic() + 60.0  # the node answers on its own thread: wait for step t's measurement
            while sum(1 for p in got if b'"step"' in p) <= t and time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        node.close()
        bus.close()
    messages = [json.loads(p) for p in got if b'"step"' in p]
    assert len(messages) == 40 and not any("rf" in m for m in messages)
    with_adverts = [m for m in messages if m.get("adverts")]
    assert with_adverts and len(with_adverts) < 40  # a packet every 0.45 s: most 0.1 s steps carry none
    assert all(isinstance(a["rssi_dbm"], float) and a["rssi_dbm"] == round(a["rssi_dbm"]) for m in with_adverts for a in m["adverts"])


def test_a_recording_keeps_each_steps_adverts_and_empty_steps(tmp_path):
    from ra2vipas.services.rigs.recording import _Entry, read_mcap, write_mcap

    eid = "c1.0.ra2vipas.1"
    steps = [Measurement(episode_id=eid, step=0, pan_rad=0.0, frames=(),
                         adverts=(Advertisement(receiver="iso", rssi_dbm=-61, channel=38, offset_s=0.03),)),
             Measurement(episode_id=eid, step=1, pan_rad=0.2, frames=())]
    entries = [_Entry(keys.measurement("rig-1"), dump(m), 1_000 + t) for t, m in enumerate(steps)]
    path = tmp_path / "ble.mcap"
    assert write_mcap(path, entries, campaign={"id": "c1"}, results=None, source="live") == 2
    recorded = read_mcap(path).episodes[eid].measurements
    assert recorded[0].rssi_dbm("iso") == (-61,) and recorded[0].adverts[0].channel == 38
    assert recorded[1].advertisements() == () and recorded[1].rf is None  # a step with nothing stays nothing
