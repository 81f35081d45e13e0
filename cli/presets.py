"""``ra2vipas presets list|show``: the named scenarios and every parameter with its range."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.table import Table

from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stdout
from ra2vipas.services.orchestrator.presets import preset_object, preset_summaries
from ra2vipas.services.protocol.scenario import PRESETS, ScenarioError

app = typer.Typer(help="Scenario presets and their parameters (the same as GET /presets; no server needed).", no_args_is_help=True)


@app.command("list")
def list_presets(as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False) -> None:
    """List the presets."""
    if as_json:
        print_json(preset_summaries())
        return
    table = Table(title="Scenario presets")
    table.add_column("name")
    table.add_column("description")
    for p in preset_summaries():
        table.add_row(p["name"], p["description"])
    stdout.print(table)


@app.command("show")
def show_preset(
    name: Annotated[str, typer.Argument(help="Preset name, e.g. paper.", autocompletion=lambda incomplete: [p for p in PRESETS if p.startswith(incomplete)])],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Every parameter of a preset with its value and allowed range (override with --set NAME=VALUE)."""
    try:
        obj = preset_object(name)
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    if as_json:
        print_json(obj)
        return
    table = Table(title=f"{name}: {obj['description']}")
    for col in ("parameter", "value", "allowed", "meaning"):
        table.add_column(col)
    for field, p in obj["parameters"].items():
        table.add_row(field, str(p["value"]), p["allowed"], p["description"] or "")
    stdout.print(table)
    if obj["parameters"].get("antenna_model", {}).get("value") == "paper":
        stdout.print("note: Rx(dir) dips where it is aligned under antenna_model=paper (eq. 6 scales the dBm path loss by ϱ): "
                     "point where Rx(dir) is weakest, or --set antenna_model=db-gain for a reading that peaks when aligned",
                     markup=False, highlight=False)
