"""The wire contract: key expressions by plane, and the checked-in JSON Schemas."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import zenoh
from pydantic import ValidationError

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    WIRE_MESSAGES,
    Command,
    EpisodeResult,
    EpisodeStart,
    Measurement,
    PODRequest,
    TrainingRequest,
    episode_control_adapter,
    training_job_id,
)
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.schemas import schema_documents

ROOT = Path(__file__).resolve().parents[2]
RIG = "rig-7"

CONCRETE = {
    "data": [keys.command(RIG), keys.measurement(RIG), keys.training(RIG)],
    "control": [keys.episode_control(RIG)],
    "result": [keys.episode_result(RIG), keys.episode_timing(RIG), keys.episode_rejected(RIG)],
    "truth": [keys.episode_truth(RIG), keys.training_truth(RIG)],
    "model": [keys.pod_model()],
    "rig": [keys.rig_info(RIG), keys.rig_policies(RIG)],
    "alive": [keys.alive(role, "x") for role in keys.ROLES],
}
WILDCARDS = {
    "data": [keys.training_any()],
    "control": [keys.episode_control_all()],
    "result": [keys.episode_result_all(), keys.episode_timing_all(), keys.episode_rejected_all()],
    "truth": [keys.episode_truth_all(), keys.training_truth_any()],
    "rig": [keys.rig_info_any(), keys.rig_policies_any()],
    "alive": [keys.alive_all()],
}


def test_every_key_lives_under_its_own_plane():
    for plane, ks in CONCRETE.items():
        for k in ks:
            assert k.startswith(f"{keys.PREFIX}/{plane}/"), k
            zenoh.KeyExpr(k)  # a valid key expression


@pytest.mark.parametrize("plane", sorted(WILDCARDS))
def test_no_wildcard_crosses_a_plane(plane):
    for pattern in WILDCARDS[plane]:
        expr = zenoh.KeyExpr(pattern)
        for other, ks in CONCRETE.items():
            for k in ks:
                assert expr.intersects(zenoh.KeyExpr(k)) == (other == plane and _same_family(pattern, k)), (pattern, k)


def _same_family(pattern: str, key: str) -> bool:
    p, k = pattern.split("/"), key.split("/")
    return p[-1] == "**" or (len(p) == len(k) and p[-1] == k[-1])


def test_every_key_covers_every_plane_and_nothing_else():
    everything = zenoh.KeyExpr(keys.every_key())
    assert all(everything.includes(zenoh.KeyExpr(k)) for ks in (*CONCRETE.values(), *WILDCARDS.values()) for k in ks)
    assert not everything.intersects(zenoh.KeyExpr("ra2vipas/v2/data/rig-1/command"))


def test_what_controllers_and_learners_subscribe_to_never_touches_the_truth_plane():
    controller = [keys.episode_control(RIG), keys.measurement(RIG), keys.pod_model(), keys.rig_info(RIG)]
    learner = [keys.pod_model(), keys.training_any()]
    for pattern in controller + learner:
        for k in CONCRETE["truth"]:
            assert not zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(k))


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "rig$", "x" * 65, "rig 1"])
def test_rig_names_must_be_one_plain_chunk(bad):
    with pytest.raises(ValueError):
        keys.command(bad)


def test_alive_keys_parse_back():
    assert keys.parse_alive(keys.alive("controller", "rig-3")) == ("controller", "rig-3")
    assert keys.parse_alive(keys.command("rig-3")) is None
    assert keys.rig_of(keys.measurement("rig-3")) == "rig-3"


def test_checked_in_schemas_are_the_generated_ones():
    generated = schema_documents()
    folder = ROOT / "docs" / "schemas"
    on_disk = {p.name: json.loads(p.read_text()) for p in folder.glob("*.json")}
    assert set(on_disk) == set(generated), "run `ra2vipas protocol schemas docs/schemas`"
    for name, doc in generated.items():
        assert on_disk[name] == json.loads(json.dumps(doc)), f"{name} is stale: run `ra2vipas protocol schemas docs/schemas`"


def test_protocol_doc_names_every_key_family_and_message():
    text = (ROOT / "docs" / "protocol.md").read_text()
    for ks in CONCRETE.values():
        for k in ks:
            generic = "/".join("{rig}" if part == RIG else ("{name}" if part == "x" else part) for part in k.split("/"))
            if "/alive/" in generic:
                generic = f"{keys.PREFIX}/alive/"
            assert generic in text, generic
    for model in WIRE_MESSAGES:
        assert model.__name__ in text, model.__name__


def _start() -> EpisodeStart:
    return EpisodeStart(episode_id="abc.0.ra2vipas.1", campaign_id="abc", test_index=0, algorithm="ra2vipas", seed=1,
                        scenario=build_scenario("paper"))


def test_messages_round_trip_through_json():
    start = _start()
    assert episode_control_adapter.validate_json(start.model_dump_json()) == start
    m = Measurement.model_validate({"episode_id": "e.1", "step": 3, "pan_rad": 0.5, "rf": {"iso_rssi_dbm": -40.0, "dir_rssi_dbm": -30.0},
                                    "frames": [{"box_bearings_rad": [-0.1, 0.2]}, {"box_bearings_rad": []}]})
    assert Measurement.model_validate_json(m.model_dump_json()) == m
    r = EpisodeResult(episode_id="e.1", rig="rig-1", estimates_rad=(0.1, 0.2), pans_rad=(0.0, 0.3), rewards=(0.5, 0.6))
    assert EpisodeResult.model_validate_json(r.model_dump_json()) == r


@pytest.mark.parametrize("payload", [
    '{"episode_id": "e", "step": 0, "pan_rad": NaN}',
    '{"episode_id": "e", "step": 0, "pan_rad": 0.1, "extra": 1}',
    '{"episode_id": "e/../x", "step": 0, "pan_rad": 0.1}',
    '{"episode_id": "e", "step": "zero", "pan_rad": 0.1}',
    '{"episode_id": "e", "step": 0, "pan_rad": 1e9}',
])
def test_bad_commands_are_rejected(payload):
    with pytest.raises(ValidationError):
        Command.model_validate_json(payload)


def test_training_job_id_is_deterministic_and_depends_on_scenario_and_seed():
    a, b = build_scenario("paper"), build_scenario("paper", {"n_train": 100})
    assert training_job_id(a, 1) == training_job_id(build_scenario("paper"), 1)
    assert len({training_job_id(a, 1), training_job_id(a, 2), training_job_id(b, 1)}) == 3
    PODRequest(scenario=a, seed=1)
    TrainingRequest(job_id=training_job_id(a, 1), scenario=a, seed=1)
    assert math.isfinite(a.rf_period_s)
