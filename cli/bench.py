"""``ra2vipas bench ...``: the speed benchmarks the project ships (JSON for scripts).

The harnesses are services/benchmarks/ (each returns its report); this module parses and
checks the options, hands the harnesses that need one a local stack (cli/stack.py), and prints.
"""

from __future__ import annotations

import os
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stdout
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.plots import READ_PAUSE_S
from ra2vipas.services.protocol.messages import MAX_TESTS

app = typer.Typer(help="Speed benchmarks (print JSON with --json).", no_args_is_help=True)


def _complete_policies(incomplete: str) -> list[str]:
    """Shell completion of a policy name: every installed policy (``registry.names()``)."""
    from ra2vipas.services.controller import registry

    return [n for n in registry.names() if n.startswith(incomplete)]


def _check_preset(preset: str) -> None:
    """A usage error unless ``preset`` is a scenario preset."""
    from ra2vipas.services.protocol.scenario import PRESETS

    if preset not in PRESETS:
        fail(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}", EXIT_USAGE)


def _sizes(text: str, option: str) -> list[int]:
    """Comma-separated campaign sizes (tests) of a memory benchmark; a usage error if malformed."""
    try:
        sizes = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        fail(f"{option} expects comma-separated integers, got {text!r}", EXIT_USAGE)
    bad = [n for n in sizes if not 1 <= n <= MAX_TESTS]
    if bad:
        fail(f"{option}: a campaign has 1 to {MAX_TESTS} tests, got {bad[0]}", EXIT_USAGE)
    return sizes


def _local_stack(*, rigs: int, db_path: str, log_dir: str, window: int = 8, rig_layout: str | None = None):
    """A benchmark's stack (services/benchmarks/common.py's ``StackFactory``): cli/stack.py's,
    on a free port, its services logging warnings only."""
    from ra2vipas.cli.stack import Stack, StackConfig, free_port

    layout = {"rig_layout": rig_layout} if rig_layout else {}
    return Stack(StackConfig(rigs=rigs, port=free_port(), db_path=db_path, window=window, log_dir=log_dir, log_level="WARNING", **layout))


@app.command("step")
def bench_step(
    algorithm: Annotated[str, typer.Option(help="Controller algorithm to time.")] = "ra2vipas",
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Episodes to time.")] = 10,
    seed: Annotated[int, typer.Option(min=0)] = 1,
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ...).")] = "paper",
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help=(
        "Override a scenario parameter, e.g. --set box_heights=true (repeatable; see `ra2vipas presets show paper`)."))] = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Time one controller step (measurement in, decision out) on a preset's scenario, in-process.

    Reports the median and p99 over all steps and over the last step of each test (when the
    controller holds n_test = 120 samples). Targets: median <= 1 ms; on dynamic also p99 <= 3 ms.
    """
    from ra2vipas.services.benchmarks.step import controller_step
    from ra2vipas.services.controller.registry import BUILTINS
    from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario, parse_overrides

    if algorithm not in BUILTINS:  # it times the built-ins' Controller
        fail(f"unknown algorithm {algorithm!r}; choose from {', '.join(BUILTINS)}", EXIT_USAGE)
    _check_preset(preset)
    try:
        changed = parse_overrides(overrides or [])
        build_scenario(preset, changed)
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    report = controller_step(algorithm, tests, seed, preset, changed)
    if as_json:
        print_json(report)
    else:
        stdout.print(
            f"controller step ({algorithm}): median {report['median_ms']:.3f} ms, p99 {report['p99_ms']:.3f} ms, "
            f"median at n=120 {report['median_ms_at_n_test']:.3f} ms over {report['steps']} steps"
        )


def parse_seeds(text: str) -> list[int]:
    """Campaign seeds from ``1-5``, ``1,3,7`` or both (``1-3,7``): sorted, each once. Raises
    ValueError (the message says what is wrong) for anything else (a sign included: seeds are
    non-negative) or a range that runs backwards: a benchmark over no seed would print nothing and
    succeed."""
    chosen: set[int] = set()
    for part in text.split(","):
        low, sep, high = part.strip().partition("-")
        try:
            first, last = (int(low), int(high)) if sep else (int(low), int(low))
        except ValueError:
            raise ValueError(f"expected e.g. 1-5 or 1,3,7, got {text!r}") from None
        if last < first:
            raise ValueError(f"the range {part.strip()!r} runs backwards (write {last}-{first})")
        chosen.update(range(first, last + 1))
    return sorted(chosen)


@app.command("learner")
def bench_learner(
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ble, ...).")] = "dynamic",
    seeds: Annotated[str, typer.Option(help="Campaign seeds, e.g. 1-5 or 1,3,7.")] = "1-5",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Score the POD learner on each seed's training episode: R², the RMSE against the POD the
    RSSI predicts p*(r), and the oracle fit's RMSE (issue 20). Target on dynamic: RMSE <= 1.3 x
    the oracle's on every seed."""
    from ra2vipas.services.benchmarks.learner import learner

    _check_preset(preset)
    try:
        chosen = parse_seeds(seeds)
    except ValueError as exc:
        fail(f"--seeds: {exc}", EXIT_USAGE)
    out = learner(preset, chosen)
    if as_json:
        print_json(out)
        return
    for r in out["seeds"]:
        stdout.print(f"seed {r['seed']}: R² {r['r2']:.3f}  RMSE vs p*(r) {r['rmse']:.3f}  oracle {r['oracle_rmse']:.3f}  "
                     f"({r['ratio']:.2f}x)  {r['train_seconds']:.2f} s")


@app.command("walkers")
def bench_walkers(
    preset: Annotated[str, typer.Option(help="Scenario preset (dynamic, ble-dynamic, ...).")] = "ble-dynamic",
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests of the campaign.")] = 200,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed.")] = 1,
    algorithm: Annotated[str, typer.Option("--algorithm", "-a", autocompletion=_complete_policies,
                                           help="The policy to profile: any installed one (`ra2vipas policies`) or module:Class.")] = "ra2vipas",
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help=(
        "Override a scenario parameter, e.g. --set box_heights=true (repeatable; see `ra2vipas presets show dynamic`)."))] = None,
    window: Annotated[int, typer.Option(min=1, max=10000, help="The bound's window: the last this many steps.")] = 20,
    boxed: Annotated[int, typer.Option(min=1, max=10000, help="The bound counts a walking Tx boxed in at least this many of them ...")] = 5,
    recent: Annotated[int, typer.Option(min=1, max=10000, help="... and in one of the last this many.")] = 3,
    workers: Annotated[int, typer.Option("--workers", "-w", min=0, max=256, help="Worker processes (0: one per CPU core).")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Where a policy's losses are: its final DR with a walking Tx and with a standing one, and a
    bound on what naming a walker among the people the camera saw would reach at the pans the
    policy chose (every walking Tx boxed in at least --boxed of the last --window steps and in one
    of the last --recent counted right; docs/radio.md). Ground truth scores the episodes
    afterwards; the policy sees only measurements. ~17 s for 200 tests of ble-dynamic on 2 cores.

    Example:

        ra2vipas bench walkers --preset dynamic --set box_heights=true --tests 200 --seed 1
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ra2vipas.cli.output import stderr
    from ra2vipas.services.benchmarks import walkers
    from ra2vipas.services.protocol.scenario import ScenarioError, parse_overrides

    _check_preset(preset)
    try:
        changed = parse_overrides(overrides or [])
        walkers.validate(preset, changed, algorithm, window, boxed, recent)  # before the bar shows (run checks again, for its API callers)
        with Progress(TextColumn("[bold]walkers[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("tests"), TimeElapsedColumn(),
                      console=stderr, transient=True) as bar:
            task = bar.add_task("tests", total=tests)
            report = walkers.run(preset, tests, seed, algorithm, changed, workers or None,
                                 lambda done, total: bar.update(task, completed=done), window=window, boxed=boxed, recent=recent)
    except (ScenarioError, ValueError) as err:  # a bad parameter, an unknown policy (registry.UnknownPolicy), a bad window
        fail(str(err), EXIT_USAGE)
    if as_json:
        print_json(report)
        return
    w, s, b = report["walking"], report["standing"], report["bound"]

    def part(block: dict) -> str:
        return f"{block['dr']:.3f} of {block['tests']}" if block["tests"] else "none"

    stdout.print(f"{report['algorithm']} on {preset}, seed {seed}, {tests} tests: DR {report['dr']:.3f}; "
                 f"walking Tx {part(w)}, standing Tx {part(s)}")
    stdout.print(f"bound (a walking Tx boxed in >= {b['boxed']} of the last {b['window']} steps and in one of the last "
                 f"{b['recent']} named right; {b['walking_tests_boxed']} such tests): DR {b['dr']:.3f}")


@app.command("mesh")
def bench_mesh(
    rigs: Annotated[int, typer.Option("--rig-count", min=0, max=16, help="Sensor+controller pairs for fast mode (0: one per CPU core).")] = 0,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=0, max=16)] = None,
    window: Annotated[int, typer.Option(min=1, max=256, help="Episodes in flight per rig.")] = 8,
    tests: Annotated[int, typer.Option(min=0, max=1000, help="Tests of the fast-mode campaign (0: skip).")] = 50,
    realtime_tests: Annotated[int, typer.Option(min=0, max=64, help="Tests of the realtime campaign (0: skip); 8 tests give ~950 samples, so p99 rests on ~10 of them.")] = 8,
    memory_tests: Annotated[str, typer.Option(help="Campaign sizes whose orchestrator peak memory to measure, comma-separated, e.g. 1000,10000 (default: none).")] = "",
    memory_steps: Annotated[int, typer.Option(min=1, max=1000, help="n_test of the memory campaigns (short, so 10 000 tests take minutes).")] = 20,
    memory_algorithm: Annotated[str, typer.Option(help="The algorithm of the memory campaigns.")] = "rapas",
    preset: Annotated[str, typer.Option(help="Scenario preset of the fast and realtime campaigns (paper, dynamic, ...).")] = "paper",
    inprocess: Annotated[bool, typer.Option(help="Also run the fast campaign in-process on one worker: mesh_over_inprocess.")] = True,
    rig_layout: Annotated[str, typer.Option("--rig-layout", help="How the rigs run (as `ra2vipas up --rig-layout`): one-process, split, or both (each measured in turn; the top-level figures are one-process's, by_layout has both).")] = "one-process",
    realtime_beside_busy: Annotated[bool, typer.Option("--realtime-beside-busy/--realtime-alone", help="Run the realtime campaign on rig-1 of a two-rig stack while rig-2 runs fast campaigns throughout (the machine as a busy neighbour leaves it), or on a rig alone.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Start local stacks and measure them through the real processes.

    Rigs run as `ra2vipas up` runs them (--rig-layout one-process: a rig's sensors and
    controller in one process on one Zenoh session; split: two processes per rig; both: each
    layout measured in turn, the top-level figures one-process's, ``by_layout`` both; the report
    names the layout in ``rig_layout``).
    Fast mode: the PRESET campaign (TESTS tests x ra2vipas, rapas, ravipas x 120 steps) in
    lockstep on RIG_COUNT rigs; reports control steps per second (target >= 2 200 on 2 cores
    for paper, >= 2 000 for dynamic).
    Realtime mode: REALTIME_TESTS tests paced at T_RF on one rig (one platform in the loop),
    by default on rig-1 of a two-rig stack while rig-2 runs fast campaigns of the same preset
    throughout (``realtime.beside_busy_rig`` says how fast it went meanwhile); with
    --realtime-alone on a rig alone (with --rig-count 1, on the fast campaign's stack after it).
    Reports the sample-to-command latency p50/p99 measured by the sensors (targets p50 <= 1 ms,
    p99 <= 3 ms). Both report ``step_breakdown``: per step, each service's time queued on its event
    loop, decoding and validating, computing, encoding and publishing, as the services measured
    it, and the transport between them (services/transport/costs.py). The fast campaign is
    also run in-process on one worker: ``mesh_over_inprocess`` is mesh steps/s over that
    (``--no-inprocess`` skips it). ``cpu_ms_per_step`` is the CPU one control step of the fast
    campaign cost each service (summed over rigs; from the first episode on), and
    ``cpu_efficiency`` the in-process step's CPU over the mesh's: what a mesh core does of what
    an in-process core does, a ratio the machine's other load hardly moves. Memory (with --memory-tests): one campaign of each size (MEMORY_STEPS steps,
    MEMORY_ALGORITHM) on RIG_COUNT rigs, each on a fresh stack; reports the orchestrator
    process's peak resident memory (VmHWM) and its resident memory before and after (VmRSS).
    Every stack is stopped afterwards.

    Examples:

        ra2vipas bench mesh --json

        ra2vipas bench mesh --preset dynamic --realtime-tests 0 --json

        ra2vipas bench mesh --rig-layout both --json

        ra2vipas bench mesh --tests 0 --realtime-tests 0 --memory-tests 1000,10000 --json
    """
    from ra2vipas.services.benchmarks.mesh import mesh
    from ra2vipas.services.controller import registry

    if memory_algorithm not in registry.names():
        fail(f"unknown algorithm {memory_algorithm!r}; choose from {', '.join(registry.names())}", EXIT_USAGE)
    _check_preset(preset)
    sizes = _sizes(memory_tests, "--memory-tests")
    from ra2vipas.cli.stack import RIG_LAYOUTS

    if rig_layout not in (*RIG_LAYOUTS, "both"):
        fail(f"--rig-layout: unknown layout {rig_layout!r}; choose from {', '.join(RIG_LAYOUTS)}, both", EXIT_USAGE)
    layouts = RIG_LAYOUTS if rig_layout == "both" else (rig_layout,)
    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count") or max(1, min(os.cpu_count() or 1, 16))
    try:
        report = mesh(_local_stack, rigs=rigs, window=window, tests=tests, realtime_tests=realtime_tests, memory_tests=sizes,
                      memory_steps=memory_steps, memory_algorithm=memory_algorithm, preset=preset, inprocess=inprocess,
                      rig_layouts=layouts, realtime_beside_busy=realtime_beside_busy)
    except BenchmarkError as err:
        fail(str(err))
    if as_json:
        print_json(report)
        return
    if tests or realtime_tests:
        for layout, part in (report.get("by_layout") or {report["rig_layout"]: report}).items():
            lat = part["latency_ms"] or {}
            busy = (part.get("realtime") or {}).get("beside_busy_rig")
            beside = f", beside {busy['rig']} at {busy['steps_per_second']} steps/s" if busy else ""
            stdout.print(f"mesh ({rigs} {layout} rigs): {part['steps_per_second']} control steps/s in fast mode (target 2200), "
                         f"{part.get('mesh_over_inprocess')} x in-process on 1 worker; realtime sample->command latency p50 "
                         f"{lat.get('p50')} ms, p99 {lat.get('p99')} ms (targets 1 and 3){beside}")
    b = (report.get("fast") or {}).get("step_breakdown") or {}
    if b.get("step_ms") is not None:
        c = b["controller"]
        stdout.print(f"per step: controller busy {b['controller_busy_ms']} ms (compute {c['compute_ms']}, publish {c['publish_ms']}, "
                     f"decode {c['decode_ms']}, encode {c['encode_ms']}), sensors busy {b['sensors_busy_ms']} ms, transport "
                     f"{b['transport_ms']} ms; mesh over in-process (1 worker): {report.get('mesh_over_inprocess')}")
    for m in report.get("memory") or []:
        stdout.print(f"{m['tests']} tests ({m['steps']} steps, {m['algorithm']}, {rigs} rigs): orchestrator peak RSS "
                     f"{m['orchestrator_peak_rss_mb']} MB ({m['orchestrator_rss_before_mb']} MB before the campaign, "
                     f"{m['orchestrator_rss_after_mb']} MB after), {m['seconds']} s")


@app.command("orchestrator")
def bench_orchestrator(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests of the campaign (x 3 algorithms = episodes).")] = 1000,
    rig_count: Annotated[int, typer.Option(min=1, max=64, help="Fake rigs answering episodes.")] = 4,
    window: Annotated[int, typer.Option(min=1, max=1024, help="Episodes in flight per rig.")] = 64,
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ...).")] = "paper",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """How many episodes one orchestrator scores and stores per second, with rigs faked at the
    wire level (services/rigs/instant.py: each EpisodeStart is answered at once by a
    precomputed EpisodeTruth and EpisodeResult), so nothing but the orchestrator does real work.

    Starts a stack without rigs (router, learner, orchestrator), joins it with RIG_COUNT
    instant rigs in this process and runs the PRESET campaign (TESTS tests x ra2vipas, rapas,
    ravipas). Reports ``episodes_per_second`` (the campaign's steps/s over its n_test: episodes
    over the orchestrator's own time from the campaign's first episode to its last, after
    training; target >= 1 000 for paper episodes), and the orchestrator's and the fake rigs'
    CPU use while it ran (in cores, polled every 0.25 s; 1.0 = one core: the orchestrator's
    scheduler thread, holding the GIL, saturates about there).

    Example:

        ra2vipas bench orchestrator --json
    """
    from ra2vipas.services.benchmarks.orchestrator import orchestrator

    _check_preset(preset)
    try:
        report = orchestrator(_local_stack, tests=tests, rig_count=rig_count, window=window, preset=preset)
    except BenchmarkError as err:
        fail(str(err))
    if as_json:
        print_json(report)
        return
    stdout.print(f"orchestrator: {report['episodes_per_second']} {preset} episodes/s scored and stored ({report['episodes']} episodes, "
                 f"{rig_count} instant rigs x {window} in flight; target 1000); orchestrator CPU {report['orchestrator_cpu']} cores, "
                 f"fake rigs {report['fake_rigs_cpu']}")


@app.command("plots")
def bench_plots(
    clients: Annotated[int, typer.Option(min=1, max=500, help="Concurrent plot clients.")] = 50,
    readers: Annotated[int, typer.Option(min=1, max=64, help="Clients reading non-plot routes, each pausing "
                                                             f"{READ_PAUSE_S} s between requests.")] = 4,
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Tests of the measured campaign (paper preset, "
                                                             "ra2vipas, rapas, ravipas).")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the measured campaign.")] = 1,
    repeats: Annotated[int, typer.Option(min=1, max=10, help="Runs of the campaign without and with plot load, "
                                                             "alternating.")] = 3,
    fixtures: Annotated[int, typer.Option(min=1, max=10, help="Finished campaigns whose figures the plot clients ask for.")] = 2,
    fixture_tests: Annotated[int, typer.Option(min=1, max=1000, help="Tests of each finished campaign.")] = 20,
    rigs: Annotated[int, typer.Option("--rig-count", min=0, max=16, help="Rigs (0: one per CPU core).")] = 0,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=0, max=16)] = None,
    retry_cap: Annotated[float, typer.Option(min=0.0, max=60.0, help="Longest wait of a plot client after a 503 "
                                                                     "(it honours Retry-After up to this).")] = 1.0,
    client_nice: Annotated[int, typer.Option(min=0, max=19, help="Niceness of the plot clients' process (0: they compete "
                                                                 "for the CPU like the tester's clients did).")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Plots under load: start a local stack, finish FIXTURES campaigns, then run the paper
    campaign REPEATS times without and with CLIENTS plot clients asking for those campaigns'
    figures (DR, POD and every episode, PNG and SVG: most are not cached yet), while READERS
    clients read /campaigns, /campaigns/{id}, /campaigns/{id}/results and /health.

    Reports the p99 latency of those reads under plot load (target <= 200 ms) and how much the
    plot load slows the campaign: median control steps/s without over with, minus 1 (target
    <= 10 %). Every process is stopped afterwards.
    """
    from ra2vipas.services.benchmarks.plots import plots

    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count") or max(1, min(os.cpu_count() or 1, 16))
    try:
        report = plots(_local_stack, clients=clients, readers=readers, tests=tests, seed=seed, repeats=repeats,
                       fixtures=fixtures, fixture_tests=fixture_tests, rigs=rigs, retry_cap=retry_cap, client_nice=client_nice)
    except BenchmarkError as err:
        fail(str(err))
    if as_json:
        print_json(report)
    else:
        base, loaded = report["without_plots"], report["with_plots"]
        stdout.print(f"non-plot reads under {clients} plot clients: p99 {report['read_p99_ms']} ms (target <= 200; "
                     f"{base['read_p99_ms']} ms without plots); campaign {base['steps_per_second']} -> "
                     f"{loaded['steps_per_second']} control steps/s: slowdown {report['slowdown_pct']} % (target <= 10)")


@app.command("robustness")
def bench_robustness(
    tests: Annotated[int, typer.Option(min=2, max=MAX_TESTS, help="Paired tests per scenario.")] = 200,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed of every scenario.")] = 1,
    scenario: Annotated[Optional[list[str]], typer.Option("--scenario", help="Run only these scenarios (repeatable; default: all).")] = None,
    workers: Annotated[int, typer.Option(min=0, max=256, help="Worker processes (0: one per CPU core).")] = 0,
    algorithm: Annotated[Optional[list[str]], typer.Option("--algorithm", "-a", autocompletion=_complete_policies,
                                                           help="Add this policy's column and its paired difference against "
                                                                "Ra²ViPAS (repeatable): any installed policy (`ra2vipas policies`) "
                                                                "or module:Class.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Every algorithm on a spread of worlds (placement, crowds, noise, antenna shapes and
    models, fields of view, frame rates, clutter, walkers), paired test by test, beside the
    oracle reference (the Bayes-MAP choice given the true model, the true trajectories and a
    sweep's measurements: a bound, never a controller input).

    Per scenario: final DR of each algorithm with its Wilson 95 % interval, the paired
    difference Ra²ViPAS - best single cue with its 95 % interval (requirement: upper bound >= 0),
    and Ra²ViPAS / oracle. Takes minutes: ~20 scenarios x 200 tests x 4 algorithms. Each
    --algorithm adds that policy's column and Ra²ViPAS - it, paired the same way (with
    McNemar's exact p in --json); the other columns do not change.

    Example:

        ra2vipas bench robustness --algorithm greedy --scenario paper --scenario clutter
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ra2vipas.cli.output import stderr
    from ra2vipas.services.orchestrator import robustness

    try:
        with Progress(TextColumn("[bold]robustness[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("tests"), TimeElapsedColumn(),
                      console=stderr, transient=True) as bar:
            task = bar.add_task("tests", total=tests * len(scenario or robustness.SCENARIOS))
            report = robustness.run(tests, seed, scenario, workers or None, lambda done, total: bar.update(task, completed=done),
                                    algorithms=algorithm or ())
    except ValueError as err:  # an unknown scenario or policy (registry.UnknownPolicy)
        fail(str(err), EXIT_USAGE)
    if as_json:
        print_json(report)
        return
    from rich.table import Table

    columns = report.get("algorithms", robustness.ALGORITHMS)
    others = [a for a in columns if a not in robustness.ALGORITHMS]
    table = Table(title=f"Robustness: {tests} paired tests per scenario, seed {seed}; DR at the horizon")
    for col in ("scenario", *columns, "oracle", "Ra²ViPAS - best cue [95% CI]", *(f"Ra²ViPAS - {a} [95% CI]" for a in others),
                "Ra²ViPAS/oracle"):
        table.add_column(col, justify="left" if col == "scenario" else "right")

    def difference(d: dict, versus: str = "") -> str:
        lo, hi = d["difference_ci95"]
        return f"{d['difference']:+.3f} [{lo:+.3f}, {hi:+.3f}]{versus}" + ("" if d["not_worse"] else " ✗")

    for name, s in report["scenarios"].items():
        table.add_row(name, *(f"{s['dr'][a]:.3f}" if a in s["dr"] else "—" for a in (*columns, "oracle")), difference(s, f" vs {s['best_single_cue']}"),
                      *(difference(s["versus_ra2vipas"][a]) for a in others),
                      "—" if s["ra2vipas_over_oracle"] is None else f"{s['ra2vipas_over_oracle']:.3f}")
    stdout.print(table)
    for name, found in (report.get("policies") or {}).items():
        stdout.print(f"{name}: {found['package']} {found['version']}")


@app.command("calibrate")
def bench_calibrate(
    tests: Annotated[int, typer.Option(min=2, max=MAX_TESTS, help="Tests per scenario.")] = 40,
    seed: Annotated[int, typer.Option(min=0, help="Seed (use one no benchmark uses).")] = 1001,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated subset of: ra2vipas, rapas, ravipas, sweep (default: all); each map is fitted on its own runs, so a subset prints the same maps.")] = None,
    from_s: Annotated[float, typer.Option("--from-s", min=0.0, max=60.0, help="Fit on the steps whose sample is taken this many seconds or more after the start (0: every step).")] = 0.0,
    workers: Annotated[Optional[int], typer.Option(min=1, max=1024, help="Worker processes running the scenarios (default: the CPU count); the maps do not depend on it.")] = None,
    scenarios: Annotated[Optional[str], typer.Option("--scenarios", help="Comma-separated subset of the fitting worlds (default: all of paper, paper-uniform, crowd-40, noise-6dB, db-gain, wide-lobe, fov-45, nu-3, dynamic, dynamic-static): fit on the worlds you deploy in. The shipped maps use all of them, so --write refuses a subset.")] = None,
    write: Annotated[bool, typer.Option("--write", help="Write the maps into the shipped file (services/controller/data/confidence_maps.json), one named coefficient each, with this command.")] = False,
    joint: Annotated[bool, typer.Option("--joint", help="Fit the maps of the searches for several tags at once (issue 21; named ALGORITHM-joint), on every tag's steps in worlds with 2-3 tags.")] = False,
    adverts: Annotated[bool, typer.Option("--adverts", help="Fit the maps of a rig of BLE advertisements (protocol 1.3; named ALGORITHM-adverts, used when the rig's radio is adverts) on the BLE worlds: ble, ble-uniform, ble-dynamic, ble-dynamic-static, ble-recorded (--scenarios chooses among these); with --joint, ALGORITHM-joint-adverts on those worlds with 2-3 tags.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Refit the controllers' confidence maps (Platt scaling with covariates the controller
    measures: how likely the Tx walks, the fading correlation, the clutter density, the crowding
    around the answer) on a mix of simulated scenarios, and print them with the expected
    calibration error before and after. The shipped maps (services/controller/data/confidence_maps.json)
    come from `ra2vipas bench calibrate --tests 40 --seed 1001 --write` (Ra²ViPAS's with `--from-s 3`), and those of a
    rig of BLE advertisements from the same with `--adverts`."""
    from ra2vipas.cli.output import stderr
    from ra2vipas.cli.simulate import parse_algorithms
    from ra2vipas.services.orchestrator.calibration import PACKET_SCENARIOS, SCENARIOS, calibrate
    from ra2vipas.services.protocol.scenario import ScenarioError

    try:
        names = parse_algorithms(algorithms)
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    table = PACKET_SCENARIOS if adverts else SCENARIOS
    worlds = list(table)
    if joint and scenarios is not None:
        fail("--scenarios chooses among the single-tag worlds; --joint fits on its own (drop one of them)", EXIT_USAGE)
    if scenarios is not None:
        worlds = list(dict.fromkeys(w.strip() for w in scenarios.split(",") if w.strip()))
        unknown = [w for w in worlds if w not in table]
        if unknown or not worlds:
            fail(f"--scenarios: unknown world(s) {', '.join(map(repr, unknown)) or '(none given)'}; choose among {', '.join(table)}",
                 EXIT_USAGE)
        if write and worlds != list(table):
            fail("--write ships maps fitted on every world: drop --scenarios (or keep the map printed, without --write)", EXIT_USAGE)
    report = calibrate(names, tests, seed, progress=lambda what: stderr.print(f"calibrate: {what}"), from_s=from_s,
                       workers=workers or os.cpu_count() or 1, scenarios=worlds, joint=joint, adverts=adverts)
    if write:
        from ra2vipas.services.controller.confidence import MAPS_FILE, write_maps

        write_maps(report)
        stderr.print(f"calibrate: wrote {', '.join(report['algorithms'])} into {MAPS_FILE}")
    if as_json:
        print_json(report)
    else:
        for name, a in report["algorithms"].items():
            stdout.print(f"{name}: map {tuple(a['map'])}; ECE {a['ece_raw']} -> {a['ece_fitted']} over {a['samples']} steps")


@app.command("dashboard")
def bench_dashboard(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests per algorithm of the synthetic finished campaign (4 algorithms, 120 steps).")] = 10000,
    repeats: Annotated[int, typer.Option(min=1, max=1000, help="Requests per page for the server's render time.")] = 10,
    chromium: Annotated[Optional[str], typer.Option(envvar="RA2VIPAS_CHROMIUM", help="Chromium executable for first paint and page weight.")] = "/usr/bin/chromium",
    no_browser: Annotated[bool, typer.Option("--no-browser", help="Time the server only.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """The dashboard's pages: server render time (the campaign page of a 10 000-test campaign:
    target < 1 s), and in a headless Chromium first paint, load and page weight, cold and warm."""
    from pathlib import Path

    from ra2vipas.services.benchmarks import dashboard

    if not no_browser and (not chromium or not Path(chromium).exists()):
        fail(f"no Chromium at {chromium!r} (install the Debian package chromium, set --chromium, or use --no-browser)", EXIT_USAGE)
    report = dashboard.run(tests=tests, repeats=repeats, chromium=None if no_browser else chromium)
    if as_json:
        print_json(report)
        return
    for name, s in report["server"].items():
        stdout.print(f"{name:42s} server p50 {s['p50_ms']:7.1f} ms  p95 {s['p95_ms']:7.1f} ms  {s['bytes'] / 1024:7.1f} KiB")
    for name, b in (report["browser"] or {}).items():
        if isinstance(b, dict):
            c = b["cold"]
            stdout.print(f"{name:42s} first paint {c['first_paint_ms']} ms, load {c['load_ms']} ms, "
                         f"{c['transferred_bytes'] / 1024:.1f} KiB in {c['requests']} requests (cold)")


@app.command("simulate")
def bench_simulate(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests of the speed campaign (paper scenario, every algorithm).")] = 30,
    workers: Annotated[int, typer.Option(min=0, max=1024, help="Workers of the parallel run (0: one per CPU core).")] = 0,
    seed: Annotated[int, typer.Option(min=0)] = 1,
    memory_tests: Annotated[str, typer.Option(help="Campaign sizes whose peak memory to measure, comma-separated ('' for none).")] = "1000,10000",
    memory_steps: Annotated[int, typer.Option(min=1, max=1000, help="n_test of the memory campaigns (short, so 10 000 tests take minutes, not an hour).")] = 20,
    memory_algorithm: Annotated[str, typer.Option(help="The algorithm of the memory campaigns.")] = "rapas",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """`ra2vipas simulate` on one core and on every core, in the same run: steps/s of each, the
    speedup, and whether the two results objects are identical (they must be), beside
    ``cpu_loop_speedup``: what a pure CPU loop gains on as many processes just before and just
    after (the ceiling the machine's other load leaves; N on an idle N-core machine). Then the peak
    resident memory of campaigns of 1 000 and 10 000 tests, each in a fresh process: flat,
    because outcomes are reduced as they arrive and no per-step trace is kept.

    Target: speedup >= 1.7 on 2 cores. Timings are wall-clock: other load on the machine lowers them.
    """
    from ra2vipas.services.benchmarks.simulate import simulate
    from ra2vipas.services.controller import registry

    if memory_algorithm not in registry.names():
        fail(f"unknown algorithm {memory_algorithm!r}; choose from {', '.join(registry.names())}", EXIT_USAGE)
    sizes = _sizes(memory_tests, "--memory-tests")
    try:
        report = simulate(tests, workers, seed, sizes, memory_steps, memory_algorithm)
    except BenchmarkError as err:
        fail(str(err))
    if as_json:
        print_json(report)
        return
    stdout.print(f"simulate, paper scenario, {tests} tests x {len(registry.BUILTINS)} algorithms ({report['steps']} steps): "
                 f"{report['steps_per_second_1']:.0f} steps/s on 1 worker, {report['steps_per_second_n']:.0f} on {report['workers']}: "
                 f"speedup {report['speedup']} (a CPU loop: {report['cpu_loop_speedup']}); results identical: {report['identical']}")
    for m in report["memory"]:
        stdout.print(f"{m['tests']} tests ({m['steps']} steps, {m['algorithm']}, {m['workers']} workers): peak RSS "
                     f"{m['parent_peak_rss_mb']} MB (parent, {m['parent_rss_growth_mb']:+} MB during the run), {m['worker_peak_rss_mb']} MB "
                     f"(largest worker), {m['seconds']} s")
