"""The Ra²ViPAS controller and its baselines: measurements in, next pan angle and estimate out.

One ``Controller`` runs one test. Each call to ``step`` takes what the platform sensed at
pan angle s_t (``StepMeasurement``: two RSSI values and the nu frames of anonymous box
bearings) and returns the next pan angle s_{t+1} and the current estimate gamma_hat_t of the
Tx bearing (paper eqs. 25-27). It never sees ranges, identities or the true POD.

What it believes, after t samples:

* **Radio** (``LobeGP``): Rx(dir)'s RSSI over the pan angle is a GP with an explicit lobe
  basis; its profile log-likelihood l_RF(gamma) says how well "the main lobe is centred at
  gamma" explains the directional samples (the paper's J_RF, eq. 24, without knowing rho).
* **Vision** (``DetectionTracker`` + the learned POD): every detected target i has an
  empirical POD p~_i = k_i/n_i; the Tx's POD is predicted from the mean iso RSSI,
  p_hat = p_hat_D(z_iso) (Sec. III-A). The detectability score is the likelihood ratio
  l_D(i) = log N(p~_i; p_hat, v_i) - it is largest when the PODs match (MISSION defect 1:
  the paper's -|p_hat - p~| is never positive and its product with y_RF prefers
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
* every ``probe_every``-th step, a discrimination probe: the pan where the two leading
  hypotheses predict the most different RSSI (Box & Hill 1967), alternating sides, because
  samples on the flanks of the lobe locate it, samples at its flat top do not.

Algorithms (paper Sec. IV-B, plus one): ``ra2vipas`` fuses both; ``rapas`` uses Rx(dir)
only (estimate = lobe centre on the grid); ``ravipas`` uses the camera and Rx(iso) only;
``sweep`` fuses both but pans evenly round the circle, to show what active sensing buys.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.circle_gp import LobeGP
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.tracks import DetectionTracker, wrap
from ra2vipas.services.protocol.measurements import StepMeasurement
from ra2vipas.services.protocol.pod import PODModel


class Algorithm(str, Enum):
    ra2vipas = "ra2vipas"
    rapas = "rapas"
    ravipas = "ravipas"
    sweep = "sweep"


ALGORITHMS: tuple[str, ...] = tuple(a.value for a in Algorithm)


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

    def __post_init__(self) -> None:
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
    rssi_grows_with_alignment: bool  # True: stronger reads higher (db-gain); False: paper's |g| rho


@dataclass(frozen=True)
class Decision:
    """The controller's answer to one step."""

    step: int
    next_pan_rad: float
    estimate_rad: float  # gamma_hat_t
    reward: float  # fused objective at the pan the sample was taken at
    probe: bool  # whether next_pan is a discrimination probe


class PODLookup:
    """p_hat_D(r), its standard deviation and slope, interpolated from a ``PODModel``."""

    def __init__(self, model: PODModel, min_std: float) -> None:
        self.r = np.asarray(model.rssi_grid_dbm, dtype=float)
        self.mean = np.asarray(model.mean, dtype=float)
        self.std = np.maximum(np.asarray(model.std, dtype=float), min_std)
        self.slope = np.gradient(self.mean, self.r)
        self.rf_noise_db = float(model.rf_noise_db)
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
        self.settings = cfg = settings or ControllerSettings()
        self.pod = PODLookup(pod_model, cfg.min_pod_std)
        self.circle = CircleGrid(cfg.grid_points)
        self.grid = self.circle.angles
        self._flat = np.zeros(self.grid.size)
        self.uses_radio = self.algorithm is not Algorithm.ravipas
        self.uses_camera = self.algorithm is not Algorithm.rapas
        sigma = max(self.pod.rf_noise_db, 0.1)
        self.rf = LobeGP(
            self.circle, noise_var=sigma**2, lobe_width=cfg.lobe_width_rad,
            lobe_sign=1 if sensors.rssi_grows_with_alignment else -1,
            residual_length_scale=cfg.residual_length_scale_rad,
            residual_var=cfg.residual_std_db**2, capacity=max(sensors.steps, 1),
        )
        self.tracks = DetectionTracker(sensors.fov_half_angle_rad, sensors.box_bearing_noise_rad)
        self.warmup = cfg.warmup_steps if cfg.warmup_steps is not None else math.ceil(math.pi / sensors.fov_half_angle_rad)
        self._view_frames = np.zeros(self.grid.size)  # frames in which each grid bearing was in view
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
        self._view_frames[self.circle.window(s, self.tracks.count_limit)] += len(m.frames)
        if self.uses_camera:
            self.tracks.update(s, m.frames)
        if self.uses_radio:
            self.rf.add(s, m.rf.dir_rssi_dbm)
            l_rf, amplitude, offset = self.rf.lobe_fit()
            best = int(np.argmax(l_rf))
            lobe = (best, float(amplitude[best]), float(offset[best]))
        else:
            l_rf, lobe = self._flat, None
        l_tracks = self._track_loglik(l_rf)
        post = _softmax(l_tracks)
        estimate = self._estimate(l_rf, l_tracks)
        reward = self._mass_at(s, post) * self._rf_at(s, lobe)
        next_pan, probe = self._next_pan(t, l_rf, lobe, l_tracks, post)
        return Decision(step=t, next_pan_rad=float(wrap(next_pan)), estimate_rad=float(wrap(estimate)), reward=reward, probe=probe)

    # -- beliefs ------------------------------------------------------------------------------
    def _iso_mean_and_std(self) -> tuple[float, float]:
        mean = self._iso_sum / self._n
        var = max(self._iso_sq / self._n - mean * mean, 0.0)
        sigma = math.sqrt(var * self._n / (self._n - 1)) if self._n > 2 else self.pod.rf_noise_db
        return mean, max(sigma, 0.1)

    def _track_loglik(self, l_rf: np.ndarray) -> np.ndarray:
        """l(i) = l_RF(gamma_i) + l_D(i) for every track (camera algorithms only), with
        l_D(i) = log N(p~_i; p_hat, v_i) and v_i = std(p_hat)^2 + (slope sigma)^2 / t + p~(1-p~)/n_i."""
        if not self.uses_camera or not len(self.tracks):
            return np.empty(0)
        z_iso, sigma = self._iso_mean_and_std()
        p_hat, p_std, slope = self.pod(z_iso)
        var_model = p_std**2 + (slope * sigma) ** 2 / self._n
        out = np.empty(len(self.tracks))
        return _kernels.track_loglik(l_rf, self.circle.step, self.tracks.bearing, self.tracks.detections,
                                     self.tracks.frames_in_view, p_hat, var_model, out)

    def _estimate(self, l_rf: np.ndarray, l_tracks: np.ndarray) -> float:
        """gamma_hat_t: the detected bearing with the largest fused log-posterior, unless the
        likelihood of having missed the Tx at some undetected bearing is larger."""
        if l_tracks.size:
            best_track = int(np.argmax(l_tracks))
            if not self.uses_radio:
                return float(self.tracks.bearing[best_track])
            z_iso, _ = self._iso_mean_and_std()
            p_hat = self.pod(z_iso)[0]
            best_missed, _ = _kernels.best_missed(l_rf, self._view_frames, math.log(max(1.0 - p_hat, 1e-3)))
            if l_tracks[best_track] >= best_missed:
                return float(self.tracks.bearing[best_track])
            return self._refined_argmax(l_rf + self._view_frames * math.log(max(1.0 - p_hat, 1e-3)))
        if self.uses_radio and self._n:
            return self._refined_argmax(l_rf)
        return self.first_pan()

    def _refined_argmax(self, values: np.ndarray) -> float:
        """Grid argmax refined by a parabola through its two neighbours."""
        j = int(np.argmax(values))
        M = values.size
        a, b, c = values[(j - 1) % M], values[j], values[(j + 1) % M]
        den = a - 2.0 * b + c
        shift = 0.5 * (a - c) / den if den < 0 else 0.0
        return float(self.grid[j] + np.clip(shift, -0.5, 0.5) * (2 * math.pi / M))

    def _rf_at(self, s: float, lobe) -> float:
        """J_RF at one pan angle: the normalised posterior mean of the best lobe fit."""
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
            return self._probe(l_rf, l_tracks), True
        # GP-UCB on the fused objective (eq. 25): a(s) = U_D(s) (J_RF(s) + sqrt(beta) sigma(s))
        if lobe is not None and self._n:
            j, A, c = lobe
            mean, sd = self.rf.posterior(j, A, c)
        else:
            A, c = 0.0, 0.0
            mean = sd = self._flat
        bearings = self.tracks.bearing if post.size else np.empty(0)
        arg = _kernels.acquire(mean, c, A, sd, math.sqrt(cfg.beta), bearings, post if post.size else np.empty(0),
                               self._view_frames, 2.0 * sensors.frames_per_rf, self.circle.step, self.tracks.count_limit,
                               self.uses_camera)
        return float(self.grid[arg]), False

    def _probe(self, l_rf: np.ndarray, l_tracks: np.ndarray) -> float:
        """The pan where the two leading hypotheses' lobes differ most, on alternating sides."""
        if l_tracks.size >= 2:
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
    )
