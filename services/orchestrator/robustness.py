"""The robustness benchmark (``ra2vipas bench robustness``): every algorithm on a spread of
worlds, paired test by test, beside the oracle reference.

Per scenario: each algorithm's final DR with its Wilson 95 % interval; the paired difference
Ra²ViPAS minus the best single cue (RaPAS, the directional receiver alone, or RaViPAS, the
camera and the omnidirectional receiver) with its 95 % interval (a normal interval on the
per-test differences, which are paired because every algorithm meets the same world in test
k); and the oracle's DR (``services.orchestrator.oracle``: the Bayes-MAP choice given the true
model, the true trajectories and a sweep's measurements; on BLE advertisements the packets'
joint Gaussian, ``packet_oracle_choice``; none on a recorded channel, which has no model). Tests run in a process pool; every
draw depends only on (seed, test index), so the numbers do not depend on the worker count.

Any other policy (``run(..., algorithms=["greedy"])``: a registered name or ``module:Class``,
``services/controller/registry.py``) gets its own column beside the built-ins and its paired
difference against Ra²ViPAS (``versus_ra2vipas``: the same normal interval on the per-test
differences, with McNemar's exact test); the built-ins' numbers do not change with it.
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from typing import Any, Callable

import numpy as np

from ra2vipas.services.controller import registry
from ra2vipas.services.orchestrator.engine import worker_pool
from ra2vipas.services.orchestrator.metrics import Z95, paired_comparison, wilson_interval
from ra2vipas.services.orchestrator.oracle import oracle_choice
from ra2vipas.services.orchestrator.simulate import run_test, train_pod
from ra2vipas.services.protocol.scenario import Scenario, build_scenario

ALGORITHMS = registry.BUILTINS
"""The columns every run has (the built-ins, in their order); ``run(algorithms=...)`` adds others."""
SINGLE_CUES = ("rapas", "ravipas")

SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("paper", {}),
    "uniform": ("paper-uniform", {}),
    "sparse-10": ("paper", {"n_targets": 10}),
    "crowd-60": ("paper-uniform", {"n_targets": 60, "rf_noise_db": 4.0}),
    "noise-2dB": ("paper-uniform", {"rf_noise_db": 2.0}),
    "noise-6dB": ("paper", {"rf_noise_db": 6.0}),
    "lobe-0.05": ("paper", {"antenna_curvature": 0.05}),
    "lobe-2": ("paper-uniform", {"antenna_curvature": 2.0}),
    "db-gain": ("paper", {"antenna_model": "db-gain"}),
    "db-gain-wide": ("paper-uniform", {"antenna_model": "db-gain", "antenna_curvature": 0.2}),
    "fov-10": ("paper", {"fov_half_angle_deg": 10.0}),
    "fov-45": ("paper-uniform", {"fov_half_angle_deg": 45.0}),
    "nu-3": ("paper", {"frames_per_rf": 3}),
    "nu-30": ("paper-uniform", {"frames_per_rf": 30}),
    "clutter": ("paper", {"clutter_rate": 0.5, "box_bearing_noise_deg": 1.0}),
    "dynamic-standing": ("dynamic", {"walking_fraction": 0.0}),
    "dynamic": ("dynamic", {}),
    # real radios (issue 20): BLE advertisements, a simulated building and a recorded one
    "ble": ("ble", {}),
    "ble-dynamic": ("ble-dynamic", {}),
    "ble-recorded": ("ble-recorded", {}),
}


@lru_cache(maxsize=4)
def _scenario_and_model(name: str, seed: int) -> tuple[Scenario, Any]:
    preset, overrides = SCENARIOS[name]
    scenario = build_scenario(preset, overrides)
    return scenario, train_pod(scenario, seed).model


def run_chunk(name: str, seed: int, tests: list[int], others: tuple[str, ...] = ()) -> dict[str, list[int]]:
    """Final hits (0/1) of every built-in, of the policies ``others`` and of the oracle on the
    given tests of a scenario (what a pool worker runs; the POD model is trained once per
    worker and scenario)."""
    scenario, model = _scenario_and_model(name, seed)
    out: dict[str, list[int]] = {a: [] for a in (*ALGORITHMS, *others, "oracle")}
    for k in tests:
        for a in (*ALGORITHMS, *others):
            out[a].append(int(run_test(scenario, seed, k, a, model).hits[-1]))
        if scenario.radio.value == "recorded":  # a recording has no model to be an oracle of
            continue
        choice, tx = oracle_choice(scenario, seed, k)
        out["oracle"].append(int(choice == tx))
    if scenario.radio.value == "recorded":
        del out["oracle"]
    return out


def paired_difference(hits_a: list[int], hits_b: list[int]) -> tuple[float, float]:
    """The mean of the per-test differences a - b of two policies' final hits on the same tests
    (paired: test k is the same world for both) and the half-width of its normal 95 % interval
    (infinite with one test)."""
    diff = np.asarray(hits_a, dtype=float) - np.asarray(hits_b, dtype=float)
    half = Z95 * float(diff.std(ddof=1)) / math.sqrt(diff.size) if diff.size > 1 else float("inf")
    return float(diff.mean()), half


def _difference(mean: float, half: float) -> dict[str, Any]:
    return {"difference": round(mean, 4), "difference_ci95": [round(mean - half, 4), round(mean + half, 4)],
            "not_worse": bool(mean + half >= 0.0)}


def summarize_scenario(name: str, hits: dict[str, list[int]]) -> dict[str, Any]:
    """The report of one scenario from its per-test final hits (every built-in's, the oracle's
    and any other policy's: those get a ``versus_ra2vipas`` block each)."""
    n = len(hits["ra2vipas"])
    block: dict[str, Any] = {"preset": SCENARIOS[name][0], "overrides": SCENARIOS[name][1], "tests": n, "dr": {}, "ci95": {}}
    for a, h in hits.items():
        block["dr"][a] = round(sum(h) / n, 4)
        block["ci95"][a] = [round(v, 4) for v in wilson_interval(sum(h), n)]
    best = max(SINGLE_CUES, key=lambda a: (sum(hits[a]), a == "rapas"))
    block["best_single_cue"] = best
    block.update(_difference(*paired_difference(hits["ra2vipas"], hits[best])))
    oracle = block["dr"].get("oracle")  # none on a recorded channel
    block["ra2vipas_over_oracle"] = round(block["dr"]["ra2vipas"] / oracle, 4) if oracle else None
    others = [a for a in hits if a not in ALGORITHMS and a != "oracle"]
    if others:
        block["versus_ra2vipas"] = {}
        for a in others:  # Ra²ViPAS - a, as the table's Ra²ViPAS - best single cue; not_worse: Ra²ViPAS's
            mcnemar = paired_comparison("ra2vipas", hits["ra2vipas"], a, hits[a])
            block["versus_ra2vipas"][a] = {**_difference(*paired_difference(hits["ra2vipas"], hits[a])),
                                           "only_ra2vipas": mcnemar["only_a"], "only_other": mcnemar["only_b"],
                                           "p_value": mcnemar["p_value"]}
    return block


def run(tests: int = 200, seed: int = 1, scenarios: list[str] | None = None, workers: int | None = None,
        progress: Callable[[int, int], None] | None = None, algorithms: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """The benchmark: ``tests`` paired tests per scenario, on ``workers`` processes (default:
    every core), of the built-ins and of the policies ``algorithms`` (registered names or
    ``module:Class``; a built-in among them is already there).

    Raises
    ------
    ValueError
        An unknown scenario, or a policy that is not installed (``registry.UnknownPolicy``).
    """
    names = list(scenarios or SCENARIOS)
    unknown = [s for s in names if s not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenario {unknown[0]!r}; choose from {', '.join(SCENARIOS)}")
    others = tuple(a for a in (registry.check(list(algorithms)) if algorithms else []) if a not in ALGORITHMS)
    workers = max(1, workers or os.cpu_count() or 1)
    chunk = max(1, min(25, tests // max(1, workers)))
    jobs = [(name, list(range(lo, min(tests, lo + chunk)))) for name in names for lo in range(0, tests, chunk)]
    hits: dict[str, dict[str, list[tuple[int, int]]]] = {name: {a: [] for a in (*ALGORITHMS, *others, "oracle")} for name in names}
    done = 0
    with worker_pool(workers) as pool:
        futures = {pool.submit(run_chunk, name, seed, ks, others): (name, ks) for name, ks in jobs}
        for future, (name, ks) in futures.items():
            part = future.result()
            for a, h in part.items():
                hits[name][a] += list(zip(ks, h))
            if "oracle" not in part:
                hits[name].pop("oracle", None)
            done += len(ks)
            if progress:
                progress(done, tests * len(names))
    report: dict[str, Any] = {"benchmark": "robustness", "tests": tests, "seed": seed, "workers": workers, "scenarios": {}}
    if others:  # absent otherwise, so the built-ins' report is what it always was
        report["algorithms"] = [*ALGORITHMS, *others]
        report["policies"] = registry.provenance(others)
    for name in names:
        ordered = {a: [h for _, h in sorted(v)] for a, v in hits[name].items()}
        report["scenarios"][name] = summarize_scenario(name, ordered)
    report["all_not_worse"] = all(s["not_worse"] for s in report["scenarios"].values())
    return report
