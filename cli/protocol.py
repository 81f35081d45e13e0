"""``ra2vipas protocol schemas OUTDIR``: the wire messages' JSON Schemas for third-party nodes;
``ra2vipas protocol check --rig NAME | --controller NAME``: the conformance kits."""

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
    rig: Annotated[Optional[str], typer.Option("--rig", help="The rig whose sensors node to check.")] = None,
    controller: Annotated[Optional[str], typer.Option("--controller", metavar="RIG", help="The rig whose controller to check (the kit then plays that rig's sensors, the orchestrator and the learner: run it while the rig's sensors node is down).")] = None,
    policy: Annotated[Optional[str], typer.Option("--policy", help="With --controller: the policy its episodes name [default: ra2vipas if it serves it, else the first it announces].")] = None,
    timeout: Annotated[float, typer.Option(min=0.5, max=600.0, help="How long to wait for any one answer [s].")] = 5.0,
    wait: Annotated[Optional[float], typer.Option(min=0.5, max=3600.0, help="How long to wait for the node to come up (its liveliness token) [s; default: --timeout]. Start the kit, then the node: the kit probes it the moment its token appears, which checks that the token is declared last.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as one JSON line.")] = False,
    tags_seconds: Annotated[float, typer.Option("--tags-seconds", min=4.0, max=600.0, metavar="S", help="With --rig: how long the tags rule's episode may run while a tag the node says it hears is still unheard [s]; it runs 4 s when every tag is heard by then. A beacon that advertises every few seconds needs a few intervals.")] = 20.0,
    grid_tolerance: Annotated[Optional[float], typer.Option("--grid-tolerance", min=1.0, max=1000.0, metavar="MS", help="With --rig: how far a realtime sample may arrive from t0 + k T_RF [ms; default: the larger of 30 ms and T_RF/4]. The kit's own receipt counts too: widen it on a loaded machine.")] = None,
    mode: ModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None, zenoh_config: ConfigOpt = None,
) -> None:
    """Drive a live node through scripted episodes and print a pass/fail report per protocol
    rule; exit 0 if no rule failed, 1 otherwise. With --rig, a sensors node (fast and realtime,
    a command before its start, duplicates, an EpisodeStop mid-episode, malformed messages, an
    episode searching for every tag a node says it hears, a training episode); with
    --controller, a controller (its policies, Command(0), lockstep, duplicate and out-of-order
    measurements, its EpisodeResult, an EpisodeStop mid-episode, an unserved policy, malformed
    messages, two episodes at once). Run it on a rig no campaign is
    using. To check that the node declares its liveliness token last, start the kit first
    (with --wait) and then the node."""
    import logging

    from ra2vipas.cli.output import stderr
    from ra2vipas.cli.services import zenoh_settings
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    if (rig is None) == (controller is None):
        fail("give either --rig NAME (check its sensors node) or --controller NAME (check its controller)", 2)
    if policy is not None and controller is None:
        fail("--policy goes with --controller", 2)
    if grid_tolerance is not None and rig is None:
        fail("--grid-tolerance goes with --rig", 2)
    if policy is not None:
        import re

        from ra2vipas.services.protocol.messages import POLICY_NAME_PATTERN

        if not re.match(POLICY_NAME_PATTERN, policy):
            fail(f"--policy {policy!r} is not a policy name ({POLICY_NAME_PATTERN})", 2)
    name = rig if rig is not None else controller
    try:
        check_chunk(name, "rig")
    except ValueError as err:
        fail(str(err), 2)
    logging.getLogger("ra2vipas").setLevel(logging.ERROR)
    settings = zenoh_settings(mode, connect, listen, zenoh_config)
    try:
        bus = ZenohBus(settings)
    except Exception as err:  # zenoh raises ZError for bad endpoints, unreachable routers, ...
        fail(f"cannot open the Zenoh session: {err}")
    try:
        if rig is not None:
            from ra2vipas.services.rigs.conformance import ConformanceKit, report

            kit = ConformanceKit(bus, rig, timeout, grid_tolerance_s=None if grid_tolerance is None else grid_tolerance / 1e3,
                                 tags_seconds=tags_seconds)
            what, role = f"rig {rig}", "sensors"
        else:
            from ra2vipas.services.rigs.controller_conformance import ControllerKit, report

            up = _tokens(bus)
            if ("sensors", controller) in up:
                fail(f"the sensors node of rig {controller} is up: the kit plays that rig's sensors, so stop it first (or check "
                     f"the controller under a rig name no node uses)", 2)
            if any(role == "learner" for role, _ in up):
                fail("a learner is up on this mesh: the kit plays the learner (a query for the POD model reaches one of the two), "
                     "so check the controller on a router without one", 2)
            kit = ControllerKit(bus, controller, timeout, policy)
            what, role = f"the controller of rig {controller}", "controller"
        stderr.print(f"watching for {what} (its token alive/{role}/{name}, up to {timeout if wait is None else wait:g} s) ...")
        try:
            results = kit.run(wait=wait)
        finally:
            kit.close()
    finally:
        bus.close()
    _print(report(results), f"Conformance of {what} (docs/protocol.md)", as_json)


def _tokens(bus, wait: float = 1.0) -> set[tuple[str, str]]:
    """The (role, name) of every liveliness token up on the mesh (current tokens arrive within
    ``wait`` s)."""
    import threading
    import time

    from ra2vipas.services.protocol import keys

    seen: set[tuple[str, str]] = set()
    lock = threading.Lock()

    def note(key: str, alive: bool) -> None:
        parsed = keys.parse_alive(key)
        if alive and parsed is not None:
            with lock:
                seen.add(parsed)

    handle = bus.watch_alive(keys.alive_all(), note)
    try:
        time.sleep(wait)
    finally:
        handle.undeclare()
    with lock:
        return set(seen)


def _print(body: dict, title: str, as_json: bool) -> None:
    """The report as one JSON line, or as a table and a last line naming the failed rules;
    exit 1 if a rule failed."""
    from ra2vipas.cli.output import stdout

    if as_json:
        print(json.dumps(body, separators=(",", ":")))
    else:
        from rich.table import Table

        table = Table(title=title)
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
