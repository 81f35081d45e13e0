"""The in-process engine on every core (engine.run_points): the same results value for value on
any number of workers, equal to reducing every outcome at once, and a study's points round robin."""

from __future__ import annotations

import pytest

from ra2vipas.services.controller.policy import ALGORITHMS
from ra2vipas.services.orchestrator import engine
from ra2vipas.services.orchestrator.engine import Point, plan, run_points
from ra2vipas.services.orchestrator.simulate import run_campaign, run_test, summarize, train_pod
from ra2vipas.services.protocol.scenario import build_scenario
from tests.conftest import differences, small_scenario, untimed

TINY = {"steps": 25, "n_train": 150, "n_targets": 8}


@pytest.fixture(scope="module")
def scenario():
    return small_scenario(**TINY)


@pytest.fixture(scope="module")
def reference(scenario):
    """Every outcome held at once and reduced by metrics.summarize_algorithm (simulate.summarize):
    what the streamed reduction must equal."""
    pod = train_pod(scenario, 5)
    outcomes = {a: [run_test(scenario, 5, k, a, pod.model, None, 0.6) for k in range(6)] for a in ALGORITHMS}
    return summarize("paper", scenario, 6, 5, pod, outcomes, None, 0.6)


def test_workers_2_equals_workers_1_equals_the_whole_array_reduction(scenario, reference):
    one = run_campaign("paper", scenario, tests=6, seed=5, stop_confidence=0.6, workers=1)
    two = run_campaign("paper", scenario, tests=6, seed=5, stop_confidence=0.6, workers=2)
    assert untimed(one) == untimed(two), differences(untimed(one), untimed(two))
    assert untimed(one) == untimed(reference), differences(untimed(one), untimed(reference))
    assert "decision" in one["algorithms"]["ra2vipas"] and "calibration" in one["algorithms"]["ra2vipas"]


def test_a_study_on_two_workers_equals_its_points_run_alone(scenario):
    points = [Point("paper", scenario.model_copy(update={"n_targets": n}), 3, 2, ("ra2vipas", "rapas")) for n in (4, 12)]
    together = run_points(points, workers=2)
    assert together.workers == 2 and together.steps == 2 * 3 * 2 * scenario.steps
    for p, res in zip(points, together.results):
        alone = run_points([p], workers=1).results[0]
        assert untimed(res) == untimed(alone), differences(untimed(res), untimed(alone))
        assert res["scenario"]["n_targets"] == p.scenario.n_targets


def test_progress_counts_every_episode_once(scenario):
    calls: list[tuple[int, int]] = []
    run_points([Point("paper", scenario, 4, 1, ("rapas",))], workers=2, progress=lambda d, t: calls.append((d, t)))
    assert [d for d, _ in calls] == [1, 2, 3, 4] and {t for _, t in calls} == {4}


def test_plan_interleaves_the_points_test_by_test():
    pts = [Point("paper", None, n, 1, ("rapas",)) for n in (3, 1, 2)]  # type: ignore[arg-type]
    assert list(plan(pts, 1)) == [(0, 0, 1), (1, 0, 1), (2, 0, 1), (0, 1, 2), (2, 1, 2), (0, 2, 3)]
    assert list(plan(pts, 2)) == [(0, 0, 2), (1, 0, 1), (2, 0, 2), (0, 2, 3)]


def test_chunks_are_small_enough_to_balance_the_workers():
    assert engine.chunk_tests(10_000, 1) == 1
    assert engine.chunk_tests(50, 2) == 1
    assert engine.chunk_tests(10_000, 2) == engine.MAX_CHUNK_TESTS
    assert engine.chunk_tests(100_000, 64) == 16 and engine.chunk_tests(2_000, 64) == 1


def test_no_point_is_an_error():
    with pytest.raises(ValueError):
        run_points([])


def test_by_default_a_small_campaign_runs_in_this_process_and_a_large_one_on_every_core(monkeypatch):
    """A worker costs seconds to start: the default is one per core, but only as many as the work
    (control steps, and POD training samples) pays for."""
    monkeypatch.setattr(engine, "default_workers", lambda: 8)
    paper = build_scenario("paper")
    assert engine.workers_for([Point("paper", paper, 2, 1, ("rapas", "sweep"))]) == 1
    assert engine.workers_for([Point("paper", paper, 50, 1, ("ra2vipas", "rapas", "ravipas", "sweep"))]) == 2
    assert engine.workers_for([Point("paper", paper, 1000, 1, ("rapas",))]) == 8
    # training counts: ten points with their own seeds train ten models
    assert engine.workers_for([Point("paper", paper, 1, s, ("rapas",)) for s in range(10)]) == 4
    assert engine.workers_for([Point("paper", paper, 1, 1, ("rapas",)) for _ in range(10)]) == 1
