"""``ra2vipas rigs``: the rigs and learners the orchestrator sees through Zenoh liveliness."""

from __future__ import annotations

from ra2vipas.cli.client import DEFAULT_API, ApiOpt, Client, JsonOpt, TokenOpt
from ra2vipas.cli.output import print_json, rigs_table, stdout


def rigs(as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """List the rigs (live while both sensors and controller are up) and the learners."""
    body = Client(api, token).request("GET", "/rigs")
    if as_json:
        print_json(body)
    else:
        stdout.print(rigs_table(body))
