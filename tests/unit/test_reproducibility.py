"""The rules by which numbers recorded on another machine are compared
(services/orchestrator/reproducibility.py): each can fail."""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.orchestrator import reproducibility as r


def test_a_draw_digest_ignores_last_bits_and_sees_a_real_change():
    draws = [{"rssi": [-41.2345678912, -55.5], "bearings": [0.1, -3.0]}, [1, 2, 3]]
    nudged = [{"rssi": [np.nextafter(-41.2345678912, 0.0) - 2e-14, -55.5], "bearings": [0.1 + 1e-15, -3.0]}, [1, 2, 3]]
    moved = [{"rssi": [-41.2345, -55.5], "bearings": [0.1, -3.0]}, [1, 2, 3]]
    assert r.draw_digest(draws) == r.draw_digest(nudged)
    assert r.draw_digest(draws) != r.draw_digest(moved)
    assert r.draw_digest([[1, 2, 3]]) != r.draw_digest([[1, 3, 2]])  # integers and order exactly
    assert r.canonical(-0.0) == 0.0 and r.canonical(math.inf) == "inf"


def _record(digests: dict[str, list[str]], hits: dict[str, str]) -> dict:
    return {"choices_sha256": digests, "final_hits": hits}


def test_decisions_may_take_another_path_at_near_ties_only_within_the_bounds():
    then = _record({"a": [f"d{k}" for k in range(10)], "b": [f"e{k}" for k in range(10)]}, {"a": "1" * 10, "b": "1" * 10})
    same = _record(dict(then["choices_sha256"]), dict(then["final_hits"]))
    assert r.decision_drift([("c", same, then)]) == ([], [])

    # two of twenty trajectories elsewhere (10 %), one with another final hit (5 %): within the bounds
    few = _record({"a": ["x0", *then["choices_sha256"]["a"][1:]], "b": ["y0", *then["choices_sha256"]["b"][1:]]},
                  {"a": "0" + "1" * 9, "b": "1" * 10})
    problems, flipped = r.decision_drift([("c", few, then)])
    assert problems == [] and flipped == [("c", "a", 0), ("c", "b", 0)]

    # a change of behaviour: most trajectories elsewhere
    many = _record({"a": [f"z{k}" for k in range(10)], "b": then["choices_sha256"]["b"]}, then["final_hits"])
    assert any("took another path" in p for p in r.decision_drift([("c", many, then)])[0])

    # too many final hits changed, even on paths that may differ
    hits = _record({"a": ["x0", "x1", *then["choices_sha256"]["a"][2:]], "b": then["choices_sha256"]["b"]},
                   {"a": "00" + "1" * 8, "b": "1" * 10})
    assert any("final hits changed" in p for p in r.decision_drift([("c", hits, then)])[0])

    # a final hit may never change where the choices did not
    scored = _record(then["choices_sha256"], {"a": "1" * 9 + "0", "b": "1" * 10})
    assert r.decision_drift([("c", scored, then)])[0] == ["c: a test 9: final hit '0' != '1' with the same choices"]

    # the oracle has no choices: its hits must be equal
    oracle = _record(then["choices_sha256"], {**then["final_hits"], "oracle": "0"})
    assert r.decision_drift([("c", oracle, {**then, "final_hits": {**then["final_hits"], "oracle": "1"}})])[0]


def test_results_compare_fits_within_their_tolerance_and_decisions_exactly():
    then = {"pod": {"r2": 0.98795}, "algorithms": {"a": {"dr": [0.5, 0.75], "ci95": [0.4, 0.9],
                                                         "calibration": {"ece_final": 0.0104}}}}

    def now(r2=0.98795, dr=(0.5, 0.75), ci=(0.4, 0.9), ece=0.0104):
        return {"pod": {"r2": r2}, "algorithms": {"a": {"dr": list(dr), "ci95": list(ci), "calibration": {"ece_final": ece}}}}

    exact = r.results_tolerance({}, tests=4)
    assert r.differences(now(r2=0.98795 + 5e-5, ece=0.0104 + 5e-4), then, exact) == []
    assert r.differences(now(r2=0.98845), then, exact) == ["/pod/r2: 0.98845 != 0.98795 (tolerance 0.0001)"]
    assert r.differences(now(ece=0.0124), then, exact)
    assert r.differences(now(dr=(0.5, 1.0)), then, exact) == ["/algorithms/a/dr[1]: 1.0 != 0.75"]

    one_flip = r.results_tolerance({"a": 1}, tests=4)
    assert r.differences(now(dr=(0.5, 1.0), ci=(0.5, 1.0), ece=0.2), then, one_flip) == []
    assert r.differences(now(dr=(0.0, 0.75)), then, one_flip)  # two tests' worth
    assert r.differences(now(r2=0.9), then, one_flip)  # the POD model is not the algorithm's


def test_per_test_outcomes_and_paired_blocks_of_a_flipped_algorithm_are_left_to_the_decision_check():
    then = {"outcomes": {"a": [1, 1], "b": [1, 0]}, "paired": [{"a": "a", "b": "b", "p_value": 1.0}]}
    now = {"outcomes": {"a": [1, 0], "b": [1, 0]}, "paired": [{"a": "a", "b": "b", "p_value": 0.5}]}
    assert r.differences(now, then, r.results_tolerance({}, tests=2))
    assert r.differences(now, then, r.results_tolerance({"a": 1}, tests=2)) == []
    assert r.differences({**now, "outcomes": {"a": [1, 1], "b": [0, 0]}}, then, r.results_tolerance({"a": 1}, tests=2))
