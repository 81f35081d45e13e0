"""``ra2vipas bench step``: one controller step (measurement in, decision out), in-process."""

from __future__ import annotations

import statistics
import time

from ra2vipas.services.benchmarks.common import percentile

# The median step the issues ask for, by the number of tags searched: 1 ms for one tag (the paper's
# worlds and the radio's, issue 20), 1.5 ms for the joint search over K = 3 (issue 21); none stated otherwise.
TARGET_MEDIAN_MS = {1: 1.0, 3: 1.5}


def controller_step(algorithm: str, tests: int, seed: int, preset: str, overrides: dict | None = None) -> dict:
    """Time every step of ``tests`` episodes of the built-in ``algorithm`` on ``preset``'s
    scenario (with ``overrides``, as ``--set`` gives them): the median and p99 over all steps and
    over the last step of each test (when the controller holds n_test samples). ``algorithm`` is a
    built-in, ``preset`` a known preset; a scenario with several tags (``ward``) times the joint
    search for all of them (issue 21)."""
    from ra2vipas.services.controller.policy import Controller, sensor_config_from_scenario, tuned_settings
    from ra2vipas.services.orchestrator.simulate import new_policy, train_pod
    from ra2vipas.services.protocol.scenario import build_scenario
    from ra2vipas.services.sensors.world import SimulatedPlatform

    scenario = build_scenario(preset, overrides or {})
    pod = train_pod(scenario, seed)
    all_ms: list[float] = []
    last_ms: list[float] = []
    for k in range(tests):
        platform = SimulatedPlatform(scenario, seed, k)
        if scenario.n_tags > 1:  # the built-in's joint search over the K tags (what a campaign runs)
            controller = new_policy(algorithm, scenario, seed, k, pod.model)
        else:
            controller = Controller(algorithm, sensor_config_from_scenario(scenario), pod.model, tuned_settings(algorithm))
        pan = controller.first_pan()
        for t in range(scenario.steps):
            m = platform.sense(t, pan)
            started = time.perf_counter()
            decision = controller.step(m)
            elapsed = (time.perf_counter() - started) * 1e3
            all_ms.append(elapsed)
            pan = decision.next_pan_rad
        last_ms.append(elapsed)
    return {
        "benchmark": "controller-step",
        "algorithm": algorithm,
        "preset": preset,
        "overrides": dict(overrides or {}),
        "n_tags": scenario.n_tags,
        "tests": tests,
        "steps": len(all_ms),
        "median_ms": round(statistics.median(all_ms), 4),
        "p99_ms": round(percentile(all_ms, 99), 4),
        "median_ms_at_n_test": round(statistics.median(last_ms), 4),
        "pod_train_seconds": round(pod.train_seconds, 4),
        "target_median_ms": TARGET_MEDIAN_MS.get(scenario.n_tags),
    }
