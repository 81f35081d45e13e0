"""The POD learner on protocol 1.3 packets (0..n advertisements per training sample), and the
honest score beside R² (issue 20): RMSE against p*(r) and the oracle fit's RMSE."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.learner.pod import (
    TrainingDataError,
    _kalman_loglik,
    _kalman_loglik_packets,
    fit_pod,
    oracle_fit,
    packet_statistics,
    predict,
    r2_score,
    score_pod,
    unimodal_fit,
)
from ra2vipas.services.protocol.measurements import Advertisement, CameraFrame, TrainingSample
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.world import TrainingEpisode


def _sample(j: int, values: list[float]) -> TrainingSample:
    return TrainingSample(index=j, frames=(CameraFrame(),), adverts=tuple(Advertisement(receiver="iso", rssi_dbm=v) for v in values))


def test_packet_statistics_keep_every_packet_and_make_up_none():
    zbar, n = packet_statistics([_sample(0, [-60, -62]), _sample(1, []), _sample(2, [-55])])
    assert n.tolist() == [2, 0, 1] and zbar[0] == -61.0 and math.isnan(zbar[1]) and zbar[2] == -55.0


def test_one_packet_per_sample_is_the_plain_walk_likelihood():
    rng = np.random.default_rng(3)
    z = np.cumsum(rng.normal(0.0, 0.5, 200)) - 50.0 + rng.normal(0.0, 2.0, 200)
    for a, b, R in ((-1.0, 0.1, 4.0), (0.3, -0.2, 9.0)):
        assert _kalman_loglik_packets(z, np.ones(z.size), a, b, R, -50.0) == pytest.approx(_kalman_loglik(z, a, b, R, -50.0), rel=1e-12)


def test_samples_without_packets_only_diffuse_and_several_packets_weigh_more():
    z = np.array([-60.0, 0.0, -61.0])
    none = _kalman_loglik_packets(z, np.array([1.0, 0.0, 1.0]), -1.0, 0.0, 4.0, -60.0)
    # an empty sample between two packets = one walk step more between them, no observation
    two = _kalman_loglik_packets(np.array([-60.0, -61.0]), np.array([1.0, 1.0]), math.log(2.0 * math.exp(-1.0)), 0.0, 4.0, -60.0)
    assert none == pytest.approx(two, rel=1e-12)
    one = _kalman_loglik_packets(np.array([-60.0, -70.0]), np.array([1.0, 1.0]), -1.0, 0.0, 4.0, -60.0)
    four = _kalman_loglik_packets(np.array([-60.0, -70.0]), np.array([1.0, 4.0]), -1.0, 0.0, 4.0, -60.0)
    assert four < one  # four packets at -70 contradict the walk more than one does


def test_the_learner_trains_from_packets_with_empty_samples():
    # white 2.5 dB packets, no channel offsets nor shadowing: what is left to learn is the packet stream itself
    sc = build_scenario("ble", {"shadowing_db": 0.0, "adv_interval_s": 0.1, "channel_offset_db": 0.0, "rf_noise_db": 2.5})
    episode = TrainingEpisode(sc, 2)
    samples = list(episode.samples())
    assert sum(1 for s in samples if not s.adverts) > 100 and all(s.iso_rssi_dbm is None for s in samples)
    learned = fit_pod(samples)
    r2 = r2_score(episode.truth.pod, predict(learned.model, episode.truth.rssi_dbm))
    assert r2 > 0.95, r2
    assert 2.2 < learned.model.rf_noise_db < 2.9  # one packet's spread: 2.5 dB, whole dBm
    with pytest.raises(TrainingDataError, match=r"carries 5 Rx\(iso\) advertisements in 50 samples; the POD learner needs at least 10"):
        fit_pod([_sample(j, [-60.0] if j < 5 else []) for j in range(50)])


def test_unimodal_fit_rises_then_falls_and_the_oracle_is_exact_without_shadowing():
    x = np.linspace(-80.0, -30.0, 400)
    bump = np.exp(-0.5 * ((x + 55.0) / 8.0) ** 2)
    noisy = bump + np.random.default_rng(0).normal(0.0, 0.1, x.size)
    fit = unimodal_fit(x, noisy)
    peak = int(np.argmax(fit))
    assert np.all(np.diff(fit[:peak + 1]) >= -1e-12) and np.all(np.diff(fit[peak:]) <= 1e-12)
    assert np.sqrt(np.mean((fit - bump) ** 2)) < 0.06
    episode = TrainingEpisode(build_scenario("paper"), 1)
    assert np.sqrt(np.mean((oracle_fit(episode.truth.rssi_dbm, episode.truth.pod) - episode.truth.pod) ** 2)) < 0.02


def test_the_score_reports_rmse_beside_r2_and_the_oracles_rmse_under_shadowing():
    episode = TrainingEpisode(build_scenario("dynamic"), 1)
    learned = fit_pod(list(episode.samples()))
    truth = episode.truth
    score = score_pod(learned.model, truth.rssi_dbm, truth.pod, truth.pod_at_range)
    assert score.r2 == pytest.approx(r2_score(truth.pod, predict(learned.model, truth.rssi_dbm)))
    assert score.rmse == pytest.approx(float(np.sqrt(np.mean((predict(learned.model, truth.rssi_dbm) - truth.pod) ** 2))))
    assert 0.01 < score.oracle_rmse < 0.3  # the POD is not a function of the RSSI: even the oracle misses p*


def test_channel_offsets_are_estimated_and_removed_where_packets_say_their_channel():
    from ra2vipas.services.learner.pod import LearnerSettings

    sc = build_scenario("ble", {"shadowing_db": 0.0, "adv_interval_s": 0.1, "channel_offset_db": 4.0, "rf_noise_db": 1.0,
                                "rssi_step_db": 0.0})
    episode = TrainingEpisode(sc, 1)
    samples = list(episode.samples())
    assert {a.channel for s in samples for a in s.adverts} == {37, 38, 39}
    truth = episode._packets.channel_offsets_db[0]
    truth = truth - truth.mean()
    learned = fit_pod(samples)
    estimated = np.array([learned.channel_offsets[c] for c in (37, 38, 39)])
    assert np.max(np.abs(estimated - truth)) < 1.0, (estimated, truth)  # drawn with sigma 4 dB
    assert fit_pod(samples, LearnerSettings(channel_offsets=False)).channel_offsets is None
    blind = [TrainingSample(index=s.index, frames=s.frames, adverts=tuple(a.model_copy(update={"channel": None}) for a in s.adverts))
             for s in samples]
    assert fit_pod(blind).channel_offsets is None  # no channels: nothing to estimate


def test_the_learner_service_says_why_a_training_episode_cannot_be_learned_from():
    """A training stream too thin to fit (BLE, 40 samples: 8 advertisements) is an error reply that says so and names
    n_train, not an internal error; the in-process path raises the scenario's error with the same words."""
    from ra2vipas.services.learner.node import LearnerNode
    from ra2vipas.services.orchestrator.simulate import train_pod
    from ra2vipas.services.protocol.messages import PODRequest
    from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario
    from ra2vipas.services.sensors.node import SensorsNode
    from ra2vipas.services.transport.bus import MemoryBus, QueryError

    short = build_scenario("ble", {"n_train": 40})
    bus = MemoryBus()
    sensors = SensorsNode(bus, "rig-1")
    learner = LearnerNode(bus, "l1")
    try:
        with pytest.raises(QueryError) as err:
            learner.model_for(PODRequest(scenario=short, seed=1))
    finally:
        learner.close()
        sensors.close()
        bus.close()
    assert "cannot learn the POD from the training episode: the training stream carries 8 Rx(iso) advertisements in 40 " \
           "samples; the POD learner needs at least 10 (n_train = 40: raise it)" in str(err.value)
    with pytest.raises(ScenarioError, match="n_train = 40 is too short a training episode"):
        train_pod(short, 1, cache=False)
