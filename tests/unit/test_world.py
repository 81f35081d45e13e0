"""The simulated world: physics of Table I, target placement, sensing and seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.protocol.measurements import CameraFrame, StepMeasurement, TrainingSample
from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import (
    SimulatedPlatform,
    TrainingEpisode,
    episode_streams,
    place_targets,
    training_streams,
)
from tests.conftest import make_platform, polar_positions, small_scenario

# -- physics -----------------------------------------------------------------------------------


def test_wrap_range_and_identity():
    x = np.linspace(-20.0, 20.0, 2001)
    w = physics.wrap(x)
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(x), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-12)
    assert physics.wrap(math.pi) == pytest.approx(-math.pi)
    assert physics.wrap(math.radians(179) - math.radians(-179)) == pytest.approx(math.radians(-2))


def test_path_loss_is_log_distance():
    sc = build_scenario("paper")
    assert physics.path_loss_dbm(sc, 1.0) == pytest.approx(-30.0)
    # n = 2: -20 dB per decade, -6.02 dB per doubling
    assert physics.path_loss_dbm(sc, 10.0) == pytest.approx(-50.0)
    assert physics.path_loss_dbm(sc, 4.0) - physics.path_loss_dbm(sc, 2.0) == pytest.approx(-20 * math.log10(2))
    d = np.linspace(0.3, 9.0, 50)
    np.testing.assert_allclose(physics.range_from_rssi(sc, physics.path_loss_dbm(sc, d)), d, rtol=1e-12)
    sc4 = build_scenario("paper", {"path_loss_exponent": 4.0, "path_loss_ref_dbm": -40.0, "path_loss_ref_distance_m": 2.0})
    assert physics.path_loss_dbm(sc4, 20.0) == pytest.approx(-80.0)


def test_attenuation_shape():
    sc = build_scenario("paper")
    assert physics.attenuation(sc, 0.0) == pytest.approx(1.0)
    assert physics.attenuation(sc, 1.0) == pytest.approx(0.5)
    assert physics.attenuation(sc, 2.0) == 0.0  # clipped at 0
    x = np.linspace(-math.pi, math.pi, 101)
    np.testing.assert_allclose(physics.attenuation(sc, x), physics.attenuation(sc, -x))
    np.testing.assert_allclose(physics.attenuation(sc, x + 2 * math.pi), physics.attenuation(sc, x))
    assert np.all((physics.attenuation(sc, x) >= 0) & (physics.attenuation(sc, x) <= 1))


def test_directional_rssi_models():
    paper = build_scenario("paper")
    dbg = build_scenario("paper", {"antenna_model": "db-gain", "antenna_floor_db": -20.0})
    d = 2.0
    g = physics.path_loss_dbm(paper, d)
    mis = np.linspace(-math.pi, math.pi, 361)
    # paper (eq. 6): g * rho, so |z| is largest when aligned and z -> 0 far from the lobe
    zp = physics.directional_rssi_dbm(paper, d, mis)
    np.testing.assert_allclose(zp, g * physics.attenuation(paper, mis))
    assert np.argmax(np.abs(zp)) == np.argmin(np.abs(mis))
    assert np.argmin(zp) == np.argmin(np.abs(mis))
    assert zp.max() == 0.0
    # db-gain: z = g + gain, highest when aligned, never below g + floor
    zd = physics.directional_rssi_dbm(dbg, d, mis)
    assert np.argmax(zd) == np.argmin(np.abs(mis))
    assert zd.max() == pytest.approx(g)
    assert zd.min() == pytest.approx(g - 20.0)
    assert physics.directional_rssi_dbm(dbg, d, 1.0) == pytest.approx(g + 10 * math.log10(0.5))


def test_pod_is_equation_22():
    sc = build_scenario("paper")
    d = np.array([0.5, 1.0, 2.5, 3.0, 4.5, 6.0, 7.0])
    expected = 1.0 / ((1.0 + np.exp(4.0 * (d - 4.5))) * (1.0 + np.exp(-(d - 2.5))))
    np.testing.assert_allclose(physics.pod(sc, d), expected, rtol=1e-12)
    assert np.all((physics.pod(sc, np.linspace(0, 100, 1000)) >= 0) & (physics.pod(sc, np.linspace(0, 100, 1000)) <= 1))
    r = physics.path_loss_dbm(sc, d)
    np.testing.assert_allclose(physics.pod_of_rssi(sc, r), expected, rtol=1e-9)


# -- placement -----------------------------------------------------------------------------------


def test_reference_placement_constraints_over_many_draws():
    sc = build_scenario("paper")
    rng = np.random.default_rng(12345)
    tx_seen = np.zeros(sc.n_targets, dtype=int)
    for _ in range(300):
        truth = place_targets(sc, rng)
        assert truth.positions_m.shape == (sc.n_targets, 2)
        assert np.all(np.abs(truth.positions_m) <= sc.arena_half_width_m)
        d = truth.ranges_m
        assert np.all(d >= sc.min_target_range_m)
        assert truth.tx_range_m < sc.tx_max_range_m
        others = np.delete(d, truth.tx_index)
        assert np.all(np.abs(others - truth.tx_range_m) > sc.min_range_gap_m)
        tx_seen[truth.tx_index] += 1
    # the Tx index is drawn at random: every slot gets used, none dominates
    assert np.all(tx_seen > 0)
    assert tx_seen.max() < 40


def test_reference_placement_respects_custom_limits():
    sc = build_scenario("paper", {"n_targets": 6, "tx_max_range_m": 2.0, "min_range_gap_m": 2.5, "min_target_range_m": 1.0})
    rng = np.random.default_rng(7)
    for _ in range(100):
        truth = place_targets(sc, rng)
        assert 1.0 <= truth.tx_range_m < 2.0
        others = np.delete(truth.ranges_m, truth.tx_index)
        assert np.all(others >= 1.0)
        assert np.all(np.abs(others - truth.tx_range_m) > 2.5)


def test_uniform_placement_drops_the_range_constraints():
    sc = build_scenario("paper-uniform")
    rng = np.random.default_rng(3)
    tx_far = gap_violated = 0
    pts = []
    for _ in range(200):
        truth = place_targets(sc, rng)
        pts.append(truth.positions_m)
        assert np.all(truth.ranges_m >= sc.min_target_range_m)
        tx_far += truth.tx_range_m >= sc.tx_max_range_m
        others = np.delete(truth.ranges_m, truth.tx_index)
        gap_violated += np.any(np.abs(others - truth.tx_range_m) <= sc.min_range_gap_m)
    assert tx_far > 20
    assert gap_violated > 150
    pts = np.concatenate(pts)
    assert np.all(np.abs(pts) <= 5.0)
    # uniform in the square (minus the small disc): mean ~ 0, var ~ (2w)^2 / 12
    np.testing.assert_allclose(pts.mean(axis=0), 0.0, atol=0.15)
    np.testing.assert_allclose(pts.var(axis=0), 100.0 / 12.0, rtol=0.05)


def test_infeasible_placement_raises_scenario_error():
    sc = build_scenario("paper", {"n_targets": 2, "arena_half_width_m": 1.0, "tx_max_range_m": 1.0, "min_range_gap_m": 50.0})
    with pytest.raises(ScenarioError, match="infeasible"):
        place_targets(sc, np.random.default_rng(0))


def test_ground_truth_geometry():
    truth = make_platform(small_scenario(), polar_positions([2.0, 3.0, 4.0], [10.0, 179.0, -90.0]), tx_index=1).truth
    np.testing.assert_allclose(truth.ranges_m, [2.0, 3.0, 4.0])
    np.testing.assert_allclose(np.degrees(truth.bearings_rad), [10.0, 179.0, -90.0])
    assert truth.tx_range_m == pytest.approx(3.0)
    assert math.degrees(truth.tx_bearing_rad) == pytest.approx(179.0)


# -- seeding ----------------------------------------------------------------------------------------


def test_episode_streams_are_keyed_by_seed_and_test():
    a = episode_streams(5, 3).placement.random(8)
    b = episode_streams(5, 3).placement.random(8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, episode_streams(5, 4).placement.random(8))
    assert not np.array_equal(a, episode_streams(6, 3).placement.random(8))
    s = episode_streams(5, 3)
    draws = [s.placement.random(8), s.rf.random(8), s.camera.random(8)]
    assert not np.array_equal(draws[0], draws[1]) and not np.array_equal(draws[1], draws[2])
    assert not np.array_equal(training_streams(5).placement.random(8), a)


def test_platform_layout_is_the_placement_stream():
    sc = small_scenario()
    for k in (0, 1, 7):
        expected = place_targets(sc, episode_streams(11, k).placement)
        truth = SimulatedPlatform(sc, 11, k).truth
        np.testing.assert_array_equal(truth.positions_m, expected.positions_m)
        assert truth.tx_index == expected.tx_index


def test_same_seed_same_measurements_different_seed_different_layout():
    sc = small_scenario()
    p1, p2 = SimulatedPlatform(sc, 4, 2), SimulatedPlatform(sc, 4, 2)
    pans = np.linspace(-3, 3, 25)
    for t, pan in enumerate(pans):
        assert p1.sense(t, pan) == p2.sense(t, pan)
    layouts = {SimulatedPlatform(sc, seed, 2).truth.positions_m.tobytes() for seed in range(6)}
    assert len(layouts) == 6
    layouts = {SimulatedPlatform(sc, 4, k).truth.positions_m.tobytes() for k in range(6)}
    assert len(layouts) == 6


def test_radio_noise_does_not_depend_on_where_the_camera_looked():
    """RF and camera draw from separate streams: the RSSI noise of step t is the same whatever
    the pan history (paired comparison of algorithms)."""
    sc = small_scenario()
    a, b = SimulatedPlatform(sc, 9, 0), SimulatedPlatform(sc, 9, 0)
    rng = np.random.default_rng(0)
    for t in range(30):
        pa, pb = rng.uniform(-math.pi, math.pi, 2)
        ma, mb = a.sense(t, pa), b.sense(t, pb)
        assert ma.rf.iso_rssi_dbm == mb.rf.iso_rssi_dbm
        na = ma.rf.dir_rssi_dbm - float(physics.directional_rssi_dbm(sc, a.truth.tx_range_m, pa - a.truth.tx_bearing_rad))
        nb = mb.rf.dir_rssi_dbm - float(physics.directional_rssi_dbm(sc, b.truth.tx_range_m, pb - b.truth.tx_bearing_rad))
        assert na == pytest.approx(nb, abs=1e-9)


# -- sensing -----------------------------------------------------------------------------------------


def test_sense_returns_a_measurement_with_nu_sorted_frames():
    sc = small_scenario(n_targets=20)
    platform = SimulatedPlatform(sc, 1, 0)
    fov = sc.fov_half_angle_rad
    slack = 6 * sc.box_bearing_noise_rad
    boxes = 0
    for t, pan in enumerate(np.linspace(-math.pi, math.pi, 40, endpoint=False)):
        m = platform.sense(t, pan)
        assert isinstance(m, StepMeasurement)
        assert m.step == t and m.pan_rad == pan
        assert len(m.frames) == sc.frames_per_rf
        for f in m.frames:
            assert isinstance(f, CameraFrame)
            b = np.asarray(f.box_bearings_rad)
            assert np.all(np.diff(b) >= 0), "boxes must be sorted: order carries no identity"
            assert np.all(np.abs(b) <= fov + slack)
            boxes += b.size
        StepMeasurement.model_validate(m.model_dump())  # valid against the published schema
    assert boxes > 0


def test_rssi_noise_std_matches_rf_noise_db():
    sigma = 2.0
    sc = small_scenario(rf_noise_db=sigma)
    platform = make_platform(sc, polar_positions([2.0, 4.0], [0.0, 90.0]), tx_index=0, seed=2)
    pan = 0.3
    n = 4000
    ms = [platform.sense(t, pan) for t in range(n)]
    iso = np.array([m.rf.iso_rssi_dbm for m in ms])
    dir_ = np.array([m.rf.dir_rssi_dbm for m in ms])
    g = float(physics.path_loss_dbm(sc, 2.0))
    dir_mean = float(physics.directional_rssi_dbm(sc, 2.0, pan))
    tol_mean = 4 * sigma / math.sqrt(n)
    assert iso.mean() == pytest.approx(g, abs=tol_mean)
    assert dir_.mean() == pytest.approx(dir_mean, abs=tol_mean)
    assert iso.std(ddof=1) == pytest.approx(sigma, rel=0.06)
    assert dir_.std(ddof=1) == pytest.approx(sigma, rel=0.06)
    assert abs(np.corrcoef(iso, dir_)[0, 1]) < 4 / math.sqrt(n)


@pytest.mark.parametrize("model", ["paper", "db-gain"])
def test_noiseless_rssi_is_the_channel_model(model):
    sc = small_scenario(rf_noise_db=0.0, antenna_model=model)
    platform = make_platform(sc, polar_positions([2.5, 4.0], [120.0, -30.0]), tx_index=0)
    for t, pan in enumerate(np.linspace(-math.pi, math.pi, 13)):
        m = platform.sense(t, pan)
        assert m.rf.iso_rssi_dbm == pytest.approx(float(physics.path_loss_dbm(sc, 2.5)))
        assert m.rf.dir_rssi_dbm == pytest.approx(float(physics.directional_rssi_dbm(sc, 2.5, pan - math.radians(120.0))))


def test_detection_frequency_matches_pod():
    sc = small_scenario()
    d = 3.0
    platform = make_platform(sc, polar_positions([d, 4.0], [10.0, 90.0]), tx_index=1, seed=5)
    p = float(physics.pod(sc, d))
    steps = 500
    counts = np.empty(steps)
    boxes = []
    for t in range(steps):
        m = platform.sense(t, 0.0)
        counts[t] = sum(len(f.box_bearings_rad) for f in m.frames)
        for f in m.frames:
            boxes.extend(f.box_bearings_rad)
    nu = sc.frames_per_rf
    freq = counts.sum() / (steps * nu)
    assert freq == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / (steps * nu)))
    # independent Bernoulli frames: count per step ~ Binomial(nu, p)
    assert counts.var(ddof=1) == pytest.approx(nu * p * (1 - p), rel=0.25)
    boxes = np.asarray(boxes)
    assert boxes.mean() == pytest.approx(math.radians(10.0), abs=4 * sc.box_bearing_noise_rad / math.sqrt(boxes.size))
    assert boxes.std(ddof=1) == pytest.approx(sc.box_bearing_noise_rad, rel=0.1)


def test_targets_outside_the_field_of_view_are_never_detected():
    sc = small_scenario()
    # at 2.5 m the POD is ~0.5; the targets sit just outside the half FoV of 22.5 deg
    platform = make_platform(sc, polar_positions([2.5, 2.5, 3.0], [25.0, -25.0, 180.0]), tx_index=0)
    for t in range(100):
        assert all(not f.box_bearings_rad for f in platform.sense(t, 0.0).frames)


def test_camera_sees_across_the_wrap():
    sc = small_scenario()
    platform = make_platform(sc, polar_positions([3.0], [179.0]), tx_index=0, seed=1)
    rel = []
    for t in range(100):
        for f in platform.sense(t, math.radians(-179.0)).frames:
            rel.extend(f.box_bearings_rad)
    assert len(rel) > 300  # p_D(3 m) ~ 0.62 of 1000 frames
    assert np.mean(rel) == pytest.approx(math.radians(-2.0), abs=math.radians(0.1))


def test_two_targets_in_view_give_sorted_boxes():
    sc = small_scenario()
    platform = make_platform(sc, polar_positions([3.0, 3.0], [5.0, -5.0]), tx_index=0, seed=3)
    two = 0
    for t in range(100):
        for f in platform.sense(t, 0.0).frames:
            b = f.box_bearings_rad
            assert len(b) <= 2
            assert list(b) == sorted(b)
            two += len(b) == 2
    assert two > 100


# -- training episode ------------------------------------------------------------------------------------


def test_training_episode_follows_the_walk_of_table_one():
    sc = build_scenario("paper", {"n_train": 3000})
    ep = TrainingEpisode(sc, 2)
    d = ep.truth.ranges_m
    assert len(ep) == 3000 and d.size == 3000
    assert np.all((d >= sc.train_min_range_m) & (d <= sc.train_max_range_m))
    steps = np.diff(d)
    free = (d[:-1] > 0.5 + 1.0) & (d[:-1] < 7.0 - 1.0) & (d[1:] > 0.5) & (d[1:] < 7.0)
    assert steps[free].std() == pytest.approx(math.sqrt(sc.train_step_var_m2), rel=0.08)
    np.testing.assert_allclose(ep.truth.rssi_dbm, physics.path_loss_dbm(sc, d))
    np.testing.assert_allclose(ep.truth.pod, physics.pod(sc, d))
    samples = list(ep.samples())
    assert all(isinstance(s, TrainingSample) for s in samples)
    assert [s.index for s in samples] == list(range(3000))
    assert all(len(s.frames) == sc.frames_per_rf for s in samples)
    z = np.array([s.iso_rssi_dbm for s in samples])
    assert (z - ep.truth.rssi_dbm).std() == pytest.approx(sc.rf_noise_db, rel=0.06)
    k = np.array([sum(1 for f in s.frames if f.box_bearings_rad) for s in samples])
    expected = sc.frames_per_rf * ep.truth.pod
    # the camera looks at the Tx: detections follow its POD
    assert k.sum() == pytest.approx(expected.sum(), rel=0.03)
    boxes = np.concatenate([np.asarray(f.box_bearings_rad) for s in samples for f in s.frames])
    assert np.all(np.abs(boxes) < 6 * sc.box_bearing_noise_rad)


def test_training_episode_is_seeded():
    sc = small_scenario()
    a, b, c = TrainingEpisode(sc, 1), TrainingEpisode(sc, 1), TrainingEpisode(sc, 2)
    np.testing.assert_array_equal(a.truth.ranges_m, b.truth.ranges_m)
    assert list(a.samples()) == list(b.samples())
    assert not np.array_equal(a.truth.ranges_m, c.truth.ranges_m)


@pytest.mark.parametrize("model", ["paper", "db-gain"])
def test_scalar_directional_rssi_equals_the_array_version(model):
    from ra2vipas.services.sensors import physics

    sc = build_scenario("paper", {"antenna_model": model})
    g = float(physics.path_loss_dbm(sc, 2.7))
    for delta in np.linspace(-7.0, 7.0, 57):
        expected = float(physics.directional_rssi_dbm(sc, 2.7, delta))
        assert physics.directional_rssi_scalar(sc, g, float(delta)) == pytest.approx(expected, abs=1e-12)
