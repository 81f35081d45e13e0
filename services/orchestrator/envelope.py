"""The results object's envelope (preset, scenario, tests, seed, POD fit, speed, the algorithms'
blocks, the paired comparisons, the policies' provenance), for ``simulate`` and the orchestrator
alike: a module of its own so the orchestrator, which runs no episode, builds and serves results
without importing the simulator, the controllers and the learner's fit (``simulate`` imports them
all: ~1 s of CPU the first time an orchestrator finished a campaign or served its results).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ra2vipas.services.controller import registry
from ra2vipas.services.orchestrator.metrics import summarize_algorithm
from ra2vipas.services.protocol.scenario import Scenario, ScenarioError, build_scenario

if TYPE_CHECKING:
    from ra2vipas.services.learner.trained import TrainedPOD
    from ra2vipas.services.orchestrator.simulate import TestOutcome


def summarize(
    preset: str,
    scenario: Scenario,
    tests: int,
    seed: int,
    pod: TrainedPOD,
    outcomes: dict[str, list[TestOutcome]],
    steps_per_second: float | None,
    stop_confidence: float = 0.0,
) -> dict[str, Any]:
    """The results object (same shape for ``simulate --json`` and the REST API)."""
    algorithms = {}
    for name, runs in outcomes.items():
        runs = sorted(runs, key=lambda o: o.test_index)
        confidences = np.array([o.confidences for o in runs]) if runs and all(o.confidences for o in runs) else None
        algorithms[name] = summarize_algorithm(
            np.array([o.hits for o in runs]),
            np.array([o.in_fov for o in runs]),
            scenario.rf_period_s,
            confidences,
            [o.decided_step for o in runs] if stop_confidence > 0.0 else None,
        )
    resolved = scenario.model_dump(mode="json")
    out = {
        "id": None,  # the campaign's id where one names it (the API's results); None in this process
        "preset": preset,
        "overrides": overrides_of(preset, resolved),
        "scenario": resolved,
        "tests": tests,
        "seed": seed,
        "pod": {"r2": pod.r2, "train_seconds": round(pod.train_seconds, 4)},
        "algorithms": algorithms,
        "steps_per_second": None if steps_per_second is None else round(steps_per_second, 1),
    }
    if stop_confidence > 0.0:
        out["stop_confidence"] = stop_confidence
    if outcomes:
        from ra2vipas.services.orchestrator.metrics import paired_comparisons

        finals: dict[str, list[int | None]] = {}
        for name, runs in outcomes.items():
            finals[name] = [None] * tests
            for o in runs:
                if 0 <= o.test_index < tests and o.hits:
                    finals[name][o.test_index] = int(o.hits[-1])
        out["outcomes"] = finals
        out["paired"] = paired_comparisons(finals)
    add_provenance(out)
    return out


def add_provenance(results: dict[str, Any]) -> None:
    """Say in ``results["policies"]`` which package and version each policy outside the built-ins
    came from (absent when every policy is a built-in, so their results are unchanged)."""
    found = registry.provenance(results["algorithms"])
    if found:
        results["policies"] = found
    else:
        results.pop("policies", None)


def overrides_of(preset: str, scenario: dict[str, Any]) -> dict[str, Any]:
    """What was run besides the preset: the parameters of ``scenario`` (JSON data) whose value
    differs from the preset's, with the scenario's types, in the scenario's order; the
    ``--set NAME=VALUE`` options that rebuild it from the preset. Empty for an unknown preset."""
    try:
        base = build_scenario(preset, {}).model_dump(mode="json")
    except ScenarioError:
        return {}
    return {name: value for name, value in scenario.items() if base.get(name) != value}
