"""The streamed reduction (reduce.AlgorithmTally) against the reduction over every outcome at once
(metrics.summarize_algorithm): value for value, in any arrival order."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.orchestrator.metrics import expected_calibration_error, summarize_algorithm
from ra2vipas.services.orchestrator.reduce import AlgorithmTally

STEPS = 60
PERIOD = 0.1


def outcomes(seed: int, tests: int, decide: bool = False):
    """Random per-step hits, in-FoV flags and confidences with full 53-bit mantissas (so float
    sums in different orders do differ in their last bits), and early decisions held to the end."""
    rng = np.random.default_rng(seed)
    hits = rng.random((tests, STEPS)) < np.linspace(0.2, 0.95, STEPS)
    in_fov = rng.random((tests, STEPS)) < 0.7
    conf = rng.random((tests, STEPS)) ** 1.7 * (1.0 - 1e-9) + rng.random((tests, STEPS)) * 1e-9
    decided: list[int | None] = [None] * tests
    if decide:
        for k in range(tests):
            if rng.random() < 0.7:
                d = int(rng.integers(0, STEPS))
                decided[k] = d
                hits[k, d:] = hits[k, d]
                in_fov[k, d:] = in_fov[k, d]
                conf[k, d:] = conf[k, d]
    return hits, in_fov, conf, decided


def tally(hits, in_fov, conf, decided, order, decisions: bool) -> dict:
    t = AlgorithmTally(STEPS, PERIOD)
    for k in order:
        t.add(hits[k], in_fov[k], conf[k], decided[k], STEPS if decided[k] is None else decided[k] + 1)
    return t.summary(decisions=decisions)


@pytest.mark.parametrize("decide", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tally_equals_the_whole_array_reduction_in_any_order(seed, decide):
    tests = 257
    hits, in_fov, conf, decided = outcomes(seed, tests, decide)
    expected = summarize_algorithm(hits, in_fov, PERIOD, conf, decided if decide else None)
    rng = np.random.default_rng(100 + seed)
    orders = [list(range(tests)), list(reversed(range(tests))), list(rng.permutation(tests)), list(rng.permutation(tests))]
    for order in orders:
        assert tally(hits, in_fov, conf, decided, order, decide) == expected


def test_the_same_outcomes_in_two_orders_give_identical_blocks():
    hits, in_fov, conf, decided = outcomes(7, 500, decide=True)
    forward = tally(hits, in_fov, conf, decided, range(500), True)
    shuffled = tally(hits, in_fov, conf, decided, np.random.default_rng(3).permutation(500), True)
    assert forward == shuffled
    assert forward["calibration"]["ece_all"] is not None and forward["decision"]["accuracy"] is not None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_unrounded_ece_over_every_step_is_the_same_in_any_order(seed):
    """Rounding to 6 digits hides most last-bit differences; the unrounded ECE must be equal too,
    or a value that falls on a rounding boundary would differ between two arrival orders."""
    hits, in_fov, conf, decided = outcomes(seed, 257)
    expected = expected_calibration_error(conf, hits)
    rng = np.random.default_rng(seed)
    for order in (range(257), reversed(range(257)), rng.permutation(257)):
        t = AlgorithmTally(STEPS, PERIOD)
        for k in order:
            t.add(hits[k], in_fov[k], conf[k])
        assert t.ece_all() == expected


def test_float_running_sums_would_depend_on_the_order():
    """Why the tally sums exactly: the same confidences summed as floats in two orders differ
    (so a float tally would fail the tests above now and then)."""
    _, _, conf, _ = outcomes(0, 257, False)
    values = conf.ravel()
    perm = np.random.default_rng(1).permutation(values.size)
    forward = 0.0
    for v in values.tolist():
        forward += v
    shuffled = 0.0
    for v in values[perm].tolist():
        shuffled += v
    assert forward != shuffled


def test_without_confidences_there_is_no_calibration_block():
    hits, in_fov, conf, decided = outcomes(4, 30)
    t = AlgorithmTally(STEPS, PERIOD)
    for k in range(30):
        t.add(hits[k], in_fov[k], conf[k] if k != 5 else None)
    block = t.summary()
    assert "calibration" not in block
    assert block == summarize_algorithm(hits, in_fov, PERIOD)


def test_a_series_of_the_wrong_length_is_refused():
    t = AlgorithmTally(STEPS, PERIOD)
    with pytest.raises(ValueError):
        t.add(np.ones(STEPS - 1, bool), np.ones(STEPS - 1, bool))
    with pytest.raises(ValueError):
        t.add(np.ones(STEPS, bool), np.ones(STEPS, bool), np.full(STEPS + 1, 0.5))
    with pytest.raises(ValueError):
        AlgorithmTally(STEPS, PERIOD).summary()
