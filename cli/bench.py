"""``ra2vipas bench ...``: the speed benchmarks the project ships (JSON for scripts)."""

from __future__ import annotations

import statistics
import time
from typing import Annotated

import typer

from cli.output import EXIT_USAGE, fail, print_json, stdout
from services.controller.policy import ALGORITHMS

app = typer.Typer(help="Speed benchmarks (print JSON with --json).", no_args_is_help=True)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    idx = min(len(ordered) - 1, max(0, round(q / 100.0 * (len(ordered) - 1))))
    return ordered[idx]


@app.command("step")
def bench_step(
    algorithm: Annotated[str, typer.Option(help="Controller algorithm to time.")] = "ra2vipas",
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Episodes to time.")] = 10,
    seed: Annotated[int, typer.Option(min=0)] = 1,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Time one controller step (measurement in, decision out) on the paper scenario, in-process.

    Reports the median and p99 over all steps and over the last step of each test (when the
    controller holds n_test = 120 samples). Target: median <= 1 ms.
    """
    if algorithm not in ALGORITHMS:
        fail(f"unknown algorithm {algorithm!r}; choose from {', '.join(ALGORITHMS)}", EXIT_USAGE)
    from services.controller.policy import Controller, sensor_config_from_scenario
    from services.orchestrator.simulate import train_pod
    from services.protocol.scenario import build_scenario
    from services.sensors.world import SimulatedPlatform

    scenario = build_scenario("paper")
    pod = train_pod(scenario, seed)
    all_ms: list[float] = []
    last_ms: list[float] = []
    for k in range(tests):
        platform = SimulatedPlatform(scenario, seed, k)
        controller = Controller(algorithm, sensor_config_from_scenario(scenario), pod.model)
        pan = controller.first_pan()
        for t in range(scenario.steps):
            m = platform.sense(t, pan)
            started = time.perf_counter()
            decision = controller.step(m)
            elapsed = (time.perf_counter() - started) * 1e3
            all_ms.append(elapsed)
            pan = decision.next_pan_rad
        last_ms.append(elapsed)
    report = {
        "benchmark": "controller-step",
        "algorithm": algorithm,
        "tests": tests,
        "steps": len(all_ms),
        "median_ms": round(statistics.median(all_ms), 4),
        "p99_ms": round(_percentile(all_ms, 99), 4),
        "median_ms_at_n_test": round(statistics.median(last_ms), 4),
        "pod_train_seconds": round(pod.train_seconds, 4),
        "target_median_ms": 1.0,
    }
    if as_json:
        print_json(report)
    else:
        stdout.print(
            f"controller step ({algorithm}): median {report['median_ms']:.3f} ms, p99 {report['p99_ms']:.3f} ms, "
            f"median at n=120 {report['median_ms_at_n_test']:.3f} ms over {report['steps']} steps"
        )
