"""What a policy believes from the camera: the vision belief parts (issue 19).

``CameraBelief`` follows the targets the detector's anonymous boxes show (``BearingTracker``),
keeps where the camera has looked (frames per grid bearing), and holds the POD evidence: every
detected target i has an empirical POD p~_i = k_i/n_i (eq. 9); the Tx's POD is predicted from
the mean Rx(iso) RSSI, p_hat = p_hat_D(z_iso) (Sec. III-A), as a Beta distribution; a track's
detections are scored by the beta-binomial Bayes factor against an ordinary target's POD, and
a bearing where nothing was detected by the probability that the Tx was missed there. These
are largest when the PODs match (the paper's -|p_hat - p~| is never positive, and its product
with y_RF prefers misalignment).

``VisionBelief`` itself is "no camera" (RaPAS): no tracks, every pan equally worth a look.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from scipy.special import gammaln

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.range_cue import RangeCue
from ra2vipas.services.controller.rf_belief import IsoLevel
from ra2vipas.services.controller.tracks import BearingTracker
from ra2vipas.services.protocol.pod import PODModel


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
        self._r = self.r.tolist()
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
            i = bisect.bisect_left(self._r, rssi) - 1  # np.searchsorted(self.r, rssi) - 1, on a list (no numpy call)
            r0, m0, s0, g0 = rows[i]
            r1, m1, s1, g1 = rows[i + 1]
            w = (rssi - r0) / (r1 - r0)
            out = (m0 + w * (m1 - m0), s0 + w * (s1 - s0), g0 + w * (g1 - g0))
        self._last = (rssi, out)
        return out


def _runs_of(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the value, the length) of each run of equal neighbouring values of ``frames``."""
    starts, lengths = np.empty(frames.size, dtype=np.int64), np.empty(frames.size, dtype=np.int64)
    r = _kernels.runs(frames, starts, lengths)
    return frames[starts[:r]], lengths[:r]


def _repeated_miss(values: np.ndarray, lengths: np.ndarray, alpha: float, beta: float, base: float) -> np.ndarray:
    """gammaln(v + beta) - gammaln(v + alpha + beta) + base for each run's value v, repeated over its run."""
    return np.repeat(gammaln(values + beta) - gammaln(values + alpha + beta) + base, lengths)


def _per_run(frames: np.ndarray, alpha: float, beta: float, base: float) -> np.ndarray:
    """gammaln(frames + beta) - gammaln(frames + alpha + beta) + base, evaluated once per run of
    equal neighbouring values (cells the camera saw in the same frames: a few dozen runs of 360
    cells) and repeated over the run: the same doubles, a tenth of the gammaln calls."""
    return _repeated_miss(*_runs_of(frames), alpha, beta, base)


def beta_of(mean: float, var: float) -> tuple[float, float]:
    """Beta(alpha, beta) with this mean and variance (moment matching; kept proper and not
    sharper than the variance allows)."""
    m = min(max(mean, 1e-3), 1.0 - 1e-3)
    kappa = max(m * (1.0 - m) / max(var, 1e-6) - 1.0, 0.5)
    return m * kappa, (1.0 - m) * kappa


class VisionBelief:
    """The vision belief interface, and its "no camera" implementation.

    Attributes
    ----------
    sees : bool
        Whether it uses the camera at all.
    tracks : BearingTracker or None
        The confirmed targets in bearing.
    """

    sees = False
    tracks: BearingTracker | None = None

    def update(self, pan_rad: float, frames) -> None:
        """Take step t's camera frames (``CameraFrame``: anonymous box bearings), taken at pan
        ``pan_rad``."""

    def range_loglik(self, iso: IsoLevel) -> np.ndarray | None:
        """Per track, the range cue's log Bayes factor (``range_cue.RangeCue``: the range its
        boxes' heights give against the range Rx(iso)'s level gives); None when boxes carry no
        heights or the cue is off."""
        return None

    def mass_at(self, pan_rad: float, post: np.ndarray) -> float:
        """U_D(s): the posterior mass of the tracks in view at s, 1 where the camera has not looked
        yet (1 everywhere without a camera)."""
        return 1.0

    def clutter_density(self) -> float:
        """False boxes per frame per radian (the tracker's estimate; 0 without a camera)."""
        return 0.0

    def crowding(self, estimate_rad: float, scale_rad: float) -> float:
        """exp(-d / scale), d the bearing gap from the answer to the nearest other track."""
        return 0.0


class CameraBelief(VisionBelief):
    """The bearing tracker, where the camera looked, and the POD evidence.

    Parameters
    ----------
    circle : CircleGrid
        The pan grid.
    fov_half_angle_rad, box_bearing_noise_rad, rf_period_s : float
        The rig's camera and T_RF.
    frames_per_rf : int
        nu, frames per step (a bearing seen in fewer than 2 nu frames counts as unseen).
    pod : PODLookup
        p_hat_D(r), the learned POD model.
    recent_memory_s : float
        Memory of the recent view counts (the frames a walking Tx could have been missed in).
    pod_floor_std : float
        Misspecification of the POD model, added to its predictive std.
    null_pod_prior : (float, float)
        Beta prior of a non-Tx target's POD.
    pod_outlier : float
        Probability that the POD model says nothing about the Tx (hidden, shadowed, misfit).
    occlusion_halfwidth_rad : float
        An undetected target this close to a track's bearing may stand behind it ...
    occluded_probability : float
        ... and is then hidden with this probability (its misses say nothing).
    ranges : RangeCue or None
        The boxes' heights as a range cue (``range_cue``), when the rig's boxes carry them.
    """

    sees = True

    def __init__(self, circle: CircleGrid, fov_half_angle_rad: float, box_bearing_noise_rad: float, rf_period_s: float,
                 frames_per_rf: int, pod: PODLookup, recent_memory_s: float = 0.8, pod_floor_std: float = 0.08,
                 null_pod_prior: tuple[float, float] = (1.0, 1.0), pod_outlier: float = 0.2,
                 occlusion_halfwidth_rad: float = math.radians(5.0), occluded_probability: float = 0.9,
                 ranges: RangeCue | None = None) -> None:
        self.circle, self.pod, self.frames_per_rf = circle, pod, frames_per_rf
        self.pod_floor_std, self.null_pod_prior, self.pod_outlier = pod_floor_std, null_pod_prior, pod_outlier
        self.occlusion_halfwidth_rad, self.occluded_probability = occlusion_halfwidth_rad, occluded_probability
        self.tracks = BearingTracker(fov_half_angle_rad, box_bearing_noise_rad, rf_period_s)
        self.forget = math.exp(-rf_period_s / recent_memory_s)
        self.view_frames = np.zeros(circle.size)  # frames in which each grid bearing was in view
        self.view_recent = np.zeros(circle.size)  # the same, discounted over the recent memory
        self._outlier = np.empty(circle.size)
        self.ranges = ranges
        self.rf_period_s = rf_period_s
        self._steps = 0

    def update(self, pan_rad, frames) -> None:
        self.tracks.update(pan_rad, frames, self.view_frames)
        if self.ranges is not None:
            self.ranges.update(pan_rad, frames, self.tracks, self._steps * self.rf_period_s)
        self._steps += 1
        window = self.circle.window(pan_rad, self.tracks.count_limit)
        # view_frames[window] += nu; view_recent *= forget; view_recent[window] += nu (one compiled pass)
        _kernels.count_views(window, float(len(frames)), self.forget, self.view_frames, self.view_recent)

    def tx_pod(self, iso: IsoLevel) -> tuple[float, float]:
        """Beta(alpha, beta) of the Tx's POD: mean p_hat_D(z_iso), variance std(p_hat)^2 +
        (slope sigma_z)^2 / t + pod_floor_std^2. Without an Rx(iso) sample yet, an ordinary
        target's (``null_pod_prior``: the POD then tells the Tx from no one)."""
        if not iso.n:
            return self.null_pod_prior
        z_iso, sigma = iso.mean_and_std()
        p_hat, p_std, slope = self.pod(z_iso)
        var = p_std**2 + (slope * sigma) ** 2 / iso.n + self.pod_floor_std**2
        return beta_of(p_hat, var)

    def range_loglik(self, iso: IsoLevel) -> np.ndarray | None:
        return None if self.ranges is None else self.ranges.log_likelihood(self.tracks, iso)

    def miss_loglik(self, alpha: float, beta: float) -> tuple[np.ndarray, np.ndarray]:
        """Per grid bearing, log P(no detection in the frames that looked there | POD ~
        Beta(alpha, beta)) = log B(alpha, n + beta) - log B(alpha, beta): over every frame (a
        standing Tx) and over the recent ones (a walking Tx)."""
        values, lengths = self._view_runs()
        # _repeated_miss(values, lengths, alpha, beta, gammaln(alpha + beta) - gammaln(beta)) with one gammaln call over
        # every argument (elementwise: the same doubles), the sums, differences and the repeat compiled
        r = values.size
        args = np.empty(2 * r + 2)
        _kernels.miss_arguments(values, alpha, beta, args)
        M = self.view_frames.size
        per_cell = np.empty(2 * M)  # every frame's cells, then the recent ones'
        _kernels.repeat_miss(gammaln(args, out=args), r, lengths, per_cell)
        return per_cell[:M], per_cell[M:]

    def _view_runs(self) -> tuple[np.ndarray, np.ndarray]:
        """The runs (``_runs_of``) of ``view_frames`` followed by those of ``view_recent``, kept
        until the next ``update`` (the K tags of a step each ask, with their own POD): gammaln is
        elementwise, so one call over both gives each's doubles (``_per_run``)."""
        kept = getattr(self, "_runs_kept", None)
        if kept is None or kept[0] != self._steps:
            # np.concatenate of the two _runs_of, in one compiled pass
            size = self.view_frames.size + self.view_recent.size
            values, lengths = np.empty(size), np.empty(size, dtype=np.int64)
            r = _kernels.runs_of_both(self.view_frames, self.view_recent, values, lengths)
            kept = self._runs_kept = (self._steps, values[:r], lengths[:r])
        return kept[1], kept[2]

    def miss_outlier(self) -> np.ndarray:
        """Per grid bearing, the probability that an undetected Tx there was never visible:
        ``pod_outlier`` everywhere, ``occluded_probability`` within ``occlusion_halfwidth_rad``
        of a confirmed track (in a crowd the target the camera cannot see is most often right
        behind one it sees)."""
        out = self._outlier
        if getattr(self, "_outlier_for", None) is self.tracks._view:  # the same tracks (K tags read it once each)
            return out
        self._outlier_for = self.tracks._view
        out.fill(self.pod_outlier)
        if self.occluded_probability > self.pod_outlier and len(self.tracks):
            circle = self.circle
            h = int(math.floor((self.occlusion_halfwidth_rad + 1e-12) / circle.step))
            # the cells within h of each track's nearest cell, np.rint((wrap(bearing) + pi) / step) % M
            _kernels.mark_arcs(out, self.tracks.bearing, circle.step, h, float(self.occluded_probability))
        return out

    def mass_at(self, pan_rad, post) -> float:
        mass = _kernels.mass_at(self.tracks.bearing, post, pan_rad, self.tracks.count_limit) if post.size else 0.0
        unseen = self.view_frames[self.circle.nearest(pan_rad)] < 2 * self.frames_per_rf
        return max(mass, 1.0) if unseen else mass

    def clutter_density(self) -> float:
        return self.tracks.clutter_density

    def crowding(self, estimate_rad, scale_rad) -> float:
        if len(self.tracks) < 2:
            return 0.0
        # the second smallest gap (the smallest: the track named), as np.sort(np.abs(wrap(bearing - estimate)))[1]
        return math.exp(-float(_kernels.second_gap(self.tracks.bearing, float(estimate_rad))) / scale_rad)
