"""The built-in controllers' settings and the controller of one test: measurements in, next pan
angle and estimate out.

One ``Controller`` runs one test of a built-in algorithm. Each call to ``step`` takes what the
platform sensed at pan angle s_t (``StepMeasurement``: two RSSI values and the nu frames of
anonymous box bearings) and returns the next pan angle s_{t+1} and the current estimate
gamma_hat_t of the Tx bearing (paper eqs. 25-27). It never sees ranges, identities or the true
POD. It is a ``Composition`` (``composed.py``) of parts with one job each, chosen for the
algorithm in ``builtins.py``:

* **Radio** (``rf_belief.py``): when the rig says how Rx(dir) responds (paper eq. 6 or the
  dB-gain model; the descriptor's ``rx_dir``) and the algorithm hears both receivers
  (``ra2vipas``, ``sweep``), ``RFFilterBelief``: a grid Bayes filter over the Tx bearing with a
  standing and a walking motion model, each sample scored by the rig's response with the level
  read from Rx(iso) (the same channel, eq. 5), quasi-differenced for AR(1) fading, Student-t
  innovations. Otherwise (an ``unknown`` response, or ``rapas``, which by definition hears
  Rx(dir) only) ``LobeBelief``: Rx(dir)'s RSSI over the pan angle as a GP with an explicit
  generic lobe basis, whose profile log-likelihood l_RF(gamma) says how well "the main lobe is
  centred at gamma" explains the directional samples (the paper's J_RF, eq. 24, without knowing
  rho), beside a recent-samples lobe for a walking Tx.
* **Vision** (``vision_belief.py``): the bearing tracker and the POD evidence, the likelihood
  of each target's detections under the POD the Tx's RSSI predicts, p_hat = p_hat_D(z_iso)
  (Sec. III-A).
* **Fusion** (``fusion.py``): l(i) = l_RF(gamma_i) + l_D(i) over the detected targets, against
  "the Tx is a target the camera never detected".
* **Acquisition** (``acquisition.py``): a warm-up sweep, then GP-UCB on the fused objective
  (eq. 25) with a discrimination probe every ``probe_every``-th step; or an even sweep.
* **Confidence** (``confidence.py``): the raw posterior through the algorithm's fitted map.

A trap for a new policy: under the ``paper`` antenna model (eq. 6) Rx(dir) reads
z_dir = g(d) * rho, a negative dBm path loss scaled by rho <= 1 (1 when aligned), so the reading
*dips* where the antenna points at the Tx (at 2 m: -36 dBm aligned, 0 dBm at 90 deg); "point where
Rx(dir) is strongest" looks away. Score Rx(dir) samples by the rig's response (as the parts do),
never by their raw level; under ``db-gain`` (z_dir = g(d) + 10 log10 rho) the reading peaks when
aligned.

Algorithms (paper Sec. IV-B, plus one): ``ra2vipas`` fuses both; ``rapas`` uses Rx(dir)
only (estimate = lobe centre on the grid); ``ravipas`` uses the camera and Rx(iso) only;
``sweep`` fuses both but pans evenly round the circle, to show what active sensing buys.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

from ra2vipas.services.controller.composed import Composition, Decision
from ra2vipas.services.controller.confidence import CROWDING_SCALE_RAD, RAW_CONFIDENCE_CLIP, ConfidenceMap, shipped_map
from ra2vipas.services.controller.range_cue import RangeModel
from ra2vipas.services.controller.vision_belief import PODLookup
from ra2vipas.services.protocol.pod import PODModel

__all__ = ["ALGORITHMS", "CROWDING_SCALE_RAD", "RAW_CONFIDENCE_CLIP", "Algorithm", "Controller", "ControllerSettings", "Decision",
           "PODLookup", "SensorConfig", "TUNING", "sensor_config_from_descriptor", "sensor_config_from_scenario", "tuned_settings",
           "with_range_model"]


class Algorithm(str, Enum):
    ra2vipas = "ra2vipas"
    rapas = "rapas"
    ravipas = "ravipas"
    sweep = "sweep"


ALGORITHMS: tuple[str, ...] = tuple(a.value for a in Algorithm)


@dataclass(frozen=True)
class ControllerSettings:
    """Tuning of the controller. Defaults are what the benchmarks use; ``builtins.py`` hands each
    field to the part it tunes (``radio``, ``camera``, ``active_search``, ``Fusion``, ``Confidence``).

    ``beta`` is the UCB exploration weight (eq. 25); ``probe_every`` = 0 and
    ``warmup_steps`` = 0 give the paper's plain GP-UCB.
    """

    beta: float = 4.0
    grid_points: int = 360  # cells of the bearing grid (1 degree) for a rig of RSSI pairs
    # ... and for a rig of BLE advertisements (SensorConfig.radio "adverts"; 1/3 degree): a db-gain lobe's flank near its
    # floor moves a packet's expected RSSI by 1-5 dB per degree, so a 1-degree grid (and the interpolation of a track's
    # evidence between its cells) loses what the packets say about two people 0.2-1 degree apart (docs/radio.md, measured)
    packet_grid_points: int = 1080
    lobe_width_rad: float = 1.0
    residual_length_scale_rad: float = 0.5
    residual_std_db: float = 3.0
    probe_every: int = 2
    warmup_steps: int | None = None  # None: ceil(pi / fov_half_angle)
    min_pod_std: float = 0.05
    # -- fusion and confidence (fitted on simulated campaigns: services/orchestrator/calibration.py)
    rf_weight: float = 1.0  # tempering of the RF profile log-likelihood l_RF
    pod_floor_std: float = 0.08  # misspecification of the POD model, added to its predictive std
    null_pod_prior: tuple[float, float] = (1.0, 1.0)  # Beta prior of a non-Tx target's POD
    pod_outlier: float = 0.2  # probability that the POD model says nothing about the Tx (hidden, shadowed, misfit)
    missed_prior_per_rad: float = 5.0  # prior density of "the Tx is a target the camera never detected"
    occlusion_halfwidth_rad: float = math.radians(5.0)  # an undetected target this close to a track's bearing may stand behind it
    occluded_probability: float = 0.9  # probability that such a target is hidden (its misses say nothing)
    answer_window_rad: float = math.radians(2.0)  # posterior mass within this of the answer is its confidence
    # the Platt map of the raw confidence (named coefficients, confidence.py; the built-ins' are
    # shipped in data/confidence_maps.json); a coefficient vector in ConfidenceMap.FIELDS order is accepted
    confidence_calibration: ConfidenceMap | None = None
    # -- a Tx that walks
    rf_memory_s: float = 0.8  # memory of the recent-lobe fit (a walker crosses 10-30 degrees a second)
    ar1_lobe: bool = True  # the standing lobe's noise AR(1) (rho from Rx(iso)) rather than white with its evidence scaled
    tx_walk_prior: float = 0.3  # prior probability that the Tx walks
    walk_penalty: float = 2.0  # nats the recent lobe must gain to count as motion
    probe_rf_peaks: bool = False  # probe between the two best RF peaks, not the two best tracks (always when the Tx walks)
    walker_answer_from_rf: bool = True  # a Tx that walks is named where l_RF peaks (its track may lag or be lost)
    mass_in_acquisition: bool = True
    # -- the Rx(dir) response known from the rig: a grid Bayes filter over the Tx bearing (rf_filter.py)
    rf_filter: bool = True
    informative_probe: bool = True  # probes at the pan of largest predictive variance of Rx(dir) (rf_filter only)
    walk_prior_from_tracks: bool = True  # P(the Tx walks) a priori = the share of tracks seen walking (rf_filter only)
    walk_std_deg: float = 2.0  # a walking Tx's bearing change per step
    level_memory_s: float = 0.5  # memory of a walking Tx's level (range and shadowing change)
    rf_tail_dof: float = 2.0  # Student-t degrees of freedom of an RF sample's innovation (0: Gaussian)
    # the same for BLE packets once the walking model has its rate (packet_rate_walkers seen; before: rf_tail_dof) (rf_filter.
    # PacketBearingFilter; negative: rf_tail_dof): Gaussian, heavy tails bound what one packet says and a walker's estimate
    # then lags it between sparse packets (docs/radio.md, measured)
    packet_tail_dof: float = 0.0
    # -- BLE advertisements (protocol 1.3; rf_filter.PacketBearingFilter): the pair path ignores these
    channel_offset_db: float = 3.0  # prior spread of a receiver's per-advertising-channel offset (the CC0 dataset's, docs/radio.md)
    rssi_step_db: float = 1.0  # the receivers' RSSI step (whole dBm): its rounding adds step^2 / 12 to a packet's variance
    due_probe_every: int = 1  # probe in every n-th step an advertisement is due (the beacon's interval, rf_belief.PacketClock)
    packet_fading_tempering: bool = False  # temper each packet's term by its AR(1) correlation with the previous (rf_filter)
    # the standing model's evidence: all of Rx(dir)'s packets in one batch at the current level, their spread unknown
    # (rf_filter.PacketBearingFilter): ble-recorded seeds 1-5 DR 0.945 / 0.955 / 0.930 / 0.955 / 0.920 with it, 0.915 /
    # 0.910 / 0.900 / 0.915 / 0.880 with each packet scored once against the level as it stood then (docs/radio.md)
    packet_standing_batch: bool = True
    # probes aim where the next Rx(dir) packet's mean varies most over the bearing's posterior with Rx(dir)'s offset as its
    # packets so far estimate it (rf_filter.PacketBearingFilter.most_informative_pan): ble-recorded seeds 1-5 DR 0.975 /
    # 0.965 / 0.980 / 0.985 / 0.945 with it, 0.945 / 0.955 / 0.930 / 0.955 / 0.920 with the offset taken as 0 (docs/radio.md)
    packet_probe_offsets: bool = True
    # a walking Tx's bearing has a rate, prior N(0, std^2), changing by change per sqrt(s) (rf_filter.PacketBearingFilter, packets
    # only), once the camera has seen packet_rate_walkers people walk (0: never): sparse packets leave a random walk behind a walker
    packet_walk_rate_std_rad_s: float = 0.5
    packet_walk_rate_change_rad_s: float = 0.2
    packet_rate_walkers: int = 5
    receiver_offset_db: float = 8.0  # prior spread of Rx(dir)'s offset when packets carry no channel (two receivers' difference)
    # -- several tags (issue 21; joint.JointSearch): how the one pan serves the undecided tags: entropy | neediest
    tag_pan_rule: str = "entropy"
    # -- box heights as a range cue (protocol 1.3 boxes with heights; range_cue.py): used only when the rig says its boxes
    # carry heights (SensorConfig.box_heights) and a public propagation model is given (range_model: the campaign's
    # configured path loss and shadowing, range_cue.RangeModel.from_scenario; the built-ins take it from the episode's scenario)
    height_cue: bool = False  # off by default: measured not to help on dynamic with heights (docs/radio.md); heights_policy.py turns it on
    range_model: "RangeModel | None" = None
    person_height_m: tuple[float, float] = (1.5, 1.9)  # public prior of a person's height (adults standing), uniform [m]
    height_weight: float = 1.0  # tempering of the range cue's log Bayes factor
    height_floor_db: float = 2.0  # misfit of the propagation model (in quadrature with its shadowing)
    height_walk_memory_s: float = 1.0  # memory of a walking track's boxes and of the level they are scored against

    def __post_init__(self) -> None:
        if self.confidence_calibration is not None and not isinstance(self.confidence_calibration, ConfidenceMap):
            object.__setattr__(self, "confidence_calibration", ConfidenceMap.from_vector(self.confidence_calibration))
        if self.beta < 0:
            raise ValueError("beta must be >= 0")
        if self.grid_points < 16 or self.packet_grid_points < 16:
            raise ValueError("grid_points and packet_grid_points must be >= 16")
        if self.lobe_width_rad <= 0 or self.residual_length_scale_rad <= 0:
            raise ValueError("lobe_width_rad and residual_length_scale_rad must be > 0")
        if self.probe_every < 0:
            raise ValueError("probe_every must be >= 0")
        if self.tag_pan_rule not in ("entropy", "neediest"):
            raise ValueError("tag_pan_rule must be entropy or neediest")


@dataclass(frozen=True)
class SensorConfig:
    """What the controller knows about its own platform (hardware description, no world truth)."""

    steps: int
    frames_per_rf: int
    fov_half_angle_rad: float
    box_bearing_noise_rad: float
    initial_pan_rad: float
    rssi_grows_with_alignment: bool | None  # True: stronger reads higher (db-gain); False: paper's |g| rho; None: learn it
    rf_period_s: float = 0.1  # T_RF, time between control steps
    source: str = "scenario"  # where this description came from: "descriptor" (the rig's) or "scenario" (an undescribed rig)
    rx_dir: str = "paper"  # the Rx(dir) response assumed: paper | db-gain | unknown
    rx_dir_curvature: float | None = None  # a in rho = 1 - a Delta^2 (None: not known)
    rx_dir_floor_db: float = -20.0  # db-gain: the lowest gain
    box_heights: bool = False  # the detector's boxes carry their angular heights (protocol 1.3; a range cue)
    radio: str = "pair"  # what the rig's Measurements carry: pair (one RSSI pair a step) | adverts (1.3: BLE advertisements)

    def bearing_cells(self, settings: ControllerSettings) -> int:
        """Cells of the bearing grid a controller of this platform uses: ``settings.packet_grid_points``
        for a rig of advertisements, ``settings.grid_points`` for one of pairs."""
        return settings.packet_grid_points if self.radio == "adverts" else settings.grid_points


class Controller(Composition):
    """One test's controller of a built-in algorithm: the composition of parts ``builtins.compose``
    makes for it, with the algorithm's tuning (``tuned_settings``). Create it, call
    ``first_pan()``, then ``step`` for every sample.

    Parameters
    ----------
    algorithm : Algorithm or str
        ``ra2vipas``, ``rapas``, ``ravipas`` or ``sweep``.
    sensors : SensorConfig
        The platform's public description.
    pod_model : PODModel
        p_hat_D(r), learned by the learner.
    settings : ControllerSettings, optional
        The base settings (default ``ControllerSettings()``); the algorithm's ``TUNING`` goes on top.
    """

    def __init__(self, algorithm: Algorithm | str, sensors: SensorConfig, pod_model: PODModel,
                 settings: ControllerSettings | None = None) -> None:
        from ra2vipas.services.controller.builtins import compose

        self.algorithm = Algorithm(algorithm)
        self.sensors = sensors
        self.settings = tuned_settings(self.algorithm, settings, sensors.radio)
        super().__init__(sensors.initial_pan_rad, compose(self.algorithm.value, sensors, pod_model, self.settings),
                         rf_period_s=sensors.rf_period_s)


TUNING: dict[str, dict] = {
    # the confidence maps are not here: they are data (data/confidence_maps.json, written by
    # `ra2vipas bench calibrate --write`; confidence.py), added by tuned_settings.
    # RaPAS hears Rx(dir) only: no level from Rx(iso), so the generic lobe rather than the filter;
    # it names the peak of l_RF: with a walking Tx the white-noise fit, flattened by
    # (1 - rho) / (1 + rho), lets the recent lobe win more often than the sharper AR(1) fit
    "rapas": {"rf_weight": 2.0, "ar1_lobe": False, "rf_filter": False},
    # with the camera as its only cue, RaViPAS does best trusting the POD model fully
    "ravipas": {"pod_floor_std": 0.0, "pod_outlier": 0.0},
}
"""Per-algorithm departures from the ``ControllerSettings`` defaults, fitted like them on simulated
campaigns (each baseline gets its own best settings, so comparisons are fair)."""


def tuned_settings(algorithm: "Algorithm | str", base: ControllerSettings | None = None, radio: str = "pair") -> ControllerSettings:
    """The settings an algorithm runs with: ``base`` (default ``ControllerSettings()``) with the
    algorithm's own tuning (``TUNING``) on top, whoever builds the controller (in-process
    campaigns and the controller service alike); its confidence map the one fitted for the rig's
    ``radio`` (``SensorConfig.radio``: BLE advertisements have their own, ``ADVERTS_MAP_SUFFIX``)."""
    name = Algorithm(algorithm).value
    tuning = {**TUNING.get(name, {})}
    confidence_map = shipped_map(name, radio)
    if confidence_map is not None:
        tuning["confidence_calibration"] = confidence_map
    return dataclasses.replace(base or ControllerSettings(), **tuning)


def with_range_model(settings: ControllerSettings | None, context) -> ControllerSettings | None:
    """``settings`` with the episode's public propagation model (``range_cue.RangeModel``: the
    path loss and shadowing its scenario configures) when the rig's boxes carry heights, so the
    built-ins can score box ranges against the RSSI's; unchanged otherwise (or if one is set)."""
    sensors, scenario = getattr(context, "sensors", None), getattr(context, "scenario", None)
    if not getattr(sensors, "box_heights", False) or not scenario:
        return settings
    base = settings or ControllerSettings()
    if base.range_model is not None or not base.height_cue:
        return settings
    return dataclasses.replace(base, range_model=RangeModel.from_scenario(scenario))


def sensor_config_from_scenario(scenario) -> SensorConfig:
    """The hardware description a simulated platform gives its controller.

    Only properties of the platform itself: timing, camera geometry and detector accuracy,
    the receiver's reporting convention. Nothing about targets or the Tx.
    """
    from ra2vipas.services.protocol.scenario import AntennaModel

    return SensorConfig(
        steps=scenario.steps,
        frames_per_rf=scenario.frames_per_rf,
        fov_half_angle_rad=scenario.fov_half_angle_rad,
        box_bearing_noise_rad=scenario.box_bearing_noise_rad,
        initial_pan_rad=scenario.initial_pan_rad,
        rssi_grows_with_alignment=scenario.antenna_model is not AntennaModel.paper,
        rf_period_s=scenario.rf_period_s,
        source="scenario",
        rx_dir=scenario.antenna_model.value,
        rx_dir_curvature=scenario.antenna_curvature,
        rx_dir_floor_db=scenario.antenna_floor_db,
        box_heights=bool(scenario.box_heights),
        radio=_radio_of(scenario),
    )


def sensor_config_from_descriptor(descriptor, scenario) -> SensorConfig:
    """The controller's model of its platform from the rig's own ``RigDescriptor``.

    The hardware (nu, T_RF, the half field of view, the detector's bearing noise, the Rx(dir)
    response) is the rig's: the campaign's world parameters are never read for it. A field the
    rig leaves ``null`` is *configurable*: the rig (a simulator) runs with the campaign's value,
    so that value is its hardware. Only the test's length (``steps``) and its initial pan come
    from the campaign, which decides them. An ``unknown`` Rx(dir) response leaves the lobe's
    orientation to be learned from the data (``rssi_grows_with_alignment=None``).
    """
    from ra2vipas.services.protocol.scenario import AntennaModel

    def value(name: str):
        own = getattr(descriptor, name)
        return getattr(scenario, name) if own is None else own

    rx = descriptor.rx_dir
    rx_dir = scenario.antenna_model.value if rx is None else rx.model
    return SensorConfig(
        steps=scenario.steps,
        frames_per_rf=int(value("frames_per_rf")),
        fov_half_angle_rad=math.radians(value("fov_half_angle_deg")),
        box_bearing_noise_rad=math.radians(value("box_bearing_noise_deg")),
        initial_pan_rad=scenario.initial_pan_rad,
        rssi_grows_with_alignment=None if rx_dir == "unknown" else rx_dir != AntennaModel.paper.value,
        rf_period_s=float(value("rf_period_s")),
        source="descriptor",
        rx_dir=rx_dir,
        rx_dir_curvature=None if rx_dir == "unknown" else float(scenario.antenna_curvature if rx is None or rx.curvature is None
                                                                 else rx.curvature),
        rx_dir_floor_db=float(scenario.antenna_floor_db if rx is None or rx.floor_db is None else rx.floor_db),
        box_heights=bool(scenario.box_heights if descriptor.box_heights is None else descriptor.box_heights),
        radio=descriptor.radio or _radio_of(scenario),
    )


def _radio_of(scenario) -> str:
    """``SensorConfig.radio`` of a simulator that runs ``scenario``: a recorded channel delivers advertisements too."""
    from ra2vipas.services.protocol.scenario import RadioMode

    return "pair" if scenario.radio is RadioMode.pair else "adverts"
