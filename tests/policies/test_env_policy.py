"""A policy scripted through the Gymnasium environment scores the same through ``simulate``
(issue 19): the env hands a policy what the contract gives it (the POD model, the rig's
description, each step's measurement), and the same (seed, test) is the same world."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from ra2vipas.services.controller import registry
from ra2vipas.services.controller.contract import episode_context
from ra2vipas.services.orchestrator.simulate import run_test, train_pod
from ra2vipas.services.protocol.scenario import build_scenario

EXAMPLE_SRC = Path(__file__).resolve().parents[2] / "examples" / "my_policy" / "src"
OVERRIDES = {"steps": 40, "n_train": 300}


@pytest.fixture(scope="module")
def greedy():
    sys.path.insert(0, str(EXAMPLE_SRC))
    try:
        yield registry.load("my_policy:GreedyPolicy")
    finally:
        sys.path.remove(str(EXAMPLE_SRC))


@pytest.mark.parametrize("name", ["my_policy:GreedyPolicy", "ra2vipas"])
def test_a_policy_through_the_env_scores_what_simulate_scores(greedy, name):
    import gymnasium

    import ra2vipas.envs  # noqa: F401  (registers the env)

    env = gymnasium.make("ra2vipas/PanSearch-v0", preset="paper", overrides=OVERRIDES)
    scenario = build_scenario("paper", OVERRIDES)
    pod = train_pod(scenario, 3)
    for test in (0, 1):
        obs, info = env.reset(seed=3, options={"test": test})
        policy = registry.create(name, episode_context(info["sensor_config"], info["pod_model"], info["scenario"], 3, test))
        assert policy.first_pan() == info["measurement"].pan_rad
        rewards, terminated = [], False
        while not terminated:
            decision = policy.step(info["measurement"])
            obs, reward, terminated, truncated, info = env.step(np.array([decision.next_pan_rad, decision.estimate_rad]))
            rewards.append(reward)
        simulated = run_test(scenario, 3, test, name, pod.model)
        assert [bool(r) for r in rewards] == simulated.hits == [bool(h) for h in info["truth"]["hits"]]
        assert sum(simulated.hits) > 0  # a test that could tell a wrong world from the right one
    env.close()
