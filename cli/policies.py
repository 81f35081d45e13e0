"""``ra2vipas policies``: the pointing policies installed here (the same as GET /policies)."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.table import Table

from ra2vipas.cli.output import print_json, stdout


def policies(as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False) -> None:
    """List the pointing policies a campaign can name: the built-ins and every installed
    package's (entry points "ra2vipas.policies"; docs/policies.md says how to write one)."""
    from ra2vipas.services.controller import registry

    rows = registry.describe()
    if as_json:
        print_json(rows)
        return
    table = Table(title="Pointing policies")
    for col in ("name", "package", "version", "summary"):
        table.add_column(col)
    for row in rows:
        table.add_row(row["name"], row["package"], row["version"], row["summary"])
    stdout.print(table)
