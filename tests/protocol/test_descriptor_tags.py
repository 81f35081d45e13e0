"""Protocol 1.5: a node says how many tags its receivers tell apart (``RigDescriptor.tags``), and a
campaign that searches for more on that rig is refused when it is created (or, with the rig's
values, searches for as many as the rig hears) instead of rerunning episodes whose tags are never
heard."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator
from pydantic import ValidationError

from ra2vipas.services.orchestrator.rigcheck import TargetingError, resolve_targeting
from ra2vipas.services.protocol.rig import Conflict, RigDescriptor, apply_rig_values, conflicts, fewer_tags
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.schemas import schema_documents
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION, V1_4, V1_5, campaign_features, since
from ra2vipas.services.sensors.node import simulated_descriptor

ROOT = Path(__file__).resolve().parents[2]
V1_4_DIR = ROOT / "docs" / "schemas" / "v1.4"


def _hardware(rig: str = "cam-1", **extra) -> RigDescriptor:
    return RigDescriptor.model_validate({"rig": rig, "kind": "hardware", "frames_per_rf": 5, "rf_period_s": 0.1, "fov_half_angle_deg": 22.5,
                                         "box_bearing_noise_deg": 0.25, "rx_dir": {"model": "paper"}, "radio": "adverts",
                                         "protocol": "1.5", **extra})


def test_1_5_is_the_version_this_code_speaks_and_1_4_is_frozen_beside_it():
    assert PROTOCOL_VERSION == V1_5 and since(RigDescriptor, "tags") == V1_5
    current = schema_documents()
    frozen = {p.name for p in V1_4_DIR.glob("*.json")}
    assert frozen == set(current)
    for name in frozen:  # 1.5 only adds: every 1.4 property is still there
        old, new = json.loads((V1_4_DIR / name).read_text()), current[name]
        assert set(old.get("properties", {})) <= set(new.get("properties", {})), name
    assert "tags" not in json.loads((V1_4_DIR / "RigDescriptor.json").read_text())["properties"]
    assert current["RigDescriptor.json"]["properties"]["tags"]["since"] == V1_5
    text = (ROOT / "docs" / "protocol.md").read_text()
    assert "schemas/v1.4/" in text and "**1.5**" in text and "hears at most 2" in text


def test_a_descriptor_says_its_tags_and_a_1_4_descriptor_without_them_still_reads():
    d = _hardware(tags=2)
    assert d.tags == 2
    wire = json.loads(d.model_dump_json())
    assert list(Draft202012Validator(schema_documents()["RigDescriptor.json"]).iter_errors(wire)) == []
    old = {k: v for k, v in wire.items() if k != "tags"} | {"protocol": V1_4}
    assert list(Draft202012Validator(json.loads((V1_4_DIR / "RigDescriptor.json").read_text())).iter_errors(old)) == []
    assert RigDescriptor.model_validate(old).tags is None  # not said: whatever the campaign searches for
    for bad in (0, 65, 1.5):
        with pytest.raises(ValidationError):
            _hardware(tags=bad)


def test_a_campaign_that_searches_for_more_tags_than_the_rig_hears_contradicts_it():
    d = _hardware(tags=2)
    ward = build_scenario("ward")  # 3 tags
    assert ward.n_tags == 3
    matched = apply_rig_values(_hardware(), ward)  # the rig's hardware: only the tags differ
    assert matched.n_tags == 3 and conflicts(d, matched) == [Conflict("n_tags", 3, 2, "hears at most")]
    found = [c for c in conflicts(d, ward) if c.field == "n_tags"]
    assert found and found[0].describe("cam-1") == "rig cam-1: n_tags: the campaign says 3, the rig hears at most 2"
    for fewer in (1, 2):  # fewer tags than the rig hears: tags 0 .. n_tags - 1 of what it hears
        assert not [c for c in conflicts(d, build_scenario("ward", {"n_tags": fewer})) if c.field == "n_tags"]
    assert not [c for c in conflicts(_hardware(), ward) if c.field == "n_tags"]  # not said: not checked
    # the rig's values lower n_tags to what it hears, never raise it
    assert apply_rig_values(d, ward).n_tags == 2
    assert apply_rig_values(d, build_scenario("ward", {"n_tags": 1})).n_tags == 1
    assert fewer_tags(ward, None) == {} and fewer_tags(ward, 3) == {} and fewer_tags(ward, 1) == {"n_tags": 1}
    # and campaigns need no newer version for it: nothing a node receives changed
    assert all(version != V1_5 for _, version in campaign_features(None, ["ra2vipas"], ward))


def test_the_orchestrators_check_refuses_it_naming_the_rig_or_takes_the_tags_the_rigs_hear():
    ward = build_scenario("ward")
    descriptors = {"two-1": simulated_descriptor("two-1", tags=2), "one-1": simulated_descriptor("one-1", tags=1),
                   "any-1": simulated_descriptor("any-1")}
    with pytest.raises(TargetingError) as err:
        resolve_targeting(ward, "fast", ["two-1"], None, False, descriptors)
    assert err.value.errors == [("scenario.n_tags", "rig two-1 hears at most 2, the campaign says 3 (use_rig_values takes the rig's)")]
    scenario, targeting = resolve_targeting(ward, "fast", ["two-1"], None, True, descriptors)
    assert scenario.n_tags == 2 and targeting["rig_values"] == {"n_tags": 2}
    scenario, _ = resolve_targeting(ward, "fast", ["two-1", "one-1"], None, True, descriptors)
    assert scenario.n_tags == 1  # the fewest any targeted rig hears
    scenario, targeting = resolve_targeting(ward, "fast", None, None, False, descriptors)
    assert scenario.n_tags == 3 and targeting is None  # untargeted: runs on any-1, which takes any n_tags
    with pytest.raises(TargetingError) as err:
        resolve_targeting(ward, "fast", None, None, False, {k: v for k, v in descriptors.items() if k != "any-1"})
    assert [f for f, _ in err.value.errors] == ["scenario.n_tags", "scenario.n_tags"]  # no live rig hears 3 tags


def test_a_simulated_rig_can_pin_the_tags_it_hears():
    """`ra2vipas sensors --hardware n_tags=2`: a simulated rig that hears two tags, to rehearse a real
    two-tag node (its descriptor says tags 2; it simulates no more than 2 whatever a campaign asks)."""
    from ra2vipas.services.sensors.node import SensorsNode, pinned_descriptor
    from ra2vipas.services.transport.bus import MemoryBus

    d = pinned_descriptor("two-1", {"n_tags": 2})
    assert d.tags == 2 and d.kind == "simulated"
    with pytest.raises(ValueError, match="^n_tags: Input should be greater than or equal to 1$"):
        pinned_descriptor("two-1", {"n_tags": 0})
    bus = MemoryBus()
    node = SensorsNode(bus, "two-1", descriptor=d)
    try:
        assert node.hardware(build_scenario("ward")).n_tags == 2 and node.hardware(build_scenario("ward", {"n_tags": 1})).n_tags == 1
    finally:
        node.close()
        bus.close()
