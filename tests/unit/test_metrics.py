"""Scoring: the paper's association rule, Wilson intervals, time to DR level."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.orchestrator.metrics import Z95, associate, score_test, summarize_algorithm, time_to_level, wilson_interval

D = math.radians


def test_associate_picks_the_nearest_bearing():
    bearings = np.array([D(0.0), D(90.0), D(-90.0), D(170.0)])
    est = np.array([D(10.0), D(50.0), D(-100.0), D(179.0), D(-179.0), D(135.0)])
    np.testing.assert_array_equal(associate(est, bearings), [0, 1, 2, 3, 3, 3])


def test_associate_across_the_wrap():
    bearings = np.array([D(-179.0), D(170.0), D(0.0)])
    # 179 is 2 degrees from -179 and 9 from 170; a plain difference would pick 170
    np.testing.assert_array_equal(associate(np.array([D(179.0), -math.pi, math.pi]), bearings), [0, 0, 0])
    np.testing.assert_array_equal(associate(np.array([D(175.0)]), bearings), [1])


def test_associate_is_invariant_to_turns():
    rng = np.random.default_rng(0)
    bearings = rng.uniform(-math.pi, math.pi, 20)
    est = rng.uniform(-math.pi, math.pi, 200)
    ref = associate(est, bearings)
    np.testing.assert_array_equal(associate(est + 2 * math.pi, bearings - 4 * math.pi), ref)
    brute = [int(np.argmin([abs(math.remainder(e - b, 2 * math.pi)) for b in bearings])) for e in est]
    np.testing.assert_array_equal(ref, brute)


def test_score_test():
    bearings = np.array([D(-179.0), D(170.0), D(0.0)])
    est = np.array([D(0.0), D(179.0), D(172.0), D(158.0), D(-160.0)])
    hits, in_fov = score_test(est, bearings, tx_index=0, fov_half_angle_rad=D(22.5))
    np.testing.assert_array_equal(hits, [False, True, False, False, True])
    # "Tx in FoV at gamma_hat" is a different, looser criterion (the authors' code's metric)
    np.testing.assert_array_equal(in_fov, [False, True, True, False, True])


def test_wilson_known_values():
    # closed forms at the extremes: [0, z^2/(n+z^2)] and [n/(n+z^2), 1]
    z2 = Z95**2
    assert wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z2), 1.0))
    assert wilson_interval(0, 10)[1] == pytest.approx(0.27753, abs=1e-5)
    assert wilson_interval(10, 10)[0] == pytest.approx(0.72247, abs=1e-5)
    # R: prop.test(5, 10, correct=FALSE)$conf.int -> 0.2365931 0.7634069
    assert wilson_interval(5, 10) == pytest.approx((0.2365931, 0.7634069), abs=1e-7)
    # 47/50 -> [0.8378, 0.9794]
    lo, hi = wilson_interval(47, 50)
    assert lo == pytest.approx(0.83782, abs=1e-4) and hi == pytest.approx(0.97938, abs=1e-4)
    assert wilson_interval(3, 0) == (0.0, 1.0)


def test_wilson_properties():
    for n in (1, 7, 50, 200):
        prev = None
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n + 1e-12 and k / n - 1e-12 <= hi <= 1.0
            mlo, mhi = wilson_interval(n - k, n)
            assert (lo, hi) == pytest.approx((1 - mhi, 1 - mlo))
            if prev:
                assert lo >= prev[0] and hi >= prev[1]
            prev = (lo, hi)
    widths = [np.diff(wilson_interval(0.9 * n, n))[0] for n in (10, 100, 1000)]
    assert widths[0] > widths[1] > widths[2]
    # a wider z gives a wider interval
    assert np.diff(wilson_interval(5, 10, z=2.576))[0] > np.diff(wilson_interval(5, 10))[0]


def test_time_to_level():
    T = 0.1
    assert time_to_level(np.array([0.95, 0.92, 1.0]), 0.9, T) == pytest.approx(T)  # from the first sample
    assert time_to_level(np.array([0.5, 0.95, 0.8, 0.92, 0.95]), 0.9, T) == pytest.approx(0.4)  # step 3 -> 4 T
    assert time_to_level(np.array([0.95, 0.95, 0.89]), 0.9, T) is None  # ends below
    assert time_to_level(np.array([0.1, 0.2, 0.3]), 0.9, T) is None
    assert time_to_level(np.array([0.1, 0.9]), 0.9, T) == pytest.approx(0.2)  # exactly at the level counts
    assert time_to_level(np.array([0.1, 0.9 - 1e-15]), 0.9, T) == pytest.approx(0.2)  # round-off tolerated
    assert time_to_level(np.array([0.0, 0.0, 1.0]), 0.9, 0.25) == pytest.approx(0.75)
    assert time_to_level(np.array([0.85]), 0.9, T) is None


def test_summarize_algorithm():
    hits = np.array([
        [0, 1, 1, 1],
        [0, 0, 1, 1],
        [1, 1, 1, 1],
        [0, 0, 0, 1],
    ], dtype=bool)
    in_fov = np.ones_like(hits)
    in_fov[1, -1] = False
    s = summarize_algorithm(hits, in_fov, 0.1)
    assert s["dr"] == [0.25, 0.5, 0.75, 1.0]
    assert s["dr_final"] == 1.0
    assert s["ci95"] == pytest.approx(list(wilson_interval(4, 4)), abs=1e-6)
    assert len(s["dr_ci95"]) == 4
    assert s["dr_ci95"][0] == pytest.approx(list(wilson_interval(1, 4)), abs=1e-6)
    assert s["time_to_dr90_s"] == pytest.approx(0.4)
    assert s["in_fov_final"] == 0.75
