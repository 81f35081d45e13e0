"""``ra2vipas bench ...``: the speed benchmarks the project ships (JSON for scripts)."""

from __future__ import annotations

import statistics
import time
from typing import Annotated

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stdout

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
    from ra2vipas.services.controller.policy import ALGORITHMS

    if algorithm not in ALGORITHMS:
        fail(f"unknown algorithm {algorithm!r}; choose from {', '.join(ALGORITHMS)}", EXIT_USAGE)
    from ra2vipas.services.controller.policy import Controller, sensor_config_from_scenario
    from ra2vipas.services.orchestrator.simulate import train_pod
    from ra2vipas.services.protocol.scenario import build_scenario
    from ra2vipas.services.sensors.world import SimulatedPlatform

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


def _run_campaign(api: str, body: dict, timeout: float, poll: float = 0.1) -> tuple[dict, float]:
    import httpx

    started = time.perf_counter()
    c = httpx.post(f"{api}/campaigns", json=body, timeout=30).json()
    deadline = time.monotonic() + timeout
    while c["status"] not in ("done", "failed", "cancelled"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"campaign {c['id']} did not finish within {timeout:.0f} s")
        time.sleep(poll)
        c = httpx.get(f"{api}/campaigns/{c['id']}", timeout=30).json()
    wall = time.perf_counter() - started
    if c["status"] != "done":
        raise RuntimeError(f"campaign {c['id']} {c['status']}: {c.get('error')}")
    return httpx.get(f"{api}/campaigns/{c['id']}/results", timeout=30).json(), wall


@app.command("mesh")
def bench_mesh(
    rigs: Annotated[int, typer.Option(min=0, max=16, help="Sensor+controller pairs for fast mode (0: one per CPU core).")] = 0,
    window: Annotated[int, typer.Option(min=1, max=256, help="Episodes in flight per rig.")] = 8,
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Tests of the fast-mode campaign.")] = 50,
    realtime_tests: Annotated[int, typer.Option(min=0, max=64, help="Tests of the realtime campaign (0: skip); 8 tests give ~950 samples, so p99 rests on ~10 of them.")] = 8,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Start local stacks and measure them through the real processes.

    Fast mode: the paper campaign (TESTS tests x ra2vipas, rapas, ravipas x 120 steps) in
    lockstep on RIGS rigs; reports control steps per second (target >= 2 200 on 2 cores).
    Realtime mode: REALTIME_TESTS tests paced at T_RF on one rig (one platform in the loop);
    reports the sample-to-command latency p50/p99 measured by the sensors (target p99 <= 5
    ms). Every stack is stopped afterwards.
    """
    import os
    import tempfile

    from ra2vipas.cli.stack import Stack, StackConfig, StackError, free_port

    rigs = rigs or max(1, min(os.cpu_count() or 1, 16))
    algorithms = ["ra2vipas", "rapas", "ravipas"]
    report: dict = {"benchmark": "mesh", "rigs": rigs, "window": window, "targets": {"steps_per_second": 2200, "latency_p99_ms": 5.0}}
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:

        def stack_of(n: int, name: str) -> Stack:
            return Stack(StackConfig(rigs=n, port=free_port(), db_path=os.path.join(tmp, f"{name}.db"), window=window,
                                     log_dir=os.path.join(tmp, f"logs-{name}"), log_level="WARNING"))

        stack = stack_of(rigs, "fast")
        try:
            stack.start()
            fast, fast_wall = _run_campaign(stack.api_url, {"preset": "paper", "tests": tests, "seed": 1, "algorithms": algorithms}, 1800)
            report["fast"] = {
                "tests": tests, "algorithms": algorithms, "steps": tests * len(algorithms) * fast["scenario"]["steps"],
                "steps_per_second": fast["steps_per_second"], "wall_seconds_with_training": round(fast_wall, 3),
                "dr_final": {a: b["dr_final"] for a, b in fast["algorithms"].items()},
            }
            report["steps_per_second"] = fast["steps_per_second"]
        except (StackError, TimeoutError, RuntimeError) as err:
            fail(f"bench mesh (fast): {err}")
        finally:
            stack.stop()
        report["latency_ms"] = None
        if realtime_tests:
            stack = stack_of(1, "realtime")
            try:
                stack.start()
                rt, rt_wall = _run_campaign(stack.api_url, {"preset": "paper", "tests": realtime_tests, "seed": 1,
                                                            "algorithms": ["ra2vipas"], "mode": "realtime"}, 900, poll=1.0)
                report["latency_ms"] = rt.get("latency_ms")
                report["realtime"] = {"rigs": 1, "tests": realtime_tests, "samples": realtime_tests * (rt["scenario"]["steps"] - 1),
                                      "wall_seconds": round(rt_wall, 3), "dr_final": rt["algorithms"]["ra2vipas"]["dr_final"]}
            except (StackError, TimeoutError, RuntimeError) as err:
                fail(f"bench mesh (realtime): {err}")
            finally:
                stack.stop()
    if as_json:
        print_json(report)
    else:
        lat = report["latency_ms"] or {}
        stdout.print(f"mesh ({rigs} rigs): {report['steps_per_second']} control steps/s in fast mode (target 2200); "
                     f"realtime sample->command latency p50 {lat.get('p50')} ms, p99 {lat.get('p99')} ms (target p99 <= 5)")
