"""``ra2vipas bench walkers``: where a campaign's losses are — a walking Tx or a standing one — and
what the camera's own views would allow (docs/radio.md, "What a tracker that kept the walkers
could reach").

Each test runs in process (``simulate.run_test``: the policy sees the measurements only). Afterwards,
for scoring alone, the test's truth is read: whether the Tx walks (``GroundTruth.tx_walks``) and,
replaying the test from its seed at the pans the policy chose,
in how many of the last ``window`` steps the camera reported a box within ``near_deg`` of the Tx.

The *bound* counts right every walking Tx that was boxed in at least ``boxed`` of those steps and in
one of the last ``recent``, and every other test as the policy answered it: what naming a walker
among the people the camera saw would reach without pointing anywhere else. Nothing here reaches a
controller; like the oracle of the robustness benchmark it reads the simulator's ground truth.
Every draw depends only on (seed, test index), so the numbers do not depend on the worker count.
"""

from __future__ import annotations

import math
import os
from functools import lru_cache
from typing import Any, Callable

import numpy as np

from ra2vipas.services.controller import registry
from ra2vipas.services.orchestrator.engine import worker_pool
from ra2vipas.services.orchestrator.metrics import wilson_interval
from ra2vipas.services.orchestrator.simulate import run_test, train_pod
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.scenario import Scenario, build_scenario
from ra2vipas.services.sensors.world import SimulatedPlatform


@lru_cache(maxsize=2)
def _scenario_and_model(preset: str, overrides: tuple[tuple[str, Any], ...], seed: int) -> tuple[Scenario, Any]:
    scenario = build_scenario(preset, dict(overrides))
    return scenario, train_pod(scenario, seed).model


def boxed_steps(platform: SimulatedPlatform, pans: list[float], near_rad: float) -> np.ndarray:
    """Per step, whether a box the camera reported at the pan ``pans[t]`` lies within ``near_rad``
    of the Tx. ``platform``: the test made afresh from its own seed and sensed here at the same pans,
    in order, so the measurements are the ones the policy saw."""
    bearings = platform.truth.step_bearings_rad()
    tx = platform.truth.tx_index
    out = np.zeros(len(pans), dtype=bool)
    for t, pan in enumerate(pans):
        measurement = platform.sense(t, pan)
        tx_now = bearings[t, tx] if bearings.ndim == 2 else bearings[tx]
        boxes = [pan + b for frame in measurement.frames for b in frame.box_bearings_rad]
        out[t] = bool(boxes) and float(np.min(np.abs(wrap(np.asarray(boxes) - tx_now)))) <= near_rad
    return out


def run_chunk(preset: str, overrides: tuple[tuple[str, Any], ...], seed: int, tests: list[int], algorithm: str,
              near_deg: float) -> list[dict[str, Any]]:
    """Per test: its final hit, whether the Tx walks, and the steps in which the Tx was boxed."""
    scenario, model = _scenario_and_model(preset, overrides, seed)
    rows = []
    for k in tests:
        outcome = run_test(scenario, seed, k, algorithm, model)
        platform = SimulatedPlatform(scenario, seed, k)
        boxed = boxed_steps(platform, outcome.pans, math.radians(near_deg))
        rows.append({"test": k, "hit": bool(outcome.hits[-1]), "walks": platform.truth.tx_walks, "boxed": boxed.tolist()})
    return rows


def _rate(hits: list[bool]) -> dict[str, Any]:
    n = len(hits)
    return {"tests": n, "dr": round(sum(hits) / n, 4) if n else None,
            "ci95": [round(v, 4) for v in wilson_interval(sum(hits), n)] if n else None}


def summarize(rows: list[dict[str, Any]], window: int, boxed: int, recent: int) -> dict[str, Any]:
    """The DR, split by whether the Tx walks, and the bound (module docstring) from per-test rows."""
    def held(row: dict[str, Any]) -> bool:
        seen = row["boxed"]
        return row["walks"] and sum(seen[-window:]) >= boxed and any(seen[-recent:])

    return {"dr": _rate([r["hit"] for r in rows])["dr"],
            "walking": _rate([r["hit"] for r in rows if r["walks"]]),
            "standing": _rate([r["hit"] for r in rows if not r["walks"]]),
            "bound": {"window": window, "boxed": boxed, "recent": recent,
                      "walking_tests_boxed": sum(1 for r in rows if held(r)),
                      **_rate([r["hit"] or held(r) for r in rows])}}


def validate(preset: str, overrides: dict[str, Any] | None, algorithm: str, window: int, boxed: int, recent: int) -> str:
    """The policy's name once the arguments of ``run`` are known to be usable (before any worker
    starts). Raises ValueError saying what is not: a preset or parameter (``ScenarioError``), a
    scenario with several tags, a policy that is not installed, a window the bound cannot use."""
    if not 1 <= recent <= window or boxed > window:
        raise ValueError(f"need 1 <= recent <= window and boxed <= window, got window {window}, boxed {boxed}, recent {recent}")
    if build_scenario(preset, overrides or {}).n_tags > 1:
        raise ValueError("bench walkers scores one tag; this scenario has n_tags > 1")
    return registry.check([algorithm])[0]


def run(preset: str, tests: int, seed: int, algorithm: str = "ra2vipas", overrides: dict[str, Any] | None = None,
        workers: int | None = None, progress: Callable[[int, int], None] | None = None, window: int = 20,
        boxed: int = 5, recent: int = 3, near_deg: float = 2.5) -> dict[str, Any]:
    """The report (module docstring) of ``tests`` tests of ``algorithm`` on ``preset`` with
    ``overrides``, seeded ``seed``, in ``workers`` processes (None: one per core).

    Raises
    ------
    ValueError
        An unknown preset or scenario parameter, or a policy that is not installed.
    """
    algorithm = validate(preset, overrides, algorithm, window, boxed, recent)
    frozen = tuple(sorted((overrides or {}).items()))
    workers = max(1, workers or os.cpu_count() or 1)
    chunk = max(1, min(25, tests // workers))
    jobs = [list(range(lo, min(tests, lo + chunk))) for lo in range(0, tests, chunk)]
    rows: list[dict[str, Any]] = []
    with worker_pool(workers) as pool:
        futures = [pool.submit(run_chunk, preset, frozen, seed, ks, algorithm, near_deg) for ks in jobs]
        for future in futures:
            rows += future.result()
            if progress:
                progress(len(rows), tests)
    rows.sort(key=lambda r: r["test"])
    return {"benchmark": "walkers", "preset": preset, "overrides": dict(frozen), "seed": seed, "tests": tests,
            "algorithm": algorithm, "near_deg": near_deg, **summarize(rows, window, boxed, recent)}
