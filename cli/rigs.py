"""``ra2vipas rigs list``: the rigs and learners the orchestrator sees through Zenoh liveliness.

(``ra2vipas rig`` runs a rig; ``ra2vipas rigs list`` lists them. The old spelling of the list,
``ra2vipas rigs`` alone, still works, with a deprecation warning.)
"""

from __future__ import annotations

from typing import Annotated, Optional

import typer

from ra2vipas.cli.client import DEFAULT_API, ApiOpt, Client, JsonOpt, TokenOpt
from ra2vipas.cli.output import print_json, rigs_table, stdout

app = typer.Typer(help="The rigs and learners the orchestrator sees (`ra2vipas rig` runs one).", invoke_without_command=True)


@app.command("list")
def list_rigs(as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """List the rigs (live while both sensors and controller are up) and the learners.

    Example:

        ra2vipas rigs list --api http://127.0.0.1:8080
    """
    body = Client(api, token).request("GET", "/rigs")
    if as_json:
        print_json(body)
    else:
        stdout.print(rigs_table(body))


@app.callback()
def _bare(ctx: typer.Context,
          as_json: Annotated[bool, typer.Option("--json", hidden=True)] = False,
          api: Annotated[str, typer.Option("--api", envvar="RA2VIPAS_API", hidden=True)] = DEFAULT_API,
          token: Annotated[Optional[str], typer.Option("--token", envvar="RA2VIPAS_TOKEN", hidden=True)] = None) -> None:
    """The rigs and learners the orchestrator sees (`ra2vipas rig` runs one)."""
    if ctx.invoked_subcommand is None:  # `ra2vipas rigs [--json]`: the deprecated spelling of `rigs list`
        import sys

        print("warning: `ra2vipas rigs` is deprecated; use `ra2vipas rigs list`", file=sys.stderr)
        list_rigs(as_json, api, token)
