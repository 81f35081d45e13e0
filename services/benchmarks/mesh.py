"""``ra2vipas bench mesh``: local stacks measured through their real processes: control steps
per second in fast mode, the sample-to-command latency in realtime mode, what each service's
step costs (``step_breakdown``, ``cpu_ms_per_step``) and the orchestrator's peak memory."""

from __future__ import annotations

import os
import tempfile
import time

from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.common import CostListener, Stack, StackCPU, StackFactory, mb, run_campaign, status_kb

TARGET_LATENCY_P99_MS = 5.0


def target_steps_per_second(preset: str) -> int:
    return 2000 if preset == "dynamic" else 2200


def inprocess_steps_per_second(preset: str, tests: int, algorithms: list[str]) -> tuple[float, dict, float | None]:
    """The same campaign in-process on one worker (``simulate``): steps/s, DR_final per
    algorithm, and the CPU each control step cost this process [ms] (from its first episode on,
    like the steps/s: training excluded)."""
    from ra2vipas.services.orchestrator.engine import Point, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    cpu_at: list[float] = []
    run = run_points([Point(preset, build_scenario(preset), tests, 1, tuple(algorithms))], workers=1,
                     on_trained=lambda _i, _pod: cpu_at.append(time.process_time()))
    cpu_ms = 1e3 * (time.process_time() - cpu_at[0]) / run.steps if cpu_at and run.steps else None
    return run.steps_per_second or 0.0, {a: b["dr_final"] for a, b in run.results[0]["algorithms"].items()}, cpu_ms


def mesh_memory(stack: Stack, tests: int, steps: int, algorithm: str) -> dict:
    """One campaign of ``tests`` tests on a freshly started stack: the orchestrator process's
    resident memory before the campaign, after it, and its peak over its whole life (VmHWM)."""
    pid = next((c.proc.pid for c in stack.children if c.name == "orchestrator" and c.proc is not None), None)
    if pid is None:
        raise RuntimeError("the stack has no orchestrator process")
    before = status_kb(pid, "VmRSS")
    body = {"preset": "paper", "overrides": {"steps": steps}, "tests": tests, "seed": 1, "algorithms": [algorithm]}
    results, wall, _ = run_campaign(stack.api_url, body, 7200, poll=0.5)
    after, peak = status_kb(pid, "VmRSS"), status_kb(pid, "VmHWM")
    if peak is None:
        raise RuntimeError(f"cannot read /proc/{pid}/status (the orchestrator's memory)")
    return {"tests": tests, "steps": steps, "algorithm": algorithm, "episodes": tests, "seconds": round(wall, 2),
            "steps_per_second": results["steps_per_second"], "orchestrator_pid": pid, "orchestrator_peak_rss_mb": mb(peak),
            "orchestrator_rss_before_mb": mb(before), "orchestrator_rss_after_mb": mb(after),
            "dr_final": results["algorithms"][algorithm]["dr_final"]}


def mesh(launch: StackFactory, *, rigs: int, window: int, tests: int, realtime_tests: int, memory_tests: list[int],
         memory_steps: int, memory_algorithm: str, preset: str, inprocess: bool, rig_layouts: tuple[str, ...] = ("one-process",)) -> dict:
    """Each part on a stack of its own made by ``launch`` (every one stopped afterwards): the
    PRESET campaign of ``tests`` tests x the active built-ins on ``rigs`` rigs in fast mode
    (0: skip; with ``inprocess``, also in-process on one worker), ``realtime_tests`` tests paced
    at T_RF on one rig (0: skip), and one campaign of each size in ``memory_tests``.

    With ``rigs`` = 1 the realtime part runs on the fast part's stack, after its campaign.
    The fast and realtime parts run once per layout of ``rig_layouts`` ("one-process": a rig's
    two nodes in one process and one Zenoh session; "split": two processes); the report's
    top-level figures are the first layout's, and ``by_layout`` has every layout's."""
    from ra2vipas.services.controller import registry

    algorithms = [a for a in registry.BUILTINS if a != "sweep"]  # the active built-ins
    report: dict = {"benchmark": "mesh", "preset": preset, "rigs": rigs, "window": window, "rig_layout": rig_layouts[0],
                    "targets": {"steps_per_second": target_steps_per_second(preset), "latency_p99_ms": TARGET_LATENCY_P99_MS},
                    "steps_per_second": None}
    parts = {layout: {"steps_per_second": None, "latency_ms": None} for layout in rig_layouts}
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:

        def stack_of(n: int, name: str, layout: str | None = None) -> Stack:
            return launch(rigs=n, db_path=os.path.join(tmp, f"{name}.db"), log_dir=os.path.join(tmp, f"logs-{name}"), window=window,
                          rig_layout=layout)

        def fast_part(stack: Stack, part: dict) -> None:
            listener = CostListener(stack)
            cpu = StackCPU(stack)
            body = {"preset": preset, "tests": tests, "seed": 1, "algorithms": algorithms}
            try:
                fast, fast_wall, _ = run_campaign(stack.api_url, body, 1800, on_running=cpu.start, on_done=cpu.stop)
                time.sleep(0.2)
                breakdown = listener.breakdown()
            finally:
                listener.close()
            part["fast"] = {
                "tests": tests, "algorithms": algorithms, "steps": tests * len(algorithms) * fast["scenario"]["steps"],
                "steps_per_second": fast["steps_per_second"], "wall_seconds_with_training": round(fast_wall, 3),
                "dr_final": {a: b["dr_final"] for a, b in fast["algorithms"].items()},
                "step_breakdown": breakdown,
                "cpu_ms_per_step": cpu.per_step_ms(tests * len(algorithms) * fast["scenario"]["steps"]),
            }
            part["steps_per_second"] = fast["steps_per_second"]

        def realtime_part(stack: Stack, part: dict) -> None:
            listener = CostListener(stack)
            try:
                rt, rt_wall, _ = run_campaign(stack.api_url, {"preset": preset, "tests": realtime_tests, "seed": 1,
                                                              "algorithms": ["ra2vipas"], "mode": "realtime"}, 900, poll=1.0)
                time.sleep(0.2)
                breakdown = listener.breakdown(realtime=True)
            finally:
                listener.close()
            part["latency_ms"] = rt.get("latency_ms")
            part["realtime"] = {"rigs": 1, "tests": realtime_tests, "samples": realtime_tests * (rt["scenario"]["steps"] - 1),
                                "wall_seconds": round(rt_wall, 3), "dr_final": rt["algorithms"]["ra2vipas"]["dr_final"],
                                "step_breakdown": breakdown}

        # the realtime part runs on one rig: with --rigs 1 it runs on the fast part's stack, after it (one
        # stack start fewer per layout; its own campaign, so its breakdown and latency are its own)
        shared = rigs == 1 and tests and realtime_tests
        for layout, part in parts.items() if tests else ():
            stack = stack_of(rigs, f"fast-{layout}", layout)
            what = "fast"
            try:
                stack.start()
                fast_part(stack, part)
                if shared:
                    what = "realtime"
                    realtime_part(stack, part)
            except (TimeoutError, RuntimeError) as err:  # a stack that did not start raises a RuntimeError too
                raise BenchmarkError(f"bench mesh ({what}, {layout} rigs): {err}") from err
            finally:
                stack.stop()
        if tests and inprocess:
            sps1, dr1, cpu1 = inprocess_steps_per_second(preset, tests, algorithms)
            report["inprocess_steps_per_second_1"] = round(sps1, 1)
            report["inprocess_cpu_ms_per_step"] = None if cpu1 is None else round(cpu1, 4)
            for part in parts.values():
                part["mesh_over_inprocess"] = round(part["steps_per_second"] / sps1, 3) if sps1 else None
                # per-core efficiency, independent of what else the machine runs: the CPU a control step costs
                # in process over what it costs the whole mesh (1.0: a mesh core does what an in-process core does)
                mesh_cpu = part["fast"]["cpu_ms_per_step"]
                part["cpu_efficiency"] = round(cpu1 / mesh_cpu["total"], 3) if cpu1 and mesh_cpu and mesh_cpu["total"] else None
                part["fast"]["dr_final_equals_inprocess"] = dr1 == part["fast"]["dr_final"]
        for layout, part in parts.items() if realtime_tests and not shared else ():
            stack = stack_of(1, f"realtime-{layout}", layout)
            try:
                stack.start()
                realtime_part(stack, part)
            except (TimeoutError, RuntimeError) as err:
                raise BenchmarkError(f"bench mesh (realtime, {layout} rigs): {err}") from err
            finally:
                stack.stop()
        report.update(parts[rig_layouts[0]])
        if len(rig_layouts) > 1:
            report["by_layout"] = parts
        if memory_tests:
            report["memory"] = []
        for size in memory_tests:
            stack = stack_of(rigs, f"memory-{size}", rig_layouts[0])
            try:
                stack.start()
                report["memory"].append(mesh_memory(stack, size, memory_steps, memory_algorithm))
            except (TimeoutError, RuntimeError) as err:
                raise BenchmarkError(f"bench mesh (memory, {size} tests): {err}") from err
            finally:
                stack.stop()
    return report
