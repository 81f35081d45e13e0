"""The simulated BLE radio (issue 20; services/sensors/radio.py): rates, gaps, loss,
sensitivity, quantisation, per-channel offsets, spread and lag correlation, each checked
against the scenario's parameters; boxes with heights; the paper's radio untouched."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.protocol.messages import Measurement, TrainingStream, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors import physics, radio
from ra2vipas.services.sensors.world import GroundTruth, SimulatedPlatform, TrainingEpisode, episode_streams

ONE_TX = GroundTruth(positions_m=np.array([[3.0, 0.0], [0.0, 4.0]]), tx_index=0)  # Tx at 3 m, bearing 0


def _quiet(**extra):
    """A ble world with every effect off but those given: static Tx at 3 m, no shadowing."""
    values = {"shadowing_db": 0.0, "rf_noise_db": 0.0, "channel_offset_db": 0.0, "rssi_step_db": 0.0, "packet_loss_iso": 0.0,
              "packet_loss_dir": 0.0, "rx_sensitivity_dbm": -200.0, "steps": 600, "n_targets": 2}
    return build_scenario("ble", {**values, **extra})


def _run(sc, tests=20, pan=0.0):
    out = []
    for k in range(tests):
        w = SimulatedPlatform(sc, 7, k, layout=ONE_TX)
        out.append([w.sense(t, pan) for t in range(sc.steps)])
    return out


def _iso(episode):
    """(arrival time, rssi, channel) of every Rx(iso) packet of an episode."""
    return [(m.step * 0.1 + a.offset_s, a.rssi_dbm, a.channel) for m in episode for a in m.advertisements("iso")]


def test_advertising_events_keep_the_interval_plus_ble_advdelay():
    sc = _quiet()
    t = radio.advertising_times(sc, np.random.default_rng(1), 300.0)
    gaps = np.diff(t)
    assert gaps.min() >= sc.adv_interval_s and gaps.max() <= sc.adv_interval_s + sc.adv_delay_max_s
    assert abs(gaps.mean() - (sc.adv_interval_s + sc.adv_delay_max_s / 2)) < 0.001  # advDelay ~ U(0, 10 ms)


@pytest.mark.parametrize("loss", [0.0, 0.1, 0.5])
def test_packet_rate_is_the_event_rate_times_one_minus_loss(loss):
    sc = _quiet(packet_loss_iso=loss, packet_loss_dir=loss)
    episodes = _run(sc)
    duration = sc.steps * sc.rf_period_s * len(episodes)
    rate = sum(len(_iso(e)) for e in episodes) / duration
    expected = (1.0 - loss) / (sc.adv_interval_s + sc.adv_delay_max_s / 2)
    assert abs(rate - expected) < 0.05 * expected + 0.02, (rate, expected)
    gaps = np.concatenate([np.diff([p[0] for p in _iso(e)]) for e in episodes])
    assert gaps.min() >= sc.adv_interval_s - 1e-9  # one packet per event at most
    if loss == 0.0:
        assert gaps.max() <= sc.adv_interval_s + sc.adv_delay_max_s + 1e-9
    # with the measured 10 % loss the median gap is one interval (the dataset's 0.455 s)
    if loss == 0.1:
        assert abs(np.median(gaps) - 0.455) < 0.01


def test_steps_without_packets_carry_no_rf_value_and_offsets_lie_in_the_step():
    sc = _quiet(packet_loss_iso=0.1)
    episode = _run(sc, tests=1)[0]
    empty = [m for m in episode if not m.advertisements()]
    assert len(empty) > sc.steps // 2  # an advertisement every 0.45 s, steps of 0.1 s
    assert all(m.rf is None and m.rssi_dbm("iso") == () for m in empty)
    assert all(0.0 <= a.offset_s < sc.rf_period_s for m in episode for a in m.adverts)
    wire = Measurement.model_validate_json(dump(Measurement.model_construct(episode_id="e", **dict(empty[0]))))
    assert wire.advertisements() == ()


def test_rssi_is_the_level_plus_quantisation_and_nothing_below_the_sensitivity():
    sc = _quiet(rf_noise_db=2.5, rssi_step_db=1.0)
    level = float(physics.path_loss_dbm(sc, 3.0))
    values = np.array([p[1] for e in _run(sc, tests=5) for p in _iso(e)])
    assert np.all(values == np.round(values))  # whole dBm
    assert abs(values.mean() - level) < 0.3 and abs(values.std() - math.sqrt(2.5**2 + 1 / 12)) < 0.2
    coarse = np.array([p[1] for e in _run(_quiet(rf_noise_db=2.5, rssi_step_db=2.0), tests=2) for p in _iso(e)])
    assert np.all(coarse % 2.0 == 0.0)
    sensitive = _quiet(rf_noise_db=2.5, rx_sensitivity_dbm=level)
    heard = np.array([p[1] for e in _run(sensitive, tests=5) for p in _iso(e)])
    assert heard.min() >= level and 0.4 < heard.size / values.size < 0.6  # half the packets fall below it


def test_channel_offsets_and_the_scan_rotation():
    sc = _quiet(channel_offset_db=3.0, scan_interval_s=1.0)
    spreads = []
    for episode in _run(sc, tests=40):
        packets = _iso(episode)
        by_channel = {c: {v for _, v, ch in packets if ch == c} for c in radio.CHANNELS}
        assert all(len(v) == 1 for v in by_channel.values())  # no spread: one level per channel
        spreads += [next(iter(v)) for v in by_channel.values()]
        channels = [c for _, _, c in packets]
        changes = [(a, b) for a, b in zip(channels, channels[1:]) if a != b]
        assert all((b - 37) == (a - 37 + 1) % 3 for a, b in changes)  # 37 -> 38 -> 39 -> 37
        times = [t for t, _, _ in packets]
        switch = [t for t, (a, b) in zip(times[1:], zip(channels, channels[1:])) if a != b]
        assert np.all(np.diff(switch) > sc.scan_interval_s - sc.adv_interval_s - sc.adv_delay_max_s)
    level = float(physics.path_loss_dbm(sc, 3.0))
    offsets = np.array(spreads) - level
    assert abs(offsets.std() - 3.0) < 0.45 and abs(offsets.mean()) < 0.6


def test_lag_correlation_follows_the_fading_time_over_irregular_packets():
    tau = 1.0
    sc = _quiet(rf_noise_db=3.0, fading_corr_s=tau)
    level = float(physics.path_loss_dbm(sc, 3.0))
    x, y, dt = [], [], []
    for episode in _run(sc, tests=20):
        p = _iso(episode)
        for (t0, v0, _), (t1, v1, _) in zip(p, p[1:]):
            x.append(v0 - level)
            y.append(v1 - level)
            dt.append(t1 - t0)
    r = float(np.corrcoef(x, y)[0, 1])
    expected = math.exp(-np.mean(dt) / tau)
    assert abs(r - expected) < 0.05, (r, expected)
    white = _quiet(rf_noise_db=3.0)
    p = [q for e in _run(white, tests=10) for q in zip(_iso(e), _iso(e)[1:])]
    assert abs(np.corrcoef([a[1] for a, _ in p], [b[1] for _, b in p])[0, 1]) < 0.06


def test_rx_dir_hears_the_antenna_response_at_the_pan():
    sc = _quiet(rf_noise_db=0.0)
    aligned = [a.rssi_dbm for m in _run(sc, tests=1, pan=0.0)[0] for a in m.advertisements("dir")]
    away = [a.rssi_dbm for m in _run(sc, tests=1, pan=1.0)[0] for a in m.advertisements("dir")]
    level = float(physics.path_loss_dbm(sc, 3.0))
    assert aligned and np.allclose(aligned, level)
    assert away and np.allclose(away, float(physics.directional_rssi_dbm(sc, 3.0, 1.0)))


def test_draws_do_not_depend_on_the_pans():
    sc = build_scenario("ble")
    a, b = SimulatedPlatform(sc, 3, 1), SimulatedPlatform(sc, 3, 1)
    for t in range(sc.steps):
        ma, mb = a.sense(t, 0.0), b.sense(t, 0.7 * t)
        assert [x.offset_s for x in ma.advertisements("iso")] == [x.offset_s for x in mb.advertisements("iso")]
        assert ma.rssi_dbm("iso") == mb.rssi_dbm("iso")


def test_the_paper_radio_is_untouched():
    sc = build_scenario("paper")
    m = SimulatedPlatform(sc, 1, 0).sense(0, 0.0)
    assert m.rf is not None and m.adverts == () and all(not f.box_heights_rad for f in m.frames)
    assert len(episode_streams(1, 0).__dict__) == 10  # 8 streams, and since protocol 1.4 the tags stream and its seed (docs/tags.md)
    # the first six streams are those the paper world always drew from
    old = [np.random.default_rng(c) for c in np.random.SeedSequence(entropy=1, spawn_key=(0, 0)).spawn(6)]
    new = episode_streams(1, 0)
    assert [g.random() for g in old] == [new.placement.random(), new.rf.random(), new.camera.random(), new.walk.random(),
                                         new.clutter.random(), new.shadowing.random()]


def test_boxes_carry_the_targets_angular_heights():
    sc = build_scenario("paper", {"box_heights": True, "box_height_noise": 0.0, "n_targets": 2, "box_bearing_noise_deg": 0.0})
    w = SimulatedPlatform(sc, 1, 0, layout=ONE_TX)
    without = SimulatedPlatform(build_scenario("paper", {"n_targets": 2, "box_bearing_noise_deg": 0.0}), 1, 0, layout=ONE_TX)
    lo, hi = radio.angular_height(sc, 1.5, 3.0), radio.angular_height(sc, 1.9, 3.0)
    for t in range(20):
        m, plain = w.sense(t, 0.0), without.sense(t, 0.0)
        assert [f.box_bearings_rad for f in m.frames] == [f.box_bearings_rad for f in plain.frames]  # camera draws unchanged
        heights = {h for f in m.frames for h in f.box_heights_rad}
        assert len(heights) <= 1 and all(lo <= h <= hi for h in heights)
    assert abs(radio.angular_height(sc, 1.7, 4.0) - math.radians(24.2)) < math.radians(0.5)  # the 1.7 m at 4 m


def test_clutter_boxes_have_plausible_heights_and_noise_is_relative():
    sc = build_scenario("dynamic", {"box_heights": True})
    w = SimulatedPlatform(sc, 2, 0)
    heights = [h for t in range(sc.steps) for f in w.sense(t, 0.05 * t).frames for h in f.box_heights_rad]
    lowest = radio.angular_height(sc, sc.target_height_min_m, sc.arena_half_width_m * math.sqrt(2.0))
    highest = radio.angular_height(sc, sc.target_height_max_m, sc.min_target_range_m)
    assert heights and min(heights) > 0.7 * lowest and max(heights) < 1.3 * highest
    rng = np.random.default_rng(0)
    noisy = radio.noisy_heights(sc, rng, np.full(20000, 0.3))
    assert abs(noisy.std() / 0.3 - sc.box_height_noise) < 0.005


def test_training_in_a_ble_world_yields_advertisements():
    sc = build_scenario("ble", {"n_train": 300})
    samples = list(TrainingEpisode(sc, 1).samples())
    counts = [len(s.adverts) for s in samples]
    assert all(s.iso_rssi_dbm is None for s in samples) and 0 in counts and max(counts) >= 1
    assert all(a.receiver == "iso" for s in samples for a in s.adverts)
    expected = 300 * sc.rf_period_s * (1 - sc.packet_loss_iso) / (sc.adv_interval_s + sc.adv_delay_max_s / 2)
    assert abs(sum(counts) - expected) < 0.25 * expected
    TrainingStream.model_validate_json(dump(TrainingStream(job_id="j", samples=tuple(samples))))


def test_the_ble_preset_has_the_datasets_packet_statistics():
    """docs/radio.md's table, at one point (no shadowing change, every packet above the
    sensitivity): rate, median gap, spread and the lag-correlation pattern of the CC0 dataset."""
    sc = build_scenario("ble", {"n_targets": 2, "steps": 3000, "rx_sensitivity_dbm": -200.0})
    lags = {1: [], 2: [], 3: [], 6: []}
    spreads, gaps, count = [], [], 0
    for e in range(20):
        w = SimulatedPlatform(sc, 11, e, layout=ONE_TX)
        packets = _iso([w.sense(t, 0.0) for t in range(sc.steps)])
        v = np.array([p[1] for p in packets])
        v = v - v.mean()
        spreads.append(v.std())
        gaps += np.diff([p[0] for p in packets]).tolist()
        count += len(packets)
        for k in lags:
            lags[k].append(float((v[:-k] * v[k:]).mean() / v.var()))
    rate = count / (20 * sc.steps * sc.rf_period_s)
    assert abs(rate - 1.96) < 0.1 and abs(float(np.median(gaps)) - 0.455) < 0.01  # 1.96 /s, median gap 0.455 s
    assert 2.6 < float(np.median(spreads)) < 3.3  # measured median 2.9-3.2 dB
    measured = {1: 0.19, 2: -0.26, 3: -0.29, 6: 0.13}
    got = {k: float(np.mean(x)) for k, x in lags.items()}
    assert all(np.sign(got[k]) == np.sign(measured[k]) for k in measured), got
    assert all(abs(got[k] - measured[k]) < 0.15 for k in measured), got
