"""``ra2vipas bench simulate``: the in-process simulator on one worker and on many, and the peak
memory of large campaigns, each in a fresh process (``memory_probe``)."""

from __future__ import annotations

import json
import time

from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.common import load_average

TARGET_SPEEDUP = 1.7


def _spin(loops: int = 3_000_000) -> float:
    """Seconds of a pure-Python loop: a yardstick of the CPU this process gets."""
    started = time.perf_counter()
    x = 0
    for i in range(loops):
        x += i
    return time.perf_counter() - started


def cpu_available(workers: int) -> float:
    """The speedup a pure CPU loop gets on ``workers`` processes right now (1 on a busy machine,
    ``workers`` on an idle one with that many cores): what the simulate speedup can reach."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_spin, [10_000] * workers))  # started
        alone = min(pool.submit(_spin).result() for _ in range(2))
        together = max(pool.map(_spin, [3_000_000] * workers))
    return round(workers * alone / together, 3)


def memory_probe(tests: int, steps: int, algorithm: str, workers: int, seed: int) -> dict:
    """Run one in-process campaign in this (fresh) process; its peak memory: this process's
    (which reduces every outcome) and the largest worker's."""
    import resource

    from ra2vipas.services.orchestrator.engine import Point, peak_rss_kb, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    def current_rss_kb() -> int:
        try:
            with open("/proc/self/status") as f:
                return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
        except (OSError, StopIteration, ValueError):
            return 0

    scenario = build_scenario("paper", {"steps": steps})
    before = peak_rss_kb()
    rss_before = current_rss_kb()
    started = time.perf_counter()
    report = run_points([Point("paper", scenario, tests, seed, (algorithm,))], workers=workers)
    wall = time.perf_counter() - started
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"tests": tests, "steps": steps, "algorithm": algorithm, "workers": report.workers,
            "episodes": tests, "seconds": round(wall, 2),
            "steps_per_second": round(report.steps_per_second or 0.0, 1),
            "parent_peak_rss_mb": round(own / 1024, 1), "parent_peak_rss_before_run_mb": round(before / 1024, 1),
            "parent_rss_growth_mb": round((current_rss_kb() - rss_before) / 1024, 2),
            "worker_peak_rss_mb": round(report.worker_peak_rss_kb / 1024, 1),
            "dr_final": report.results[0]["algorithms"][algorithm]["dr_final"]}


def _memory_in_fresh_process(tests: int, steps: int, algorithm: str, workers: int, seed: int) -> dict:
    """``memory_probe`` in a new Python process (so its peak is this campaign's alone)."""
    import subprocess
    import sys

    probe = subprocess.run(
        [sys.executable, "-c", "import json; from ra2vipas.services.benchmarks.simulate import memory_probe; "
                               f"print(json.dumps(memory_probe({tests}, {steps}, {algorithm!r}, {workers}, {seed})))"],
        capture_output=True, text=True, timeout=7200)
    if probe.returncode != 0:
        raise BenchmarkError(f"the memory run of {tests} tests failed: {(probe.stderr.strip().splitlines() or ['?'])[-1]}")
    return json.loads(probe.stdout.strip().splitlines()[-1])


def simulate(tests: int, workers: int, seed: int, memory_tests: list[int], memory_steps: int, memory_algorithm: str) -> dict:
    """The paper campaign of ``tests`` tests of every built-in on one worker and on ``workers``
    (0: the default, one per core): steps/s of each, the speedup, whether the two results are
    identical, beside what a pure CPU loop gains on as many processes just before and just
    after; then the peak memory of a campaign of each size in ``memory_tests`` (``memory_steps``
    steps, ``memory_algorithm``), each in a fresh process."""
    from ra2vipas.services.controller import registry
    from ra2vipas.services.orchestrator.engine import Point, default_workers, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    n = workers or default_workers()
    scenario = build_scenario("paper")
    point = Point("paper", scenario, tests, seed, registry.BUILTINS)
    available_before = cpu_available(n)
    one = run_points([point], workers=1)
    many = run_points([point], workers=n)
    available_after = cpu_available(n)

    def untimed(results: dict) -> dict:
        out = json.loads(json.dumps(results))
        out.pop("steps_per_second", None)
        out["pod"].pop("train_seconds", None)
        return out

    sps1, spsn = one.steps_per_second or 0.0, many.steps_per_second or 0.0
    return {
        "benchmark": "simulate", "workers": many.workers, "tests": tests, "steps": one.steps,
        "steps_per_second_1": round(sps1, 1), "steps_per_second_n": round(spsn, 1),
        "speedup": round(spsn / sps1, 3) if sps1 else None,
        "identical": untimed(one.results[0]) == untimed(many.results[0]),
        "cpu_loop_speedup": [available_before, available_after],
        "target_speedup": TARGET_SPEEDUP, "load_average": load_average(),
        "memory": [_memory_in_fresh_process(size, memory_steps, memory_algorithm, n, seed) for size in memory_tests],
    }
