"""The compatibility policy of docs/protocol.md ("Compatibility"), enforced.

* The 1.0 schemas are frozen in ``docs/schemas/v1`` (their bytes are pinned here).
* Every message 1.0 defined still exists, with every 1.0 field; a field added since is marked
  with the version that added it (``since``) and is optional, so a 1.0 sender's message still
  validates, and a sender leaves it out at its default: a message that uses no newer feature
  is byte for byte what a 1.0 sender sent (``tests/protocol/data/v1_messages.jsonl``: messages
  encoded by the 1.0 code, commit 9fe8d16).
* For a 1.0 receiver, ``dump(message, version="1.0")`` leaves out every newer field.

The campaigns that prove it on the bus are in ``tests/nodes/test_v1_node.py``.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

from ra2vipas.services.protocol import messages
from ra2vipas.services.protocol.messages import EpisodeStart, ErrorReply, PODRequest, PODResponse, dump
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.schemas import schema_documents
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION, V1_0, VERSIONS, newer

ROOT = Path(__file__).resolve().parents[2]
V1 = ROOT / "docs" / "schemas" / "v1"
GOLDEN = [json.loads(line) for line in (Path(__file__).parent / "data" / "v1_messages.jsonl").read_text().splitlines()]

FROZEN = {
    "CameraFrame.json": "abb8f9aaeae9caf1",
    "Command.json": "38b6f363bbf12d38",
    "EpisodeControl.json": "2593fe8a9f9358a6",
    "EpisodeResult.json": "3a2b397af17ac352",
    "EpisodeStart.json": "4190cf3dcbc02fa1",
    "EpisodeStop.json": "e494d89580782215",
    "EpisodeTiming.json": "431abcc0332dbf56",
    "EpisodeTruth.json": "fc1aa52fbc687e1a",
    "ErrorReply.json": "db44ae0339af3c83",
    "Measurement.json": "09730ea758939353",
    "PODModel.json": "cac35077456edfdc",
    "PODRequest.json": "2b00bc90fec3f226",
    "PODResponse.json": "9c4dbbf71aaa0262",
    "RFSample.json": "acf89ae813ef433c",
    "Scenario.json": "3c4d1a061dd23a07",
    "TargetTrajectory.json": "2cfaa2350f2c8036",
    "TrainingRequest.json": "4af5813bea4b3c7b",
    "TrainingSample.json": "2a7047ed4d5c83d1",
    "TrainingStream.json": "f30ee25c6de1bc75",
    "TrainingTruth.json": "055a642c07340eb4",
}


def _v1(name: str) -> Draft202012Validator:
    return Draft202012Validator(json.loads((V1 / f"{name}.json").read_text()))


def test_the_1_0_schemas_are_frozen():
    on_disk = {p.name: hashlib.sha256(p.read_bytes()).hexdigest()[:16] for p in V1.glob("*.json")}
    assert on_disk == FROZEN, "docs/schemas/v1 is frozen: never regenerate or edit it"


@pytest.mark.parametrize("golden", GOLDEN, ids=[g["name"] for g in GOLDEN])
def test_a_message_that_uses_no_newer_feature_is_byte_for_byte_1_0(golden):
    cls = getattr(messages, golden["type"])
    payload = golden["payload"].encode()
    assert list(_v1(golden["type"]).iter_errors(json.loads(payload))) == []
    assert dump(cls.model_validate_json(payload)) == payload


def test_every_field_added_since_1_0_is_optional_and_says_when_it_came():
    current = schema_documents()
    for path in sorted(V1.glob("*.json")):
        old, new = json.loads(path.read_text()), current[path.name]
        for where, o, n in _objects(old, new):
            assert set(o.get("properties", {})) <= set(n.get("properties", {})), f"{path.name} {where}: a 1.0 field is gone"
            assert set(n.get("required", [])) <= set(o.get("required", [])), f"{path.name} {where}: a field became required"
            for name in set(n.get("properties", {})) - set(o.get("properties", {})):
                prop = n["properties"][name]
                assert prop.get("since") in VERSIONS and newer(prop["since"], V1_0), f"{path.name} {where}.{name}: no 'since'"
                assert "default" in prop, f"{path.name} {where}.{name}: a newer field must have a default"


def _objects(old: dict, new: dict, where: str = ""):
    """The object schemas of a 1.0 document and the current one, paired: the top level and
    each $defs entry both have."""
    yield where or ".", old, new
    for name, o in (old.get("$defs") or {}).items():
        n = (new.get("$defs") or {}).get(name)
        assert n is not None, f"{name}: a 1.0 message is gone"
        yield name, o, n


def test_a_newer_feature_goes_on_the_wire_only_when_used():
    start = EpisodeStart.model_validate_json(next(g["payload"] for g in GOLDEN if g["name"] == "EpisodeStart"))
    assert b"stop_confidence" not in dump(start)
    early = start.model_copy(update={"stop_confidence": 0.9})
    assert b'"stop_confidence":0.9' in dump(early)
    assert list(_v1("EpisodeStart").iter_errors(json.loads(dump(early)))) != []  # which is why a 1.0 rig is refused it


def test_a_1_0_receiver_gets_nothing_newer():
    model = PODModel(rssi_grid_dbm=(-90.0, -30.0), mean=(0.1, 0.9), std=(0.05, 0.03), rf_noise_db=2.5, rf_noise_correlation=0.6,
                     n_train=200, frames_per_rf=5)
    response = PODResponse(job_id="pod-0123456789abcdef", train_seconds=1.5, model=model)
    assert b"rf_noise_correlation" in dump(response)
    assert list(_v1("PODResponse").iter_errors(json.loads(dump(response, version=V1_0)))) == []
    assert dump(response, version=PROTOCOL_VERSION) == dump(response)
    request = PODRequest(scenario=build_scenario("paper"), seed=1, protocol=PROTOCOL_VERSION)
    assert PODRequest.model_validate_json(dump(request)).protocol == PROTOCOL_VERSION
    assert PODRequest.model_validate_json(dump(request, version=V1_0)).protocol == V1_0
    rejection = ErrorReply(error="x", episode_id="c.0.rapas.1.00")
    assert json.loads(dump(rejection)) == {"error": "x", "episode_id": "c.0.rapas.1.00"}


def test_the_protocol_page_states_the_policy():
    text = (ROOT / "docs" / "protocol.md").read_text()
    assert "## Compatibility" in text
    for phrase in ("docs/schemas/v1", "result/{rig}/rejected", "since", f"protocol {PROTOCOL_VERSION}", "protocol 1.0"):
        assert phrase in text, phrase
