"""The POD learner: p_hat_D(r) from the self-supervised training stream (paper Sec. III-A)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from ra2vipas.services.learner.pod import (
    LearnedPOD,
    detection_counts,
    training_clutter,
    fit_diffusion,
    fit_pod,
    forward_backward,
    predict,
    r2_score,
)
from ra2vipas.services.protocol.measurements import CameraFrame, TrainingSample
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import TrainingEpisode


@pytest.fixture(scope="module")
def paper_fit():
    sc = build_scenario("paper", {"n_train": 900})
    episode = TrainingEpisode(sc, 1)
    samples = list(episode.samples())
    return sc, episode, samples, fit_pod(samples)


def _sample(j, z, hits, nu=10):
    frames = tuple(CameraFrame(box_bearings_rad=(0.01,) if f < hits else ()) for f in range(nu))
    return TrainingSample(index=j, iso_rssi_dbm=z, frames=frames)


# -- accuracy ------------------------------------------------------------------------------------------


def test_r2_on_the_paper_training_process(paper_fit):
    sc, episode, _, learned = paper_fit
    r2 = r2_score(episode.truth.pod, predict(learned.model, episode.truth.rssi_dbm))
    assert r2 >= 0.97


def test_model_is_a_valid_pod(paper_fit):
    sc, episode, samples, learned = paper_fit
    assert isinstance(learned, LearnedPOD)
    m = learned.model
    assert isinstance(m, PODModel)
    mean, std, grid = np.asarray(m.mean), np.asarray(m.std), np.asarray(m.rssi_grid_dbm)
    assert np.all((mean >= 0.0) & (mean <= 1.0))
    assert np.all(std >= 0.0) and np.all(np.isfinite(std))
    assert np.all(np.diff(grid) > 0)
    z = np.array([s.iso_rssi_dbm for s in samples])
    assert grid[0] <= z.min() and grid[-1] >= z.max()
    assert m.n_train == 900 and m.frames_per_rf == sc.frames_per_rf
    assert learned.train_seconds > 0
    PODModel.model_validate(m.model_dump())  # survives the wire


def test_rf_noise_is_estimated_from_the_stream(paper_fit):
    sc, _, _, learned = paper_fit
    assert learned.model.rf_noise_db == pytest.approx(sc.rf_noise_db, rel=0.15)


def test_learned_pod_matches_truth_pointwise(paper_fit):
    sc, _, _, learned = paper_fit
    d = np.array([1.5, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0])
    err = predict(learned.model, physics.path_loss_dbm(sc, d)) - physics.pod(sc, d)
    assert np.max(np.abs(err)) < 0.1


def test_learner_beats_naive_binning(paper_fit):
    """Regressing labels on noisy inputs blurs p_D; the deconvolving learner must do better than
    the best-case binned average of k/nu against the observed RSSI."""
    sc, episode, samples, learned = paper_fit
    z, k, nu = detection_counts(samples)
    edges = np.linspace(z.min(), z.max(), 25)
    idx = np.clip(np.digitize(z, edges) - 1, 0, edges.size - 2)
    centres = 0.5 * (edges[1:] + edges[:-1])
    rate = np.array([(k[idx == b] / nu).mean() if np.any(idx == b) else np.nan for b in range(centres.size)])
    ok = ~np.isnan(rate)
    naive = np.interp(episode.truth.rssi_dbm, centres[ok], rate[ok])
    truth = episode.truth.pod
    assert r2_score(truth, predict(learned.model, episode.truth.rssi_dbm)) > r2_score(truth, naive)


def test_fit_is_deterministic(paper_fit):
    _, _, samples, _ = paper_fit
    a, b = fit_pod(samples[:300]), fit_pod(samples[:300])
    assert a.model == b.model and a.diffusion == b.diffusion


# -- helpers -------------------------------------------------------------------------------------------------


def test_r2_score():
    y = np.array([0.1, 0.4, 0.9, 0.3])
    assert r2_score(y, y) == 1.0
    assert r2_score(y, np.full(4, y.mean())) == pytest.approx(0.0)
    assert r2_score(y, y + 0.1) == pytest.approx(1 - 4 * 0.01 / np.sum((y - y.mean()) ** 2))
    assert r2_score(np.ones(3), np.zeros(3)) == 0.0


def test_predict_interpolates_and_clamps():
    m = PODModel(rssi_grid_dbm=(-60.0, -50.0, -40.0), mean=(0.0, 1.0, 0.5), std=(0.1, 0.1, 0.1),
                 rf_noise_db=3.0, n_train=20, frames_per_rf=10)
    np.testing.assert_allclose(predict(m, [-70.0, -55.0, -50.0, -45.0, -30.0]), [0.0, 0.5, 1.0, 0.75, 0.5])


def test_pod_model_rejects_inconsistent_grids():
    with pytest.raises(ValueError):
        PODModel(rssi_grid_dbm=(-60.0, -60.0), mean=(0.1, 0.2), std=(0.1, 0.1), rf_noise_db=1, n_train=20, frames_per_rf=10)
    with pytest.raises(ValueError):
        PODModel(rssi_grid_dbm=(-60.0, -50.0), mean=(0.1,), std=(0.1, 0.1), rf_noise_db=1, n_train=20, frames_per_rf=10)


def test_detection_counts_counts_frames_with_a_box():
    samples = [_sample(0, -40.0, 3), _sample(1, -41.0, 10), _sample(2, -42.0, 0)]
    z, k, nu = detection_counts(samples)
    np.testing.assert_array_equal(z, [-40.0, -41.0, -42.0])
    np.testing.assert_array_equal(k, [3, 10, 0])
    assert nu == 10
    frames = (CameraFrame(box_bearings_rad=(-0.1, 0.1)),) + (CameraFrame(),) * 9
    two_boxes = TrainingSample(index=0, iso_rssi_dbm=-40.0, frames=frames)
    assert detection_counts([two_boxes])[1][0] == 1


def test_inputs_are_validated():
    with pytest.raises(ValueError):
        detection_counts([])
    with pytest.raises(ValueError):
        detection_counts([_sample(0, -40.0, 1, nu=10), _sample(1, -40.0, 1, nu=9)])
    with pytest.raises(ValueError):
        fit_pod([_sample(j, -40.0, 5) for j in range(9)])


def test_forward_backward_equals_brute_force():
    rng = np.random.default_rng(0)
    n, G = 4, 3
    emission = rng.uniform(0.05, 1.0, (n, G))
    T = rng.uniform(0.1, 1.0, (G, G))
    T /= T.sum(axis=1, keepdims=True)
    post = forward_backward(emission, T)
    joint = np.zeros((n, G))
    for path in itertools.product(range(G), repeat=n):
        w = 1.0 / G * emission[0, path[0]]
        for t in range(1, n):
            w *= T[path[t - 1], path[t]] * emission[t, path[t]]
        for t in range(n):
            joint[t, path[t]] += w
    np.testing.assert_allclose(post, joint / joint.sum(axis=1, keepdims=True), rtol=1e-10)


def test_fit_diffusion_recovers_walk_and_noise():
    rng = np.random.default_rng(1)
    n, q, R = 900, 0.5, 9.0
    z = -45.0 + np.cumsum(rng.normal(0.0, math.sqrt(q), n)) + rng.normal(0.0, math.sqrt(R), n)
    a, b, R_hat, rc = fit_diffusion(z, 0.01)
    assert R_hat == pytest.approx(R, rel=0.2)
    assert 0.5 * q < math.exp(a) < 2.0 * q
    assert abs(b) < 0.1
    assert rc == pytest.approx(z.mean())


def test_kalman_likelihood_is_the_gaussian_likelihood():
    """With constant diffusion (b = 0), the local-level model's likelihood is that of
    z ~ N(z_0 1, C), C_ij = 10 R + q min(i, j) + R delta_ij (the filter starts at z_0, var 10 R)."""
    from ra2vipas.services.learner.pod import _kalman_loglik

    rng = np.random.default_rng(2)
    n, q, R = 12, 0.7, 2.0
    z = rng.normal(-50.0, 3.0, n)
    i = np.arange(n)
    C = 10 * R + q * np.minimum.outer(i, i) + R * np.eye(n)
    expected = multivariate_normal(mean=np.full(n, z[0]), cov=C).logpdf(z)
    assert _kalman_loglik(z, math.log(q), 0.0, R, 0.0) == pytest.approx(expected, rel=1e-10)


def test_small_training_set_still_gives_a_useful_model(small_pod):
    assert small_pod.r2 > 0.85
    assert small_pod.model.n_train == 300


# -- clutter in the training frames (issue 9) -----------------------------------------------------------


def test_a_clean_detector_is_recognised_as_clean(paper_fit):
    sc, episode, _, _ = paper_fit
    assert training_clutter(list(episode.samples())) == (None, 0.0)


def test_false_boxes_are_not_detections_of_the_tx():
    """With 0.3 false boxes per frame over the field of view (and a 1 degree bearing noise),
    counting every frame with a box would call many misses detections; the learner counts
    only the Tx's gate and corrects for the clutter that falls in it, and learns the POD as
    well as on a clean detector."""
    sc = build_scenario("paper", {"clutter_rate": 0.3, "box_bearing_noise_deg": 1.0})
    episode = TrainingEpisode(sc, 4)
    samples = list(episode.samples())
    gate, q = training_clutter(samples)
    assert gate == pytest.approx(4.0 * math.radians(1.0), rel=0.25)
    expected_q = 1.0 - math.exp(-0.3 / (2.0 * sc.fov_half_angle_rad) * 2.0 * gate)
    assert q == pytest.approx(expected_q, rel=0.35)
    naive = np.fromiter((sum(1 for f in s.frames if f.box_bearings_rad) for s in samples), dtype=float)
    _, k, _ = detection_counts(samples)
    assert naive.sum() > k.sum()  # the false boxes outside the gate are no longer detections
    learned = fit_pod(samples)
    r2 = r2_score(episode.truth.pod, predict(learned.model, episode.truth.rssi_dbm))
    assert r2 >= 0.95
