"""The simulated world: targets around the platform, the camera's detector and the two
receivers (paper Sec. II, Table I), and beyond the paper a cluttered, dynamic world: targets
that walk, bodies that occlude each other, false boxes, shadowing and correlated RSSI noise
(each off unless its scenario parameter turns it on).

Two things come out of here and must never be mixed: *measurements*
(``ra2vipas.services.protocol.measurements``), which is all the controller and learner see, and
*ground truth* (``GroundTruth``, ``TrainingTruth``), which only the scoring code reads.

Every random draw comes from a generator derived from the campaign seed and the test index
with ``numpy.random.SeedSequence`` (``episode_streams``), so test k draws the same numbers
whatever runs before, after or beside it, and whatever pans the controller chooses: the
walkers' trajectories, the occlusions, the shadowing along the Tx's path and the RSSI noise
are fixed when the episode starts; only which targets fall in the field of view (and so how
many camera draws a step consumes) depends on the pan.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, replace
from itertools import compress

import numpy as np

from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement, TrainingSample
from ra2vipas.services.protocol.messages import EpisodeTruth, TargetTrajectory
from ra2vipas.services.protocol.scenario import Placement, RadioMode, Scenario, ScenarioError
from ra2vipas.services.sensors import physics, radio

_TEST_STREAM = 0
_TRAINING_STREAM = 1
_MAX_DRAWS = 100_000

TRUTH_BEARING_DECIMALS = 5
"""Walkers' per-step bearings in the ground truth are rounded to 1e-5 rad (0.0006 deg) so the
``EpisodeTruth`` message stays small; scoring uses the rounded values on every path."""
TRUTH_RANGE_DECIMALS = 3


@dataclass(frozen=True)
class Streams:
    """Independent random generators of one episode.

    SeedSequence children 0-2 (placement, rf, camera) are the paper world's and keep their
    meaning; the dynamic world's draws come from further children (``spawn`` yields the same
    first children whatever their number), so a scenario with those effects off draws exactly
    what it drew before they existed.
    """

    placement: np.random.Generator
    rf: np.random.Generator
    camera: np.random.Generator
    walk: np.random.Generator  # which targets walk, their speeds and headings
    clutter: np.random.Generator  # false boxes
    shadowing: np.random.Generator  # the shadowing field
    radio: np.random.Generator  # protocol 1.3: advertising events, scan phases, channel offsets, losses, per-packet spread
    heights: np.random.Generator  # protocol 1.3: the targets' heights, the boxes' height noise, clutter heights
    tags: np.random.Generator  # protocol 1.4: the carriers of tags 1..K-1
    tags_seed: np.random.SeedSequence | None = None  # protocol 1.4: tag k's own stream is its child k (``tag_stream``)

    def tag_stream(self, k: int) -> np.random.Generator:
        """Tag k's own generator (k >= 1; tag 0 draws from ``rf``/``radio`` as the only tag always
        did): its RSSI noise, or its advertising events, channel offsets, losses and spread."""
        seq = self.tags_seed
        return np.random.default_rng(np.random.SeedSequence(entropy=seq.entropy, spawn_key=(*seq.spawn_key, k)))


def _streams(seed: int, key: tuple[int, ...]) -> Streams:
    children = np.random.SeedSequence(entropy=seed, spawn_key=key).spawn(9)
    return Streams(*(np.random.default_rng(c) for c in children), tags_seed=children[8])


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
    """The truth of one test, for scoring only (paper eqs. 7, 10).

    ``positions_m`` are the targets' positions at step 0 (and always, for the static ones);
    ``walkers`` lists the targets that walk and ``walker_positions_m[t, k]`` is where walker
    ``walkers[k]`` stands during step t (the nu frames and the RF sample of step t).
    """

    positions_m: np.ndarray  # (N, 2) target positions in F_0 at step 0
    tx_index: int  # i*
    walkers: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))  # (W,) sorted target indices
    walker_positions_m: np.ndarray | None = None  # (T, W, 2)
    tx_indices: tuple[int, ...] = ()  # K > 1 tags: the carrier of tag k (tx_indices[0] == tx_index)
    tag_addresses: tuple[str, ...] = ()  # K > 1 tags: each tag's address

    @property
    def carriers(self) -> tuple[int, ...]:
        """The target that carries each tag k = 0..K-1 (one tag: ``(tx_index,)``)."""
        return self.tx_indices or (self.tx_index,)

    @property
    def ranges_m(self) -> np.ndarray:
        """d_i at step 0."""
        return np.hypot(self.positions_m[:, 0], self.positions_m[:, 1])

    @property
    def bearings_rad(self) -> np.ndarray:
        """gamma_i = atan2(p_y, p_x) (eq. 7), at step 0."""
        return np.arctan2(self.positions_m[:, 1], self.positions_m[:, 0])

    @property
    def static(self) -> bool:
        return self.walker_positions_m is None or self.walkers.size == 0

    @property
    def tx_walks(self) -> bool:
        return not self.static and bool(np.any(self.walkers == self.tx_index))

    def positions_at(self, step: int) -> np.ndarray:
        """(N, 2) positions during step ``step``."""
        if self.static:
            return self.positions_m
        p = self.positions_m.copy()
        p[self.walkers] = self.walker_positions_m[min(step, self.walker_positions_m.shape[0] - 1)]
        return p

    def tx_positions_m(self, steps: int) -> np.ndarray:
        """(steps, 2) the Tx's position at every step."""
        return self.target_positions_m(self.tx_index, steps)

    def walks(self, target: int) -> bool:
        return not self.static and bool(np.any(self.walkers == target))

    def target_positions_m(self, target: int, steps: int) -> np.ndarray:
        """(steps, 2) where target ``target`` stands at every step (a tag's carrier: where the tag is)."""
        if self.walks(target):
            k = int(np.flatnonzero(self.walkers == target)[0])
            return self.walker_positions_m[:steps, k]
        return np.repeat(self.positions_m[target][None, :], steps, axis=0)

    def walker_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The walkers' per-step bearings and ranges, (T, W) each, rounded as the truth
        message carries them (``TRUTH_BEARING_DECIMALS``, ``TRUTH_RANGE_DECIMALS``)."""
        if self.static:
            return np.empty((0, 0)), np.empty((0, 0))
        p = self.walker_positions_m
        bearings = np.round(np.arctan2(p[..., 1], p[..., 0]), TRUTH_BEARING_DECIMALS)
        ranges = np.round(np.hypot(p[..., 0], p[..., 1]), TRUTH_RANGE_DECIMALS)
        return bearings, ranges

    def step_bearings_rad(self) -> np.ndarray:
        """What DR_t is scored against: gamma_i at every step, shape (T, N), the walkers'
        columns rounded as in the truth message; (N,) for a static world."""
        if self.static:
            return self.bearings_rad
        b = np.repeat(self.bearings_rad[None, :], self.walker_positions_m.shape[0], axis=0)
        b[:, self.walkers] = self.walker_truth()[0]
        return b

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
    """Draw the N targets and choose the Tx (the ``reference`` and ``uniform`` rules).

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


def add_walkers(sc: Scenario, rng: np.random.Generator, truth: GroundTruth) -> GroundTruth:
    """Choose the targets that walk, ``walking_fraction`` of them rounded half up (``sc.n_walkers``
    for a drawn layout), uniformly at random with the Tx among the candidates, and draw their
    trajectories over ``sc.steps`` steps from their step-0 positions (``physics.walk``). All
    draws come from ``rng``; none when nobody walks."""
    n = truth.positions_m.shape[0]
    n_walk = int(math.floor(sc.walking_fraction * n + 0.5))
    if n_walk == 0:
        return truth
    walkers = np.sort(rng.choice(n, size=n_walk, replace=False))
    paths = physics.walk(sc, rng, truth.positions_m[walkers], sc.steps)
    return GroundTruth(positions_m=truth.positions_m, tx_index=truth.tx_index, walkers=walkers, walker_positions_m=paths)


def tag_address(seed: int, tag: int) -> str:
    """Tag ``tag``'s address in a campaign seeded with ``seed``: a BLE random static address (the
    two top bits set) from a hash of both, the same in every test of the campaign (as a real
    deployment's tags keep theirs), drawn from no random stream."""
    raw = bytearray(hashlib.sha256(f"ra2vipas-tag:{seed}:{tag}".encode()).digest()[:6])
    raw[0] |= 0xC0
    return ":".join(f"{b:02X}" for b in raw)


def draw_carriers(sc: Scenario, rng: np.random.Generator, ranges_m: np.ndarray, tx_index: int) -> tuple[int, ...]:
    """The carriers of the K tags (empty for K = 1): tag 0 is carried by the Tx ``tx_index`` (the
    placement's rule chose it); tags 1..K-1, from ``rng``, by the rule that chose the Tx as far as
    the layout allows without moving anyone (``carrier_pool``): K - 1 distinct targets of the
    pool when ``one_tag_per_person``, else each uniform over the pool and the Tx (so two tags may
    share one). ``ranges_m``: every target's range at step 0."""
    k = sc.n_tags
    if k == 1:
        return ()
    n_targets = len(ranges_m)
    if sc.one_tag_per_person:
        if k > n_targets:
            raise ScenarioError(f"n_tags ({k}) exceeds the {n_targets} targets while one_tag_per_person is true")
        rest = rng.choice(carrier_pool(sc, ranges_m, tx_index, k - 1), size=k - 1, replace=False)
    else:
        pool = np.concatenate([[tx_index], carrier_pool(sc, ranges_m, tx_index, 1)])
        rest = pool[rng.integers(len(pool), size=k - 1)]
    return (int(tx_index), *(int(i) for i in rest))


def carrier_pool(sc: Scenario, ranges_m: np.ndarray, tx_index: int, need: int) -> np.ndarray:
    """The targets other than the Tx that may carry a tag (docs/tags.md, "Carriers"): with the
    ``reference`` placement, those within ``tx_max_range_m`` of the platform, as the Tx is (the
    rule's other half, no other target within ``min_range_gap_m`` of the carrier's range, cannot
    hold for several carriers without moving people), completed by the nearest others when
    fewer than ``need``; with ``uniform``, every other target. Sorted by index."""
    others = np.delete(np.arange(len(ranges_m)), tx_index)
    if sc.placement is not Placement.reference:
        return others
    near = others[ranges_m[others] < sc.tx_max_range_m]
    if len(near) < need:
        far = others[ranges_m[others] >= sc.tx_max_range_m]
        near = np.sort(np.concatenate([near, far[np.argsort(ranges_m[far], kind="stable")[:need - len(near)]]]))
    return near


def episode_truth(truth: GroundTruth, episode_id: str) -> EpisodeTruth:
    """The truth-plane message of an episode: every target's bearing and range at step 0,
    the Tx index and, per walker, its rounded per-step bearings and ranges; with K > 1 tags
    each tag's carrier and address."""
    bearings, ranges = truth.walker_truth()
    trajectories = tuple(
        TargetTrajectory.model_construct(index=int(i), bearings_rad=tuple(bearings[:, k].tolist()), ranges_m=tuple(ranges[:, k].tolist()))
        for k, i in enumerate(truth.walkers.tolist())
    ) if not truth.static else ()
    return EpisodeTruth(episode_id=episode_id, bearings_rad=tuple(float(b) for b in truth.bearings_rad),
                        ranges_m=tuple(float(r) for r in truth.ranges_m), tx_index=truth.tx_index, trajectories=trajectories,
                        tx_indices=tuple(truth.tx_indices), tag_addresses=tuple(truth.tag_addresses))


def _clutter(sc: Scenario, rng: np.random.Generator) -> list[list[float]] | None:
    """False boxes of the nu frames of one step: Poisson(``clutter_rate``) per frame, bearings
    uniform over the field of view. None when clutter is off (nothing drawn)."""
    if sc.clutter_rate <= 0.0:
        return None
    nu = sc.frames_per_rf
    counts = rng.poisson(sc.clutter_rate, size=nu)
    fov = sc.fov_half_angle_rad
    boxes = rng.uniform(-fov, fov, size=int(counts.sum())).tolist()
    out, lo = [], 0
    for c in counts.tolist():
        out.append(boxes[lo:lo + c])
        lo += c
    return out


_EMPTY_FRAME = CameraFrame.model_construct(box_bearings_rad=())
_NO_HEIGHTS_FRAME = CameraFrame.model_construct(box_bearings_rad=(), box_heights_rad=())


# model_construct of the measurement models the inner loop builds, cheaper (``_construct``: the same objects)
_new_frame = builder(CameraFrame, "box_bearings_rad")
_new_frame_with_heights = builder(CameraFrame, "box_bearings_rad", "box_heights_rad")
_new_pair = builder(RFSample, "iso_rssi_dbm", "dir_rssi_dbm")
_new_tag_pair = builder(RFSample, "iso_rssi_dbm", "dir_rssi_dbm", "tag")
_new_step = builder(StepMeasurement, "step", "pan_rad", "rf", "frames")
_new_step_tags = builder(StepMeasurement, "step", "pan_rad", "rf", "frames", "rf_tags")
_new_step_adverts = builder(StepMeasurement, "step", "pan_rad", "rf", "frames", "adverts")


def _frame(boxes: list[float]) -> CameraFrame:
    return _new_frame(tuple(sorted(boxes))) if boxes else _EMPTY_FRAME


def _frames(sc: Scenario, rng: np.random.Generator, rel_bearings: np.ndarray, p_detect: np.ndarray,
            clutter: list[list[float]] | None = None) -> tuple[CameraFrame, ...]:
    """nu frames of Bernoulli detections (eq. 9) of the targets at ``rel_bearings``, plus the
    false boxes ``clutter`` (one list per frame).

    Each box reports its bearing with Gaussian noise; boxes are sorted by bearing so their
    order carries no identity (and a false box looks like any other).
    """
    nu = sc.frames_per_rf
    n = rel_bearings.size
    if n == 0:
        if clutter is None:
            return (_EMPTY_FRAME,) * nu
        return tuple(_frame(c) for c in clutter)
    hits = (rng.random((nu, n)) < p_detect).tolist()
    boxes = (rel_bearings + rng.normal(0.0, sc.box_bearing_noise_rad, size=(nu, n))).tolist()
    if clutter is None:  # compress(row, hit): the boxes detected, in order
        return tuple(_frame(list(compress(row, hit))) for row, hit in zip(boxes, hits))
    return tuple(_frame(list(compress(row, hit)) + extra) for row, hit, extra in zip(boxes, hits, clutter))


def _frames_with_heights(sc: Scenario, rng: np.random.Generator, heights_rng: np.random.Generator, rel_bearings: np.ndarray,
                         p_detect: np.ndarray, true_heights: np.ndarray, clutter: list[list[float]] | None) -> tuple[CameraFrame, ...]:
    """``_frames`` with every box's angular height (protocol 1.3): the camera's draws are exactly
    ``_frames``'s (same generator, same order), the heights' noise and the false boxes' heights
    come from ``heights_rng``. Boxes are sorted by bearing, their heights following them."""
    nu = sc.frames_per_rf
    n = rel_bearings.size
    if n:
        hits = (rng.random((nu, n)) < p_detect).tolist()
        boxes = (rel_bearings + rng.normal(0.0, sc.box_bearing_noise_rad, size=(nu, n))).tolist()
        heights = radio.noisy_heights(sc, heights_rng, np.broadcast_to(true_heights, (nu, n))).tolist()
    else:
        hits = boxes = heights = [[]] * nu
    extra_count = sum(len(c) for c in clutter) if clutter is not None else 0
    extra_heights = radio.clutter_heights(sc, heights_rng, extra_count).tolist() if extra_count else []
    out, lo = [], 0
    for f in range(nu):
        pairs = [(b, h) for b, h, hit in zip(boxes[f], heights[f], hits[f]) if hit]
        if clutter is not None:
            c = clutter[f]
            pairs += list(zip(c, extra_heights[lo:lo + len(c)]))
            lo += len(c)
        if not pairs:
            out.append(_NO_HEIGHTS_FRAME)
            continue
        pairs.sort()
        out.append(_new_frame_with_heights(tuple(b for b, _ in pairs), tuple(h for _, h in pairs)))
    return tuple(out)


class SimulatedPlatform:
    """The camera, Rx(iso) and Rx(dir) in one simulated test.

    ``sense(step, pan)`` answers: the platform is at pan angle ``pan``; give me the RF sample
    and the nu frames (paper eqs. 8, 9). The ground truth is in ``truth`` and never in what
    ``sense`` returns.

    The world of the test is drawn here, once: the layout (or ``layout``, a scripted one:
    a ``GroundTruth`` whose walkers, if any, are used as given), the walkers and their
    trajectories, who occludes whom at every step, and the shadowing along the Tx's path.
    ``sense`` then only draws the RSSI noise (two values per step, whatever the pan) and the
    camera's detections and false boxes.
    """

    def __init__(self, scenario: Scenario, seed: int, test_index: int, layout: GroundTruth | None = None) -> None:
        self.scenario = sc = scenario
        streams = episode_streams(seed, test_index)
        truth = place_targets(sc, streams.placement) if layout is None else layout
        if truth.static:
            truth = add_walkers(sc, streams.walk, truth)
        if sc.n_tags > 1:  # protocol 1.4: tags 1..K-1 and their carriers, from the tags stream (nothing else moves)
            carriers = truth.tx_indices or draw_carriers(sc, streams.tags, truth.ranges_m, truth.tx_index)
            if len(carriers) != sc.n_tags or carriers[0] != truth.tx_index:
                raise ScenarioError(f"the layout names {len(carriers)} tag carriers for n_tags={sc.n_tags}")
            truth = replace(truth, tx_indices=tuple(carriers), tag_addresses=tuple(tag_address(seed, k) for k in range(sc.n_tags)))
        self.truth = truth
        self._rf = streams.rf
        self._camera = streams.camera
        self._clutter_rng = streams.clutter
        self._fov = sc.fov_half_angle_rad
        steps = sc.steps
        # camera: bearings and p_D at step 0 (static targets keep them), walkers per step
        self._bearings = truth.bearings_rad
        self._pod = physics.pod(sc, truth.ranges_m)
        self._walkers = truth.walkers if not truth.static else None
        if self._walkers is not None:
            wp = truth.walker_positions_m
            self._walk_bearings = np.arctan2(wp[..., 1], wp[..., 0])
            self._walk_pod = physics.pod(sc, np.hypot(wp[..., 0], wp[..., 1]))
        # occlusion (eq. 10 failing): which targets are hidden, per step if anyone walks
        self._visible = None
        if sc.body_width_m > 0.0:
            if self._walkers is None:
                self._visible = ~physics.occluded(sc.body_width_m, self._bearings, truth.ranges_m)
            else:
                b = np.repeat(self._bearings[None, :], wp.shape[0], axis=0)
                d = np.repeat(truth.ranges_m[None, :], wp.shape[0], axis=0)
                b[:, self._walkers] = self._walk_bearings
                d[:, self._walkers] = np.hypot(wp[..., 0], wp[..., 1])
                self._visible = ~physics.occluded(sc.body_width_m, b, d)
        # radio: the Tx's range and bearing, and the shadowing at its position (per step if it walks)
        self._tx_range = truth.tx_range_m
        self._tx_bearing = truth.tx_bearing_rad
        self._iso_mean = float(physics.path_loss_dbm(sc, self._tx_range))
        self._iso_means = self._tx_bearings = None
        self.shadowing = None if sc.shadowing_db <= 0.0 else physics.ShadowingField(sc.shadowing_db, sc.shadowing_corr_m, streams.shadowing)
        """The test's shadowing field S(p) [dB] (truth, None when off)."""
        if truth.tx_walks or self.shadowing is not None:
            tx_path = truth.tx_positions_m(steps) if truth.tx_walks else truth.positions_m[truth.tx_index][None, :]
            means = physics.path_loss_dbm(sc, np.hypot(tx_path[:, 0], tx_path[:, 1]))
            if self.shadowing is not None:
                means = means + self.shadowing(tx_path)
            if truth.tx_walks:
                self._iso_means = means.tolist()
                self._tx_bearings = np.arctan2(tx_path[:, 1], tx_path[:, 0]).tolist()
            else:
                self._iso_mean = float(means[0])
        # protocol 1.3: BLE advertisements (0..n per step and receiver) instead of one pair, from the radio stream
        self._packets = None
        if sc.radio is RadioMode.adverts:
            self._packets = radio.PacketSchedule(sc, streams.radio, steps)
        elif sc.radio is RadioMode.recorded:
            from ra2vipas.services.sensors import recorded

            tx_path = truth.tx_positions_m(steps)
            self._packets = recorded.RecordedSchedule(sc, streams.radio, tx_path)
        # protocol 1.4: tags 1..K-1, each on its own stream: its carrier's path, its packets or its RSSI noise
        self._tags: list[_TagLink] = []
        if sc.n_tags > 1:
            if self._packets is not None:
                self._packets.tag, self._packets.address = 0, truth.tag_addresses[0]
            for k in range(1, sc.n_tags):
                self._tags.append(_TagLink(sc, truth, k, streams.tag_stream(k), self.shadowing, self._packets))
        # protocol 1.3: boxes with heights (each target's height drawn once, from the heights stream)
        self._heights_rng = self._target_heights = None
        if sc.box_heights:
            self._heights_rng = streams.heights
            self._target_heights = streams.heights.uniform(sc.target_height_min_m, sc.target_height_max_m, size=self._bearings.size)
            self._ranges = truth.ranges_m
            if self._walkers is not None:
                self._walk_ranges = np.hypot(wp[..., 0], wp[..., 1])
        # RSSI noise: white (phi = 0) or AR(1) on each receiver
        self._phi = physics.fading_coefficient(sc)
        self._innovation = math.sqrt(1.0 - self._phi * self._phi)
        self._noise = None  # (iso, dir) of the previous step

    # -- truth accessors (for scoring and tests; never part of a measurement) ------------------
    def iso_mean_dbm(self, step: int) -> float:
        """The noiseless iso RSSI at step ``step``: g(d_Tx) plus the shadowing at the Tx."""
        return self._iso_mean if self._iso_means is None else self._iso_means[min(step, len(self._iso_means) - 1)]

    def visible_at(self, step: int) -> np.ndarray:
        """(N,) bool: which targets no nearer target hides at step ``step`` (all without bodies)."""
        if self._visible is None:
            return np.ones(self._bearings.shape[0], dtype=bool)
        return self._visible if self._visible.ndim == 1 else self._visible[min(step, self._visible.shape[0] - 1)]

    def sense(self, step: int, pan_rad: float) -> StepMeasurement:
        if self._iso_means is None:
            iso_mean, tx_bearing = self._iso_mean, self._tx_bearing
        else:
            t = min(step, len(self._iso_means) - 1)
            iso_mean, tx_bearing = self._iso_means[t], self._tx_bearings[t]
        if self._packets is not None:
            return self._sense_packets(step, pan_rad, iso_mean, tx_bearing)
        if self._tags:  # protocol 1.4: tag 0's pair drawn as always, then the others' from their own streams
            m = self._sense_pair(step, pan_rad, iso_mean, tx_bearing)
            rf_tags = tuple(tag.pair(step, pan_rad) for tag in self._tags)
            return _new_step_tags(m.step, m.pan_rad, m.rf, m.frames, rf_tags)
        return self._sense_pair(step, pan_rad, iso_mean, tx_bearing)

    def _sense_pair(self, step: int, pan_rad: float, iso_mean: float, tx_bearing: float) -> StepMeasurement:
        """The paper's radio: tag 0's (iso, dir) RSSI pair of step ``step`` and the frames."""
        sc = self.scenario
        sigma = sc.rf_noise_db
        dir_mean = physics.directional_rssi_scalar(sc, iso_mean, pan_rad - tx_bearing)
        if self._phi == 0.0:
            iso = iso_mean + self._rf.normal(0.0, sigma)
            dir_ = dir_mean + self._rf.normal(0.0, sigma)
        else:
            e_iso, e_dir = self._rf.normal(0.0, sigma), self._rf.normal(0.0, sigma)
            if self._noise is None:
                n_iso, n_dir = e_iso, e_dir  # stationary start
            else:
                n_iso = self._phi * self._noise[0] + self._innovation * e_iso
                n_dir = self._phi * self._noise[1] + self._innovation * e_dir
            self._noise = (n_iso, n_dir)
            iso, dir_ = iso_mean + n_iso, dir_mean + n_dir
        return _new_step(step, float(pan_rad), _new_pair(float(iso), float(dir_)), self._frames_at(step, pan_rad))

    def _frames_at(self, step: int, pan_rad: float) -> tuple[CameraFrame, ...]:
        sc = self.scenario
        bearings, p_detect = self._bearings, self._pod
        if self._walkers is not None:
            t = min(step, self._walk_bearings.shape[0] - 1)
            bearings, p_detect = bearings.copy(), p_detect.copy()
            bearings[self._walkers] = self._walk_bearings[t]
            p_detect[self._walkers] = self._walk_pod[t]
        if self._visible is not None:
            visible = self._visible if self._visible.ndim == 1 else self._visible[min(step, self._visible.shape[0] - 1)]
            p_detect = np.where(visible, p_detect, 0.0)
        rel = (bearings - pan_rad + np.pi) % (2.0 * np.pi) - np.pi
        in_view = np.abs(rel) <= self._fov
        if self._target_heights is None:
            return _frames(sc, self._camera, rel[in_view], p_detect[in_view], _clutter(sc, self._clutter_rng))
        ranges = self._ranges
        if self._walkers is not None:
            ranges = ranges.copy()
            ranges[self._walkers] = self._walk_ranges[min(step, self._walk_ranges.shape[0] - 1)]
        true_heights = radio.angular_height(sc, self._target_heights[in_view], ranges[in_view])
        return _frames_with_heights(sc, self._camera, self._heights_rng, rel[in_view], p_detect[in_view], true_heights,
                                    _clutter(sc, self._clutter_rng))

    def _sense_packets(self, step: int, pan_rad: float, iso_mean: float, tx_bearing: float) -> StepMeasurement:
        """Protocol 1.3: the advertisements each receiver heard during step ``step`` (maybe none)."""
        adverts = self._packets.packets(step, radio.step_levels(self.scenario, iso_mean, pan_rad, tx_bearing))
        if self._tags:  # protocol 1.4: every tag's packets, in arrival order (ties: by tag)
            every = list(adverts)
            for tag in self._tags:
                every += tag.packets(step, pan_rad)
            adverts = tuple(sorted(every, key=lambda a: (a.offset_s, a.tag)))
        return _new_step_adverts(step, float(pan_rad), None, self._frames_at(step, pan_rad), adverts)


class _TagLink:
    """The radio link of tag k >= 1 (protocol 1.4): where its carrier is, the noiseless iso level
    there (path loss plus the test's shadowing field, the same building as tag 0's), and what
    the receivers make of it, drawn from the tag's own stream ``rng``: with the paper's radio
    its own (iso, dir) RSSI noise (AR(1) when fading is on), with BLE its own advertising
    events, advDelay, channel offsets, losses and spread (the receivers' scan is the rig's,
    shared with tag 0), with a recorded channel its own recordings and cursor."""

    def __init__(self, sc: Scenario, truth: GroundTruth, k: int, rng: np.random.Generator,
                 shadowing: physics.ShadowingField | None, tag0_packets) -> None:
        self.scenario = sc
        self.tag = k
        steps = sc.steps
        path = truth.target_positions_m(truth.tx_indices[k], steps)
        means = physics.path_loss_dbm(sc, np.hypot(path[:, 0], path[:, 1]))
        if shadowing is not None:
            means = means + shadowing(path)
        self.iso_means = means.tolist()
        self.bearings = np.arctan2(path[:, 1], path[:, 0]).tolist()
        self.rng = rng
        self.phi = physics.fading_coefficient(sc)
        self.innovation = math.sqrt(1.0 - self.phi * self.phi)
        self.noise = None
        self.schedule = None
        if sc.radio is RadioMode.adverts:
            self.schedule = radio.PacketSchedule(sc, rng, steps, scan_phases_s=tag0_packets.scan_phases_s)
        elif sc.radio is RadioMode.recorded:
            from ra2vipas.services.sensors import recorded

            self.schedule = recorded.RecordedSchedule(sc, rng, path, rx=tag0_packets.rx, turn_rad=tag0_packets.turn_rad)
        if self.schedule is not None:
            self.schedule.tag, self.schedule.address = k, truth.tag_addresses[k]

    def _level(self, step: int) -> tuple[float, float]:
        t = min(step, len(self.iso_means) - 1)
        return self.iso_means[t], self.bearings[t]

    def pair(self, step: int, pan_rad: float) -> RFSample:
        """The paper's radio: this tag's (iso, dir) RSSI pair at pan ``pan_rad``."""
        sc = self.scenario
        iso_mean, bearing = self._level(step)
        dir_mean = physics.directional_rssi_scalar(sc, iso_mean, pan_rad - bearing)
        e_iso, e_dir = self.rng.normal(0.0, sc.rf_noise_db), self.rng.normal(0.0, sc.rf_noise_db)
        if self.phi != 0.0 and self.noise is not None:
            e_iso = self.phi * self.noise[0] + self.innovation * e_iso
            e_dir = self.phi * self.noise[1] + self.innovation * e_dir
        self.noise = (e_iso, e_dir)
        return _new_tag_pair(float(iso_mean + e_iso), float(dir_mean + e_dir), self.tag)

    def packets(self, step: int, pan_rad: float):
        iso_mean, bearing = self._level(step)
        return self.schedule.packets(step, radio.step_levels(self.scenario, iso_mean, pan_rad, bearing))


@dataclass(frozen=True)
class TrainingTruth:
    """The truth behind a training episode, for scoring the learner (paper eq. 23).

    ``rssi_dbm`` is the noiseless iso RSSI: the channel, g(d_j) plus the shadowing S at the
    Tx's position when ``shadowing_db`` > 0 (shadowing is part of the channel the POD is
    learned over, not measurement noise: the controller too reads the POD at the Tx's
    shadowed RSSI). It excludes the receiver noise, white or AR(1).

    ``pod`` is the true POD *as a function of that RSSI*, what p_hat_D(r) estimates. Without
    shadowing it is the paper's p_D(g^{-1}(r_j)) = p_D(d_j). With shadowing one RSSI comes from
    many ranges, so the POD is not a function of the RSSI; the function the learner estimates
    (and the controller needs: "how likely is the camera to see the Tx, given what Rx(iso)
    reads") is the regression function p*(r) = E[p_D(d) | g(d) + S = r], with S ~ N(0,
    sigma_S^2) independent of the range and d distributed as the episode's ranges
    (``pod_given_rssi``). ``pod_at_range`` keeps p_D(d_j).
    """

    ranges_m: np.ndarray  # d_j
    rssi_dbm: np.ndarray  # r_j = g(d_j) + S(p_j), the noiseless iso RSSI
    pod: np.ndarray  # p*(r_j), = p_D(d_j) without shadowing
    pod_at_range: np.ndarray | None = None  # p_D(d_j), when it differs from ``pod``
    positions_m: np.ndarray | None = None  # (n, 2) where the Tx was, when it steps sideways (shadowing)


def pod_given_rssi(sc: Scenario, ranges_m: np.ndarray, rssi_dbm: np.ndarray) -> np.ndarray:
    """p*(r) = E[p_D(d) | g(d) + S = r] at each ``rssi_dbm`` (see ``TrainingTruth``): a mixture over
    the ranges ``ranges_m`` (the episode's, equally likely) of the shadowing's Gaussian density,
    sum_i p_D(d_i) N(r; g(d_i), sigma_S^2) / sum_i N(r; g(d_i), sigma_S^2)."""
    d = np.asarray(ranges_m, dtype=float)
    g = physics.path_loss_dbm(sc, d)
    log_w = -0.5 * ((np.asarray(rssi_dbm, dtype=float)[:, None] - g[None, :]) / sc.shadowing_db) ** 2
    w = np.exp(log_w - log_w.max(axis=1, keepdims=True))
    return (w @ physics.pod(sc, d)) / w.sum(axis=1)


class TrainingEpisode:
    """The self-supervised POD training episode (paper Sec. III-A, Table I).

    The camera looks at the Tx, which walks radially: d_{j+1} = d_j + eta_j,
    eta ~ N(0, train_step_var_m2), kept in [train_min_range_m, train_max_range_m]; it
    starts at a range drawn uniformly in that interval. Each sample is the iso RSSI and the
    nu frames the detector produced at that range.

    It runs in the scenario's world: the iso RSSI noise is AR(1) when ``fading_corr_s`` > 0;
    every frame gets Poisson(``clutter_rate``) false boxes; with shadowing the Tx also steps
    sideways, as much as radially (N(0, train_step_var_m2) across its bearing, the camera
    following it), so the episode meets the shadowing of many places rather than of one line
    (along one line a few shadowing values would be taken for the path loss); its range still
    moves exactly as Table I says. The Tx is the only target in training: nothing walks past
    it and nothing occludes it.
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
        pod = physics.pod(sc, d)
        if sc.shadowing_db > 0.0:
            bearing = np.cumsum(streams.walk.normal(0.0, math.sqrt(sc.train_step_var_m2), size=n) / d)
            path = np.column_stack([d * np.cos(bearing), d * np.sin(bearing)])
            self.shadowing = physics.ShadowingField(sc.shadowing_db, sc.shadowing_corr_m, streams.shadowing)
            """The episode's shadowing field S(p) [dB] (truth; None when off)."""
            r = r + self.shadowing(path)
            self.truth = TrainingTruth(ranges_m=d, rssi_dbm=r, pod=pod_given_rssi(sc, d, r), pod_at_range=pod, positions_m=path)
        else:
            self.shadowing = None
            self.truth = TrainingTruth(ranges_m=d, rssi_dbm=r, pod=pod)
        noise = streams.rf.normal(0.0, sc.rf_noise_db, size=n)
        phi = physics.fading_coefficient(sc)
        self._iso = r + (noise if phi == 0.0 else physics.ar1(noise, phi))
        self._camera = streams.camera
        self._clutter_rng = streams.clutter
        self._pod = pod  # the camera detects at p_D(d_j)
        # protocol 1.3: the advertisements Rx(iso) hears during each sample, from the radio stream
        self._packets = None
        if sc.radio is RadioMode.adverts:
            self._packets = radio.PacketSchedule(sc, streams.radio, n, receivers=1)
        elif sc.radio is RadioMode.recorded:
            from ra2vipas.services.sensors import recorded

            path = self.truth.positions_m if self.truth.positions_m is not None else np.column_stack([d, np.zeros(n)])
            self._packets = recorded.RecordedSchedule(sc, streams.radio, path, receivers=1)
        self._true_heights = None
        if sc.box_heights:
            self._heights_rng = streams.heights
            self._true_heights = radio.angular_height(sc, streams.heights.uniform(sc.target_height_min_m, sc.target_height_max_m), d)

    def __len__(self) -> int:
        return self.scenario.n_train

    def samples(self):
        """Yield the n_train ``TrainingSample`` in order."""
        sc = self.scenario
        zero = np.zeros(1)
        for j in range(sc.n_train):
            if self._true_heights is None:
                frames = _frames(sc, self._camera, zero, self._pod[j : j + 1], _clutter(sc, self._clutter_rng))
            else:
                frames = _frames_with_heights(sc, self._camera, self._heights_rng, zero, self._pod[j : j + 1],
                                              self._true_heights[j : j + 1], _clutter(sc, self._clutter_rng))
            if self._packets is None:
                yield TrainingSample.model_construct(index=j, iso_rssi_dbm=float(self._iso[j]), frames=frames)
            else:
                adverts = self._packets.packets(j, (float(self.truth.rssi_dbm[j]),))
                yield TrainingSample.model_construct(index=j, iso_rssi_dbm=None, frames=frames, adverts=adverts)
