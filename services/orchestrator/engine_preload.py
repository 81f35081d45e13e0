"""What the engine's fork server imports before it forks any worker (``engine._context``): the
engine, and one tiny episode of every algorithm, so every worker starts warm.

A fresh process is slow on its first episode (lazy imports, caches filled on first use);
done once here, in the fork server, every worker inherits it (copy on write) instead of paying
it each. Importing this module anywhere else only costs that one warm-up. The warm-up's
scenario, seed and outcome are thrown away: they cannot touch any campaign's draws, which
come from (seed, test index) alone.
"""

from __future__ import annotations

import logging

from ra2vipas.services.orchestrator import engine  # noqa: F401  (what the workers run)


def warm_up() -> None:
    from ra2vipas.services.controller.registry import BUILTINS as ALGORITHMS
    from ra2vipas.services.orchestrator.simulate import run_test, train_pod
    from ra2vipas.services.protocol.scenario import build_scenario

    scenario = build_scenario("paper", {"steps": 3, "n_train": 40, "n_targets": 3})
    pod = train_pod(scenario, 0, cache=False)  # the fit's code warmed too, never a cache hit
    for algorithm in ALGORITHMS:
        run_test(scenario, 0, 0, algorithm, pod.model)


try:
    warm_up()
except Exception:  # noqa: BLE001 - a warm-up that fails only leaves the workers cold
    logging.getLogger(__name__).warning("engine warm-up failed; workers start cold", exc_info=True)
