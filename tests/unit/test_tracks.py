"""DetectionTracker: anonymous boxes -> static targets with empirical detection rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.controller.tracks import DetectionTracker
from ra2vipas.services.protocol.measurements import CameraFrame
from ra2vipas.services.sensors import physics
from tests.conftest import angle_error, make_platform, polar_positions, small_scenario

FOV = math.pi / 8
SIGMA = math.radians(0.25)


def _frames(rng, rel_bearings, pods, nu=10, sigma=SIGMA):
    out = []
    for _ in range(nu):
        hit = rng.random(len(pods)) < np.asarray(pods)
        b = np.asarray(rel_bearings)[hit] + rng.normal(0, sigma, hit.sum())
        out.append(CameraFrame(box_bearings_rad=tuple(sorted(float(v) for v in b))))
    return tuple(out)


def _observe(tracker, rng, bearings, pods, pans, nu=10):
    bearings = np.asarray(bearings, dtype=float)
    for pan in pans:
        rel = physics.wrap(bearings - pan)
        view = np.abs(rel) <= FOV
        tracker.update(pan, _frames(rng, rel[view], np.asarray(pods)[view], nu))


def test_single_target_bearing_and_rate():
    rng = np.random.default_rng(0)
    tr = DetectionTracker(FOV, SIGMA)
    bearing, p = math.radians(40.0), 0.6
    _observe(tr, rng, [bearing], [p], np.full(200, math.radians(35.0)))
    assert len(tr) == 1
    assert angle_error(tr.bearing[0], bearing) < 4 * SIGMA / math.sqrt(tr.boxes[0])
    p_tilde, n = tr.detection_rate()
    assert n[0] == pytest.approx(2000, abs=10)
    assert p_tilde[0] == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n[0]))


@pytest.mark.parametrize("separation_deg", [2.0, 3.0, 5.0])
def test_separates_two_targets_a_few_degrees_apart(separation_deg):
    rng = np.random.default_rng(1)
    tr = DetectionTracker(FOV, SIGMA)
    b = np.radians([10.0, 10.0 + separation_deg])
    pods = [0.85, 0.3]
    _observe(tr, rng, b, pods, np.radians(np.linspace(0.0, 20.0, 60)))
    assert len(tr) == 2
    order = np.argsort(tr.bearing)
    np.testing.assert_allclose(tr.bearing[order], b, atol=math.radians(0.2))
    p_tilde, n = tr.detection_rate()
    for i, p in zip(order, pods):
        assert p_tilde[i] == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n[i]) + 0.02)


def test_detection_rate_converges_to_the_true_pod():
    """p~ from the simulated camera approaches p_D(d) as frames accumulate."""
    sc = small_scenario(steps=400)
    d = np.array([2.0, 3.0, 4.2, 1.0])
    bearings = [-60.0, -57.0, 100.0, 150.0]
    platform = make_platform(sc, polar_positions(d, bearings), tx_index=0, seed=4)
    truth_pod = physics.pod(sc, d)
    tr = DetectionTracker(sc.fov_half_angle_rad, sc.box_bearing_noise_rad)
    pans = np.radians(np.tile([-58.0, 100.0, 150.0], 150))
    errors = []
    for t, pan in enumerate(pans):
        tr.update(pan, platform.sense(t, pan).frames)
        if t in (29, 449):
            p_tilde, _ = tr.detection_rate()
            idx = [int(np.argmin(np.abs(physics.wrap(tr.bearing - math.radians(g))))) for g in bearings]
            errors.append(np.abs(p_tilde[idx] - truth_pod))
    assert len(tr) == 4
    early, late = errors
    assert np.all(late < 0.05)
    assert late.mean() < early.mean()


def test_track_across_the_wrap():
    rng = np.random.default_rng(2)
    tr = DetectionTracker(FOV, SIGMA)
    bearing = math.radians(179.9)  # boxes land on both sides of +-pi
    _observe(tr, rng, [bearing], [0.9], np.radians(np.linspace(170.0, 190.0, 40)))
    assert len(tr) == 1
    assert angle_error(tr.bearing[0], bearing) < math.radians(0.1)


def test_two_boxes_in_one_frame_are_two_targets():
    tr = DetectionTracker(FOV, SIGMA)
    frame = CameraFrame(box_bearings_rad=(-0.001, 0.001))  # closer than the gate
    tr.update(0.0, (frame,) * 5)
    assert len(tr) == 2


def test_split_track_is_merged():
    """Two tracks opened close together, never seen in the same frame, are one target."""
    tr = DetectionTracker(FOV, SIGMA)
    gate = 4 * SIGMA
    tr.update(0.0, (CameraFrame(box_bearings_rad=(0.0,)),))
    tr.update(0.0, (CameraFrame(box_bearings_rad=(1.1 * gate,)),))
    assert len(tr) == 2  # beyond the gate: a second track
    rng = np.random.default_rng(3)
    _observe(tr, rng, [0.55 * gate], [0.8], np.zeros(30))
    assert len(tr) == 1
    assert tr.bearing[0] == pytest.approx(0.55 * gate, abs=SIGMA)


def test_frames_out_of_view_are_not_counted():
    rng = np.random.default_rng(5)
    tr = DetectionTracker(FOV, SIGMA)
    _observe(tr, rng, [0.0], [0.5], np.zeros(10))
    _, n_before = tr.detection_rate()
    tr.update(math.pi, tuple(CameraFrame() for _ in range(10)))  # looking the other way
    p_tilde, n_after = tr.detection_rate()
    np.testing.assert_array_equal(n_before, n_after)
    assert tr.in_view(0.0).all() and not tr.in_view(math.pi).any()


def test_frames_in_view_before_the_first_detection_count():
    """A target first seen at its 3rd visit was missed in the frames of the first two."""
    tr = DetectionTracker(FOV, SIGMA)
    empty = tuple(CameraFrame() for _ in range(10))
    tr.update(0.0, empty)
    tr.update(0.02, empty)
    tr.update(0.0, (CameraFrame(box_bearings_rad=(0.05,)),) + empty[1:])
    p_tilde, n = tr.detection_rate()
    assert n[0] == 30
    assert p_tilde[0] == pytest.approx(1 / 30)


def test_edge_of_view_detections_are_not_counted():
    tr = DetectionTracker(FOV, SIGMA)
    edge = FOV - SIGMA  # inside the FoV, outside the counting margin
    tr.update(0.0, (CameraFrame(box_bearings_rad=(edge,)),) * 10)
    p_tilde, n = tr.detection_rate()
    assert len(tr) == 1
    assert n[0] == 0 and p_tilde[0] == 0.0
