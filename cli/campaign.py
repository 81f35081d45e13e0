"""``ra2vipas campaign ...``: a thin HTTP client of the orchestrator's REST API."""

from __future__ import annotations

import time
from typing import Annotated, Any, Optional

import httpx
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from cli.output import EXIT_FAILED, EXIT_USAGE, fail, print_json, print_results, stderr, stdout
from services.protocol.scenario import PRESETS, ScenarioError, parse_overrides

app = typer.Typer(help="Start, watch and read campaigns on a running stack (see `ra2vipas up`).", no_args_is_help=True)

ApiOpt = Annotated[str, typer.Option("--api", envvar="RA2VIPAS_API", help="Base URL of the orchestrator API.")]
TokenOpt = Annotated[Optional[str], typer.Option("--token", envvar="RA2VIPAS_TOKEN", help="Bearer token, if the API requires one.")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON line (the last line of stdout).")]

DEFAULT_API = "http://127.0.0.1:8080"


class Client:
    """HTTP calls with the CLI's error convention: unreachable API or 4xx/5xx -> one stderr line."""

    def __init__(self, api: str, token: str | None) -> None:
        self.api = api.rstrip("/")
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=self.api, headers=headers, timeout=30.0)

    def request(self, method: str, path: str, **kw) -> Any:
        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as err:
            fail(f"cannot reach the API at {self.api} ({type(err).__name__}); is `ra2vipas up` running? (--api / RA2VIPAS_API)")
        if r.status_code >= 400:
            detail = _detail(r)
            code = EXIT_USAGE if r.status_code == 422 else EXIT_FAILED
            fail(f"{method} {path}: {r.status_code} {detail}", code)
        return r.json()


def _detail(r: httpx.Response) -> str:
    try:
        body = r.json()
    except ValueError:
        return r.text[:300]
    detail = body.get("detail", body) if isinstance(body, dict) else body
    if isinstance(detail, list) and detail and isinstance(detail[0], dict):
        first = detail[0]
        loc = ".".join(str(p) for p in first.get("loc", ())[1:])
        return f"{loc}: {first.get('msg', '')}" if loc else str(first.get("msg", ""))
    return str(detail)


def _wait(client: "Client", cid: str, as_json: bool) -> dict:
    """Poll until the campaign finishes, with a progress bar on stderr; return the campaign."""
    with Progress(TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
                  TimeElapsedColumn(), console=stderr, transient=True) as bar:
        task = bar.add_task(f"campaign {cid}", total=None)
        while True:
            c = client.request("GET", f"/campaigns/{cid}")
            p = c["progress"]
            bar.update(task, total=p["total"], completed=p["done"], description=f"campaign {cid} ({c['status']})")
            if c["status"] in ("done", "failed", "cancelled"):
                return c
            time.sleep(0.25)


def _show_results(client: Client, cid: str, as_json: bool) -> None:
    results = client.request("GET", f"/campaigns/{cid}/results")
    if as_json:
        print_json(results)
    else:
        print_results(results)


@app.command("start")
def start(
    preset: Annotated[str, typer.Option(help=f"Scenario preset: {', '.join(PRESETS)}.")] = "paper",
    tests: Annotated[int, typer.Option(min=1, max=10000, help="Monte Carlo tests per algorithm.")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed.")] = 1,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated subset of ra2vipas, rapas, ravipas, sweep (default: all).")] = None,
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help="Override a scenario parameter (repeatable).")] = None,
    mode: Annotated[str, typer.Option(help="fast (lockstep, as fast as possible) or realtime (one sample every T_RF).")] = "fast",
    name: Annotated[Optional[str], typer.Option(help="A label for the campaign.")] = None,
    wait: Annotated[bool, typer.Option("--wait", help="Show progress until it finishes, then print the DR table.")] = False,
    plot: Annotated[Optional[str], typer.Option(metavar="FILE", help="With --wait: also write the DR curves to FILE (.png or .svg).")] = None,
    embedded: Annotated[bool, typer.Option("--embedded", help="Start a local stack (Zenoh router, services, SQLite file) just for this campaign and stop it afterwards; implies --wait.")] = False,
    db: Annotated[str, typer.Option("--db", envvar="RA2VIPAS_DB", help="With --embedded: the SQLite file the results go to.")] = "ra2vipas.db",
    rigs: Annotated[int, typer.Option(min=0, max=64, help="With --embedded: sensor+controller pairs (0: one per CPU core).")] = 0,
    as_json: JsonOpt = False,
    api: ApiOpt = DEFAULT_API,
    token: TokenOpt = None,
) -> None:
    """Start a campaign on the stack; with --wait, follow it and print the results.

    With --embedded the stack runs inside this command: the quickest way to run the paper
    campaign on a laptop (`make campaign`).
    """
    from cli.simulate import parse_algorithms

    if plot is not None and not plot.lower().endswith((".png", ".svg")):
        fail(f"--plot expects a .png or .svg file name, got {plot!r}", EXIT_USAGE)

    try:
        body = {"preset": preset, "overrides": parse_overrides(overrides or []), "algorithms": parse_algorithms(algorithms),
                "tests": tests, "seed": seed, "mode": mode}
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    if mode not in ("fast", "realtime"):
        fail(f"--mode must be fast or realtime, got {mode!r}", EXIT_USAGE)
    if name:
        body["name"] = name
    if embedded:
        _run_embedded(body, db, rigs, plot, as_json)
        return
    client = Client(api, token)
    c = client.request("POST", "/campaigns", json=body)
    if not wait:
        if as_json:
            print_json(c)
        else:
            print(c["id"])
        return
    _finish(client, c["id"], plot, as_json)


def _finish(client: "Client", cid: str, plot: str | None, as_json: bool) -> None:
    c = _wait(client, cid, as_json)
    if c["status"] != "done":
        fail(f"campaign {c['id']} {c['status']}: {c.get('error') or 'no results'}")
    results = client.request("GET", f"/campaigns/{cid}/results")
    if plot:
        from services.orchestrator.plots import write_dr_plot

        try:
            write_dr_plot(results, plot)
        except OSError as err:
            fail(f"cannot write {plot}: {err.strerror or err}")
    if as_json:
        print_json(results)
    else:
        print_results(results)
        if plot:
            print(f"DR plot written to {plot}")


def _run_embedded(body: dict, db: str, rigs: int, plot: str | None, as_json: bool) -> None:
    import os
    import signal

    from cli.stack import Stack, StackConfig, StackError, free_port

    rigs = rigs or max(1, min(os.cpu_count() or 1, 16))
    stack = Stack(StackConfig(rigs=rigs, port=free_port(), db_path=db, log_level="WARNING"))
    previous = signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        stderr.print(f"starting a local stack ({rigs} rigs, database {db}) ...")
        try:
            stack.start()
        except StackError as err:
            fail(f"cannot start the local stack: {err}")
        client = Client(stack.api_url, None)
        c = client.request("POST", "/campaigns", json=body)
        stderr.print(f"campaign {c['id']} on {stack.api_url} (logs in {stack.log_dir})")
        _finish(client, c["id"], plot, as_json)
    except KeyboardInterrupt:
        fail("interrupted; the campaign stays in the database and resumes when a stack is started on it", EXIT_FAILED)
    finally:
        stack.stop()
        signal.signal(signal.SIGTERM, previous)


@app.command("status")
def status(campaign_id: Annotated[str, typer.Argument(help="Campaign id.")], as_json: JsonOpt = False,
           api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Status and progress of a campaign."""
    c = Client(api, token).request("GET", f"/campaigns/{campaign_id}")
    if as_json:
        print_json(c)
        return
    p = c["progress"]
    r2 = c["pod"]["r2"]
    stdout.print(f"{c['id']}: {c['status']}, {p['done']}/{p['total']} episodes done ({p['running']} running), "
                 f"preset {c['preset']}, {c['tests']} tests, seed {c['seed']}, POD R² {'—' if r2 is None else f'{r2:.4f}'}"
                 + (f", error: {c['error']}" if c.get("error") else ""))


@app.command("results")
def results(campaign_id: Annotated[str, typer.Argument(help="Campaign id.")], as_json: JsonOpt = False,
            api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """The DR table (or the results object with --json) of a finished campaign."""
    _show_results(Client(api, token), campaign_id, as_json)
