"""The new-campaign form has an input it can fill for every scenario parameter (a bool or a text
parameter once rendered as an empty required number field, and the form refused every campaign)."""

from __future__ import annotations

from ra2vipas.services.orchestrator.dashboard.data import parameter_inputs
from ra2vipas.services.protocol.scenario import PRESETS, Scenario


def test_every_parameter_has_an_input_the_page_renders_with_its_preset_value():
    for preset in PRESETS:
        inputs = {p["name"]: p for p in parameter_inputs(preset)}
        assert set(inputs) == set(Scenario.model_fields)
        for name, p in inputs.items():
            assert p["kind"] in ("enum", "bool", "text", "int", "float"), name
            if p["kind"] in ("enum", "bool"):
                assert p["value"] in p["options"], (preset, name)
            if p["kind"] in ("int", "float"):
                assert isinstance(p["value"], (int, float)) and not isinstance(p["value"], bool), (preset, name)
    ward = {p["name"]: p for p in parameter_inputs("ward")}
    assert ward["one_tag_per_person"]["kind"] == "bool" and ward["one_tag_per_person"]["value"] == "true"
    assert ward["radio_channel"]["kind"] == "text" and ward["radio_channel"]["value"]
