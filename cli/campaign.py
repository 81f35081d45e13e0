"""``ra2vipas campaign ...``: a thin HTTP client of the orchestrator's REST API.

start | list | show (status: one line) | watch | results | trace | cancel | delete | export | plot.
Read commands print rich tables, or JSON with ``--json``; errors are one stderr line with
exit code 1 (a failed operation) or 2 (bad usage or input).
"""

from __future__ import annotations

import sys
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from ra2vipas.cli.client import DEFAULT_API, ApiOpt, Client, JsonOpt, TokenOpt
from ra2vipas.cli.output import (
    EXIT_FAILED,
    EXIT_USAGE,
    campaign_tables,
    campaigns_table,
    check_output,
    emit_results,
    fail,
    outcomes_table,
    print_json,
    print_results,
    stderr,
    stdout,
    trace_table,
    write_file,
)
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.services.controller import registry
from ra2vipas.services.protocol.messages import MAX_TESTS
from ra2vipas.services.protocol.scenario import PRESETS, ScenarioError, parse_overrides

app = typer.Typer(help="Start, watch and read campaigns on a running stack (see `ra2vipas up`).", no_args_is_help=True)

STATUSES = ("queued", "training", "running", "done", "failed", "cancelled")
IdArg = Annotated[str, typer.Argument(help="Campaign id (see `ra2vipas campaign list`).")]


def _complete(choices):
    return lambda incomplete: [c for c in choices if c.startswith(incomplete)]


def _complete_policies(incomplete: str) -> list[str]:
    """Every installed policy (``registry.names()``, read when completing, not at import)."""
    return [n for n in registry.names() if n.startswith(incomplete)]


def _follow(client: Client, cid: str, as_json_lines: bool = False) -> dict:
    """Follow a campaign's progress (a bar on stderr; JSON lines on stdout if asked) until it
    finishes. Ctrl-C stops following, not the campaign: it says so, with the commands to
    follow or cancel it, and exits 130."""
    try:
        return _progress(client, cid, as_json_lines)
    except KeyboardInterrupt:
        api = client.api
        where = "" if api == DEFAULT_API else f" --api {api}"
        stderr.print(f"interrupted: campaign {cid} keeps running on {api}. Follow it with `ra2vipas campaign watch {cid}{where}`, "
                     f"cancel it with `ra2vipas campaign cancel {cid}{where}`.", soft_wrap=True, markup=False, highlight=False)
        raise typer.Exit(130) from None


def _progress(client: Client, cid: str, as_json_lines: bool) -> dict:
    with Progress(TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
                  TimeElapsedColumn(), console=stderr, transient=True) as bar:
        task = bar.add_task(f"campaign {cid}", total=None)

        def update(c: dict) -> None:
            p = c["progress"]
            bar.update(task, total=p["total"], completed=p["done"], description=f"campaign {cid} ({c['status']})")
            if as_json_lines:
                print_json(c)

        return client.follow(cid, update)


def _check_finished(c: dict) -> None:
    if c["status"] != "done":
        fail(f"campaign {c['id']} {c['status']}: {c.get('error') or 'no results'}")


@app.command("start")
def start(
    preset: Annotated[str, typer.Option(help=f"Scenario preset: {', '.join(PRESETS)}.", autocompletion=_complete(PRESETS))] = "paper",
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Monte Carlo tests per algorithm.")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed.")] = 1,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated pointing policies: ra2vipas, rapas, ravipas, sweep (default: all four) or any installed policy (`ra2vipas policies`).")] = None,
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help="Override a scenario parameter (repeatable).")] = None,
    mode: Annotated[str, typer.Option(help="fast (lockstep, as fast as possible) or realtime (one sample every T_RF).", autocompletion=_complete(("fast", "realtime")))] = "fast",
    name: Annotated[Optional[str], typer.Option(help="A label for the campaign.")] = None,
    stop_confidence: Annotated[float, typer.Option("--stop-confidence", min=0.0, max=0.999999, help="End each episode at the first step whose confidence reaches this, its answer final (0: off); the results then report accuracy and time to decision.")] = 0.0,
    target_rigs: Annotated[Optional[list[str]], typer.Option("--rig", metavar="NAME", help="Run only on this rig (repeatable; default: any live rig).")] = None,
    rig_kind: Annotated[Optional[str], typer.Option("--rig-kind", help="Run only on rigs of this kind: simulated, hardware or survey.")] = None,
    use_rig_values: Annotated[bool, typer.Option("--use-rig-values", help="Where the scenario contradicts a targeted rig's descriptor, take the rig's values (else the campaign is refused, naming each field).")] = False,
    record_to: Annotated[Optional[str], typer.Option("--record", metavar="FILE", help="Record every message of every episode to this MCAP file as the campaign runs (implies --wait); joins the Zenoh mesh from the RA2VIPAS_ZENOH_* environment (e.g. a stack's zenoh.env).")] = None,
    wait: Annotated[bool, typer.Option("--wait", help="Show progress until it finishes, then print the DR table.")] = False,
    plot: Annotated[Optional[str], typer.Option(metavar="FILE", help="With --wait: also write the DR curves to FILE (.png or .svg).")] = None,
    embedded: Annotated[bool, typer.Option("--embedded", help="Start a local stack (Zenoh router, services, SQLite file) just for this campaign and stop it afterwards; implies --wait.")] = False,
    db: Annotated[str, typer.Option("--db", envvar="RA2VIPAS_DB", help="With --embedded: the SQLite file the results go to.")] = "ra2vipas.db",
    rigs: Annotated[int, typer.Option("--rig-count", min=0, max=64, help="With --embedded: sensor+controller pairs (0: one per CPU core).")] = 0,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=0, max=64)] = None,
    insecure: Annotated[bool, typer.Option("--insecure", help="With --embedded: no Zenoh credentials for the local stack (any local process may join it).")] = False,
    port: Annotated[int, typer.Option("--port", min=0, max=65535, help="With --embedded: the local stack's API port, so its dashboard link is known in advance (0: any free port).")] = 0,
    as_json: JsonOpt = False,
    api: ApiOpt = DEFAULT_API,
    token: TokenOpt = None,
) -> None:
    """Start a campaign on the stack. Prints its id (with --json: the campaign object); with
    --wait, follows it with a progress bar and prints the results.

    With --embedded the stack runs inside this command: the quickest way to run the paper
    campaign on a laptop (`make campaign`). Ctrl-C while it waits stops following, not the
    campaign, and says how to follow or cancel it.

    Examples:

        ra2vipas campaign start --preset paper --tests 50 --seed 1 --wait --plot dr.png

        ra2vipas campaign start --set n_targets=30 --name crowd-30 --json

        ra2vipas campaign start --embedded --tests 50 --db results/ra2vipas.db
    """
    from ra2vipas.cli.simulate import parse_algorithms

    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count")
    if plot is not None and not plot.lower().endswith((".png", ".svg")):
        fail(f"--plot expects a .png or .svg file name, got {plot!r}", EXIT_USAGE)
    check_output(plot, "--plot")  # before the campaign runs: a bad path must not throw its results away
    check_output(record_to, "--record")
    try:
        body = {"preset": preset, "overrides": parse_overrides(overrides or []), "algorithms": parse_algorithms(algorithms),
                "tests": tests, "seed": seed, "mode": mode}
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    if mode not in ("fast", "realtime"):
        fail(f"--mode must be fast or realtime, got {mode!r}", EXIT_USAGE)
    if name:
        body["name"] = name
    if stop_confidence > 0.0:
        body["stop_confidence"] = stop_confidence
    if target_rigs:
        body["rigs"] = list(dict.fromkeys(target_rigs))
    if rig_kind is not None:
        if rig_kind not in ("simulated", "hardware", "survey"):
            fail(f"--rig-kind must be simulated, hardware or survey, got {rig_kind!r}", EXIT_USAGE)
        body["rig_kind"] = rig_kind
    if use_rig_values:
        body["use_rig_values"] = True
    if port and not embedded:
        fail("--port sets the API port of the --embedded stack; a running stack's address is --api", EXIT_USAGE)
    if embedded:
        if record_to:
            fail("--record needs a running stack (ra2vipas up), not --embedded", EXIT_USAGE)
        _run_embedded(body, db, rigs, plot, as_json, insecure, port)
        return
    client = Client(api, token)
    if record_to:
        _start_recorded(client, body, record_to, plot, as_json)
        return
    c = client.request("POST", "/campaigns", json=body)
    if not wait:
        if as_json:
            print_json(c)
        else:
            print(c["id"])
        return
    _announce(c["id"], as_json)
    _finish(client, c["id"], plot, as_json)


def _announce(cid: str, as_json: bool) -> None:
    """The id of a campaign being followed, on its own line before anything else (the progress
    bar that also shows it vanishes, and is absent when the output is piped): on stdout, or
    with --json on stderr, so stdout stays one JSON line."""
    line = f"campaign {cid}"
    if as_json:
        print(line, file=sys.stderr, flush=True)
    else:
        print(line, flush=True)


def _finish(client: Client, cid: str, plot: str | None, as_json: bool) -> None:
    _check_finished(_follow(client, cid))
    results = client.request("GET", f"/campaigns/{cid}/results")
    emit_results(results, plot, as_json)


def _start_recorded(client: Client, body: dict, output: str, plot: str | None, as_json: bool) -> None:
    """Start a campaign with a recorder already listening, follow it, write the recording."""
    from pathlib import Path

    from ra2vipas.cli.record import open_bus, save_recording
    from ra2vipas.services.rigs.recording import Recorder

    bus = open_bus(None, None, None, None)
    try:
        recorder = Recorder(bus)
        c = client.request("POST", "/campaigns", json=body)
        _announce(c["id"], as_json)
        try:
            _check_finished(_follow(client, c["id"]))
        finally:
            recorder.stop()
        count = save_recording(client, c["id"], Path(output), recorder, bus)
    finally:
        bus.close()
    stderr.print(f"recorded {count} messages to {output}")
    emit_results(client.request("GET", f"/campaigns/{c['id']}/results"), plot, as_json)


def _run_embedded(body: dict, db: str, rigs: int, plot: str | None, as_json: bool, insecure: bool = False, port: int = 0) -> None:
    """Start a local stack on ``db`` (API on ``port``, 0: a free one), run the campaign on it,
    print its results, stop the stack. Its dashboard lives only as long as this command: the
    link printed at start says so, and the end says how to open the results afterwards."""
    import os
    import signal

    from ra2vipas.cli.stack import Stack, StackConfig, StackError, free_port

    rigs = rigs or max(1, min(os.cpu_count() or 1, 16))
    stack = Stack(StackConfig(rigs=rigs, port=port or free_port(), db_path=db, log_level="WARNING", insecure=insecure))
    previous = signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        stderr.print(f"starting a local stack ({rigs} rigs, database {db}) ...")
        try:
            stack.start()
        except StackError as err:
            fail(f"cannot start the local stack: {err}")
        client = Client(stack.api_url, None)
        c = client.request("POST", "/campaigns", json=body)
        _announce(c["id"], as_json)
        stderr.print(f"campaign {c['id']} on {stack.api_url} (logs in {stack.log_dir})", soft_wrap=True, markup=False)
        stderr.print(f"dashboard (while this command runs): {stack.api_url}/ui/campaigns/{c['id']}", soft_wrap=True, markup=False)
        try:
            _finish(client, c["id"], plot, as_json)
        finally:
            stderr.print(afterwards(c["id"], db), soft_wrap=True, markup=False)
    except KeyboardInterrupt:
        fail("interrupted; the campaign stays in the database and resumes when a stack is started on it", EXIT_FAILED)
    finally:
        stack.stop()
        signal.signal(signal.SIGTERM, previous)


def afterwards(cid: str, db: str) -> str:
    """How to see an --embedded campaign once its stack has stopped."""
    from shlex import quote

    return (f"the local stack stops with this command; to open campaign {cid} in the dashboard afterwards, run "
            f"`ra2vipas up --db {quote(db)}` and browse http://127.0.0.1:8080/ui/campaigns/{cid}")


@app.command("list")
def list_campaigns(
    status: Annotated[Optional[str], typer.Option(help=f"Only campaigns in this state: {', '.join(STATUSES)}.", autocompletion=_complete(STATUSES))] = None,
    preset: Annotated[Optional[str], typer.Option(help="Only campaigns of this preset.", autocompletion=_complete(PRESETS))] = None,
    name: Annotated[Optional[str], typer.Option(help="Only campaigns with exactly this name.")] = None,
    limit: Annotated[int, typer.Option(min=1, max=200, help="Page size.")] = 20,
    offset: Annotated[int, typer.Option(min=0, help="Campaigns to skip (newest first).")] = 0,
    as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """List campaigns, newest first, with what each ran (preset, overrides, tests, seed); with
    --json: the page object, items and total.

    Example:

        ra2vipas campaign list --status done --name crowd-30
    """
    if status is not None and status not in STATUSES:
        fail(f"--status must be one of {', '.join(STATUSES)}, got {status!r}", EXIT_USAGE)
    params = {"limit": limit, "offset": offset, **({"status": status} if status else {}), **({"preset": preset} if preset else {}),
              **({"name": name} if name else {})}
    page = Client(api, token).request("GET", "/campaigns", params=params)
    if as_json:
        print_json(page)
    else:
        stdout.print(campaigns_table(page))


@app.command("show")
def show(campaign_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Status, progress, timings, POD R² and the full scenario of a campaign."""
    c = Client(api, token).request("GET", f"/campaigns/{campaign_id}")
    if as_json:
        print_json(c)
        return
    for table in campaign_tables(c):
        stdout.print(table)


@app.command("status")
def status_(campaign_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """One line: status and progress of a campaign (with --json: the campaign object, as `show`)."""
    c = Client(api, token).request("GET", f"/campaigns/{campaign_id}")
    if as_json:
        print_json(c)
        return
    p = c["progress"]
    r2 = c["pod"]["r2"]
    stdout.print(f"{c['id']}: {c['status']}, {p['done']}/{p['total']} episodes done ({p['running']} running), "
                 f"preset {c['preset']}, {c['tests']} tests, seed {c['seed']}, POD R² {'—' if r2 is None else f'{r2:.4f}'}"
                 + (f", error: {c['error']}" if c.get("error") else ""))


@app.command("watch")
def watch(campaign_id: IdArg,
          as_json: Annotated[bool, typer.Option("--json", help="Print every progress update as one JSON line; the last is the final state.")] = False,
          api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Follow a campaign with a live progress bar until it finishes. Exit code 0 if it is
    done, 1 if it failed or was cancelled; Ctrl-C stops following (exit 130), not the campaign.

    Example:

        ra2vipas campaign watch 3f2a9c0d1b7e --api http://127.0.0.1:8080
    """
    client = Client(api, token)
    final = _follow(client, campaign_id, as_json_lines=as_json)
    if not as_json:
        stdout.print(f"{campaign_id}: {final['status']}, {final['progress']['done']}/{final['progress']['total']} episodes done")
    _check_finished(final | {"id": campaign_id})


@app.command("results")
def results(
    campaign_id: IdArg,
    per_test: Annotated[bool, typer.Option("--per-test", help="The per-test outcome table instead of the DR table.")] = False,
    algorithm: Annotated[Optional[str], typer.Option(help="Only this algorithm (its DR row, or with --per-test its tests).", autocompletion=_complete_policies)] = None,
    hit: Annotated[Optional[bool], typer.Option("--hit/--miss", show_default=False, help="With --per-test: only the tests whose final answer was (--hit) or was not (--miss) the Tx.")] = None,
    limit: Annotated[int, typer.Option(min=1, max=200, help="With --per-test: page size.")] = 50,
    offset: Annotated[int, typer.Option(min=0, help="With --per-test: rows to skip.")] = 0,
    as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """The DR table of a finished campaign (with --json: the results object); with --per-test,
    how each test ended. A cancelled or failed campaign's results are those of the tests it
    recorded, marked partial.

    Examples:

        ra2vipas campaign results 3f2a9c0d1b7e --algorithm rapas

        ra2vipas campaign results 3f2a9c0d1b7e --per-test --algorithm ra2vipas --miss
    """
    if algorithm is not None and not registry.is_valid_name(algorithm):  # the API names the ones the campaign ran
        fail(f"--algorithm must be a policy name ({registry.NAME_PATTERN}), got {algorithm!r}", EXIT_USAGE)
    client = Client(api, token)
    if hit is not None and not per_test:
        fail("--hit/--miss select rows of the per-test table: add --per-test", EXIT_USAGE)
    if per_test:
        params = {"limit": limit, "offset": offset, **({"algorithm": algorithm} if algorithm else {}),
                  **({"hit": "true" if hit else "false"} if hit is not None else {})}
        page = client.request("GET", f"/campaigns/{campaign_id}/tests", params=params)
        if as_json:
            print_json(page)
        else:
            stdout.print(outcomes_table(page))
        return
    body = client.request("GET", f"/campaigns/{campaign_id}/results")
    if algorithm is not None:
        if algorithm not in body["algorithms"]:
            fail(f"campaign {campaign_id} has no results for {algorithm!r}: --algorithm must be one of the algorithms it ran "
                 f"({', '.join(body['algorithms'])})", EXIT_USAGE)
        body = {**body, "algorithms": {algorithm: body["algorithms"][algorithm]}}
        if "outcomes" in body:  # one algorithm: nothing to pair it with
            body["outcomes"] = {algorithm: body["outcomes"].get(algorithm)}
            body["paired"] = []
    if as_json:
        print_json(body)
    else:
        print_results(body)


@app.command("trace")
def trace(
    campaign_id: IdArg,
    test: Annotated[int, typer.Option("--test", min=0, max=MAX_TESTS - 1, help="The test index k.")] = 0,
    algorithm: Annotated[str, typer.Option(help="The algorithm.", autocompletion=_complete_policies)] = "ra2vipas",
    as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """One finished test step by step: pan angle, reward, estimate γ̂_t, the chosen target î_t
    and whether it is the Tx."""
    body = Client(api, token).request("GET", f"/campaigns/{campaign_id}/tests/{test}/{algorithm}")
    if as_json:
        print_json(body)
    else:
        stdout.print(trace_table(body))


@app.command("cancel")
def cancel(campaign_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Cancel a running campaign: its in-flight tests stop; the tests recorded so far stay."""
    c = Client(api, token).request("POST", f"/campaigns/{campaign_id}/cancel")
    if as_json:
        print_json(c)
    else:
        print(f"campaign {c['id']} cancelled ({c['progress']['done']}/{c['progress']['total']} episodes done)")


@app.command("delete")
def delete(campaign_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Delete a finished campaign and its recorded tests (cancel a running one first)."""
    Client(api, token).request("DELETE", f"/campaigns/{campaign_id}")
    if as_json:
        print_json({"id": campaign_id, "deleted": True})
    else:
        print(f"campaign {campaign_id} deleted")


@app.command("export")
def export(
    campaign_id: IdArg,
    fmt: Annotated[Optional[str], typer.Option("--format", "-f", help="json or csv (default: from the file extension, else json).", autocompletion=_complete(("json", "csv")))] = None,
    table: Annotated[str, typer.Option("--table", help="With csv: dr (one row per algorithm x time step) or summary (one row per algorithm: final DR, CI, t90, ...).", autocompletion=_complete(("dr", "summary")))] = "dr",
    output: Annotated[Optional[str], typer.Option("--output", "-o", metavar="FILE", help="Write here instead of stdout.")] = None,
    api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """Export the results of a finished (or, marked partial, a cancelled) campaign as JSON or
    as a tidy CSV table whose every row says what was run (campaign id, name, preset, seed,
    tests, one column per overridden parameter), so it can be reproduced from the file alone
    and several campaigns' files concatenate into one table.

    Examples:

        ra2vipas campaign export 3f2a9c0d1b7e -o dr.csv

        ra2vipas campaign export 3f2a9c0d1b7e --table summary -o summary.csv
    """
    if fmt is None:
        fmt = "csv" if output and output.lower().endswith(".csv") else "json"
    if fmt not in ("json", "csv"):
        fail(f"--format must be json or csv, got {fmt!r}", EXIT_USAGE)
    if table not in ("dr", "summary"):
        fail(f"--table must be dr or summary, got {table!r}", EXIT_USAGE)
    if table != "dr" and fmt != "csv":
        fail("--table selects a CSV table; the JSON has both (add --format csv)", EXIT_USAGE)
    check_output(output, "--output")
    params = {"format": fmt, **({"table": table} if fmt == "csv" else {})}
    r = Client(api, token).response("GET", f"/campaigns/{campaign_id}/results", params=params)
    data = r.content if fmt == "csv" else (r.text.strip() + "\n").encode()
    if output in (None, "-"):
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
        return
    write_file(data, output)
    print(f"{fmt.upper()} written to {output}", file=sys.stderr)


RUN_FIELDS = ("name", "id", "preset", "seed", "tests")


def label_value(param: str, campaign: dict, results: dict) -> str:
    """The value of ``param`` (a scenario parameter, or name / id / preset / seed / tests) for a
    campaign, as a legend label."""
    if param in RUN_FIELDS:
        value = campaign.get(param) if param in ("name", "id") else results.get(param)
        return f"{param} {value}" if param in ("seed", "tests") else str(value or campaign["id"])
    return f"{param}={results['scenario'][param]}"


def check_label(param: str) -> None:
    from difflib import get_close_matches

    from ra2vipas.services.protocol.scenario import Scenario

    known = (*RUN_FIELDS, *Scenario.model_fields)
    if param not in known:
        near = get_close_matches(param, known, n=1)
        fail(f"--label {param!r} is not a scenario parameter nor one of {', '.join(RUN_FIELDS)}"
             + (f"; did you mean {near[0]!r}?" if near else " (see `ra2vipas presets show paper`)"), EXIT_USAGE)


@app.command("plot")
def plot(
    campaign_ids: Annotated[list[str], typer.Argument(metavar="CAMPAIGN_ID...", help="One campaign id, or several to overlay their DR curves on one figure.", show_default=False)],
    kind: Annotated[str, typer.Option("--kind", "-k", help="dr: DR curves (Fig. 4); pod: learned POD (Fig. 3); reliability: calibration of the final confidences; episode: one test (needs --test and --algorithm).", autocompletion=_complete(("dr", "pod", "reliability", "episode")))] = "dr",
    label: Annotated[Optional[str], typer.Option("--label", metavar="PARAM", help="Overlay: name each campaign's curves by this scenario parameter (e.g. n_targets) or by name, id, preset, seed or tests (default: name, else id, with the overrides).")] = None,
    test: Annotated[Optional[int], typer.Option("--test", min=0, max=MAX_TESTS - 1, help="With --kind episode: the test index.")] = None,
    algorithm: Annotated[Optional[str], typer.Option(help="With --kind episode: the algorithm; with several campaigns: draw only this algorithm.", autocompletion=_complete_policies)] = None,
    output: Annotated[Optional[str], typer.Option("--output", "-o", metavar="FILE", help="PNG or SVG file (default: campaign-ID-KIND.png).")] = None,
    api: ApiOpt = DEFAULT_API, token: TokenOpt = None,
) -> None:
    """Write a campaign's figure (rendered by the server) to a file (.png or .svg); with several
    campaign ids (or --label), overlay their DR curves on one figure, drawn here.

    Examples:

        ra2vipas campaign plot 3f2a9c0d1b7e --kind pod -o pod.svg

        ra2vipas campaign plot 3f2a9c0d1b7e 8e1d0b5a9c2f 77ab01cd23ef --label n_targets -o crowd.png
    """
    overlay = len(campaign_ids) > 1 or label is not None
    first = campaign_ids[0]
    output = output or (f"campaign-{first}-{kind}.png" if not overlay else f"campaigns-{'-'.join(campaign_ids[:3])}-dr.png")
    if not output.lower().endswith((".png", ".svg")):
        fail(f"--output expects a .png or .svg file name, got {output!r}", EXIT_USAGE)
    check_output(output, "--output")
    if overlay:
        if kind != "dr":
            fail(f"several campaigns (or --label) overlay DR curves: --kind {kind} draws one campaign", EXIT_USAGE)
        if label is not None:
            check_label(label)
        _overlay(Client(api, token), campaign_ids, label, algorithm, output)
        return
    fmt = "svg" if output.lower().endswith(".svg") else "png"
    if kind in ("dr", "pod", "reliability"):
        path = f"/campaigns/{first}/plots/{kind}"
    elif kind == "episode":
        if test is None or algorithm is None:
            fail("--kind episode needs --test K and --algorithm NAME", EXIT_USAGE)
        path = f"/campaigns/{first}/tests/{test}/{algorithm}/plot"
    else:
        fail(f"--kind must be dr, pod, reliability or episode, got {kind!r}", EXIT_USAGE)
    r = Client(api, token).response("GET", path, params={"format": fmt})
    write_file(r.content, output)
    print(f"{kind} plot written to {output}")


def _overlay(client: Client, campaign_ids: list[str], label: str | None, algorithm: str | None, output: str) -> None:
    from ra2vipas.cli.output import overrides_text
    from ra2vipas.services.orchestrator.plots import overlay_title, write_overlay_plot

    runs = []
    for cid in dict.fromkeys(campaign_ids):
        campaign = client.request("GET", f"/campaigns/{cid}")
        results = client.request("GET", f"/campaigns/{cid}/results")
        if algorithm is not None:
            if algorithm not in results["algorithms"]:
                fail(f"campaign {cid} did not run {algorithm} (it ran {', '.join(results['algorithms'])})")
            results["algorithms"] = {algorithm: results["algorithms"][algorithm]}
        if label is not None:
            text = label_value(label, campaign, results)
        else:
            over = overrides_text(results.get("overrides"))
            text = (campaign["name"] or cid) + ("" if over == "—" else f" ({over})")
        if results.get("partial"):
            text += " [partial]"
        runs.append((text, results))
    title = overlay_title(runs, label)
    try:
        write_overlay_plot(runs, title, output)
    except OSError as err:
        fail(f"cannot write {output}: {err.strerror or err}")
    print(f"dr plot of {len(runs)} campaigns written to {output}")
    for line in overlay_pairs(runs):
        print(line)


def overlay_pairs(runs: list[tuple[str, dict]]) -> list[str]:
    """For campaigns with the same seed (test k meets the world drawn from (seed, k) in each,
    changed only by what differs), each algorithm compared across them test by test: one line
    per pair of campaigns and algorithm with the discordant tests and McNemar's exact p-value."""
    from ra2vipas.api import paired_test

    lines = []
    for i, (label_a, a) in enumerate(runs):
        for label_b, b in runs[i + 1:]:
            if a["seed"] != b["seed"]:
                continue
            for algorithm in a["algorithms"]:
                hits_a = (a.get("outcomes") or {}).get(algorithm)
                hits_b = (b.get("outcomes") or {}).get(algorithm)
                if not hits_a or not hits_b:
                    continue
                p = paired_test(hits_a, hits_b)
                if p["tests"]:
                    lines.append(f"paired, {algorithm}: {label_a} vs {label_b}: {p['tests']} tests, found only by the first "
                                 f"{p['only_a']}, only by the second {p['only_b']}, DR difference {p['dr_difference']:+.3f}, "
                                 f"McNemar p = {p['p_value']:.3g}")
    return lines
