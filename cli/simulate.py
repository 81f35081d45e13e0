"""``ra2vipas simulate``: the whole Monte Carlo campaign in this process, no network."""

from __future__ import annotations

import sys
import time
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from ra2vipas.cli.output import EXIT_USAGE, check_output, emit_results, fail, print_json, print_results, stderr
from ra2vipas.services.controller import registry
from ra2vipas.services.protocol.messages import MAX_TESTS
from ra2vipas.services.protocol.scenario import PRESETS, ScenarioError, build_scenario, parse_overrides


def parse_algorithms(value: str | None) -> list[str]:
    """``a,b`` -> ["a", "b"]: installed policies (``ra2vipas.policies`` entry points, the
    built-ins among them) or ``module:Class``, order kept, duplicates dropped."""
    if value is None or not value.strip():
        return list(registry.BUILTINS)
    try:
        return registry.check([raw.strip() for raw in value.split(",")])
    except registry.UnknownPolicy as err:
        raise ScenarioError(str(err)) from None


def simulate(
    preset: Annotated[str, typer.Option(help=f"Scenario preset: {', '.join(PRESETS)}.")] = "paper",
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Monte Carlo tests per algorithm (N_tests).")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed; fixes every random draw of every test.")] = 1,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated pointing policies: the built-ins " + ", ".join(registry.BUILTINS) + " (default: all four), any installed policy (`ra2vipas policies`), or module:Class.")] = None,
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help="Override a scenario parameter, e.g. --set n_targets=30 (repeatable; see `ra2vipas presets show paper`).")] = None,
    stop_confidence: Annotated[float, typer.Option("--stop-confidence", min=0.0, max=0.999999, help="End each episode at the first step whose confidence reaches this, its answer final (0: off); the results then report accuracy and time to decision.")] = 0.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print the results object as one JSON line (last line of stdout).")] = False,
    plot: Annotated[Optional[str], typer.Option(metavar="FILE", help="Write the DR curves with 95% bands to FILE (.png or .svg).")] = None,
    reliability_plot: Annotated[Optional[str], typer.Option("--reliability-plot", metavar="FILE", help="Write the reliability diagram of the final confidences to FILE (.png or .svg).")] = None,
    vary: Annotated[Optional[list[str]], typer.Option("--vary", metavar="NAME=a,b,c|NAME=a:b:step", help="Run a parameter study instead: vary a scenario parameter over a list or an inclusive range (repeatable: the grid is the product); prints one row per point x algorithm, and --plot draws the final DR against it.")] = None,
    workers: Annotated[int, typer.Option("--workers", "-w", min=0, max=1024, help="Processes to run the tests on (0: one per CPU core, fewer for a campaign too small to pay for starting them: one per ~10 000 control steps). Results are identical for any number.")] = 0,
) -> None:
    """Run the Monte Carlo campaign in-process and print the discovery-rate table.

    Trains the POD model once from the self-supervised training episode, runs every test of
    every algorithm on its own seeded world, on every core, and scores DR_t by the paper's
    association rule. With --vary, runs a parameter study: one campaign per grid point, all
    with the same seed.

    Examples:

        ra2vipas simulate --preset paper --tests 200 --seed 1 --plot dr.png

        ra2vipas simulate --set n_targets=30 --set antenna_model=db-gain -a ra2vipas,rapas --json

        ra2vipas simulate --vary n_targets=10,20,40 --tests 100 --plot crowd.png
    """
    try:
        names = parse_algorithms(algorithms)
        scenario = build_scenario(preset, parse_overrides(overrides or []))
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    for option, value in (("--plot", plot), ("--reliability-plot", reliability_plot)):
        if value is not None and not value.lower().endswith((".png", ".svg")):
            fail(f"{option} expects a .png or .svg file name, got {value!r}", EXIT_USAGE)

    for option, value in (("--plot", plot), ("--reliability-plot", reliability_plot)):
        check_output(value, option)  # before any test runs: a bad path must not throw finished work away

    if vary:
        _study(preset, tests, seed, names, overrides, stop_confidence, as_json, plot, reliability_plot, vary, workers)
        return

    from ra2vipas.services.orchestrator.simulate import pod_is_cached

    total = tests * len(names)
    if pod_is_cached(scenario, seed):
        print(f"the POD model of ({preset}, seed {seed}) is in the POD model cache (RA2VIPAS_POD_CACHE=off trains it again); "
              f"running {total} episodes", file=sys.stderr, flush=True)
    else:
        say_training(f"the POD model on {scenario.n_train} self-supervised samples ({preset}, seed {seed}), then {total} episodes")
    started = time.monotonic()

    from ra2vipas.services.orchestrator.engine import Interrupted
    from ra2vipas.services.orchestrator.simulate import run_campaign

    with Progress(
        TextColumn("[bold]simulate[/] {task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TimeRemainingColumn(), console=stderr, transient=True,
    ) as bar:
        task = bar.add_task("training the POD model", total=None)

        def trained(pod) -> None:
            done = (f"POD model loaded (R² {pod.r2:.4f}; its training took {pod.train_seconds:.1f} s)" if pod.cached
                    else f"POD model trained (R² {pod.r2:.4f}) after {time.monotonic() - started:.1f} s")
            bar.console.print(f"{done}; running {total} episodes", markup=False, highlight=False)
            bar.update(task, description="episodes", total=total, completed=0)

        try:
            results = run_campaign(preset, scenario, tests, seed, names, progress=lambda done, _: bar.update(task, completed=done),
                                   stop_confidence=stop_confidence, workers=workers or None, on_trained=trained)
        except ScenarioError as err:
            fail(str(err))
        except Interrupted as stop:
            bar.stop()
            _interrupted(stop, as_json)
    if reliability_plot:
        from ra2vipas.services.orchestrator.plots import write_reliability_plot

        try:
            write_reliability_plot(results, reliability_plot)
        except OSError as err:
            fail(f"cannot write {reliability_plot}: {err.strerror or err}")
    emit_results(results, plot, as_json)


def say_training(what: str) -> None:
    """Say at once (also when stderr is not a terminal) what the first seconds are spent on."""
    print(f"training {what}; a first run on this machine also compiles the numerical kernels "
          "(up to a minute; cached afterwards)", file=sys.stderr, flush=True)


def _interrupted(stop, as_json: bool) -> None:
    """Ctrl-C: print the results of the tests finished so far, marked partial (no figure), and
    exit 130."""
    partial = stop.report.results[0] if stop.report is not None else None
    if partial is not None:
        if as_json:
            print_json(partial)
        else:
            print_results(partial)
    recorded = sum((partial or {}).get("tests_recorded", {}).values())
    shown = f"the results above are partial ({recorded} of {stop.total} episodes)" if partial else "no test had finished"
    print(f"interrupted after {stop.done} of {stop.total} episodes: {shown}", file=sys.stderr)
    raise typer.Exit(130)


def _study(preset: str, tests: int, seed: int, names: list[str], overrides: list[str] | None, stop_confidence: float,
           as_json: bool, plot: str | None, reliability_plot: str | None, vary: list[str], workers: int) -> None:
    """``simulate --vary``: the study in this process, printed like ``ra2vipas study results``."""
    from ra2vipas.cli.study import emit_study, parse_vary_options
    from ra2vipas.services.orchestrator.engine import Interrupted, run_study
    from ra2vipas.services.orchestrator.study import StudyError

    if reliability_plot:
        fail("--reliability-plot draws one campaign; with --vary use --plot (the final DR against the varied parameters)",
             EXIT_USAGE)
    try:
        grid = parse_vary_options(vary)
        base = parse_overrides(overrides or [])
        if len(grid) > 2 and plot:
            raise StudyError(f"--plot shows one or two varied parameters; {len(grid)} are varied")
        say_training(f"the POD model of each point on {build_scenario(preset, base).n_train} self-supervised samples, then its episodes")
        with Progress(
            TextColumn("[bold]study[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("episodes"),
            TimeElapsedColumn(), TimeRemainingColumn(), console=stderr, transient=True,
        ) as bar:
            task = bar.add_task("episodes", total=None)
            try:
                results = run_study(preset, base, grid, tests, seed, names, stop_confidence, workers=workers or None,
                                    progress=lambda done, total: bar.update(task, completed=done, total=total))
            except Interrupted as stop:
                bar.stop()
                if stop.study is not None and stop.study["rows"]:
                    emit_study(stop.study, None, as_json)
                shown = "the rows above are partial (the tests finished so far)" if stop.study and stop.study["rows"] else \
                    "no test had finished"
                print(f"interrupted after {stop.done} of {stop.total} episodes: {shown}", file=sys.stderr)
                raise typer.Exit(130) from None
    except (ScenarioError, StudyError) as err:
        fail(str(err), EXIT_USAGE)
    emit_study(results, plot, as_json)
