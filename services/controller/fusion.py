"""The fusion part: from the RF and vision beliefs to the hypotheses' posterior and the answer
(issue 19).

Two kinds of hypothesis compete: "the Tx is camera track i", l(i) = rf_weight l_RF(gamma_i) +
l_D(i) (the RF belief at the track's bearing plus its POD evidence), and "the Tx is a target the
camera never detected, at grid bearing gamma", rf_weight l_RF(gamma) + log P(missed in every
frame that looked there) + a prior density. When the rig's boxes carry heights, a track's l(i)
also gains the range cue l_H(i) (``range_cue``: the range its boxes give against the range
Rx(iso)'s level gives, as a log Bayes factor against a detected target's range at random, which
is what "missed" keeps). The estimate gamma_hat_t names the most probable
(the LOS condition, eq. 10, makes the Tx one of the detected targets, but a far target's POD is
close to 0); without a camera it is the lobe centre (eq. 27).
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.rf_belief import IsoLevel, RFBelief
from ra2vipas.services.controller.vision_belief import VisionBelief


def refined_argmax(circle: CircleGrid, values: np.ndarray) -> float:
    """Grid argmax refined by a parabola through its two neighbours."""
    j = int(values.argmax())  # np.argmax without its Python wrapper
    M = values.size
    a, b, c = values[(j - 1) % M], values[j], values[(j + 1) % M]
    den = a - 2.0 * b + c
    shift = 0.5 * (a - c) / den if den < 0 else 0.0
    # np.clip(shift, -0.5, 0.5) on one number, without numpy's call (~5 us): the same double (NaN and -0.0 kept)
    return float(circle.angles[j] + min(max(shift, -0.5), 0.5) * (2 * math.pi / M))


def arc_mass(weights: np.ndarray, centre: int, half: int) -> float:
    """Sum of grid ``weights`` within ``half`` cells of ``centre`` (periodic)."""
    if 2 * half + 1 < 8:  # numpy sums so few terms left to right: compiled, the same double
        return float(_kernels.arc_sum(weights, int(centre), int(half)))
    M = weights.size
    idx = np.arange(centre - half, centre + half + 1) % M
    return float(weights[idx].sum())


def softmax(log_weights: np.ndarray) -> np.ndarray:
    if not log_weights.size:
        return log_weights
    w = np.exp(log_weights - log_weights.max())
    return w / w.sum()


def softmax_and_logsumexp(log_weights: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(softmax(l), rf_filter.logsumexp(l)) of a non-empty array from one exp: the same doubles as
    the two apart (both subtract the same max, exponentiate and sum the same array). ``out``, if
    given (a contiguous array of l's size, e.g. a row of a (K, grid) array), takes softmax(l)."""
    w = np.empty(log_weights.size) if out is None else out
    top = _kernels.less_max(log_weights, w)  # the subtraction, the sum, the division and the log compiled; the exps numpy's
    lse = _kernels.normalise_exps(np.exp(w, out=w), top)
    return w, lse


class Fusion:
    """Posterior over "the Tx is track i" and "the Tx is an undetected target at gamma", and
    the answer it gives.

    Parameters
    ----------
    circle : CircleGrid
        The pan grid.
    rf_weight : float
        Tempering of a (non-exact) RF belief's l_RF.
    missed_prior_per_rad : float
        Prior density of "the Tx is a target the camera never detected".
    answer_window_rad : float
        The posterior mass within this of the answer is its raw confidence.
    walker_answer_from_rf : bool
        A Tx that walks (P > 0.5) is named where l_RF peaks (its track may lag or be lost).

    Attributes
    ----------
    where : ndarray of shape (n,)
        After ``beliefs``: where the Tx would be now if it were track i (its bearing, or for a
        walker the camera lost, where Rx(dir) puts it within the track's reach).
    """

    def __init__(self, circle: CircleGrid, rf_weight: float = 1.0, missed_prior_per_rad: float = 5.0,
                 answer_window_rad: float = math.radians(2.0), walker_answer_from_rf: bool = True) -> None:
        self.circle = circle
        self.rf_weight, self.missed_prior_per_rad = rf_weight, missed_prior_per_rad
        self.answer_window_rad, self.walker_answer_from_rf = answer_window_rad, walker_answer_from_rf
        self.where = np.empty(0)
        self._missed = np.empty(circle.size)

    def beliefs(self, rf: RFBelief, vision: VisionBelief, iso: IsoLevel) -> tuple[np.ndarray, np.ndarray | None]:
        """Unnormalised log-posteriors of "the Tx is track i", shape (n,), and of "the Tx is an
        undetected target at grid bearing gamma", shape (M,) (None without a camera)."""
        if not vision.sees:
            return np.empty(0), None
        tracks, l_rf, step = vision.tracks, rf.log_likelihood, self.circle.step
        alpha, beta = vision.tx_pod(iso)
        a0, b0 = vision.null_pod_prior
        n = len(tracks)
        l_tracks = np.empty(n)
        self.where = np.empty(n)
        if n and rf.exact:  # the filter's trajectory evidence plus the POD evidence (``_kernels.pod_evidence``)
            l_tracks[:] = rf.track_loglik(tracks)
            means, sds, weights = tracks.components()
            _kernels.add_pod_evidence(l_tracks, tracks.detections, tracks.frames_in_view, alpha, beta, a0, b0, vision.pod_outlier)
            _kernels.track_where(l_rf, np.ascontiguousarray(means), np.ascontiguousarray(sds), np.ascontiguousarray(weights), step,
                                 3.0 * step, self.where)
        elif n:
            means, sds, weights = tracks.components()
            _kernels.track_logpost(l_rf, rf.track_loglik(tracks), step, self.rf_weight, means, sds, weights, tracks.detections,
                                   tracks.frames_in_view, alpha, beta, a0, b0, vision.pod_outlier, l_tracks, self.where)
        if n:  # boxes with heights: their range against Rx(iso)'s (a log Bayes factor; an undetected Tx's is 0)
            l_range = vision.range_loglik(iso)
            if l_range is not None:
                l_tracks += l_range
        miss_stand, miss_walk = vision.miss_loglik(alpha, beta)
        _kernels.missed_logdensity(l_rf, self.rf_weight, miss_stand, miss_walk, rf.tx_walks, math.log(self.missed_prior_per_rad * step),
                                   vision.miss_outlier(), self._missed)
        return l_tracks, self._missed

    def answer(self, rf: RFBelief, l_tracks: np.ndarray, l_missed: np.ndarray | None,
               default_rad: float) -> tuple[float, float, np.ndarray]:
        """gamma_hat_t, the raw posterior probability that the target it names is the Tx, and the
        tracks' posterior probabilities.

        With a camera: the detected target with the largest posterior, unless the posterior mass
        of "missed" within ``answer_window_rad`` of some undetected bearing is larger. Without
        (``l_missed`` None): the lobe centre (eq. 27), with the RF posterior mass around it as its
        confidence; ``default_rad`` before any RF sample.
        """
        half = max(1, int(round(self.answer_window_rad / self.circle.step)))
        l_rf = rf.log_likelihood
        if l_missed is None:
            if not rf.samples:
                return default_rad, 0.0, l_tracks
            post_grid = softmax((1.0 if rf.exact else self.rf_weight) * l_rf)
            estimate = refined_argmax(self.circle, l_rf)
            return estimate, arc_mass(post_grid, self.circle.nearest(estimate), half), l_tracks
        # one array of both hypotheses' weights exp(l - top), top the largest of both (the exps numpy's, in one call), their
        # posterior (each part summed as numpy sums it), the missed part's argmax and arc mass and the tracks' best, compiled
        M = l_missed.size
        weights = np.empty(M + l_tracks.size)
        _kernels.shift_both(l_missed, l_tracks, weights)
        missed_mass, i, post_max = _kernels.posterior_both(np.exp(weights, out=weights), M, half)
        post_missed, post = weights[:M], weights[M:]
        if post.size and (post_max >= missed_mass or not rf.listens):  # without Rx(dir), "missed" names no bearing
            estimate = float(self.where[i])
            if rf.listens and self.walker_answer_from_rf and rf.tx_walks > 0.5:
                # a walker: the tracks are where the camera last saw people, l_RF where the Tx is now
                estimate = refined_argmax(self.circle, l_rf)
            return estimate, float(post[i]) + arc_mass(post_missed, self.circle.nearest(estimate), half), post
        return refined_argmax(self.circle, l_missed), missed_mass, post
