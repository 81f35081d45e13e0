"""Scoring: the paper's association rule, Wilson intervals, time to DR level."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.orchestrator.metrics import (
    Z95,
    associate,
    decision_summary,
    expected_calibration_error,
    reliability_bins,
    score_episode,
    score_test,
    summarize_algorithm,
    time_to_level,
    wilson_interval,
)

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


# -- moving targets: the association at time t against the bearings at time t ----------------------


def test_score_test_against_per_step_bearings():
    """Target 0 walks from 0 to 40 degrees, target 1 stands at 20 degrees; the estimate stays
    at 15 degrees. Against the bearings of each step, the walker is the nearest target while it
    is between 10 and 20 degrees; a static truth (the walker frozen at its start) never sees it."""
    walker = np.radians([0.0, 8.0, 12.0, 18.0, 25.0, 32.0, 40.0])
    bearings = np.column_stack([walker, np.full(walker.size, D(20.0))])  # (T, N)
    est = np.full(walker.size, D(15.0))
    np.testing.assert_array_equal(associate(est, bearings), [1, 1, 0, 0, 1, 1, 1])
    hits, in_fov = score_test(est, bearings, tx_index=0, fov_half_angle_rad=D(10.0))
    np.testing.assert_array_equal(hits, [False, False, True, True, False, False, False])
    np.testing.assert_array_equal(in_fov, [False, True, True, True, True, False, False])  # |15 - gamma_0(t)| <= 10
    static_hits, _ = score_test(est, bearings[0], tx_index=0, fov_half_angle_rad=D(10.0))
    assert not static_hits.any()
    # per-step bearings equal to the static ones score exactly as the static ones
    rng = np.random.default_rng(2)
    b = rng.uniform(-math.pi, math.pi, 9)
    e = rng.uniform(-math.pi, math.pi, 30)
    for got, want in zip(score_test(e, np.tile(b, (30, 1)), 4, D(22.5)), score_test(e, b, 4, D(22.5))):
        np.testing.assert_array_equal(got, want)


def test_per_step_bearings_across_the_wrap_and_of_an_episode_that_ended_early():
    bearings = np.array([[D(179.0), 0.0], [D(-179.0), 0.0], [D(-170.0), 0.0]])
    np.testing.assert_array_equal(associate(np.array([math.pi, D(-178.0), D(100.0)]), bearings), [0, 0, 0])
    np.testing.assert_array_equal(associate(np.array([math.pi, D(-178.0)]), bearings), [0, 0])  # first T rows
    with pytest.raises(ValueError, match="T >= 4"):
        associate(np.zeros(4), bearings)


def test_truth_bearings_reads_trajectories_and_refuses_inconsistent_truth():
    from ra2vipas.services.orchestrator.metrics import truth_bearings
    from ra2vipas.services.protocol.messages import EpisodeTruth, TargetTrajectory

    base = dict(episode_id="e", bearings_rad=(0.1, 0.2, 0.3), ranges_m=(1.0, 2.0, 3.0), tx_index=1)
    v1 = EpisodeTruth(**base)  # a node that sends no trajectories: a static world
    np.testing.assert_array_equal(truth_bearings(v1, 4), [0.1, 0.2, 0.3])
    walk = TargetTrajectory(index=2, bearings_rad=(0.3, 0.4, 0.5, 0.6), ranges_m=(3.0, 3.1, 3.2, 3.3))
    got = truth_bearings(EpisodeTruth(**base, trajectories=(walk,)), 4)
    np.testing.assert_array_equal(got, [[0.1, 0.2, 0.3], [0.1, 0.2, 0.4], [0.1, 0.2, 0.5], [0.1, 0.2, 0.6]])
    bad = [
        (walk.model_copy(update={"index": 3}),),  # no such target
        (walk, walk),  # twice
        (walk.model_copy(update={"bearings_rad": (0.3, 0.4)}),),  # not one per step
        (walk.model_copy(update={"ranges_m": (3.0,)}),),
    ]
    for trajectories in bad:
        assert truth_bearings(EpisodeTruth(**base, trajectories=trajectories), 4) is None
    assert truth_bearings(EpisodeTruth(**{**base, "tx_index": 3}), 4) is None


# -- confidence and early decision (issue 9) ------------------------------------------------------

def test_expected_calibration_error_on_a_hand_made_case():
    # bin [0.9, 1.0]: 4 answers at 0.95 and 3 right -> |0.95 - 0.75| weighted 4/10;
    # bin [0.5, 0.6): 6 answers at 0.55, 3 right -> |0.55 - 0.5| weighted 6/10
    conf = [0.95] * 4 + [0.55] * 6
    hit = [1, 1, 1, 0] + [1, 1, 1, 0, 0, 0]
    assert expected_calibration_error(conf, hit) == pytest.approx(0.4 * 0.2 + 0.6 * 0.05)
    # a perfectly calibrated predictor, and a confidence of exactly 1 (the last bin is closed)
    assert expected_calibration_error([0.25] * 4, [1, 0, 0, 0]) == pytest.approx(0.0)
    assert expected_calibration_error([1.0, 1.0], [1, 0]) == pytest.approx(0.5)
    assert expected_calibration_error([], []) is None
    bins = reliability_bins(conf, hit)
    assert [b["n"] for b in bins] == [0, 0, 0, 0, 0, 6, 0, 0, 0, 4]
    assert bins[9]["accuracy"] == 0.75 and bins[9]["confidence"] == pytest.approx(0.95) and bins[0]["accuracy"] is None


def test_summaries_carry_calibration_when_there_are_confidences():
    hits = np.array([[0, 1, 1], [0, 0, 1]])
    conf = np.array([[0.2, 0.7, 0.9], [0.1, 0.4, 0.8]])
    block = summarize_algorithm(hits, hits, 0.1, conf)
    assert block["calibration"]["ece_final"] == pytest.approx(expected_calibration_error([0.9, 0.8], [1, 1]), abs=1e-6)
    assert block["calibration"]["ece_all"] == pytest.approx(expected_calibration_error(conf, hits), abs=1e-6)
    # the final confidences 0.9 and 0.8 fall in bins 9 and 8: half of each bin's 2c(1 - c)
    floor = 0.5 * (2 * 0.9 * 0.1) + 0.5 * (2 * 0.8 * 0.2)
    assert block["calibration"]["ece_final_floor"] == pytest.approx(floor, abs=1e-6)
    assert "decision" not in summarize_algorithm(hits, hits, 0.1)


def test_the_ece_sampling_floor_is_the_mean_ece_of_a_perfectly_calibrated_confidence():
    """Hand cases (one sample: E|c - Bernoulli(c)| = 2c(1-c); certain confidences: 0), a Monte
    Carlo of hits drawn as Bernoulli(confidence) in mixed bins, and the normal approximation used
    above ``exact_up_to`` samples per bin agreeing with the exact law on a large bin."""
    from ra2vipas.services.orchestrator.metrics import ece_sampling_floor

    assert ece_sampling_floor([0.9]) == pytest.approx(2 * 0.9 * 0.1)
    assert ece_sampling_floor([0.0, 1.0, 1.0]) == 0.0
    # two samples in one bin, mean 0.93: 0, 1 or 2 hits with probability 0.004, 0.132, 0.864
    assert ece_sampling_floor([0.9, 0.96]) == pytest.approx(0.004 * 0.93 + 0.132 * 0.43 + 0.864 * 0.07, abs=1e-9)
    assert ece_sampling_floor([]) is None and ece_sampling_floor([float("nan")]) is None
    rng = np.random.default_rng(11)
    for conf in (rng.beta(9, 1, 200), rng.uniform(0.0, 1.0, 60)):
        draws = [expected_calibration_error(conf, rng.random(conf.size) < conf) for _ in range(4000)]
        assert ece_sampling_floor(conf) == pytest.approx(np.mean(draws), abs=4 * np.std(draws) / math.sqrt(len(draws)))
        assert ece_sampling_floor(conf[::-1]) == ece_sampling_floor(conf)  # whatever order the tests arrived in
    big = rng.uniform(0.9, 1.0, 3000)
    assert ece_sampling_floor(big, exact_up_to=0) == pytest.approx(ece_sampling_floor(big, exact_up_to=5000), rel=0.01)


def test_decision_summary():
    d = decision_summary([1, 1, 0, 1], [2, None, 0, 9], 0.1)
    assert d["accuracy"] == 0.75 and d["accuracy_ci95"] == [pytest.approx(v, abs=1e-6) for v in wilson_interval(3, 4)]
    assert d["median_s"] == pytest.approx(0.3) and d["undecided"] == 0.25
    assert d["p90_s"] == pytest.approx(np.percentile([0.3, 0.1, 1.0], 90))


def test_an_early_decision_keeps_its_target_as_targets_move():
    """After a decision at step 1 the answer is the target named then, even when another one
    walks in front of the estimate later."""
    bearings = np.array([[0.0, 1.0], [0.0, 1.0], [0.02, 1.0], [0.5, 0.0]])  # target 0 walks away, 1 crosses to 0
    hits, in_fov, chosen = score_episode([0.0, 0.01], bearings, tx_index=0, fov_half_angle_rad=0.3, steps=4, decided_step=1)
    assert chosen.tolist() == [0, 0, 0, 0] and hits.tolist() == [True] * 4 and in_fov.tolist() == [True] * 4
    # without a decision the same estimate at step 3 would name target 1
    hits, _, chosen = score_episode([0.0, 0.01, 0.01, 0.01], bearings, 0, 0.3, 4)
    assert chosen.tolist() == [0, 0, 0, 1] and hits.tolist() == [True, True, True, False]


def test_the_confidence_map_fit_recovers_a_known_map_and_the_controller_applies_it():
    """bench calibrate's logistic fit finds the map that generated the hits, and a controller
    given that map reports sigmoid((A + G walks) logit(raw) + B + C walks + D rho + E clutter + F crowding),
    crowding exp(-d / 1 deg) for the gap d from its answer to the nearest other track."""
    from types import SimpleNamespace

    from ra2vipas.services.controller.confidence import Confidence, ConfidenceMap
    from ra2vipas.services.controller.rf_belief import IsoLevel
    from ra2vipas.services.controller.tracks import BearingTracker
    from ra2vipas.services.controller.vision_belief import CameraBelief, VisionBelief
    from ra2vipas.services.orchestrator.calibration import fit_platt, platt

    rng = np.random.default_rng(5)
    raw = rng.uniform(0.02, 0.98, 100000)
    cov = rng.uniform(0.0, 1.0, (raw.size, 4))
    truth = (1.3, -0.4, -2.0, 0.8, -1.5, -1.0, -0.6)
    hit = (rng.uniform(size=raw.size) < platt(raw, cov, *truth)).astype(float)
    fitted = fit_platt(raw, cov, hit)
    np.testing.assert_allclose(fitted, truth, atol=0.12)
    assert expected_calibration_error(platt(raw, cov, *fitted), hit) < 0.02
    confidence = Confidence(ConfidenceMap.from_vector(truth))
    rf = SimpleNamespace(listens=True, tx_walks=0.5)
    iso = IsoLevel(3.0)
    got = confidence(0.7, confidence.covariates(0.0, rf, VisionBelief(), iso))
    want = float(platt(np.array([0.7]), np.array([[0.5, 0.0, 0.0, 0.0]]), *truth)[0])
    assert got == pytest.approx(want)
    # with tracks: the answer at 0.0 names the track there; the nearest other is 0.5 deg away
    camera = CameraBelief.__new__(CameraBelief)
    camera.tracks = BearingTracker.__new__(BearingTracker)
    camera.tracks._bearing = np.array([0.0, math.radians(0.5), math.radians(30.0)])
    camera.tracks._view = np.arange(3)
    camera.tracks._clutter = np.array([0.0, 1.0])
    camera.tracks.count_limit = 0.3
    got = confidence(0.7, confidence.covariates(0.0, rf, camera, iso))
    want = float(platt(np.array([0.7]), np.array([[0.5, 0.0, 0.0, math.exp(-0.5)]]), *truth)[0])
    assert got == pytest.approx(want)
    # the camera alone cannot hear the Tx walk: its covariate is the share of tracks seen walking
    rf.listens = False
    camera.tracks.walking_share = lambda prior=0.3, strength=2.0: 0.8
    got = confidence(0.7, confidence.covariates(0.0, rf, camera, iso))
    want = float(platt(np.array([0.7]), np.array([[0.8, 0.0, 0.0, math.exp(-0.5)]]), *truth)[0])
    assert got == pytest.approx(want) and got != pytest.approx(float(platt(np.array([0.7]), np.array([[0.5, 0.0, 0.0, math.exp(-0.5)]]), *truth)[0]))
