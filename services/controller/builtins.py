"""The four policies ra2vipas ships (paper Sec. IV-B, plus one), behind the policy contract
(``contract.py``) and registered through the same entry-point group as anyone's
(``ra2vipas.policies`` in pyproject.toml):

* ``ra2vipas``: fuses Rx(dir), Rx(iso) and the camera, GP-UCB on the fused objective (eq. 25);
* ``rapas``: Rx(dir) only (the paper's RaPAS baseline);
* ``ravipas``: the camera and Rx(iso) only (the paper's RaViPAS baseline);
* ``sweep``: fuses both but pans evenly round the circle (what active sensing buys).

Each is a composition of parts (``composed.Parts``: an RF belief, a vision belief, the fusion, an
acquisition and the confidence map), built below by ``compose`` with the algorithm's tuning
(``policy.TUNING``); a user's policy composes the same parts its own way (docs/policies.md).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

from ra2vipas.services.controller.acquisition import GPUCB, Acquisition, ProbeSchedule, WarmUpSweep
from ra2vipas.services.controller.acquisition import Sweep as EvenSweep
from ra2vipas.services.controller.circle_gp import RecentLobe
from ra2vipas.services.controller.composed import Parts
from ra2vipas.services.controller.confidence import Confidence, shipped_map
from ra2vipas.services.controller.contract import EpisodeContext, Policy
from ra2vipas.services.controller.fusion import Fusion
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.joint import JointSearch, SequentialSearch
from ra2vipas.services.controller.policy import (
    Controller,
    ControllerSettings,
    Decision,
    SensorConfig,
    tuned_settings,
    with_range_model,
)
from ra2vipas.services.controller.range_cue import RangeCue
from ra2vipas.services.controller.rf_belief import IsoLevel, LobeBelief, RFBelief, RFFilterBelief, lobe_gp
from ra2vipas.services.controller.rf_filter import PacketBearingFilter, RxDirModel
from ra2vipas.services.controller.vision_belief import CameraBelief, PODLookup, VisionBelief
from ra2vipas.services.protocol.measurements import StepMeasurement
from ra2vipas.services.protocol.pod import PODModel


# -- the parts, as the built-ins tune them ------------------------------------------------------------
def radio(circle: CircleGrid, sensors: SensorConfig, pod: PODLookup, cfg: ControllerSettings) -> RFBelief:
    """The RF belief of a policy that hears Rx(dir): the filter when the rig says how Rx(dir)
    responds (and ``cfg.rf_filter``), else the generic lobe (its orientation learned when the
    response is unknown)."""
    lobe_sign = -1 if sensors.rssi_grows_with_alignment is False else 1
    gp = lobe_gp(circle, sensors.steps, pod.rf_noise_db, pod.rf_noise_correlation, lobe_sign, cfg.lobe_width_rad,
                 cfg.residual_length_scale_rad, cfg.residual_std_db)
    if cfg.rf_filter and sensors.rx_dir in ("paper", "db-gain") and sensors.rx_dir_curvature is not None:
        response = RxDirModel(sensors.rx_dir, sensors.rx_dir_curvature, sensors.rx_dir_floor_db)
        rff = PacketBearingFilter(circle, response, noise_db=max(pod.rf_noise_db, 0.1), rf_period_s=sensors.rf_period_s,
                                  walk_std_rad=math.radians(cfg.walk_std_deg), level_memory_s=cfg.level_memory_s,
                                  walk_prior=cfg.tx_walk_prior, tail_dof=cfg.rf_tail_dof or None,
                                  channel_offset_db=cfg.channel_offset_db, rssi_step_db=cfg.rssi_step_db,
                                  receiver_offset_db=cfg.receiver_offset_db, temper_fading=cfg.packet_fading_tempering,
                                  walk_rate_std_rad_s=cfg.packet_walk_rate_std_rad_s, walk_rate_change_rad_s=cfg.packet_walk_rate_change_rad_s,
                                  packet_tail_dof=cfg.packet_tail_dof, batch_standing=cfg.packet_standing_batch,
                                  probe_offsets=cfg.packet_probe_offsets)
        return RFFilterBelief(rff, gp, walk_prior_from_tracks=cfg.walk_prior_from_tracks, walk_prior=cfg.tx_walk_prior,
                              rate_walkers=cfg.packet_rate_walkers)
    recent = RecentLobe(circle, noise_var=gp.noise_var, lobe_width=cfg.lobe_width_rad, lobe_sign=lobe_sign,
                        memory_s=cfg.rf_memory_s, rf_period_s=sensors.rf_period_s)
    return LobeBelief(gp, recent, learn_lobe=sensors.rssi_grows_with_alignment is None, ar1=cfg.ar1_lobe,
                      walk_prior=cfg.tx_walk_prior, walk_penalty=cfg.walk_penalty)


def camera(circle: CircleGrid, sensors: SensorConfig, pod: PODLookup, cfg: ControllerSettings) -> CameraBelief:
    """The vision belief: the bearing tracker and the POD evidence, and the boxes' heights as a
    range cue when the rig's boxes carry them and a propagation model is given (``range_cue``)."""
    ranges = None
    if cfg.height_cue and cfg.range_model is not None and getattr(sensors, "box_heights", False):
        ranges = RangeCue(cfg.range_model, cfg.person_height_m, sensors.box_bearing_noise_rad, cfg.height_walk_memory_s,
                          cfg.height_floor_db, weight=cfg.height_weight)
    return CameraBelief(circle, sensors.fov_half_angle_rad, sensors.box_bearing_noise_rad, sensors.rf_period_s,
                        sensors.frames_per_rf, pod, recent_memory_s=cfg.rf_memory_s, pod_floor_std=cfg.pod_floor_std,
                        null_pod_prior=cfg.null_pod_prior, pod_outlier=cfg.pod_outlier,
                        occlusion_halfwidth_rad=cfg.occlusion_halfwidth_rad, occluded_probability=cfg.occluded_probability,
                        ranges=ranges)


def active_search(circle: CircleGrid, sensors: SensorConfig, cfg: ControllerSettings) -> Acquisition:
    """A warm-up sweep of ceil(pi / half-FoV) pans, then GP-UCB with a probe every
    ``probe_every``-th step."""
    warmup = cfg.warmup_steps if cfg.warmup_steps is not None else math.ceil(math.pi / sensors.fov_half_angle_rad)
    ucb = GPUCB(circle, sensors.frames_per_rf, beta=cfg.beta, use_mass=cfg.mass_in_acquisition)
    probes = ProbeSchedule(circle, ucb, every=cfg.probe_every, start=warmup, lobe_width_rad=cfg.lobe_width_rad,
                           informative=cfg.informative_probe, rf_peaks=cfg.probe_rf_peaks, due_every=cfg.due_probe_every)
    return WarmUpSweep(sensors.initial_pan_rad, warmup, then=probes)


def _parts(circle, sensors, pod, cfg, rf: RFBelief, vision: VisionBelief, acquisition: Acquisition) -> Parts:
    return Parts(iso=IsoLevel(pod.rf_noise_db), rf=rf, vision=vision,
                 fusion=Fusion(circle, rf_weight=cfg.rf_weight, missed_prior_per_rad=cfg.missed_prior_per_rad,
                               answer_window_rad=cfg.answer_window_rad, walker_answer_from_rf=cfg.walker_answer_from_rf),
                 acquisition=acquisition, confidence=Confidence(cfg.confidence_calibration, walk_prior=cfg.tx_walk_prior))


# -- the four compositions ----------------------------------------------------------------------------
def ra2vipas(circle, sensors, pod, cfg) -> Parts:
    """Rx(dir) + Rx(iso) + camera fused, active search."""
    return _parts(circle, sensors, pod, cfg, radio(circle, sensors, pod, cfg), camera(circle, sensors, pod, cfg),
                  active_search(circle, sensors, cfg))


def rapas(circle, sensors, pod, cfg) -> Parts:
    """Rx(dir) only (no camera), active search."""
    return _parts(circle, sensors, pod, cfg, radio(circle, sensors, pod, cfg), VisionBelief(), active_search(circle, sensors, cfg))


def ravipas(circle, sensors, pod, cfg) -> Parts:
    """The camera and Rx(iso) only (no RF belief), active search (without probes: nothing to probe)."""
    return _parts(circle, sensors, pod, cfg, RFBelief(circle), camera(circle, sensors, pod, cfg), active_search(circle, sensors, cfg))


def sweep(circle, sensors, pod, cfg) -> Parts:
    """Both cues fused, an even sweep."""
    return _parts(circle, sensors, pod, cfg, radio(circle, sensors, pod, cfg), camera(circle, sensors, pod, cfg),
                  EvenSweep(sensors.initial_pan_rad, sensors.steps))


COMPOSITIONS = {"ra2vipas": ra2vipas, "rapas": rapas, "ravipas": ravipas, "sweep": sweep}


def compose(algorithm: str, sensors: SensorConfig, pod_model: PODModel, settings: ControllerSettings) -> Parts:
    """The parts of a built-in ``algorithm`` for one episode, with ``settings`` (already tuned:
    ``policy.tuned_settings``)."""
    circle = CircleGrid(sensors.bearing_cells(settings))
    return COMPOSITIONS[algorithm](circle, sensors, PODLookup(pod_model, settings.min_pod_std), settings)


class BuiltinPolicy(Policy):
    """A built-in: the ``Controller`` with this policy's algorithm. Its decisions are the
    controller's ``Decision`` (the contract's fields plus the confidence map's covariates)."""

    algorithm: ClassVar[str] = ""
    reads_rx_dir: ClassVar[bool] = True
    """Whether its decisions use the directional receiver's readings (``rigcheck``: a wrong
    Rx(dir) model shows in these policies' DR)."""

    def __init__(self, context: EpisodeContext, settings: ControllerSettings | None = None) -> None:
        super().__init__(context)
        settings = with_range_model(settings, context)
        n_tags = int(context.scenario.get("n_tags", 1) or 1)
        if n_tags > 1:  # issue 21: one belief per tag over the shared camera tracks, one pan for all
            self.controller = joint_search(self.algorithm, context, n_tags, settings)
        else:
            self.controller = Controller(self.algorithm, context.sensors, context.pod_model, settings)

    def first_pan(self) -> float:
        return self.controller.first_pan()

    def step(self, measurement: StepMeasurement) -> Decision:
        return self.controller.step(measurement)


def joint_search(algorithm: str, context: EpisodeContext, n_tags: int, settings: ControllerSettings | None = None) -> JointSearch:
    """The search for ``n_tags`` tags at once of a built-in ``algorithm`` (``joint.JointSearch``):
    the algorithm's parts once per tag, every tag's vision belief the first tag's (one tracker
    over the people the camera sees), the first tag's acquisition for the one pan, and the
    algorithm's map fitted on joint searches (``{algorithm}-joint`` in the maps file, ``bench
    calibrate --joint``) where one ships; the scenario's ``one_tag_per_person`` and the context's
    ``stop_confidence`` apply."""
    cfg = tuned_settings(algorithm, settings, context.sensors.radio)
    # fitted on joint searches (``bench calibrate --joint``), on BLE advertisements their own (``--joint --adverts``)
    joint_map = shipped_map(f"{algorithm}-joint", context.sensors.radio)
    if joint_map is not None:
        cfg = dataclasses.replace(cfg, confidence_calibration=joint_map)
    tags = [compose(algorithm, context.sensors, context.pod_model, cfg) for _ in range(n_tags)]
    tags = [tags[0]] + [dataclasses.replace(p, vision=tags[0].vision) for p in tags[1:]]
    return JointSearch(context.sensors.initial_pan_rad, tags, rf_period_s=context.sensors.rf_period_s, pan_rule=cfg.tag_pan_rule,
                       one_tag_per_person=bool(context.scenario.get("one_tag_per_person", True)),
                       stop_confidence=context.stop_confidence)


class Ra2ViPAS(BuiltinPolicy):
    name = algorithm = "ra2vipas"
    summary = "Ra2ViPAS: Rx(dir) + Rx(iso) + camera fused, GP-UCB over the pan angle"


class RaPAS(BuiltinPolicy):
    name = algorithm = "rapas"
    summary = "RaPAS: Rx(dir) only"


class RaViPAS(BuiltinPolicy):
    name = algorithm = "ravipas"
    summary = "RaViPAS: camera + Rx(iso) only"
    reads_rx_dir = False


class Sweep(BuiltinPolicy):
    name = algorithm = "sweep"
    summary = "sweep: both cues fused, pans evenly round the circle (non-active)"


class Ra2ViPASSequential(BuiltinPolicy):
    """The one-tag-at-a-time baseline of issue 21 (``joint.SequentialSearch``): Ra²ViPAS searches
    for tag 0 until decided (``stop_confidence``) or its share of the horizon is spent, then for
    tag 1 afresh, and so on. With one tag it is Ra²ViPAS, step for step."""

    name = "ra2vipas-seq"
    algorithm = "ra2vipas"
    summary = "Ra2ViPAS one tag at a time: a fresh single-tag search per tag, each until decided or its share of the horizon"

    def __init__(self, context: EpisodeContext, settings: ControllerSettings | None = None) -> None:
        Policy.__init__(self, context)
        cfg = tuned_settings(self.algorithm, settings, context.sensors.radio)
        sensors = context.sensors
        self.controller = SequentialSearch(sensors.initial_pan_rad, lambda: compose(self.algorithm, sensors, context.pod_model, cfg),
                                           n_tags=int(context.scenario.get("n_tags", 1) or 1), steps=sensors.steps,
                                           rf_period_s=sensors.rf_period_s, stop_confidence=context.stop_confidence)
