"""The simulated world: targets around the platform, the camera's detector and the two
receivers (paper Sec. II, Table I).

Two things come out of here and must never be mixed: *measurements*
(``ra2vipas.services.protocol.measurements``), which is all the controller and learner see, and
*ground truth* (``GroundTruth``, ``TrainingTruth``), which only the scoring code reads.

Every random draw comes from a generator derived from the campaign seed and the test index
with ``numpy.random.SeedSequence`` (``episode_streams``), so test k draws the same numbers
whatever runs before, after or beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement, TrainingSample
from ra2vipas.services.protocol.scenario import Placement, Scenario, ScenarioError
from ra2vipas.services.sensors import physics

_TEST_STREAM = 0
_TRAINING_STREAM = 1
_MAX_DRAWS = 100_000


@dataclass(frozen=True)
class Streams:
    """Independent random generators of one episode."""

    placement: np.random.Generator
    rf: np.random.Generator
    camera: np.random.Generator


def _streams(seed: int, key: tuple[int, ...]) -> Streams:
    children = np.random.SeedSequence(entropy=seed, spawn_key=key).spawn(3)
    return Streams(*(np.random.default_rng(c) for c in children))


def episode_streams(seed: int, test_index: int) -> Streams:
    """Generators of test ``test_index`` of a campaign seeded with ``seed``.

    They depend on nothing else, so results do not depend on worker count or order, and all
    algorithms meet the same world in test k (paired comparison).
    """
    return _streams(seed, (_TEST_STREAM, test_index))


def training_streams(seed: int) -> Streams:
    """Generators of the POD training episode of a campaign seeded with ``seed``."""
    return _streams(seed, (_TRAINING_STREAM,))


@dataclass(frozen=True)
class GroundTruth:
    """The truth of one test, for scoring only (paper eqs. 7, 10)."""

    positions_m: np.ndarray  # (N, 2) target positions in F_0
    tx_index: int  # i*

    @property
    def ranges_m(self) -> np.ndarray:
        return np.hypot(self.positions_m[:, 0], self.positions_m[:, 1])

    @property
    def bearings_rad(self) -> np.ndarray:
        """gamma_i = atan2(p_y, p_x) (eq. 7)."""
        return np.arctan2(self.positions_m[:, 1], self.positions_m[:, 0])

    @property
    def tx_bearing_rad(self) -> float:
        return float(self.bearings_rad[self.tx_index])

    @property
    def tx_range_m(self) -> float:
        return float(self.ranges_m[self.tx_index])


def _draw_point(sc: Scenario, rng: np.random.Generator, accept) -> np.ndarray:
    w = sc.arena_half_width_m
    for _ in range(_MAX_DRAWS):
        p = rng.uniform(-w, w, size=2)
        d = math.hypot(p[0], p[1])
        if d >= sc.min_target_range_m and accept(d):
            return p
    raise ScenarioError(
        "target placement is infeasible with these parameters "
        "(check arena_half_width_m, min_target_range_m, tx_max_range_m, min_range_gap_m)"
    )


def place_targets(sc: Scenario, rng: np.random.Generator) -> GroundTruth:
    """Draw the N targets and choose the Tx (MISSION: ``reference`` and ``uniform`` rules).

    ``reference``: the Tx uniform in the square with range below ``tx_max_range_m``; every
    other target uniform in the square with |d_i - d_Tx| > ``min_range_gap_m``.
    ``uniform``: all targets uniform in the square. In both, no target is closer than
    ``min_target_range_m``. The Tx's index is drawn at random.
    """
    if sc.placement is Placement.reference:
        tx = _draw_point(sc, rng, lambda d: d < sc.tx_max_range_m)
        d_tx = math.hypot(tx[0], tx[1])
        others = [_draw_point(sc, rng, lambda d: abs(d - d_tx) > sc.min_range_gap_m) for _ in range(sc.n_targets - 1)]
    else:
        tx = _draw_point(sc, rng, lambda d: True)
        others = [_draw_point(sc, rng, lambda d: True) for _ in range(sc.n_targets - 1)]
    tx_index = int(rng.integers(sc.n_targets))
    others.insert(tx_index, tx)
    return GroundTruth(positions_m=np.asarray(others, dtype=float).reshape(sc.n_targets, 2), tx_index=tx_index)


def _frames(sc: Scenario, rng: np.random.Generator, rel_bearings: np.ndarray, p_detect: np.ndarray) -> tuple[CameraFrame, ...]:
    """nu frames of Bernoulli detections (eq. 9) of the targets at ``rel_bearings``.

    Each box reports its bearing with Gaussian noise; boxes are sorted by bearing so their
    order carries no identity.
    """
    nu = sc.frames_per_rf
    n = rel_bearings.size
    if n == 0:
        empty = CameraFrame.model_construct(box_bearings_rad=())
        return (empty,) * nu
    hits = (rng.random((nu, n)) < p_detect).tolist()
    boxes = (rel_bearings + rng.normal(0.0, sc.box_bearing_noise_rad, size=(nu, n))).tolist()
    return tuple(
        CameraFrame.model_construct(box_bearings_rad=tuple(sorted(b for b, h in zip(row, hit) if h)))
        for row, hit in zip(boxes, hits)
    )


class SimulatedPlatform:
    """The camera, Rx(iso) and Rx(dir) in one simulated test.

    ``sense(step, pan)`` answers: the platform is at pan angle ``pan``; give me the RF sample
    and the nu frames (paper eqs. 8, 9). The ground truth is in ``truth`` and never in what
    ``sense`` returns.
    """

    def __init__(self, scenario: Scenario, seed: int, test_index: int) -> None:
        self.scenario = scenario
        streams = episode_streams(seed, test_index)
        self.truth = place_targets(scenario, streams.placement)
        self._rf = streams.rf
        self._camera = streams.camera
        self._bearings = self.truth.bearings_rad
        self._pod = physics.pod(scenario, self.truth.ranges_m)
        self._tx_range = self.truth.tx_range_m
        self._tx_bearing = self.truth.tx_bearing_rad
        self._iso_mean = float(physics.path_loss_dbm(scenario, self._tx_range))
        self._fov = scenario.fov_half_angle_rad

    def sense(self, step: int, pan_rad: float) -> StepMeasurement:
        sc = self.scenario
        sigma = sc.rf_noise_db
        iso = self._iso_mean + self._rf.normal(0.0, sigma)
        dir_mean = physics.directional_rssi_scalar(sc, self._iso_mean, pan_rad - self._tx_bearing)
        dir_ = dir_mean + self._rf.normal(0.0, sigma)
        rel = (self._bearings - pan_rad + np.pi) % (2.0 * np.pi) - np.pi
        in_view = np.abs(rel) <= self._fov
        frames = _frames(sc, self._camera, rel[in_view], self._pod[in_view])
        return StepMeasurement.model_construct(
            step=step,
            pan_rad=float(pan_rad),
            rf=RFSample.model_construct(iso_rssi_dbm=float(iso), dir_rssi_dbm=float(dir_)),
            frames=frames,
        )


@dataclass(frozen=True)
class TrainingTruth:
    """The truth behind a training episode, for scoring the learner (paper eq. 23)."""

    ranges_m: np.ndarray  # d_j
    rssi_dbm: np.ndarray  # r_j = g(d_j), the noiseless iso RSSI
    pod: np.ndarray  # p_D(d_j)


class TrainingEpisode:
    """The self-supervised POD training episode (paper Sec. III-A, Table I).

    The camera looks at the Tx, which walks radially: d_{j+1} = d_j + eta_j,
    eta ~ N(0, train_step_var_m2), kept in [train_min_range_m, train_max_range_m]; it
    starts at a range drawn uniformly in that interval. Each sample is the iso RSSI and the
    nu frames the detector produced at that range.
    """

    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.scenario = scenario
        sc = scenario
        streams = training_streams(seed)
        n = sc.n_train
        lo, hi = sc.train_min_range_m, sc.train_max_range_m
        d = np.empty(n)
        d_j = streams.placement.uniform(lo, hi)
        steps = streams.placement.normal(0.0, math.sqrt(sc.train_step_var_m2), size=n)
        for j in range(n):
            d[j] = d_j
            d_j = min(max(d_j + steps[j], lo), hi)
        r = physics.path_loss_dbm(sc, d)
        self.truth = TrainingTruth(ranges_m=d, rssi_dbm=r, pod=physics.pod(sc, d))
        self._iso = r + streams.rf.normal(0.0, sc.rf_noise_db, size=n)
        self._camera = streams.camera

    def __len__(self) -> int:
        return self.scenario.n_train

    def samples(self):
        """Yield the n_train ``TrainingSample`` in order."""
        sc = self.scenario
        zero = np.zeros(1)
        for j in range(sc.n_train):
            frames = _frames(sc, self._camera, zero, self.truth.pod[j : j + 1])
            yield TrainingSample.model_construct(index=j, iso_rssi_dbm=float(self._iso[j]), frames=frames)
