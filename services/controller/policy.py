"""The Ra²ViPAS controller and its baselines: measurements in, next pan angle and estimate out.

One ``Controller`` runs one test. Each call to ``step`` takes what the platform sensed at
pan angle s_t (``StepMeasurement``: two RSSI values and the nu frames of anonymous box
bearings) and returns the next pan angle s_{t+1} and the current estimate gamma_hat_t of the
Tx bearing (paper eqs. 25-27). It never sees ranges, identities or the true POD.

A trap for a new policy: under the ``paper`` antenna model (eq. 6) Rx(dir) reads
z_dir = g(d) * rho, a negative dBm path loss scaled by rho <= 1 (1 when aligned), so the reading
*dips* where the antenna points at the Tx (at 2 m: -36 dBm aligned, 0 dBm at 90 deg); "point where
Rx(dir) is strongest" looks away. Score Rx(dir) samples by the rig's response (as below), never
by their raw level; under ``db-gain`` (z_dir = g(d) + 10 log10 rho) the reading peaks when aligned.

What it believes, after t samples:

* **Radio**, when the rig says how Rx(dir) responds (paper eq. 6 or the dB-gain model; the
  descriptor's ``rx_dir``) and the algorithm hears both receivers (``ra2vipas``, ``sweep``):
  ``RFBearingFilter``, a grid Bayes filter over the Tx bearing with a standing and a walking
  motion model, each sample scored by the rig's response with the level read from Rx(iso)
  (the same channel, eq. 5), quasi-differenced for AR(1) fading, Student-t innovations; it
  gives l_RF(gamma) (the posterior of the Tx's bearing *now*), P(the Tx walks) as a Bayes
  factor, and each camera track's trajectory evidence. Otherwise (an ``unknown`` response, or
  ``rapas``, which by definition hears Rx(dir) only) ``LobeGP``: Rx(dir)'s RSSI over the pan
  angle as a GP with an explicit generic lobe basis, whose profile log-likelihood l_RF(gamma)
  says how well "the main lobe is centred at gamma" explains the directional samples (the
  paper's J_RF, eq. 24, without knowing rho), beside a recent-samples lobe for a walking Tx.
* **Vision** (``tracks.BearingTracker`` + the learned POD): every detected target i has an
  empirical POD p~_i = k_i/n_i; the Tx's POD is predicted from the mean iso RSSI,
  p_hat = p_hat_D(z_iso) (Sec. III-A). The detectability score is the likelihood ratio
  l_D(i) = log N(p~_i; p_hat, v_i) - it is largest when the PODs match (the
  paper's -|p_hat - p~| is never positive and its product with y_RF prefers
  misalignment).
* **Fusion**: l(i) = l_RF(gamma_i) + l_D(i). The estimate is the maximiser over the detected
  bearings (the LOS condition, eq. 10, makes the Tx one of them); a bearing where no target
  was ever detected competes with l_RF(gamma) + n_view(gamma) log(1 - p_hat), the
  likelihood of having missed the Tx there.

Where it looks next:

* a warm-up sweep of ceil(pi / half-FoV) evenly spaced pans sees every target once;
* then GP-UCB on the fused objective (eq. 25): a(s) = U_D(s) (J_RF(s) + sqrt(beta) sigma(s)),
  with J_RF the posterior mean of the normalised lobe and U_D the posterior mass of candidate
  targets in view at s (1 where the camera has not looked yet);
* every ``probe_every``-th step, a discrimination probe: with the filter, the pan whose Rx(dir)
  reading the posterior of gamma is least sure of (largest predictive variance: the most
  informative sample, MacKay 1992); with the generic lobe, the pan where the two leading
  hypotheses predict the most different RSSI (Box & Hill 1967), alternating sides. Samples on
  the flanks of the lobe locate it, samples at its flat top do not.

Algorithms (paper Sec. IV-B, plus one): ``ra2vipas`` fuses both; ``rapas`` uses Rx(dir)
only (estimate = lobe centre on the grid); ``ravipas`` uses the camera and Rx(iso) only;
``sweep`` fuses both but pans evenly round the circle, to show what active sensing buys.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy.special import gammaln

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.circle_gp import LobeGP, RecentLobe
from ra2vipas.services.controller.confidence import ConfidenceMap, shipped_maps
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.rf_filter import RFBearingFilter, RxDirModel, logsumexp
from ra2vipas.services.controller.tracks import BearingTracker
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.measurements import StepMeasurement
from ra2vipas.services.protocol.pod import PODModel


class Algorithm(str, Enum):
    ra2vipas = "ra2vipas"
    rapas = "rapas"
    ravipas = "ravipas"
    sweep = "sweep"


ALGORITHMS: tuple[str, ...] = tuple(a.value for a in Algorithm)

RAW_CONFIDENCE_CLIP = 0.01
"""The raw posterior enters the confidence map clipped to [0.01, 0.99]: beyond, it says more about
the model's own assumptions than about the world (a posterior of 1 - 1e-9 is wrong a few percent
of the time in a crowd), and a map linear in an unbounded logit would have to flatten every
confidence to tame those few."""

CROWDING_SCALE_RAD = math.radians(1.0)
"""Scale of the crowding covariate exp(-d / scale) of the confidence map (see Controller._calibrated)."""


@dataclass(frozen=True)
class ControllerSettings:
    """Tuning of the controller. Defaults are what the benchmarks use.

    ``beta`` is the UCB exploration weight (eq. 25); ``probe_every`` = 0 and
    ``warmup_steps`` = 0 give the paper's plain GP-UCB.
    """

    beta: float = 4.0
    grid_points: int = 360
    lobe_width_rad: float = 1.0
    residual_length_scale_rad: float = 0.5
    residual_std_db: float = 3.0
    probe_every: int = 2
    warmup_steps: int | None = None  # None: ceil(pi / fov_half_angle)
    min_pod_std: float = 0.05
    # -- fusion and confidence (fitted on simulated campaigns: services/controller/calibration.py)
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

    def __post_init__(self) -> None:
        if self.confidence_calibration is not None and not isinstance(self.confidence_calibration, ConfidenceMap):
            object.__setattr__(self, "confidence_calibration", ConfidenceMap.from_vector(self.confidence_calibration))
        if self.beta < 0:
            raise ValueError("beta must be >= 0")
        if self.grid_points < 16:
            raise ValueError("grid_points must be >= 16")
        if self.lobe_width_rad <= 0 or self.residual_length_scale_rad <= 0:
            raise ValueError("lobe_width_rad and residual_length_scale_rad must be > 0")
        if self.probe_every < 0:
            raise ValueError("probe_every must be >= 0")


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



@dataclass(frozen=True)
class Decision:
    """The controller's answer to one step."""

    step: int
    next_pan_rad: float
    estimate_rad: float  # gamma_hat_t
    reward: float  # fused objective at the pan the sample was taken at
    probe: bool  # whether next_pan is a discrimination probe
    confidence: float = 0.0  # posterior probability that the target named by estimate_rad is the Tx
    raw_confidence: float = 0.0  # the same under the controller's own model, before calibration
    tx_walks: float = 0.0  # how likely the Tx walks, from Rx(dir) (a walking Tx may have left the answer)
    noise_correlation: float = 0.0  # rho of the RSSI noise, from Rx(iso) (fading: fewer independent samples)
    clutter_density: float = 0.0  # false boxes per frame per radian, from the tracker
    crowding: float = 0.0  # exp(-d / 1 deg), d the bearing gap from the answer to the nearest other track


class PODLookup:
    """p_hat_D(r), its standard deviation and slope, interpolated from a ``PODModel``."""

    def __init__(self, model: PODModel, min_std: float) -> None:
        self.r = np.asarray(model.rssi_grid_dbm, dtype=float)
        self.mean = np.asarray(model.mean, dtype=float)
        self.std = np.maximum(np.asarray(model.std, dtype=float), min_std)
        self.slope = np.gradient(self.mean, self.r)
        self.rf_noise_db = float(model.rf_noise_db)
        self.rf_noise_correlation = float(model.rf_noise_correlation)
        self._rows = list(zip(self.r.tolist(), self.mean.tolist(), self.std.tolist(), self.slope.tolist()))
        self._last: tuple[float, tuple[float, float, float]] | None = None

    def __call__(self, rssi: float) -> tuple[float, float, float]:
        """(mean, std, slope) at ``rssi`` by linear interpolation, clamped at the grid's ends."""
        if self._last is not None and self._last[0] == rssi:
            return self._last[1]
        rows = self._rows
        if rssi <= rows[0][0]:
            out = rows[0][1:]
        elif rssi >= rows[-1][0]:
            out = rows[-1][1:]
        else:
            i = int(np.searchsorted(self.r, rssi)) - 1
            r0, m0, s0, g0 = rows[i]
            r1, m1, s1, g1 = rows[i + 1]
            w = (rssi - r0) / (r1 - r0)
            out = (m0 + w * (m1 - m0), s0 + w * (s1 - s0), g0 + w * (g1 - g0))
        self._last = (rssi, out)
        return out


class Controller:
    """One test's controller. Create it, call ``first_pan()``, then ``step`` for every sample."""

    def __init__(self, algorithm: Algorithm | str, sensors: SensorConfig, pod_model: PODModel,
                 settings: ControllerSettings | None = None) -> None:
        self.algorithm = Algorithm(algorithm)
        self.sensors = sensors
        self.settings = cfg = tuned_settings(self.algorithm, settings)
        self.pod = PODLookup(pod_model, cfg.min_pod_std)
        self.circle = CircleGrid(cfg.grid_points)
        self.grid = self.circle.angles
        self._flat = np.zeros(self.grid.size)
        self.uses_radio = self.algorithm is not Algorithm.ravipas
        self.uses_camera = self.algorithm is not Algorithm.rapas
        sigma = max(self.pod.rf_noise_db, 0.1)
        # the generic lobe models the noise as white (tempered by the AR(1) correlation read from
        # Rx(iso)): with correlated noise it takes the innovation's std, sigma sqrt(1 - phi^2)
        white_sigma = max(self.pod.rf_noise_db * math.sqrt(1.0 - self.pod.rf_noise_correlation**2), 0.1)
        # an unknown Rx(dir) response: the lobe's orientation (a peak, or the paper's dip) is learned
        # from the data, step by step (``_learn_lobe``); a peak until the data say otherwise
        self.learn_lobe = sensors.rssi_grows_with_alignment is None
        lobe_sign = -1 if sensors.rssi_grows_with_alignment is False else 1
        self.rf = LobeGP(
            self.circle, noise_var=white_sigma**2, lobe_width=cfg.lobe_width_rad,
            lobe_sign=lobe_sign,
            residual_length_scale=cfg.residual_length_scale_rad,
            residual_var=cfg.residual_std_db**2, capacity=max(sensors.steps, 1),
        )
        self.recent = RecentLobe(self.circle, noise_var=white_sigma**2, lobe_width=cfg.lobe_width_rad,
                                 lobe_sign=lobe_sign, memory_s=cfg.rf_memory_s,
                                 rf_period_s=sensors.rf_period_s)
        self.rff = None
        if cfg.rf_filter and self.uses_radio and sensors.rx_dir in ("paper", "db-gain") and sensors.rx_dir_curvature is not None:
            self.rff = RFBearingFilter(self.circle, RxDirModel(sensors.rx_dir, sensors.rx_dir_curvature, sensors.rx_dir_floor_db),
                                       noise_db=sigma, rf_period_s=sensors.rf_period_s, walk_std_rad=math.radians(cfg.walk_std_deg),
                                       level_memory_s=cfg.level_memory_s, walk_prior=cfg.tx_walk_prior,
                                       tail_dof=cfg.rf_tail_dof or None)
        self._dir_samples: list[tuple[float, float]] = []
        self._iso_prev: float | None = None
        self._iso_diff_sq = 0.0
        self.tx_walks = 0.0  # probability that the Tx walks, from Rx(dir)
        self.tracks = BearingTracker(sensors.fov_half_angle_rad, sensors.box_bearing_noise_rad, sensors.rf_period_s)
        self.warmup = cfg.warmup_steps if cfg.warmup_steps is not None else math.ceil(math.pi / sensors.fov_half_angle_rad)
        self._view_frames = np.zeros(self.grid.size)  # frames in which each grid bearing was in view
        self._view_recent = np.zeros(self.grid.size)  # the same, discounted over the recent-lobe memory
        self._missed_buffer = np.empty(self.grid.size)
        self._outlier_buffer = np.empty(self.grid.size)
        self._walks = self._rho = self._clutter = self._crowding = 0.0  # the confidence map's covariates, as of the last step
        self._iso_sum = 0.0
        self._iso_sq = 0.0
        self._n = 0
        self._probes = 0

    # -- public -----------------------------------------------------------------------------
    def first_pan(self) -> float:
        """s_0, the pan angle of the first sample."""
        return float(wrap(self.sensors.initial_pan_rad))

    def step(self, m: StepMeasurement) -> Decision:
        """Take the measurement of step t; return s_{t+1} and gamma_hat_t."""
        s = float(m.pan_rad)
        t = int(m.step)
        self._n += 1
        self._iso_sum += m.rf.iso_rssi_dbm
        self._iso_sq += m.rf.iso_rssi_dbm**2
        if self.uses_camera:
            self.tracks.update(s, m.frames, self._view_frames)
        self._view_frames[self.circle.window(s, self.tracks.count_limit)] += len(m.frames)
        self._view_recent *= self.recent.forget
        self._view_recent[self.circle.window(s, self.tracks.count_limit)] += len(m.frames)
        if self._iso_prev is not None:
            self._iso_diff_sq += (m.rf.iso_rssi_dbm - self._iso_prev) ** 2
        self._iso_prev = m.rf.iso_rssi_dbm
        if self.uses_radio and self.rff is not None:
            self._dir_samples.append((s, m.rf.dir_rssi_dbm))  # for the lobe's model check, fitted once asked (lobe_evidence)
            self.rff.add(s, m.rf.iso_rssi_dbm, m.rf.dir_rssi_dbm)
            if self.uses_camera:
                if self.settings.walk_prior_from_tracks:  # the Tx is one of the targets: it walks as often as they do
                    self.rff.walk_prior = min(max(self.tracks.walking_share(self.settings.tx_walk_prior), 0.01), 0.99)
                self.rff.follow(self.tracks.ids.tolist(), *self.tracks.components())
            l_rf = self.rff.log_posterior()
            self.tx_walks = self.rff.p_walk
            lobe = None
        elif self.uses_radio:
            if self.settings.ar1_lobe:  # in steps of 0.05: each change refits the samples so far
                self.rf.set_noise_correlation(round(self._noise_correlation() * 20.0) / 20.0)
            self.rf.add(s, m.rf.dir_rssi_dbm)
            self.recent.add(s, m.rf.dir_rssi_dbm)
            if self.learn_lobe:
                self._learn_lobe()
            if self.uses_camera:
                self.recent.follow(self.tracks.ids.tolist(), self.tracks.bearing.tolist())
            l_static, amplitude, offset = self.rf.lobe_fit()
            best = int(np.argmax(l_static))
            lobe = (best, float(amplitude[best]), float(offset[best]))
            l_rf = self._rf_loglik(l_static, best)
        else:
            l_rf, lobe = self._flat, None
        l_tracks, l_missed = self._beliefs(l_rf)
        estimate, raw_confidence, post = self._answer(l_rf, l_tracks, l_missed)
        reward = self._mass_at(s, post) * self._rf_at(s, lobe)
        next_pan, probe = self._next_pan(t, l_rf, lobe, l_tracks, post)
        return Decision(step=t, next_pan_rad=float(wrap(next_pan)), estimate_rad=float(wrap(estimate)), reward=reward, probe=probe,
                        confidence=round(self._calibrated(raw_confidence, estimate), 6), raw_confidence=float(raw_confidence),
                        tx_walks=self._walks, noise_correlation=self._rho, clutter_density=self._clutter, crowding=self._crowding)

    def _walks_covariate(self) -> float:
        """How likely the Tx walks, as this algorithm can tell: from Rx(dir) when it listens
        (``tx_walks``); for the camera alone, the share of targets the tracker sees walking (the
        Tx is one of them; a walking Tx's POD changes with its range, which the camera-only
        posterior does not model)."""
        if self.uses_radio or not self.uses_camera:
            return self.tx_walks
        return float(self.tracks.walking_share(self.settings.tx_walk_prior))

    def lobe_evidence(self) -> float | None:
        """log-likelihood ratio of the lobe orientation in use against the opposite one, over every
        Rx(dir) sample so far: the best profile likelihood over the lobe centre (``LobeGP.lobe_fit``)
        with the amplitude's sign as used, minus the same with the sign flipped. Strongly negative
        when the directional RSSI contradicts the assumed antenna model (e.g. a dB-gain antenna,
        whose reading peaks at the Tx, modelled as the paper's dip). None without Rx(dir) samples."""
        if self._dir_samples:  # the filter ran the episode: fit the generic lobe to its samples now, once
            for s, z in self._dir_samples:
                self.rf.add(s, z)
            self._dir_samples.clear()
        if not self.uses_radio or self.rf.n_ == 0:
            return None
        used = float(self.rf.lobe_fit()[0].max())
        return used - float(self.rf.lobe_fit(-self.rf.lobe_sign)[0].max())

    @property
    def lobe(self) -> str | None:
        """``peak`` or ``dip``: the lobe orientation in use (None without Rx(dir))."""
        return None if not self.uses_radio else ("peak" if self.rf.lobe_sign > 0 else "dip")

    def _learn_lobe(self) -> None:
        """Unknown Rx(dir) response: use the lobe orientation the samples so far support best (the
        larger maximised profile likelihood of the two signs of A, a generalised likelihood ratio
        with the same number of parameters on both sides). Both lobe fits keep sufficient statistics
        that do not depend on the sign, so switching costs nothing but the next profile."""
        evidence = self.lobe_evidence()
        if evidence is not None and evidence < 0.0:
            self.rf.lobe_sign = -self.rf.lobe_sign
            self.recent.lobe_sign = self.rf.lobe_sign

    # -- beliefs ------------------------------------------------------------------------------
    def _iso_mean_and_std(self) -> tuple[float, float]:
        mean = self._iso_sum / self._n
        var = max(self._iso_sq / self._n - mean * mean, 0.0)
        sigma = math.sqrt(var * self._n / (self._n - 1)) if self._n > 2 else self.pod.rf_noise_db
        return mean, max(sigma, 0.1)

    def _noise_correlation(self) -> float:
        """rho, the lag-1 correlation of the RSSI noise, from Rx(iso): for AR(1) noise,
        Var(z_t - z_t-1) = 2 sigma^2 (1 - rho). A walking Tx's drift reads as correlation, which
        only makes the RF evidence count less."""
        if self._n < 10:
            return 0.0
        _, sigma = self._iso_mean_and_std()
        rho = 1.0 - (self._iso_diff_sq / (self._n - 1)) / (2.0 * sigma * sigma)
        return min(max(rho, 0.0), 0.95)

    def _rf_loglik(self, l_static: np.ndarray, best: int) -> np.ndarray:
        """l_RF over the lobe centre now: a mixture of "the Tx stands" (the lobe fitted to every
        sample) and "the Tx walks" (the lobe fitted to recent samples, ``RecentLobe``), weighted
        by how much better the recent samples fit a lobe elsewhere than where all samples put it
        (a generalised likelihood ratio, less a penalty for the freedom to move). Both are
        scaled by (1 - rho) / (1 + rho), the share of independent information in AR(1) noise,
        and normalised over the circle (so a track's walking score is on the same footing)."""
        cfg = self.settings
        rho = self._noise_correlation()
        self._kappa = kappa = (1.0 - rho) / (1.0 + rho)
        l_recent = self.recent.profile()
        moved = float(l_recent.max() - l_recent[best]) * kappa
        prior = cfg.tx_walk_prior
        logit = math.log(prior / (1.0 - prior)) + moved - cfg.walk_penalty
        self.tx_walks = 1.0 / (1.0 + math.exp(-min(max(logit, -50.0), 50.0)))
        stand = l_static if cfg.ar1_lobe else kappa * l_static  # an AR(1) lobe fit has the correlation in it
        walk = kappa * l_recent
        self._stand_rf = stand - logsumexp(stand)
        self._walk_norm = logsumexp(walk)
        walk = walk - self._walk_norm
        self._log_stand, self._log_walk = math.log(max(1.0 - self.tx_walks, 1e-300)), math.log(max(self.tx_walks, 1e-300))
        return np.logaddexp(self._log_stand + self._stand_rf, self._log_walk + walk)

    def _track_rf(self) -> np.ndarray:
        """l_RF of each confirmed track: standing where it is (the all-sample lobe at its
        bearing), or walking as the track did (the recent lobe along its trajectory), mixed as
        in ``_rf_loglik``."""
        tracks = self.tracks
        stand = self.circle.interp(self._stand_rf, tracks.bearing)
        walk = self._kappa * self.recent.follow_profile(tracks.ids.tolist()) - self._walk_norm
        return np.logaddexp(self._log_stand + stand, self._log_walk + walk)

    def _beliefs(self, l_rf: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Unnormalised log-posteriors of the hypotheses "the Tx is track i" and "the Tx is a
        target the camera never detected, at grid bearing gamma" (camera algorithms only).

        Each is rf_weight * l_RF(bearing) plus the camera's evidence: the Tx's POD is predicted
        from the mean iso RSSI, p_hat = p_hat_D(z_iso) (Sec. III-A), with variance std(p_hat)^2 +
        (slope sigma_z)^2 / t + pod_floor_std^2, as a Beta distribution; a track's k detections in
        n frames are scored by the beta-binomial Bayes factor against an ordinary target's POD
        (``_kernels.pod_evidence``), and an undetected bearing by the probability that the Tx was
        missed in every frame that looked there. Largest when the PODs match (the paper's
        -|p_hat - p~| is never positive).
        """
        if not self.uses_camera:
            return np.empty(0), None
        cfg = self.settings
        z_iso, sigma = self._iso_mean_and_std()
        p_hat, p_std, slope = self.pod(z_iso)
        var = p_std**2 + (slope * sigma) ** 2 / self._n + cfg.pod_floor_std**2
        alpha, beta = _beta_of(p_hat, var)
        a0, b0 = cfg.null_pod_prior
        l_tracks = np.empty(len(self.tracks))
        self._track_where = np.empty(len(self.tracks))
        if len(self.tracks) and self.rff is not None:
            self._tracks_from_filter(l_rf, alpha, beta, a0, b0, l_tracks)
        elif len(self.tracks):
            track_rf = self._track_rf() if self.uses_radio else np.zeros(len(self.tracks))
            means, sds, weights = self.tracks.components()
            _kernels.track_logpost(l_rf, track_rf, self.circle.step, cfg.rf_weight, means, sds, weights,
                                   self.tracks.detections, self.tracks.frames_in_view, alpha, beta, a0, b0, cfg.pod_outlier, l_tracks,
                                   self._track_where)
        # log P(no detection in n frames | POD ~ Beta(alpha, beta)) = log B(alpha, n + beta) - log B(alpha, beta)
        base = gammaln(alpha + beta) - gammaln(beta)
        miss_stand = gammaln(self._view_frames + beta) - gammaln(self._view_frames + alpha + beta) + base
        miss_walk = gammaln(self._view_recent + beta) - gammaln(self._view_recent + alpha + beta) + base
        l_missed = _kernels.missed_logdensity(l_rf, cfg.rf_weight, miss_stand, miss_walk, self.tx_walks,
                                              math.log(cfg.missed_prior_per_rad * self.circle.step), self._miss_outlier(),
                                              self._missed_buffer)
        return l_tracks, l_missed

    def _tracks_from_filter(self, l_rf: np.ndarray, alpha: float, beta: float, a0: float, b0: float, out: np.ndarray) -> None:
        """Log-posteriors of "the Tx is track i" from the RF filter's trajectory evidence (on the
        footing of ``l_rf``, the normalised posterior of the Tx's bearing) and the camera's POD
        evidence; ``_track_where[i]`` is where that Tx is now: the track's bearing, or for a
        walker the camera has lost sight of (its walking model dominant and wide), where Rx(dir)
        puts it within its reach."""
        cfg, rff, circle = self.settings, self.rff, self.circle
        ids = self.tracks.ids.tolist()
        joint = np.logaddexp(rff.log_joint_stand, rff.log_joint_walk)
        out[:] = rff.track_evidence(ids) - logsumexp(joint)
        means, sds, weights = self.tracks.components()
        det, frames = self.tracks.detections, self.tracks.frames_in_view
        for i in range(len(ids)):
            out[i] += _kernels.pod_evidence(det[i], frames[i], alpha, beta, a0, b0, cfg.pod_outlier)
        _kernels.track_where(l_rf, np.ascontiguousarray(means), np.ascontiguousarray(sds), np.ascontiguousarray(weights), circle.step,
                             3.0 * circle.step, self._track_where)

    def _miss_outlier(self) -> np.ndarray:
        """Per grid bearing, the probability that an undetected Tx there was never visible: the
        POD model's ``pod_outlier`` everywhere, ``occluded_probability`` within
        ``occlusion_halfwidth_rad`` of a confirmed track (a body in front of it: in a crowd the
        target the camera cannot see is most often right behind one it sees)."""
        cfg = self.settings
        out = self._outlier_buffer
        out.fill(cfg.pod_outlier)
        if cfg.occluded_probability > cfg.pod_outlier and len(self.tracks):
            circle = self.circle
            h = int(math.floor((cfg.occlusion_halfwidth_rad + 1e-12) / circle.step))
            centres = np.rint((wrap(self.tracks.bearing) + math.pi) / circle.step).astype(np.int64) % circle.size
            out[(centres[:, None] + np.arange(-h, h + 1)[None, :]) % circle.size] = cfg.occluded_probability
        return out

    def _answer(self, l_rf: np.ndarray, l_tracks: np.ndarray, l_missed: np.ndarray | None) -> tuple[float, float, np.ndarray]:
        """gamma_hat_t, the raw posterior probability that the target it names is the Tx, and
        the tracks' posterior probabilities.

        Camera algorithms name the detected target with the largest posterior, unless the
        posterior mass of "missed" within ``answer_window_rad`` of some undetected bearing is
        larger (the LOS condition, eq. 10, makes the Tx one of the detected targets, but a far
        target's POD is close to 0). RaPAS names the lobe centre (eq. 27), with the RF posterior
        mass around it as its confidence.
        """
        cfg = self.settings
        half = max(1, int(round(cfg.answer_window_rad / self.circle.step)))
        if l_missed is None:  # rapas
            if not self._n:
                return self.first_pan(), 0.0, l_tracks
            post_grid = _softmax((1.0 if self.rff is not None else cfg.rf_weight) * l_rf)
            estimate = self._refined_argmax(l_rf)
            return estimate, _arc_mass(post_grid, self.circle.nearest(estimate), half), l_tracks
        top = max(float(l_missed.max()), float(l_tracks.max()) if l_tracks.size else -np.inf)
        w_missed = np.exp(l_missed - top)
        w_tracks = np.exp(l_tracks - top)
        total = float(w_missed.sum() + w_tracks.sum())
        post_missed, post = w_missed / total, w_tracks / total
        j = int(np.argmax(post_missed))
        missed_mass = _arc_mass(post_missed, j, half)
        if post.size and (float(post.max()) >= missed_mass or not self.uses_radio):  # without Rx(dir), "missed" names no bearing
            i = int(np.argmax(post))
            estimate = float(self._track_where[i])
            if self.uses_radio and self._n and cfg.walker_answer_from_rf and self.tx_walks > 0.5:
                # a walker: the tracks are where the camera last saw people, l_RF where the Tx is now
                estimate = self._refined_argmax(l_rf)
            return estimate, float(post[i]) + _arc_mass(post_missed, self.circle.nearest(estimate), half), post
        if not self._n:
            return self.first_pan(), 0.0, post
        return self._refined_argmax(l_missed), missed_mass, post

    def _calibrated(self, raw: float, estimate: float) -> float:
        """The confidence reported: the raw posterior through the algorithm's fitted Platt map
        sigmoid((A + G tx_walks) logit(raw) + B + C tx_walks + D rho + E clutter + F crowding) (raw
        clipped to [0.01, 0.99], ``RAW_CONFIDENCE_CLIP``; G: a walking Tx's posterior is worth less
        per unit of logit), whose covariates,
        all measured by the controller itself, stand for what its model leaves out: a walking Tx
        may have moved off the answer by the time it is scored (tx_walks, ``_walks_covariate``:
        for the camera alone, the share of targets seen walking); correlated fading
        leaves fewer independent RF samples than the AR(1) model credits (rho, from Rx(iso));
        false boxes make tracks that are not people (the tracker's clutter density); another
        target within a degree or so of the answer may be the one the association rule names
        (crowding, exp(-d / 1 deg) for the gap d to the nearest other track). Identity when no
        map is set."""
        self._walks = self._walks_covariate()
        self._rho = self._noise_correlation() if self._n else 0.0
        self._clutter = self.tracks.clutter_density if self.uses_camera else 0.0
        self._crowding = 0.0
        if self.uses_camera and len(self.tracks) >= 2:
            gaps = np.sort(np.abs(wrap(self.tracks.bearing - estimate)))
            self._crowding = math.exp(-float(gaps[1]) / CROWDING_SCALE_RAD)  # gaps[0]: the track named
        if self.settings.confidence_calibration is None:
            return float(min(max(raw, 0.0), 1.0))
        p = min(max(raw, RAW_CONFIDENCE_CLIP), 1.0 - RAW_CONFIDENCE_CLIP)
        logit = math.log(p / (1.0 - p))
        return self.settings.confidence_calibration(logit, self._walks, self._rho, self._clutter, self._crowding)

    def _refined_argmax(self, values: np.ndarray) -> float:
        """Grid argmax refined by a parabola through its two neighbours."""
        j = int(np.argmax(values))
        M = values.size
        a, b, c = values[(j - 1) % M], values[j], values[(j + 1) % M]
        den = a - 2.0 * b + c
        shift = 0.5 * (a - c) / den if den < 0 else 0.0
        return float(self.grid[j] + np.clip(shift, -0.5, 0.5) * (2 * math.pi / M))

    def _rf_at(self, s: float, lobe) -> float:
        """J_RF at one pan angle: the normalised posterior mean of the best lobe fit (with the
        filter: the antenna gain expected under its posterior of gamma)."""
        if self.rff is not None:
            post = np.exp(self.rff.log_posterior())
            return float(self.rff.response.gain(s - self.circle.angles) @ post)
        if lobe is None or lobe[1] == 0.0:
            return 1.0
        j, A, c = lobe
        return (self.rf.mean_at(s, j, A, c) - c) / A

    def _mass_at(self, s: float, post: np.ndarray) -> float:
        """U_D(s) at one pan angle: posterior mass of the tracks in view, 1 where unseen."""
        if not self.uses_camera:
            return 1.0
        mass = _kernels.mass_at(self.tracks.bearing, post, s, self.tracks.count_limit) if post.size else 0.0
        unseen = self._view_frames[self.circle.nearest(s)] < 2 * self.sensors.frames_per_rf
        return max(mass, 1.0) if unseen else mass

    # -- actions ------------------------------------------------------------------------------
    def _next_pan(self, t, l_rf, lobe, l_tracks, post) -> tuple[float, bool]:
        sensors, cfg = self.sensors, self.settings
        if self.algorithm is Algorithm.sweep:
            return sensors.initial_pan_rad + 2.0 * math.pi * (t + 1) / max(sensors.steps, 1), False
        if t + 1 < self.warmup:
            return sensors.initial_pan_rad + 2.0 * math.pi * (t + 1) / self.warmup, False
        if self.uses_radio and cfg.probe_every and (t + 1 - self.warmup) % cfg.probe_every == 0:
            if self.rff is not None and cfg.informative_probe:
                return self.rff.most_informative_pan(), True
            return self._probe(l_rf, l_tracks), True
        # GP-UCB on the fused objective (eq. 25): a(s) = U_D(s) (J_RF(s) + sqrt(beta) sigma(s))
        if self.rff is not None:  # J_RF: the antenna gain expected under the filter's posterior of gamma
            mean, sd = self.rff.predicted_gain()
            A, c = 1.0, 0.0
        elif lobe is not None and self._n:
            j, A, c = lobe
            mean, sd = self.rf.posterior(j, A, c)
            if self.tx_walks > 0.5:  # a walking Tx is where the recent samples put it
                mean = self.recent.mean()
                _, A, c = self.recent.best_
        else:
            A, c = 0.0, 0.0
            mean = sd = self._flat
        bearings = self.tracks.bearing if post.size else np.empty(0)
        arg = _kernels.acquire(mean, c, A, sd, math.sqrt(cfg.beta), bearings, post if post.size else np.empty(0),
                               self._view_frames, 2.0 * sensors.frames_per_rf, self.circle.step, self.tracks.count_limit,
                               self.uses_camera and cfg.mass_in_acquisition)
        return float(self.grid[arg]), False

    def _probe(self, l_rf: np.ndarray, l_tracks: np.ndarray) -> float:
        """The pan where the two leading hypotheses' lobes differ most, on alternating sides."""
        if l_tracks.size >= 2 and not self.settings.probe_rf_peaks and self.tx_walks <= 0.5:
            top = np.argsort(-l_tracks)[:2]
            g1, g2 = self.tracks.bearing[top[0]], self.tracks.bearing[top[1]]
        else:
            order = np.argsort(-l_rf)
            g1 = self.grid[order[0]]
            apart = np.abs(wrap(self.grid[order] - g1)) >= math.radians(3.0)
            g2 = self.grid[order[apart][0]] if apart.any() else g1 + math.radians(3.0)
        self._probes += 1
        arg = _kernels.probe(self.grid, float(g1), float(g2), self.settings.lobe_width_rad, bool(self._probes % 2))
        return float(self.grid[arg])


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


def tuned_settings(algorithm: "Algorithm | str", base: ControllerSettings | None = None) -> ControllerSettings:
    """The settings an algorithm runs with: ``base`` (default ``ControllerSettings()``) with the
    algorithm's own tuning (``TUNING``) on top, whoever builds the controller (in-process
    campaigns and the controller service alike)."""
    name = Algorithm(algorithm).value
    tuning = {**TUNING.get(name, {})}
    confidence_map = shipped_maps().get(name)
    if confidence_map is not None:
        tuning["confidence_calibration"] = confidence_map
    return dataclasses.replace(base or ControllerSettings(), **tuning)


def _beta_of(mean: float, var: float) -> tuple[float, float]:
    """Beta(alpha, beta) with this mean and variance (moment matching; kept proper and not
    sharper than the variance allows)."""
    m = min(max(mean, 1e-3), 1.0 - 1e-3)
    kappa = max(m * (1.0 - m) / max(var, 1e-6) - 1.0, 0.5)
    return m * kappa, (1.0 - m) * kappa


def _arc_mass(weights: np.ndarray, centre: int, half: int) -> float:
    """Sum of grid ``weights`` within ``half`` cells of ``centre`` (periodic)."""
    M = weights.size
    idx = np.arange(centre - half, centre + half + 1) % M
    return float(weights[idx].sum())


def _softmax(log_weights: np.ndarray) -> np.ndarray:
    if not log_weights.size:
        return log_weights
    w = np.exp(log_weights - log_weights.max())
    return w / w.sum()


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
    )
