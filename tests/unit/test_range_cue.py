"""Box heights as a range cue (issue 20; services/controller/range_cue.py): the range a track's
boxes give against the range Rx(iso)'s level gives, used only when the rig's boxes carry heights,
with the campaign's public propagation model and a public prior on a person's height."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ra2vipas.services.controller.builtins import Ra2ViPAS
from ra2vipas.services.controller.contract import episode_context
from ra2vipas.services.controller.heights_policy import Ra2ViPASHeights
from ra2vipas.services.controller.policy import (
    Controller,
    ControllerSettings,
    sensor_config_from_descriptor,
    sensor_config_from_scenario,
    with_range_model,
)
from ra2vipas.services.controller.range_cue import RangeCue, RangeModel, RecentStats, height_prior, log10_span
from ra2vipas.services.controller.rf_belief import IsoLevel
from ra2vipas.services.protocol.measurements import CameraFrame
from ra2vipas.services.protocol.rig import RigDescriptor
from ra2vipas.services.sensors import radio
from ra2vipas.services.sensors.world import SimulatedPlatform
from tests.conftest import run_closed_loop, small_scenario

ON = ControllerSettings(height_cue=True)
MODEL = RangeModel(ref_dbm=-30.0, exponent=2.0, ref_distance_m=1.0, shadowing_db=4.0)


class _Tracks:
    """The few fields of a ``BearingTracker`` the cue reads."""

    def __init__(self, bearings_deg, walking=None) -> None:
        self.bearing = np.radians(np.asarray(bearings_deg, dtype=float))
        self.ids = np.arange(self.bearing.size) + 7
        self.walking = np.zeros(self.bearing.size) if walking is None else np.asarray(walking, dtype=float)

    def __len__(self) -> int:
        return self.bearing.size


def _frame(bearings_deg, ranges_m, height_m=1.7) -> CameraFrame:
    h = 2.0 * np.arctan(height_m / (2.0 * np.asarray(ranges_m, dtype=float)))
    return CameraFrame(box_bearings_rad=tuple(np.radians(bearings_deg).tolist()), box_heights_rad=tuple(h.tolist()))


def _iso(level_dbm: float, n: int = 40, sd: float = 1.0) -> IsoLevel:
    iso = IsoLevel(3.0)
    for k, v in enumerate(level_dbm + sd * np.resize([1.0, -1.0], n)):
        iso.add(float(v), 0.1 * k)
    return iso


def test_range_from_a_box_inverts_the_angle_a_person_subtends():
    """eq. 1: d = H / (2 tan(h/2)) exactly for a camera at half the person's height, and within
    1.5 % of the range for the world's camera at 1 m (H = 1.7 m) from 1 m out."""
    for d in (0.7, 2.0, 4.0, 7.0):
        h = 2.0 * math.atan(1.7 / (2.0 * d))
        assert 10 ** (math.log10(1.7) - log10_span(np.array([h]))[0]) == pytest.approx(d, rel=1e-9)
    sc = small_scenario(box_heights=True)
    for d in (1.0, 2.0, 4.0, 7.0):
        h = float(radio.angular_height(sc, 1.7, d))
        assert abs(10 ** (math.log10(1.7) - log10_span(np.array([h]))[0]) / d - 1.0) < 0.015


def test_height_prior_matches_a_uniform_height():
    m, v = height_prior(1.5, 1.9)
    h = np.log10(np.linspace(1.5, 1.9, 200_001))
    assert m == pytest.approx(h.mean(), abs=1e-6) and v == pytest.approx(h.var(), rel=1e-3)
    assert height_prior(1.7, 1.7) == (pytest.approx(math.log10(1.7)), 0.0)


def test_recent_stats_forget_at_their_times():
    s = RecentStats(1.0)
    s.add([0.0], 0.0)
    s.add([10.0], 1.0)
    mean, _, n_eff = s.mean_var()
    w = math.exp(-1.0)
    assert mean == pytest.approx(10.0 / (1.0 + w)) and n_eff == pytest.approx((1 + w) ** 2 / (1 + w * w))
    forever = RecentStats(math.inf)
    forever.add([0.0, 10.0], 0.0)
    forever.add([5.0], 100.0)
    assert forever.mean_var()[0] == pytest.approx(5.0)


def _cue_after(tracks: _Tracks, ranges_m, steps: int = 20, **kw) -> RangeCue:
    cue = RangeCue(MODEL, box_bearing_noise_rad=math.radians(0.5), **kw)
    bearings = np.degrees(tracks.bearing)
    for t in range(steps):
        cue.update(0.0, [_frame(bearings, ranges_m)] * 5, tracks, 0.1 * t)
    return cue


def test_the_track_whose_box_range_agrees_with_the_level_is_favoured():
    """Two tracks at 2 m and 5 m: a level of -30 - 20 log10(2) favours the first, one of
    -30 - 20 log10(5) the second; the factors are log Bayes factors against the tracks' mean."""
    tracks = _Tracks([-10.0, 10.0])
    cue = _cue_after(tracks, [2.0, 5.0])
    near = cue.log_likelihood(tracks, _iso(-30.0 - 20.0 * math.log10(2.0)))
    far = cue.log_likelihood(tracks, _iso(-30.0 - 20.0 * math.log10(5.0)))
    assert near[0] > near[1] + 0.5 and far[1] > far[0] + 0.5
    for lr in (near, far):  # log-mean-exp of the factors is 0: "missed" (0) is a track at random
        assert math.log(np.mean(np.exp(lr))) == pytest.approx(0.0, abs=1e-9)
    # the model's spread tempers it: with 20 dB of shadowing the two hardly differ
    loose = _cue_after(tracks, [2.0, 5.0], floor_db=20.0).log_likelihood(tracks, _iso(-30.0 - 20.0 * math.log10(2.0)))
    assert 0.0 < loose[0] - loose[1] < 0.2 * (near[0] - near[1])


def test_a_track_without_heights_and_a_frame_without_heights_say_nothing():
    tracks = _Tracks([-10.0, 10.0, 30.0])
    cue = RangeCue(MODEL, box_bearing_noise_rad=math.radians(0.5))
    cue.update(0.0, [CameraFrame(box_bearings_rad=(math.radians(-10.0), math.radians(10.0)))] * 5, tracks, 0.0)  # a v1 frame
    assert cue.boxes == 0 and cue.log_likelihood(tracks, _iso(-36.0)) is None
    cue.update(0.0, [_frame([-10.0, 10.0], [2.0, 5.0])] * 5, tracks, 0.1)
    lr = cue.log_likelihood(tracks, _iso(-36.0))
    assert lr[2] == 0.0 and lr[0] != 0.0 and lr[1] != 0.0
    assert cue.log_likelihood(tracks, IsoLevel(3.0)) is None  # no Rx(iso) reading yet
    # a box outside every track's gate joins none
    cue.update(0.0, [_frame([-20.0], [1.0])] * 5, tracks, 0.2)
    assert cue.boxes == 10


def test_a_walking_track_is_scored_on_its_recent_boxes_and_level():
    """A walker seen at 10 m for 5 s, then at 2 m for 2 s, and a level that says 2 m: read as a
    walker (its recent boxes) it agrees as well as a standing target at 2 m; read as standing
    (every box it got) it does not."""
    cue = RangeCue(MODEL, box_bearing_noise_rad=math.radians(0.5), walk_memory_s=0.5)
    iso = IsoLevel(3.0)
    both = _Tracks([0.0, 40.0])
    for t in range(70):
        d = 10.0 if t < 50 else 2.0
        cue.update(0.0, [_frame([0.0, 40.0], [d, 2.0])] * 5, both, 0.1 * t)
        iso.add(-30.0 - 20.0 * math.log10(2.0), 0.1 * t)
    walking = cue.log_likelihood(_Tracks([0.0, 40.0], walking=[1.0, 0.0]), iso)
    standing = cue.log_likelihood(both, iso)
    assert abs(walking[0] - walking[1]) < 0.3
    assert standing[0] < standing[1] - 1.0


def test_with_range_model_only_when_the_boxes_carry_heights(small_pod):
    sc = small_scenario(box_heights=True, shadowing_db=3.0, path_loss_ref_dbm=-40.0, path_loss_exponent=2.5)
    ctx = episode_context(sensor_config_from_scenario(sc), small_pod.model, sc, 1, 0)
    assert with_range_model(None, ctx) is None  # the cue is off by default: nothing to add
    cfg = with_range_model(ON, ctx)
    assert cfg.range_model == RangeModel(ref_dbm=-40.0, exponent=2.5, ref_distance_m=1.0, shadowing_db=3.0)
    plain = small_scenario()
    assert with_range_model(ON, episode_context(sensor_config_from_scenario(plain), small_pod.model, plain, 1, 0)) is ON
    off = ControllerSettings(height_cue=False)
    assert with_range_model(off, ctx) is off
    # the rig's descriptor decides: a rig whose boxes carry no heights turns the cue off whatever the campaign says
    rig = RigDescriptor(rig="r", kind="simulated", box_heights=False, protocol="1.3")
    assert sensor_config_from_descriptor(rig, sc).box_heights is False
    assert sensor_config_from_descriptor(RigDescriptor(rig="r", kind="simulated", protocol="1.3"), sc).box_heights is True


def test_the_cue_reads_a_public_prior_never_the_world_s_heights(small_pod):
    """The world's height range is the world's business: the controller's prior is its own
    setting (1.5-1.9 m), so a world of 1.0-1.1 m people does not move it."""
    sc = small_scenario(box_heights=True, target_height_min_m=1.0, target_height_max_m=1.1)
    policy = Ra2ViPASHeights(episode_context(sensor_config_from_scenario(sc), small_pod.model, sc, 1, 0))
    cue = policy.controller.parts.vision.ranges
    assert cue is not None and (cue.m_h, cue.v_h) == height_prior(1.5, 1.9)
    assert set(dataclasses.asdict(cue.model)) == {"ref_dbm", "exponent", "ref_distance_m", "shadowing_db"}


def _decisions(policy, platform, steps=30):
    return [(d.next_pan_rad, d.estimate_rad, d.confidence) for d in run_closed_loop(policy, platform, steps)]


def test_the_cue_changes_the_decisions_only_when_heights_are_on(small_pod):
    """With box heights on, Ra2ViPAS with the cue decides differently from the built-in (off by
    default: no cue); a rig without heights builds no cue and decides as the built-in does."""
    sc = small_scenario("dynamic", box_heights=True)
    ctx = episode_context(sensor_config_from_scenario(sc), small_pod.model, sc, 2, 1)
    with_cue = _decisions(Ra2ViPASHeights(ctx), SimulatedPlatform(sc, 2, 1))
    without = _decisions(Ra2ViPAS(ctx), SimulatedPlatform(sc, 2, 1))
    assert Ra2ViPASHeights(ctx).controller.parts.vision.ranges is not None
    assert Ra2ViPAS(ctx).controller.parts.vision.ranges is None  # the built-in: off by default
    assert [d[2] for d in with_cue] != [d[2] for d in without]
    plain = small_scenario("dynamic")
    ctx = episode_context(sensor_config_from_scenario(plain), small_pod.model, plain, 2, 1)
    policy = Ra2ViPASHeights(ctx)
    assert policy.controller.parts.vision.ranges is None
    same = Controller("ra2vipas", sensor_config_from_scenario(plain), small_pod.model)
    assert _decisions(policy, SimulatedPlatform(plain, 2, 1)) == _decisions(same, SimulatedPlatform(plain, 2, 1))
