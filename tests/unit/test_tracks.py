"""BearingTracker: anonymous boxes -> static targets with empirical detection rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.controller.tracks import BearingTracker, TrackerSettings
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
    tr = BearingTracker(FOV, SIGMA)
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
    tr = BearingTracker(FOV, SIGMA)
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
    tr = BearingTracker(sc.fov_half_angle_rad, sc.box_bearing_noise_rad)
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
    tr = BearingTracker(FOV, SIGMA)
    bearing = math.radians(179.9)  # boxes land on both sides of +-pi
    _observe(tr, rng, [bearing], [0.9], np.radians(np.linspace(170.0, 190.0, 40)))
    assert len(tr) == 1
    assert angle_error(tr.bearing[0], bearing) < math.radians(0.1)


def test_two_boxes_in_one_frame_are_two_targets():
    tr = BearingTracker(FOV, SIGMA)
    frame = CameraFrame(box_bearings_rad=(-0.001, 0.001))  # closer than the gate
    tr.update(0.0, (frame,) * 5)
    assert len(tr) == 2


def test_split_track_is_merged():
    """Two tracks opened close together, never seen in the same frame, are one target."""
    tr = BearingTracker(FOV, SIGMA, settings=TrackerSettings(omega0=0.01, q_walk=1e-6))  # nobody walks here
    gate = 4 * SIGMA
    tr.update(0.0, (CameraFrame(box_bearings_rad=(0.0,)),))
    tr.update(0.0, (CameraFrame(box_bearings_rad=(1.6 * gate,)),))
    assert len(tr) == 2  # too far apart for one target: a second track
    rng = np.random.default_rng(3)
    _observe(tr, rng, [0.8 * gate], [0.8], np.zeros(30))
    assert len(tr) == 1
    assert tr.bearing[0] == pytest.approx(0.8 * gate, abs=SIGMA)


def test_frames_out_of_view_are_not_counted():
    rng = np.random.default_rng(5)
    tr = BearingTracker(FOV, SIGMA)
    _observe(tr, rng, [0.0], [0.5], np.zeros(10))
    _, n_before = tr.detection_rate()
    tr.update(math.pi, tuple(CameraFrame() for _ in range(10)))  # looking the other way
    p_tilde, n_after = tr.detection_rate()
    # nothing counted for the frames that looked away (a standing track's counts are barely
    # discounted: it might have started walking)
    assert np.all(n_after <= n_before) and np.all(n_after > 0.999 * n_before)
    assert tr.in_view(0.0).all() and not tr.in_view(math.pi).any()


def test_frames_in_view_before_the_first_detection_count():
    """A target first seen at its 3rd visit was missed in the frames of the first two."""
    tr = BearingTracker(FOV, SIGMA)
    empty = tuple(CameraFrame() for _ in range(10))
    tr.update(0.0, empty)
    tr.update(0.02, empty)
    tr.update(0.0, (CameraFrame(box_bearings_rad=(0.05,)),) + empty[1:])
    p_tilde, n = tr.detection_rate()
    assert n[0] == 30
    assert p_tilde[0] == pytest.approx(1 / 30)


def test_edge_of_view_detections_are_not_counted():
    tr = BearingTracker(FOV, SIGMA)
    edge = FOV - SIGMA  # inside the FoV, outside the counting margin
    tr.update(0.0, (CameraFrame(box_bearings_rad=(edge,)),) * 10)
    p_tilde, n = tr.detection_rate()
    assert len(tr) == 1
    assert n[0] == 0 and p_tilde[0] == 0.0


# -- targets that move (issue 9) ------------------------------------------------------------------

def test_a_crossing_pair_is_followed_without_swapping():
    """Two people cross in front of the camera at the same angular speed in opposite
    directions; each track keeps following the person it started on."""
    rng = np.random.default_rng(11)
    tr = BearingTracker(FOV, SIGMA, 0.1)
    steps = 60
    a = np.radians(np.linspace(20.0, 40.0, steps))  # walks left
    b = np.radians(np.linspace(40.0, 20.0, steps))  # walks right; they meet at step ~30
    pan = math.radians(30.0)
    ids = None
    for t in range(steps):
        tr.update(pan, _frames(rng, [a[t] - pan, b[t] - pan], [0.8, 0.8]))
        if t == 10:
            assert len(tr) == 2
            ids = {int(tr.ids[int(np.argmin(np.abs(physics.wrap(tr.bearing - g))))]): name for name, g in (("a", a[t]), ("b", b[t]))}
            assert len(ids) == 2
    final = dict(zip(tr.ids.tolist(), tr.bearing.tolist()))
    assert set(ids) <= set(final), "a track was lost at the crossing"
    for tid, name in ids.items():
        truth = (a if name == "a" else b)[-1]
        assert angle_error(final[tid], truth) < math.radians(1.0), f"track of {name} ended at {math.degrees(final[tid]):.1f} deg"
    assert all(w > 0.5 for w in tr.walking)  # both are recognised as walkers


def test_a_standing_target_keeps_a_sharp_bearing_while_out_of_view():
    rng = np.random.default_rng(12)
    tr = BearingTracker(FOV, SIGMA, 0.1)
    _observe(tr, rng, [0.3], [0.7], np.full(20, 0.3))
    before = float(tr.bearing[0])
    _observe(tr, rng, [0.3], [0.7], np.full(60, math.pi))  # 6 s looking the other way
    assert tr.walking[0] < 0.2 and angle_error(float(tr.bearing[0]), before) < 1e-4
    _observe(tr, rng, [0.3], [0.7], np.full(5, 0.3))
    assert len(tr) == 1  # found again, not a new target


def test_a_lone_false_box_does_not_become_a_target_in_a_cluttered_scene():
    """With clutter (false boxes uniform over the field of view, every frame), boxes that do not
    come back where the camera looks again are not targets; a real target is."""
    rng = np.random.default_rng(13)
    tr = BearingTracker(FOV, math.radians(1.0), 0.1)
    target = 0.1
    for t in range(150):
        pan = 0.0
        frames = []
        for _ in range(10):
            boxes = list(rng.uniform(-FOV, FOV, rng.poisson(0.3)))
            if rng.random() < 0.6:
                boxes.append(target - pan + rng.normal(0, math.radians(1.0)))
            frames.append(CameraFrame(box_bearings_rad=tuple(sorted(boxes))))
        tr.update(pan, tuple(frames))
    assert tr.clutter_density == pytest.approx(0.3 * 10 / 10 / (2 * tr.count_limit), rel=0.5)  # ~0.38 false boxes / frame / rad
    assert any(angle_error(b, target) < math.radians(0.5) for b in tr.bearing)
    assert len(tr) <= 3, f"{len(tr)} tracks from one target and clutter"
