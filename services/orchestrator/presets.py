"""Presets as data: a preset's description and every scenario parameter with its value,
allowed range and meaning. Shared by ``GET /presets/{name}`` and ``ra2vipas presets show``."""

from __future__ import annotations

from typing import Any

from ra2vipas.services.protocol.scenario import PRESET_DESCRIPTIONS, PRESETS, Scenario, build_scenario, field_range


def preset_summaries() -> list[dict[str, str]]:
    return [{"name": name, "description": PRESET_DESCRIPTIONS[name]} for name in PRESETS]


def preset_object(name: str) -> dict[str, Any]:
    """The preset ``name`` with every parameter's value, range and meaning.

    Raises
    ------
    ScenarioError
        Unknown preset.
    """
    values = build_scenario(name).model_dump(mode="json")
    return {
        "name": name,
        "description": PRESET_DESCRIPTIONS[name],
        "parameters": {
            field: {"value": values[field], "allowed": field_range(field), "description": info.description}
            for field, info in Scenario.model_fields.items()
        },
    }
