"""Protocol 1.4 (issue 21; docs/tags.md): RF evidence names its tag, the truth names each tag's
carrier, a result may carry one trace per tag; a message without them is what 1.3 (and 1.0)
sent, and a campaign with several tags goes only to rigs that speak 1.4."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from pydantic import ValidationError

from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeStart, EpisodeTruth, Measurement, TagResult, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.schemas import schema_documents
from ra2vipas.services.protocol.versions import (
    PROTOCOL_VERSION,
    V1_3,
    V1_4,
    VERSIONS,
    campaign_features,
    describe_missing,
    missing_features,
    newer,
)
from ra2vipas.services.sensors.world import SimulatedPlatform, episode_truth

ROOT = Path(__file__).resolve().parents[2]
V1_3_DIR = ROOT / "docs" / "schemas" / "v1.3"


def _frozen(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((V1_3_DIR / f"{name}.json").read_text()))


def _current(name: str) -> Draft202012Validator:
    return Draft202012Validator(schema_documents()[f"{name}.json"])


def test_1_4_follows_1_3_and_1_3_is_frozen_beside_it():
    assert VERSIONS.index(V1_4) == VERSIONS.index(V1_3) + 1 and not newer(V1_4, PROTOCOL_VERSION)
    current = schema_documents()
    frozen = {p.name for p in V1_3_DIR.glob("*.json")}
    assert frozen and frozen <= set(current)
    for name in frozen:  # 1.4 only adds: every 1.3 property is still there
        old, new = json.loads((V1_3_DIR / name).read_text()), current[name]
        assert set(old.get("properties", {})) <= set(new.get("properties", {})), name
        for d, body in (old.get("$defs") or {}).items():
            assert set(body.get("properties", {})) <= set(new["$defs"][d].get("properties", {})), f"{name} {d}"
    text = (ROOT / "docs" / "protocol.md").read_text()
    assert "schemas/v1.3/" in text and "**1.4**" in text


def test_untagged_1_3_messages_read_as_tag_0_and_go_out_unchanged():
    payload = (b'{"episode_id":"e","step":0,"pan_rad":0.0,"frames":[],'
               b'"adverts":[{"receiver":"iso","rssi_dbm":-62,"channel":37,"offset_s":0.012},{"receiver":"dir","rssi_dbm":-70}]}')
    m = Measurement.model_validate_json(payload)
    assert m.tags() == (0,) and m.rssi_dbm("iso") == (-62,) and m.rssi_dbm("iso", tag=1) == ()
    assert dump(m) == (b'{"step":0,"pan_rad":0.0,"frames":[],"adverts":[{"receiver":"iso","rssi_dbm":-62.0,"channel":37,"offset_s":0.012},'
                       b'{"receiver":"dir","rssi_dbm":-70.0,"channel":null,"offset_s":0.0}],"episode_id":"e"}')  # no tag, no address
    pair = Measurement.model_validate_json(b'{"episode_id":"e","step":1,"pan_rad":0.1,"rf":{"iso_rssi_dbm":-40.5,"dir_rssi_dbm":-35.0},"frames":[]}')
    assert pair.tags() == (0,) and pair.rssi_dbm("dir") == (-35.0,) and pair.pairs() == (pair.rf,)
    assert dump(pair) == b'{"step":1,"pan_rad":0.1,"rf":{"iso_rssi_dbm":-40.5,"dir_rssi_dbm":-35.0},"frames":[],"episode_id":"e"}'


@pytest.mark.parametrize("preset", ["paper", "dynamic", "ble", "ble-recorded"])
def test_a_single_tag_worlds_messages_are_valid_1_3_messages(preset):
    sc = build_scenario(preset, {"steps": 20})
    platform = SimulatedPlatform(sc, 1, 0)
    for t in range(sc.steps):
        m = platform.sense(t, 0.1 * t)
        wire = json.loads(dump(Measurement.model_construct(episode_id="e", **{k: getattr(m, k) for k in type(m).model_fields})))
        assert list(_frozen("Measurement").iter_errors(wire)) == []
    assert list(_frozen("EpisodeTruth").iter_errors(json.loads(dump(episode_truth(platform.truth, "e"))))) == []
    start = EpisodeStart(episode_id="c.0.ra2vipas.1", campaign_id="c", test_index=0, algorithm="ra2vipas", seed=1, scenario=sc)
    assert list(_frozen("EpisodeStart").iter_errors(json.loads(dump(start)))) == []


def test_tagged_evidence_is_1_4_only():
    tagged = {"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": [],
              "adverts": [{"receiver": "iso", "rssi_dbm": -62, "tag": 2, "address": "C3:5A:01:9E:44:B2"}]}
    m = Measurement.model_validate(tagged)
    assert m.tags() == (2,) and m.rssi_dbm("iso") == () and m.rssi_dbm("iso", tag=2) == (-62,)
    wire = json.loads(dump(m))
    assert list(_current("Measurement").iter_errors(wire)) == []
    assert list(_frozen("Measurement").iter_errors(wire)) != []  # a 1.3 controller would reject it: rule 4 keeps it away
    pairs = {"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": [], "rf": {"iso_rssi_dbm": -40.0, "dir_rssi_dbm": -35.0},
             "rf_tags": [{"iso_rssi_dbm": -50.0, "dir_rssi_dbm": -55.0, "tag": 1}, {"iso_rssi_dbm": -45.0, "dir_rssi_dbm": -44.0, "tag": 2}]}
    m = Measurement.model_validate(pairs)
    assert m.tags() == (0, 1, 2) and m.rssi_dbm("iso", tag=1) == (-50.0,) and m.rssi_dbm("dir", tag=None) == (-35.0, -55.0, -44.0)
    assert [a.tag for a in m.advertisements(tag=None)] == [0, 0, 1, 1, 2, 2]
    assert Measurement.model_validate_json(dump(m)) == m


@pytest.mark.parametrize("bad", [
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60, "tag": -1}]},
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60, "tag": 64}]},
    {"adverts": [{"receiver": "iso", "rssi_dbm": -60, "address": "c3:5a:01:9e:44:b2:00"}]},
    {"rf_tags": [{"iso_rssi_dbm": -50.0, "dir_rssi_dbm": -55.0, "tag": 1}]},  # without tag 0's pair
    {"rf": {"iso_rssi_dbm": -40.0, "dir_rssi_dbm": -35.0}, "rf_tags": [{"iso_rssi_dbm": -50.0, "dir_rssi_dbm": -55.0}]},  # tag 0 twice
])
def test_malformed_tags_are_rejected(bad):
    with pytest.raises(ValidationError):
        Measurement.model_validate({"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": [], **bad})


def test_the_truth_names_each_tags_carrier():
    base = {"episode_id": "e", "bearings_rad": [0.0, 1.0, 2.0], "ranges_m": [1.0, 2.0, 3.0], "tx_index": 1, "trajectories": []}
    assert EpisodeTruth.model_validate(base).carriers == (1,)
    assert json.loads(dump(EpisodeTruth.model_validate(base))) == base  # as a 1.0 sender sent it
    many = EpisodeTruth.model_validate({**base, "tx_indices": [1, 1, 2], "tag_addresses": ["C0:00:00:00:00:01", "C0:00:00:00:00:02",
                                                                                          "C0:00:00:00:00:03"]})
    assert many.carriers == (1, 1, 2)
    for bad in ({"tx_indices": [0, 1]}, {"tx_indices": [1, 3]}, {"tx_indices": [1, 2], "tag_addresses": ["C0:00:00:00:00:01"]}):
        with pytest.raises(ValidationError):
            EpisodeTruth.model_validate({**base, **bad})


def test_a_result_may_carry_one_trace_per_tag():
    base = {"episode_id": "e", "rig": "r", "estimates_rad": [0.1, 0.2], "pans_rad": [0.0, 0.3], "rewards": [0.0, 0.0]}
    single = EpisodeResult.model_validate(base)
    assert b'"tags"' not in dump(single) and list(_frozen("EpisodeResult").iter_errors(json.loads(dump(single)))) == []
    tags = [{"tag": 0, "estimates_rad": [0.1, 0.2], "confidences": [0.4, 0.9], "decided_step": 1},
            {"tag": 1, "estimates_rad": [1.1, 1.2]}]
    many = EpisodeResult.model_validate({**base, "tags": tags})
    assert [t.tag for t in many.tags] == [0, 1] and many.tags[0].decided_step == 1 and many.tags[1].confidences == ()
    assert EpisodeResult.model_validate_json(dump(many)) == many
    assert list(_current("EpisodeResult").iter_errors(json.loads(dump(many)))) == []
    for bad in ([tags[0], {**tags[1], "tag": 0}], [{**tags[1], "estimates_rad": [1.1]}]):
        with pytest.raises(ValidationError):
            EpisodeResult.model_validate({**base, "tags": bad})
    for bad in ({"tag": 0, "estimates_rad": [0.1], "confidences": [0.2, 0.3]}, {"tag": 0, "estimates_rad": [0.1], "decided_step": 1}):
        with pytest.raises(ValidationError):
            TagResult.model_validate(bad)


def test_a_campaign_with_several_tags_needs_rigs_that_speak_1_4():
    assert campaign_features(scenario=build_scenario("dynamic")) == []
    features = campaign_features(scenario=build_scenario("ward"))
    assert features == [("scenario parameter 'n_tags'", V1_4)]
    missing = missing_features(V1_3, features)
    assert missing == features and not missing_features(V1_4, features)
    assert describe_missing("old-1", V1_3, *missing[0]) == (
        "rig old-1 speaks protocol 1.3; scenario parameter 'n_tags' needs protocol 1.4 (a node that does not know the field "
        "rejects every EpisodeStart that carries it)")
    start = EpisodeStart(episode_id="c.0.ra2vipas.1", campaign_id="c", test_index=0, algorithm="ra2vipas", seed=1,
                         scenario=build_scenario("ward"))
    assert list(_frozen("EpisodeStart").iter_errors(json.loads(dump(start)))) != []  # which is why a 1.3 rig is refused it
