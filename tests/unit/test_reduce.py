"""The streamed reduction (reduce.AlgorithmTally) against the reduction over every outcome at once
(metrics.summarize_algorithm): value for value, in any arrival order."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ra2vipas.services.orchestrator.metrics import expected_calibration_error, summarize_algorithm
from ra2vipas.services.orchestrator.reduce import AlgorithmTally, LatencyTally

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


def latencies_ms(rng, n: int) -> list[float]:
    """Sample-to-command latencies as the sensors report them: milliseconds rounded to 4
    decimals, a long right tail, and many ties."""
    return [round(float(v), 4) for v in 0.2 + rng.gamma(1.5, 0.4, n)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_latency_tally_is_np_percentile_value_for_value_in_any_batching(seed):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 10, 119, 1000, 4321):
        values = latencies_ms(rng, n) if n % 2 else [round(1.0 + 0.0005 * int(k), 4) for k in rng.integers(0, 40, n)]
        tally = LatencyTally()
        cuts = sorted(rng.integers(0, n, 5).tolist())
        for lo, hi in zip([0, *cuts], [*cuts, n]):
            tally.add(values[lo:hi])
        assert tally.count == n
        for q in (0, 1, 25, 50, 90, 99, 99.9, 100):
            assert tally.percentiles([q]) == [float(np.percentile(values, q))], (n, q)
        assert tally.summary() == {"p50": round(float(np.percentile(values, 50)), 4),
                                   "p99": round(float(np.percentile(values, 99)), 4)}
    assert LatencyTally().summary() is None


def test_the_end_of_campaign_reduction_holds_no_per_step_latency():
    """What the scheduler runs when a realtime campaign ends (``scheduler.reduce_recorded`` over
    the recorded episodes, streamed): from 500 to 2 000 episodes of 120 steps, its peak memory
    grows by a few scalars per test, not by the 1 500 x 119 latencies (~5.7 MB as a list);
    and its p50/p99 are numpy's over every latency."""
    import tracemalloc

    from ra2vipas.services.orchestrator.scheduler import reduce_recorded
    from ra2vipas.services.protocol.scenario import build_scenario

    scenario = build_scenario("paper", {"steps": 120})
    rng = np.random.default_rng(5)
    stored = [json.dumps(latencies_ms(rng, 119)) for _ in range(400)]  # as the episodes table holds them
    hits = [bool(t % 3) for t in range(120)]
    check = json.dumps({"sensor_model": "scenario", "rx_dir": "paper", "lobe": "dip", "lobe_evidence": 1.5})

    def recorded(episodes: int):
        for k in range(episodes):  # rows as Store.episode_outcomes yields them, one at a time, decoded
            yield {"algorithm": "ra2vipas", "hits": list(hits), "in_fov": list(hits), "confidences": None, "decided_step": None,
                   "n_estimates": 120, "latencies": json.loads(stored[k % len(stored)]), "rig": "rig-1",
                   "model_check": json.loads(check)}

    def peak_kib(episodes: int) -> float:
        tracemalloc.start()
        try:
            tallies, latencies, checks = reduce_recorded(recorded(episodes), ["ra2vipas"], scenario)
            assert tallies["ra2vipas"].tests == episodes and latencies.count == episodes * 119 and checks.total == episodes
            return tracemalloc.get_traced_memory()[1] / 1024
        finally:
            tracemalloc.stop()

    small, large = peak_kib(500), peak_kib(2000)
    assert large - small < 512, f"peak {small:.0f} KiB for 500 episodes, {large:.0f} KiB for 2 000"
    _, latencies, _ = reduce_recorded(recorded(700), ["ra2vipas"], scenario)
    every = [v for row in recorded(700) for v in row["latencies"]]
    assert latencies.summary() == {"p50": round(float(np.percentile(every, 50)), 4),
                                   "p99": round(float(np.percentile(every, 99)), 4)}
