"""Presets as data: a preset's description and every scenario parameter with its value,
allowed range and meaning. Shared by ``GET /presets/{name}`` and ``ra2vipas presets show``."""

from __future__ import annotations

from typing import Any

from ra2vipas.services.protocol.scenario import PRESET_DESCRIPTIONS, PRESETS, Scenario, build_scenario, field_range

# What a researcher needs before writing a policy on Rx(dir): under the paper's model (eq. 6) a
# negative dBm value is scaled by rho <= 1, so the reading dips where the antenna is aligned.
ANTENNA_NOTE = ("paper (eq. 6): z_dir = g(d)·ϱ scales a negative dBm path loss by ϱ ≤ 1 (1 when aligned), so Rx(dir) is "
                "LOWEST when it points at the Tx (at 2 m: -36.0 dBm aligned, -24.9 at 45°, 0 at 90°): a policy that points "
                "where Rx(dir) is strongest looks away from the Tx. db-gain: z_dir = g(d) + 10 log10 ϱ, strongest when aligned "
                "(-36.0, -37.6, -56.0 dBm)")
NOTES = {"antenna_model": ANTENNA_NOTE}


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
            field: {"value": values[field], "allowed": field_range(field),
                    "description": f"{info.description}. {NOTES[field]}" if field in NOTES else info.description}
            for field, info in Scenario.model_fields.items()
        },
    }
