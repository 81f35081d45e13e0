"""The in-process campaign: determinism, independence of tests, the results object."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.controller.policy import ALGORITHMS
from ra2vipas.services.learner.pod import predict, r2_score
from ra2vipas.services.orchestrator import simulate
from ra2vipas.services.orchestrator.metrics import wilson_interval
from ra2vipas.services.orchestrator.simulate import run_campaign, run_test, train_pod
from ra2vipas.services.sensors.world import SimulatedPlatform, TrainingEpisode
from tests.conftest import small_scenario

TIMING = {"train_seconds", "steps_per_second"}
TINY = {"steps": 25, "n_train": 150, "n_targets": 8}


def _without_timing(obj):
    if isinstance(obj, dict):
        return {k: _without_timing(v) for k, v in obj.items() if k not in TIMING}
    if isinstance(obj, list):
        return [_without_timing(v) for v in obj]
    return obj


@pytest.fixture(scope="module")
def tiny_campaign():
    sc = small_scenario(**TINY)
    calls = []
    result = run_campaign("paper", sc, tests=3, seed=11, progress=lambda done, total: calls.append((done, total)))
    return sc, result, calls


def test_same_seed_same_results(tiny_campaign):
    sc, first, _ = tiny_campaign
    second = run_campaign("paper", sc, tests=3, seed=11)
    assert _without_timing(first) == _without_timing(second)
    assert set(first) - set(_without_timing(first)) == {"steps_per_second"}
    assert "train_seconds" in first["pod"]


def test_results_object(tiny_campaign):
    sc, result, calls = tiny_campaign
    assert result["preset"] == "paper" and result["tests"] == 3 and result["seed"] == 11
    assert result["scenario"] == sc.model_dump(mode="json")
    assert set(result["algorithms"]) == set(ALGORITHMS)
    assert 0.0 < result["pod"]["r2"] <= 1.0
    for block in result["algorithms"].values():
        assert len(block["dr"]) == sc.steps and len(block["dr_ci95"]) == sc.steps
        assert all(abs(v * 3 - round(v * 3)) < 1e-5 and 0.0 <= v <= 1.0 for v in block["dr"])
        assert block["dr_final"] == block["dr"][-1]
        k = round(block["dr_final"] * 3)
        assert block["ci95"] == pytest.approx(list(wilson_interval(k, 3)), abs=1e-6)
    assert result["steps_per_second"] is None or result["steps_per_second"] > 0
    # progress: once per episode, in order
    total = 3 * len(ALGORITHMS)
    assert calls == [(i, total) for i in range(1, total + 1)]


def test_campaign_matches_its_tests(tiny_campaign):
    """The summary is the reduction of run_test outcomes: recompute one algorithm by hand."""
    sc, result, _ = tiny_campaign
    pod = train_pod(sc, 11)
    assert result["pod"]["r2"] == pod.r2
    hits = np.array([run_test(sc, 11, k, "ra2vipas", pod.model).hits for k in range(3)])
    assert result["algorithms"]["ra2vipas"]["dr"] == pytest.approx(list(hits.mean(axis=0)), abs=1e-6)


def test_test_outcome_does_not_depend_on_what_ran_before(small_pod):
    sc = small_scenario(steps=30)
    alone = run_test(sc, 5, 3, "ra2vipas", small_pod.model)
    for k in range(3):
        for alg in ALGORITHMS:
            run_test(sc, 5, k, alg, small_pod.model)
    after = run_test(sc, 5, 3, "ra2vipas", small_pod.model)
    assert alone == after
    assert isinstance(alone, simulate.TestOutcome) and alone.test_index == 3 and alone.algorithm == "ra2vipas"


def test_outcome_is_consistent_with_its_world(small_pod):
    sc = small_scenario(steps=30)
    out = run_test(sc, 5, 1, "ra2vipas", small_pod.model)
    truth = SimulatedPlatform(sc, 5, 1).truth
    assert len(out.pans) == len(out.estimates) == len(out.hits) == len(out.chosen) == len(out.in_fov) == sc.steps
    assert out.pans[0] == pytest.approx(sc.initial_pan_rad)
    assert [c == truth.tx_index for c in out.chosen] == out.hits


def test_algorithms_meet_the_same_world(small_pod):
    """Paired comparison: the world of test k is drawn from (seed, k) only."""
    sc = small_scenario(steps=20)
    truths = {alg: SimulatedPlatform(sc, 9, 2).truth for alg in ALGORITHMS}
    outs = {alg: run_test(sc, 9, 2, alg, small_pod.model) for alg in ALGORITHMS}
    first = truths[ALGORITHMS[0]]
    for t in truths.values():
        np.testing.assert_array_equal(t.positions_m, first.positions_m)
    # the sweep and ra2vipas take the same first sample, so they see the same first measurement
    assert outs["sweep"].pans[0] == outs["ra2vipas"].pans[0]


def test_different_seeds_give_different_worlds_and_outcomes(small_pod):
    sc = small_scenario(steps=30)
    layouts = {SimulatedPlatform(sc, seed, 0).truth.positions_m.tobytes() for seed in (1, 2, 3)}
    assert len(layouts) == 3
    a = run_test(sc, 1, 0, "ra2vipas", small_pod.model)
    b = run_test(sc, 2, 0, "ra2vipas", small_pod.model)
    assert a.estimates != b.estimates


def test_train_pod_is_deterministic_and_scored_against_truth():
    sc = small_scenario(n_train=200)
    a, b = train_pod(sc, 4), train_pod(sc, 4)
    assert a.model == b.model and a.r2 == b.r2
    ep = TrainingEpisode(sc, 4)
    assert a.r2 == pytest.approx(r2_score(ep.truth.pod, predict(a.model, ep.truth.rssi_dbm)), abs=1e-6)
    assert train_pod(sc, 5).model != a.model


def test_campaign_with_a_subset_of_algorithms():
    sc = small_scenario(**TINY)
    result = run_campaign("paper", sc, tests=2, seed=11, algorithms=["rapas"])
    assert list(result["algorithms"]) == ["rapas"]
    assert _without_timing(result) == _without_timing(run_campaign("paper", sc, tests=2, seed=11, algorithms=["rapas"]))


def test_an_episode_ends_at_its_first_confident_step_and_keeps_its_answer(small_pod):
    sc = small_scenario()
    full = run_test(sc, 5, 0, "ra2vipas", small_pod.model)
    assert len(full.confidences) == sc.steps and all(0.0 <= c <= 1.0 for c in full.confidences) and full.decided_step is None
    threshold = sorted(full.confidences)[len(full.confidences) // 2]  # reached somewhere in the episode
    d = next(t for t, c in enumerate(full.confidences) if c >= threshold)
    early = run_test(sc, 5, 0, "ra2vipas", small_pod.model, stop_confidence=threshold)
    assert early.decided_step == d and len(early.estimates) == d + 1
    assert early.estimates == full.estimates[: d + 1]  # the same episode up to the decision
    assert early.hits == full.hits[: d + 1] + [full.hits[d]] * (sc.steps - d - 1)  # the answer of step d holds
    assert early.confidences == full.confidences[: d + 1] + [full.confidences[d]] * (sc.steps - d - 1)
