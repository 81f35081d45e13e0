"""``ra2vipas protocol schemas OUTDIR``: the wire messages' JSON Schemas for third-party nodes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import fail
from ra2vipas.cli.services import ConfigOpt, ConnectOpt, ListenOpt, ModeOpt
from ra2vipas.services.protocol.schemas import schema_documents

app = typer.Typer(help="The wire protocol (key expressions and message schemas).", no_args_is_help=True)


@app.command("schemas")
def schemas(outdir: Annotated[Path, typer.Argument(help="Directory to write one <Message>.json per message into.")]) -> None:
    """Write the JSON Schema of every wire message into OUTDIR."""
    try:
        outdir.mkdir(parents=True, exist_ok=True)
        for name, doc in sorted(schema_documents().items()):
            (outdir / name).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    except OSError as err:
        fail(f"cannot write schemas to {outdir}: {err.strerror or err}")
    print(f"wrote {len(schema_documents())} schemas to {outdir}")


@app.command("check")
def check(
    rig: Annotated[str, typer.Option("--rig", help="The rig (sensors node) to check.")],
    timeout: Annotated[float, typer.Option(min=0.5, max=600.0, help="How long to wait for any one answer [s].")] = 5.0,
    wait: Annotated[Optional[float], typer.Option(min=0.5, max=3600.0, help="How long to wait for the rig to come up (its liveliness token) [s; default: --timeout]. Start the kit, then the node: the kit probes it the moment its token appears, which checks that the token is declared last.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as one JSON line.")] = False,
    mode: ModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None, zenoh_config: ConfigOpt = None,
) -> None:
    """Drive a live sensors node through scripted episodes (fast and realtime, a command before
    its start, duplicates, an EpisodeStop mid-episode, malformed messages, a training episode)
    and print a pass/fail report per protocol rule. Exit 0 if no rule failed, 1 otherwise. Run it
    on a rig no campaign is using (it moves the rig). To check that the node declares its
    liveliness token last, start the kit first (with --wait) and then the node."""
    import logging

    from ra2vipas.cli.output import stderr, stdout
    from ra2vipas.cli.services import zenoh_settings
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.rigs.conformance import ConformanceKit, report
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    try:
        check_chunk(rig, "rig")
    except ValueError as err:
        fail(str(err), 2)
    logging.getLogger("ra2vipas").setLevel(logging.ERROR)
    settings = zenoh_settings(mode, connect, listen, zenoh_config)
    try:
        bus = ZenohBus(settings)
    except Exception as err:  # zenoh raises ZError for bad endpoints, unreachable routers, ...
        fail(f"cannot open the Zenoh session: {err}")
    try:
        kit = ConformanceKit(bus, rig, timeout)
        stderr.print(f"watching for rig {rig} (its token alive/sensors/{rig}, up to {timeout if wait is None else wait:g} s) ...")
        try:
            results = kit.run(wait=wait)
        finally:
            kit.close()
    finally:
        bus.close()
    body = report(results)
    if as_json:
        print(json.dumps(body, separators=(",", ":")))
    else:
        from rich.table import Table

        table = Table(title=f"Conformance of rig {rig} (docs/protocol.md)")
        for col in ("rule", "result", "what it checks", "detail"):
            table.add_column(col)
        for r in body["rules"]:
            colour = {"pass": "green", "fail": "bold red", "skip": "yellow"}[r["status"]]
            table.add_row(r["rule"], f"[{colour}]{r['status']}[/]", r["what"], r["detail"])
        stdout.print(table)
        failed = [r["rule"] for r in body["rules"] if r["status"] == "fail"]
        stdout.print("all rules pass" if not failed else f"{len(failed)} rule(s) failed: {', '.join(failed)}")
    if not body["passed"]:
        raise typer.Exit(1)
