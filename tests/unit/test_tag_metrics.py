"""The results of a search for several tags at once (issue 21), on hand-made outcomes."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.orchestrator.metrics import expected_calibration_error, summarize_tags, wilson_interval

T_RF = 0.1


def _outcomes():
    # 4 tests, 2 tags, 3 steps. Tag 0 is found in tests 0-2 from step 1 on; tag 1 in tests 0, 1, 3 at the end.
    hits = np.zeros((4, 2, 3))
    hits[0:3, 0, 1:] = 1
    hits[[0, 1, 3], 1, 2] = 1
    hits[0, 1, 1] = 1
    return hits


def test_per_tag_discovery_rates_and_all_found_are_counted_per_step():
    hits = _outcomes()
    out = summarize_tags(hits, hits, T_RF)
    assert [block["dr"] for block in out["per_tag"]] == [[0.0, 0.75, 0.75], [0.0, 0.25, 0.75]]
    # all tags found: test 0 at steps 1-2, test 1 at step 2 (tag 0 right, tag 1 right), test 3 never (tag 0 wrong)
    assert out["all_found"]["dr"] == [0.0, 0.25, 0.5]
    lo, hi = wilson_interval(2, 4)
    assert out["all_found"]["ci95"] == [round(lo, 6), round(hi, 6)]
    assert out["mean_tag_dr_final"] == 0.75
    assert out["all_found"]["time_to_dr90_s"] is None


def test_per_tag_calibration_is_each_tags_own():
    hits = _outcomes()
    conf = np.full(hits.shape, 0.5)
    conf[:, 0, :] = 0.9  # tag 0: 0.9 sure, right 3 times in 4 at the end; tag 1: 0.5 sure, right 3 in 4
    out = summarize_tags(hits, hits, T_RF, confidences=conf)
    ece = [block["calibration"]["ece_final"] for block in out["per_tag"]]
    assert ece == [pytest.approx(0.15), pytest.approx(0.25)]
    assert ece[0] == pytest.approx(expected_calibration_error(conf[:, 0, -1], hits[:, 0, -1]))


def test_time_until_all_tags_are_decided_is_the_last_tags_decision():
    hits = _outcomes()
    decided = [[0, 2], [1, 1], [None, 0], [2, 1]]
    out = summarize_tags(hits, hits, T_RF, decided_steps=decided)
    # all decided at steps 2, 1, never, 2 -> times 0.3, 0.2, 0.3 s; one test in four undecided
    assert out["all_decided"] == {"median_s": 0.3, "p90_s": pytest.approx(0.3), "undecided": 0.25}
    assert out["per_tag"][0]["decision"]["undecided"] == 0.25


def test_one_tag_gives_the_single_tag_block():
    hits = _outcomes()[:, :1, :]
    out = summarize_tags(hits, hits, T_RF)
    assert out["all_found"]["dr"] == out["per_tag"][0]["dr"]


def test_shapes_that_do_not_match_are_refused():
    with pytest.raises(ValueError, match="one shape"):
        summarize_tags(np.zeros((2, 3)), np.zeros((2, 3)), T_RF)
