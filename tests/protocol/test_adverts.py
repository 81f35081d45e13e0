"""Protocol 1.3 (issue 20): per step, the advertisements each receiver heard, possibly none;
boxes with heights and scores. A 1.0 node's ``rf`` pair still reads as one advertisement per
receiver, and a message that uses no 1.3 feature is what a 1.0 sender sent."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from pydantic import ValidationError

from ra2vipas.services.protocol.measurements import Advertisement, CameraFrame, StepMeasurement, TrainingSample
from ra2vipas.services.protocol.messages import EpisodeStart, Measurement, TrainingStream, dump, training_job_id
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.schemas import schema_documents
from ra2vipas.services.protocol.versions import campaign_features, missing_features

ROOT = Path(__file__).resolve().parents[2]
V1 = ROOT / "docs" / "schemas" / "v1"


def _v1(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((V1 / f"{name}.json").read_text()))


def _current(name: str) -> Draft202012Validator:
    return Draft202012Validator(schema_documents()[f"{name}.json"])


def test_a_1_0_pair_reads_as_one_advertisement_per_receiver():
    m = Measurement.model_validate_json(b'{"episode_id":"e","step":2,"pan_rad":0.1,"rf":{"iso_rssi_dbm":-40.5,"dir_rssi_dbm":-35.0},'
                                        b'"frames":[{"box_bearings_rad":[0.1]}]}')
    ads = m.advertisements()
    assert [(a.receiver, a.rssi_dbm, a.channel, a.offset_s) for a in ads] == [("iso", -40.5, None, 0.0), ("dir", -35.0, None, 0.0)]
    assert m.rssi_dbm("iso") == (-40.5,) and m.rssi_dbm("dir") == (-35.0,)
    assert b"adverts" not in dump(m) and b"box_heights_rad" not in dump(m)


def test_adverts_carry_integers_channels_offsets_and_may_be_empty():
    payload = {"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": [],
               "adverts": [{"receiver": "iso", "rssi_dbm": -62, "channel": 37, "offset_s": 0.012},
                           {"receiver": "dir", "rssi_dbm": -70, "offset_s": 0.05},
                           {"receiver": "iso", "rssi_dbm": -61.5, "channel": 39, "offset_s": 0.13}]}
    m = Measurement.model_validate(payload)
    assert m.rf is None
    assert m.rssi_dbm("iso") == (-62, -61.5) and m.rssi_dbm("dir") == (-70,)
    assert [a.channel for a in m.advertisements("iso")] == [37, 39]
    wire = json.loads(dump(m))
    assert "rf" not in wire and len(wire["adverts"]) == 3
    assert list(_current("Measurement").iter_errors(wire)) == []
    assert list(_v1("Measurement").iter_errors(wire)) != []  # a 1.0 controller would reject it: rule 4 keeps it away

    empty = Measurement(episode_id="e", step=1, pan_rad=0.0, frames=())
    assert empty.advertisements() == () and empty.rssi_dbm("iso") == () and empty.rssi_dbm("dir") == ()
    assert json.loads(dump(empty)) == {"episode_id": "e", "step": 1, "pan_rad": 0.0, "frames": []}  # no made-up value


@pytest.mark.parametrize("bad", [
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60}], "rf": {"iso_rssi_dbm": -60.0, "dir_rssi_dbm": -60.0}},
    {"adverts": [{"receiver": "both", "rssi_dbm": -60}]},
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60, "channel": 12}]},
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60, "offset_s": -0.1}]},
    {"adverts": [{"receiver": "iso", "rssi_dbm": "-60"}]},
])
def test_malformed_adverts_are_rejected(bad):
    with pytest.raises(ValidationError):
        Measurement.model_validate({"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": [], **bad})


def test_boxes_may_carry_one_height_and_score_each():
    f = CameraFrame(box_bearings_rad=(-0.1, 0.2), box_heights_rad=(0.4, 0.2), box_scores=(0.9, 0.55))
    assert CameraFrame.model_validate_json(dump(f)) == f
    assert b"box_heights_rad" not in dump(CameraFrame(box_bearings_rad=(0.1,)))
    for bad in ({"box_heights_rad": (0.4,)}, {"box_scores": (0.1, 0.2, 0.3)}, {"box_heights_rad": (0.4, -0.1)}, {"box_scores": (0.5, 1.5)}):
        with pytest.raises(ValidationError):
            CameraFrame(box_bearings_rad=(-0.1, 0.2), **bad)


def test_training_samples_take_either_form():
    old = TrainingSample.model_validate({"index": 0, "iso_rssi_dbm": -44.0, "frames": []})
    new = TrainingSample.model_validate({"index": 1, "frames": [], "adverts": [{"receiver": "iso", "rssi_dbm": -45}, {"receiver": "iso", "rssi_dbm": -47}]})
    none = TrainingSample.model_validate({"index": 2, "frames": []})
    assert old.rssi_dbm() == (-44.0,) and new.rssi_dbm() == (-45, -47) and none.rssi_dbm() == ()
    stream = TrainingStream(job_id="j", samples=(old, new, none))
    assert TrainingStream.model_validate_json(dump(stream)) == stream
    assert list(_v1("TrainingSample").iter_errors(json.loads(dump(old)))) == []  # a 1.0 sample stays 1.0
    with pytest.raises(ValidationError):
        TrainingSample.model_validate({"index": 0, "iso_rssi_dbm": -44.0, "frames": [], "adverts": [{"receiver": "iso", "rssi_dbm": -45}]})


def test_step_measurement_with_neither_form_has_no_rf_evidence():
    m = StepMeasurement(step=0, pan_rad=0.0, frames=())
    assert m.advertisements() == ()
    assert Advertisement(receiver="dir", rssi_dbm=-80).offset_s == 0.0


def test_a_scenario_with_the_1_3_radio_needs_rigs_that_speak_1_3():
    assert campaign_features(scenario=build_scenario("paper")) == []
    assert campaign_features(scenario=build_scenario("dynamic")) == []
    features = campaign_features(scenario=build_scenario("ble"))
    assert ("scenario parameter 'radio'", "1.3") in features
    assert missing_features("1.2", features) and not missing_features("1.3", features)
    start = EpisodeStart(episode_id="c.0.ra2vipas.1", campaign_id="c", test_index=0, algorithm="ra2vipas", seed=1,
                         scenario=build_scenario("paper"))
    assert list(_v1("EpisodeStart").iter_errors(json.loads(dump(start)))) == []  # the 1.3 parameters stay off the wire


def test_a_paper_scenario_keeps_its_training_job_id():
    """The POD cache key hashes the scenario as it goes on the wire: the 1.3 parameters at their
    defaults leave the paper presets' ids as they were (value computed before 1.3)."""
    assert training_job_id(build_scenario("paper"), 1) == "pod-0fba6f1a5c47f8c4"
    assert training_job_id(build_scenario("ble"), 1) != training_job_id(build_scenario("paper"), 1)


def test_a_rig_says_what_its_measurements_carry_and_a_campaign_that_contradicts_it_is_a_conflict():
    from ra2vipas.services.protocol.rig import RigDescriptor, apply_rig_values, conflicts

    base = {"rig": "cam-1", "kind": "hardware", "frames_per_rf": 10, "rf_period_s": 0.1, "fov_half_angle_deg": 22.5,
            "box_bearing_noise_deg": 0.25, "rx_dir": {"model": "db-gain"}}
    old = RigDescriptor.model_validate(base)  # a 1.1 descriptor: the pair, no heights
    assert old.radio is None and old.box_heights is None and b"radio" not in dump(old)
    ble = RigDescriptor.model_validate({**base, "radio": "adverts", "box_heights": True, "protocol": "1.3"})
    found = {c.field: (c.campaign, c.rig) for c in conflicts(ble, build_scenario("paper", {"antenna_model": "db-gain"}))}
    assert found == {"radio": ("pair", "adverts"), "box_heights": (False, True)}
    applied = apply_rig_values(ble, build_scenario("paper"))
    assert applied.radio.value == "adverts" and applied.box_heights is True
    assert not conflicts(ble, applied)
