"""``ra2vipas study ...``: parameter studies on a running stack, a thin HTTP client of ``/studies``.

start | list | show | watch | results | plot | cancel | delete. Read commands print rich
tables, or JSON with ``--json``; errors are one stderr line with exit code 1 (a failed
operation) or 2 (bad usage or input). ``ra2vipas simulate --vary ...`` runs the same study in
this process and prints the same results object (``study_table`` / ``--json``).
"""

from __future__ import annotations

import time
from typing import Annotated, Any, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from ra2vipas.cli.client import DEFAULT_API, FINISHED, ApiOpt, Client, JsonOpt, TokenOpt
from ra2vipas.cli.output import EXIT_USAGE, check_output, fail, print_json, stderr, stdout, write_file
from ra2vipas.services.protocol.messages import MAX_TESTS
from ra2vipas.services.protocol.scenario import PRESETS, ScenarioError, parse_overrides

app = typer.Typer(help="Parameter studies: DR against scenario parameters, one campaign per grid point (see `ra2vipas up`).",
                  no_args_is_help=True)

STATUSES = ("queued", "training", "running", "done", "failed", "cancelled")
IdArg = Annotated[str, typer.Argument(help="Study id (see `ra2vipas study list`).")]
VaryOpt = Annotated[Optional[list[str]], typer.Option(
    "--vary", metavar="NAME=a,b,c|NAME=a:b:step",
    help="A scenario parameter to vary: a list of values or an inclusive range (repeatable: the grid is the product).")]
POLL_S = 1.0


def parse_vary_options(items: list[str] | None) -> dict[str, list[Any]]:
    """``--vary`` options -> ``{name: [values]}`` (typed), in the order given.

    Raises
    ------
    StudyError
        A malformed option, an unknown parameter, a bad value, or a parameter given twice.
    """
    from ra2vipas.services.orchestrator.study import StudyError, parse_vary

    vary: dict[str, list[Any]] = {}
    for item in items or []:
        name, values = parse_vary(item)
        if name in vary:
            raise StudyError(f"--vary {name} given twice; list all its values in one option", name=name)
        vary[name] = values
    return vary


# -- tables ---------------------------------------------------------------------------------------

def _cell(value: Any, fmt: str = "{:.3f}") -> str:
    if value is None:
        return "—"
    if isinstance(value, float):
        return fmt.format(value)
    return str(value)


def study_table(results: dict[str, Any]) -> Table:
    """The study's rows: one per point x algorithm, with the varied values, the final DR and its
    Wilson interval, t90, in-FoV, POD R² (and the final-confidence ECE when reported)."""
    params = results["parameters"]
    calibrated = any(r.get("calibration_ece_final") is not None for r in results["rows"])
    decided = any(r.get("decision_accuracy") is not None for r in results["rows"])
    title = (f"Study {results.get('id') or '(in-process)'}: {results['preset']}, {results['tests']} tests per point, "
             f"seed {results['seed']}" + (" — partial" if results.get("partial") else ""))
    table = Table(title=title)
    for name in params:
        table.add_column(name, justify="right")
    for col in ("algorithm", "tests", "DR final", "95% CI", "t90", "in-FoV", "POD R²"):
        table.add_column(col, justify="left" if col == "algorithm" else "right", no_wrap=col == "95% CI")
    if calibrated:
        table.add_column("ECE final", justify="right")
    if decided:
        table.add_column("accuracy", justify="right")
        table.add_column("median decision", justify="right")
    previous = None
    for row in results["rows"]:
        values = tuple(row.get(n) for n in params)
        shown = [_cell(v, "{:g}") for v in values] if values != previous else [""] * len(params)
        previous = values
        lo, hi = row.get("ci95_lo"), row.get("ci95_hi")
        t90 = row.get("time_to_dr90_s")
        cells = [*shown, row["algorithm"], str(row["tests"]), _cell(row.get("dr_final")),
                 "—" if lo is None else f"{lo:.3f}–{hi:.3f}", "—" if t90 is None else f"{t90:g} s", _cell(row.get("in_fov_final")),
                 _cell(row.get("pod_r2"), "{:.4f}")]
        if calibrated:
            cells.append(_cell(row.get("calibration_ece_final")))
        if decided:
            cells += [_cell(row.get("decision_accuracy")), _cell(row.get("decision_median_s"), "{:g} s")]
        table.add_row(*cells)
    return table


def print_study_results(results: dict[str, Any]) -> None:
    stdout.print(study_table(results))
    line = f"{len(results['points'])} points x {len(results['algorithms'])} algorithms"
    if results.get("steps_per_second"):
        line += f"; {results['steps_per_second']:.0f} control steps/s"
    if results.get("workers"):
        line += f" on {results['workers']} worker{'s' if results['workers'] > 1 else ''}"
    stdout.print(line)
    stdout.print("DR: paper's association rule (eq. 11) at the last step; 95% CI: Wilson interval; t90: time after which DR "
                 "stays >= 0.9; every point runs the same seed, so points are paired test by test.")


def emit_study(results: dict[str, Any], plot: str | None, as_json: bool, metric: str = "dr_final") -> None:
    """Write the study figure if asked, then print the results: one JSON line, or the table."""
    if plot:
        from ra2vipas.services.orchestrator.plots import write_study_plot

        try:
            write_study_plot(results, metric, plot)
        except ValueError as err:
            fail(str(err), EXIT_USAGE)
        except OSError as err:
            fail(f"cannot write {plot}: {err.strerror or err}")
    if as_json:
        print_json(results)
    else:
        print_study_results(results)
        if plot:
            print(f"study plot ({metric}) written to {plot}")


def studies_table(page: dict[str, Any]) -> Table:
    """One page of ``GET /studies``."""
    items = page["items"]
    first = page["offset"] + 1 if items else 0
    table = Table(title=f"Studies {first}–{page['offset'] + len(items)} of {page['total']}")
    for col in ("id", "name", "status", "preset", "varied", "points", "tests", "seed", "episodes", "created"):
        table.add_column(col, no_wrap=col in ("id", "created"))
    for s in items:
        p = s["progress"]
        varied = ", ".join(f"{k}×{len(v)}" for k, v in s["vary"].items())
        table.add_row(s["id"], s["name"] or "", s["status"], s["preset"], varied, str(s["points_total"]), str(s["tests"]),
                      str(s["seed"]), f"{p['done']}/{p['total']}", time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(s["created_at"])))
    return table


def study_tables(s: dict[str, Any]) -> list[Table]:
    """``GET /studies/{id}`` for people: the study, then its points."""
    about = Table(title=f"Study {s['id']}", show_header=False)
    about.add_column("field", style="bold")
    about.add_column("value")
    p = s["progress"]
    elapsed = s.get("elapsed_s")
    rows = [("name", s["name"] or ""), ("status", s["status"]), ("progress", f"{p['done']}/{p['total']} episodes"),
            ("preset", s["preset"]), ("overrides", ", ".join(f"{k}={v}" for k, v in s["overrides"].items()) or "—"),
            ("varied", "; ".join(f"{k} = {', '.join(map(str, v))}" for k, v in s["vary"].items())),
            ("points", str(s["points_total"])), ("tests per point", str(s["tests"])), ("seed", str(s["seed"])),
            ("algorithms", ", ".join(s["algorithms"])), ("mode", s["mode"]),
            ("elapsed", "—" if elapsed is None else f"{elapsed:.1f} s")]
    if s.get("stop_confidence"):
        rows.append(("stop confidence", str(s["stop_confidence"])))
    if s.get("error"):
        rows.append(("error", s["error"]))
    for k, v in rows:
        about.add_row(k, v)
    points = Table(title="Points")
    for name in s["parameters"]:
        points.add_column(name, justify="right")
    for col in ("campaign", "status", "episodes", "POD R²"):
        points.add_column(col)
    for pt in s.get("points") or []:
        pp = pt["progress"]
        r2 = pt["pod"]["r2"]
        points.add_row(*[str(pt["values"].get(n)) for n in s["parameters"]], pt["campaign_id"], pt["status"],
                       f"{pp['done']}/{pp['total']}", "—" if r2 is None else f"{r2:.4f}")
    return [about, points]


# -- commands -------------------------------------------------------------------------------------

def _follow(client: Client, sid: str) -> dict:
    """Poll a study until it finishes, with one progress bar over every point's episodes."""
    with Progress(TextColumn("[bold]{task.description}[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
                  TimeElapsedColumn(), TimeRemainingColumn(), console=stderr, transient=True) as bar:
        task = bar.add_task(f"study {sid}", total=None)
        while True:
            s = client.request("GET", f"/studies/{sid}")
            p = s["progress"]
            bar.update(task, total=p["total"], completed=p["done"], description=f"study {sid} ({s['status']})")
            if s["status"] in FINISHED:
                return s
            time.sleep(POLL_S)


def _check_plot(plot: str | None, option: str = "--plot") -> None:
    """A figure's file name: .png or .svg (usage error), in a folder that can be written."""
    if plot is not None and not plot.lower().endswith((".png", ".svg")):
        fail(f"{option} expects a .png or .svg file name, got {plot!r}", EXIT_USAGE)
    check_output(plot, option)


@app.command("start")
def start(
    vary: VaryOpt = None,
    preset: Annotated[str, typer.Option(help=f"Scenario preset: {', '.join(PRESETS)}.")] = "paper",
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Monte Carlo tests per point and algorithm.")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="The seed of every point (points are paired test by test).")] = 1,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated pointing policies: the built-ins (default: all four), any installed policy (`ra2vipas policies`), or module:Class.")] = None,
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help="Override a scenario parameter at every point (repeatable).")] = None,
    mode: Annotated[str, typer.Option(help="fast or realtime.")] = "fast",
    name: Annotated[Optional[str], typer.Option(help="A label for the study.")] = None,
    stop_confidence: Annotated[float, typer.Option("--stop-confidence", min=0.0, max=0.999999, help="End each episode at the first step this confident (0: off).")] = 0.0,
    wait: Annotated[bool, typer.Option("--wait", help="Show progress over the whole study until it finishes, then print its table.")] = False,
    plot: Annotated[Optional[str], typer.Option(metavar="FILE", help="With --wait: also write the final DR against the varied parameter(s) to FILE (.png or .svg).")] = None,
    as_json: JsonOpt = False,
    api: ApiOpt = DEFAULT_API,
    token: TokenOpt = None,
) -> None:
    """Start a study: one campaign per point of the grid of --vary values, all with the same seed.
    Prints its id (with --json: the study object); with --wait, follows it and prints its table.

    Example:

        ra2vipas study start --vary n_targets=10,20,40 --vary rf_noise_db=2:6:1 --tests 100 --wait
    """
    from ra2vipas.cli.simulate import parse_algorithms
    from ra2vipas.services.orchestrator.study import StudyError

    _check_plot(plot)
    if mode not in ("fast", "realtime"):
        fail(f"--mode must be fast or realtime, got {mode!r}", EXIT_USAGE)
    try:
        varied = parse_vary_options(vary)
        body: dict[str, Any] = {"preset": preset, "overrides": parse_overrides(overrides or []), "vary": varied,
                                "algorithms": parse_algorithms(algorithms), "tests": tests, "seed": seed, "mode": mode}
    except (ScenarioError, StudyError) as err:
        fail(str(err), EXIT_USAGE)
    if not varied:
        fail("give at least one --vary NAME=a,b,c (or NAME=a:b:step)", EXIT_USAGE)
    if name:
        body["name"] = name
    if stop_confidence > 0.0:
        body["stop_confidence"] = stop_confidence
    client = Client(api, token)
    s = client.request("POST", "/studies", json=body)
    if not wait:
        if as_json:
            print_json(s)
        else:
            print(s["id"])
        return
    _finish(client, s["id"], plot, as_json)


def _finish(client: Client, sid: str, plot: str | None, as_json: bool) -> None:
    s = _follow(client, sid)
    results = client.request("GET", f"/studies/{sid}/results")
    emit_study(results, plot, as_json)
    if s["status"] != "done":
        fail(f"study {sid} {s['status']}: {s.get('error') or 'not every point finished'}")


@app.command("list")
def list_(
    status: Annotated[Optional[str], typer.Option(help="Only studies in this state: " + ", ".join(STATUSES) + ".")] = None,
    limit: Annotated[int, typer.Option(min=1, max=500, help="Page size.")] = 50,
    offset: Annotated[int, typer.Option(min=0, help="Studies to skip.")] = 0,
    as_json: JsonOpt = False,
    api: ApiOpt = DEFAULT_API,
) -> None:
    """List studies, newest first."""
    if status is not None and status not in STATUSES:
        fail(f"--status must be one of {', '.join(STATUSES)}, got {status!r}", EXIT_USAGE)
    params: dict[str, Any] = {"limit": limit, "offset": offset}
    if status:
        params["status"] = status
    page = Client(api, None).request("GET", "/studies", params=params)
    if as_json:
        print_json(page)
    else:
        stdout.print(studies_table(page))


@app.command("show")
def show(study_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API) -> None:
    """A study: its grid, status, progress over every point, and each point's campaign."""
    s = Client(api, None).request("GET", f"/studies/{study_id}")
    if as_json:
        print_json(s)
    else:
        for table in study_tables(s):
            stdout.print(table)


@app.command("watch")
def watch(study_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API) -> None:
    """Follow a study with a progress bar over all its points until it finishes, then print its table."""
    client = Client(api, None)
    _finish(client, study_id, None, as_json)


@app.command("results")
def results(
    study_id: IdArg,
    csv: Annotated[Optional[str], typer.Option("--csv", metavar="FILE", help="Write the rows as CSV to FILE ('-': stdout).")] = None,
    as_json: JsonOpt = False,
    api: ApiOpt = DEFAULT_API,
) -> None:
    """The study's table: one row per point x algorithm (partial while it runs)."""
    client = Client(api, None)
    check_output(csv, "--csv")
    if csv is not None:
        text = client.response("GET", f"/studies/{study_id}/results", params={"format": "csv"}).text
        if csv == "-":
            print(text, end="")
        else:
            write_file(text.encode(), csv)
            print(f"CSV written to {csv}")
        return
    body = client.request("GET", f"/studies/{study_id}/results")
    if as_json:
        print_json(body)
    else:
        print_study_results(body)


@app.command("plot")
def plot(
    study_id: IdArg,
    output: Annotated[str, typer.Option("--output", "-o", metavar="FILE", help="Where to write the figure (.png or .svg).")],
    metric: Annotated[str, typer.Option(help="A results field: dr_final, time_to_dr90_s, in_fov_final, pod_r2, calibration_ece_final, ...")] = "dr_final",
    api: ApiOpt = DEFAULT_API,
) -> None:
    """Write the study's metric against its varied parameter (a heat map when two vary)."""
    _check_plot(output, "--output")
    fmt = "svg" if output.lower().endswith(".svg") else "png"
    data = Client(api, None).response("GET", f"/studies/{study_id}/plots/{metric}", params={"format": fmt}).content
    write_file(data, output)
    print(f"study plot ({metric}) written to {output}")


@app.command("cancel")
def cancel(study_id: IdArg, as_json: JsonOpt = False, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Cancel every unfinished point of a study (the tests recorded so far are kept)."""
    s = Client(api, token).request("POST", f"/studies/{study_id}/cancel")
    if as_json:
        print_json(s)
    else:
        print(f"study {s['id']} {s['status']}")


@app.command("delete")
def delete(study_id: IdArg, api: ApiOpt = DEFAULT_API, token: TokenOpt = None) -> None:
    """Delete a finished study, its points' campaigns and every test they recorded."""
    Client(api, token).request("DELETE", f"/studies/{study_id}")
    print(f"study {study_id} deleted")
