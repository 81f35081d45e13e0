"""``ra2vipas presets list|show``: the named scenarios and every parameter with its range."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.table import Table

from cli.output import EXIT_FAILED, fail, print_json, stdout
from services.protocol.scenario import PRESET_DESCRIPTIONS, PRESETS, Scenario, ScenarioError, build_scenario, field_range

app = typer.Typer(help="Scenario presets and their parameters.", no_args_is_help=True)


def preset_object(name: str) -> dict:
    """A preset as data: its description and every parameter with value, range and meaning."""
    scenario = build_scenario(name)
    values = scenario.model_dump(mode="json")
    return {
        "name": name,
        "description": PRESET_DESCRIPTIONS[name],
        "parameters": {
            field: {"value": values[field], "allowed": field_range(field), "description": info.description}
            for field, info in Scenario.model_fields.items()
        },
    }


@app.command("list")
def list_presets(as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False) -> None:
    """List the presets."""
    if as_json:
        print_json([{"name": n, "description": PRESET_DESCRIPTIONS[n]} for n in PRESETS])
        return
    table = Table(title="Scenario presets")
    table.add_column("name")
    table.add_column("description")
    for name in PRESETS:
        table.add_row(name, PRESET_DESCRIPTIONS[name])
    stdout.print(table)


@app.command("show")
def show_preset(
    name: Annotated[str, typer.Argument(help="Preset name, e.g. paper.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Every parameter of a preset with its value and allowed range (override with --set NAME=VALUE)."""
    try:
        obj = preset_object(name)
    except ScenarioError as err:
        fail(str(err), EXIT_FAILED)
    if as_json:
        print_json(obj)
        return
    table = Table(title=f"{name}: {obj['description']}")
    for col in ("parameter", "value", "allowed", "meaning"):
        table.add_column(col)
    for field, p in obj["parameters"].items():
        table.add_row(field, str(p["value"]), p["allowed"], p["description"] or "")
    stdout.print(table)
