"""Where the Tx is now, from Rx(dir) and Rx(iso), when the rig says how Rx(dir) responds.

A grid Bayes filter over the Tx bearing gamma (the lobe centre), with two motion models:

* **stands**: gamma is fixed; the posterior is the product of every sample's likelihood;
* **walks**: gamma_t = gamma_{t-1} + w_t, w_t ~ N(0, sigma_w^2) (a hidden Markov model on the
  grid; the prediction is a circular convolution);

and their posterior model probabilities from the marginal likelihoods (the two filters'
one-step predictive normalisers), so P(walk) is a Bayes factor, not a heuristic.

Each sample's likelihood uses the rig's Rx(dir) response (paper eq. 6: z_dir = L rho(s - gamma),
or the dB-gain model z_dir = L + 10 log10 max(rho, floor)) with the level L read from Rx(iso)
(the same channel: path loss and shadowing, eq. 5): the mean of every iso sample for a Tx that
stands, an exponentially weighted mean (``level_memory_s``) for one that walks, its range and
shadowing changing. The RSSI noise is AR(1) in time (fading, ``noise_correlation``): each
sample enters quasi-differenced, (z_t - rho z_{t-1}) - (mu_t - rho mu_{t-1}) with variance
sigma^2 (1 - rho^2), the generalised-least-squares form of correlated noise (Cochrane & Orcutt),
so correlated samples are not counted as independent ones.

Beside the Tx's bearing on the grid, the filter scores hypotheses "the Tx is camera track i"
(``follow``): each sample's likelihood at where the track was when the sample was taken (its
predicted bearing, smeared over the track's uncertainty), accumulated relative to the walking
filter's predictive normaliser. That is the evidence of the track's whole trajectory, as the
oracle computes it with the true trajectories, rather than of its bearing now.

Everything is a log-density per grid cell relative to one baseline (the walking filter's
marginal likelihood), so the standing and walking posteriors, tracks and untracked bearings are
on one footing: ``log_joint_stand`` + ``log_joint_walk`` normalised over the grid is the
posterior of the Tx's bearing now.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.grid import CircleGrid


def antenna_gain(misalignment_rad: np.ndarray, curvature: float) -> np.ndarray:
    """rho(Delta) = 1 - a wrap(Delta)^2 clipped to [0, 1] (paper eq. 6)."""
    d = (np.asarray(misalignment_rad, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi
    return np.clip(1.0 - curvature * d * d, 0.0, 1.0)


_GAIN_ROWS: dict[tuple[float, int, float], np.ndarray] = {}
_GAIN_TABLES: dict[tuple[float, int, int, bool], np.ndarray] = {}


try:  # numpy >= 2: np.fft.rfft and irfft are these ufuncs behind argument checks that cost more than the 360-cell FFTs
    from numpy.fft import _pocketfft_umath as _pocketfft
except ImportError:  # numpy 1.x
    _pocketfft = None
_AXES = [(0,), (), (0,)]


def convolve_periodic(x: np.ndarray, kernel_fft: np.ndarray) -> np.ndarray:
    """np.fft.irfft(np.fft.rfft(x) * kernel_fft, n=x.size): x's circular convolution with the kernel
    whose rfft is ``kernel_fft``. On numpy >= 2 the ufuncs np.fft calls, with the arguments it gives
    them (norm "backward": 1 forward, 1 / n back), called directly: the same doubles, ~8 instead of
    ~25 us on 360 cells."""
    n = x.size
    if _pocketfft is None:
        return np.fft.irfft(np.fft.rfft(x) * kernel_fft, n=n)
    spectrum = np.empty(n // 2 + 1, dtype=complex)
    (_pocketfft.rfft_n_even if n % 2 == 0 else _pocketfft.rfft_n_odd)(x, 1, axes=_AXES, out=spectrum)
    out = np.empty(n)
    scale = _INVERSE_SCALE.get(n)
    if scale is None:  # np.reciprocal(n, dtype=np.float64), kept per n (the call costs ~2 us, the 360-cell FFTs ~4 us each)
        scale = _INVERSE_SCALE[n] = np.reciprocal(n, dtype=np.float64)
    _pocketfft.irfft(spectrum * kernel_fft, scale, axes=_AXES, out=out)
    return out


_INVERSE_SCALE: dict[int, np.float64] = {}


def _gain_row(curvature: float, circle: CircleGrid, pan_rad: float) -> np.ndarray:
    """antenna_gain(pan_rad - circle.angles, curvature), read-only, kept per (curvature, grid, pan):
    the pans a controller commands repeat (grid points), and each sample, the answer's J_RF and the
    posterior's expected gain read this row (the same doubles as computing it again)."""
    key = (curvature, circle.size, pan_rad)
    row = _GAIN_ROWS.get(key)
    if row is None:
        if len(_GAIN_ROWS) >= 4096:
            _GAIN_ROWS.clear()
        row = antenna_gain(pan_rad - circle.angles, curvature)
        row.flags.writeable = False
        _GAIN_ROWS[key] = row
    return row


def _gain_table(curvature: float, circle: CircleGrid, stride: int = 1, squared: bool = False) -> np.ndarray:
    """antenna_gain(angles[::stride, None] - angles[None, :], curvature), (M / stride, M), C-contiguous
    and read-only: element (i, j) is the gain at grid pan i * stride of a Tx at grid bearing j,
    computed once per (curvature, grid, stride) (elementwise, so any (pans x cells) block of it is
    what computing that block gives); ``squared``: each element times itself, kept the same way."""
    key = (curvature, circle.size, stride, squared)
    table = _GAIN_TABLES.get(key)
    if table is None:
        if len(_GAIN_TABLES) >= 16:
            _GAIN_TABLES.clear()
        if squared:
            gain = _gain_table(curvature, circle, stride)
            table = gain * gain
        else:
            table = antenna_gain(circle.angles[::stride, None] - circle.angles[None, :], curvature)
        table.flags.writeable = False
        _GAIN_TABLES[key] = table
    return table


def _columns(table: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """table[:, keep]: a view of the columns when ``keep`` is a run of cells (the posterior's support
    mostly is), a new C-contiguous array by ``np.take`` otherwise. A product with a vector gives the
    same doubles either way (OpenBLAS's gemv does not depend on the row stride: checked on its
    Prescott, Nehalem, Sandybridge and Haswell kernels), without copying the block."""
    if keep.size and keep[-1] - keep[0] + 1 == keep.size:
        return table[:, keep[0]:keep[-1] + 1]
    return table.take(keep, axis=1)  # np.take without its Python wrapper


_WINDOWS: list = [None]  # the last tracks' windows: (means, sds, weights as given, step, M, what smear_windows returned)


def smear_windows(means, sds, weights, circle: CircleGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    """(means, sds, weights) as C-contiguous doubles and the Gaussian windows ``follow`` averages
    each IMM component's sample likelihood over (``_kernels.smear_windows``: they depend on the
    tracks only). Kept for the last tracks when their arrays are read-only and own their data (the
    tracker's ``components()``: one set of objects a step, which the K tags' filters all follow)."""
    kept = _WINDOWS[0]
    if kept is not None and kept[0] is means and kept[1] is sds and kept[2] is weights and kept[3] == circle.step \
            and kept[4] == circle.size:
        return kept[5]
    frozen = all(isinstance(a, np.ndarray) and not a.flags.writeable and a.base is None for a in (means, sds, weights))
    given = (means, sds, weights)
    means, sds, weights = (np.ascontiguousarray(a, dtype=float) for a in given)
    n = means.shape[0]
    first, count, offset = np.empty((n, 2), dtype=np.int64), np.empty((n, 2), dtype=np.int64), np.empty((n, 2), dtype=np.int64)
    den = np.empty((n, 2))
    w = _kernels.smear_windows(means, sds, weights, circle.step, circle.size, first, count, offset, den)
    out = (means, sds, weights, (first, count, offset, w, den))
    if frozen:
        _WINDOWS[0] = (*given, circle.step, circle.size, out)
    return out


class RxDirModel:
    """The mean of Rx(dir) given the level L and the misalignment: the rig's response."""

    def __init__(self, model: str, curvature: float, floor_db: float = -20.0) -> None:
        if model not in ("paper", "db-gain"):
            raise ValueError(f"a known Rx(dir) response is paper or db-gain, not {model!r}")
        self.model = model
        self.curvature = float(curvature)
        self.floor = 10.0 ** (float(floor_db) / 10.0)

    def gain(self, misalignment_rad: np.ndarray) -> np.ndarray:
        return antenna_gain(misalignment_rad, self.curvature)

    def gain_over(self, pan_rad: float, circle: CircleGrid) -> np.ndarray:
        """``gain(pan_rad - circle.angles)``, read-only (kept per pan: ``_gain_row``)."""
        return _gain_row(self.curvature, circle, pan_rad)

    def gain_table(self, circle: CircleGrid, stride: int = 1, squared: bool = False) -> np.ndarray:
        """``gain(angles[::stride, None] - angles[None, :])``, (M / stride, M), read-only (``_gain_table``;
        ``squared``: its elements squared)."""
        return _gain_table(self.curvature, circle, stride, squared)

    def mean(self, level: float, gain: np.ndarray) -> np.ndarray:
        """E[z_dir] for the level L (dBm) and the antenna gain rho (eq. 6 or its dB form)."""
        if self.model == "paper":
            return level * gain
        return level + 10.0 * np.log10(np.maximum(gain, self.floor))

    def level_slope(self, gain: np.ndarray) -> np.ndarray:
        """d E[z_dir] / d L: how an error in the level moves the mean."""
        return gain if self.model == "paper" else np.ones_like(gain)


class RFBearingFilter:
    """The grid filter described in the module docstring.

    Parameters
    ----------
    circle : CircleGrid
        The M candidate bearings.
    response : RxDirModel
        Rx(dir)'s response.
    noise_db : float
        sigma of the RSSI noise on each receiver [dB].
    rf_period_s : float
        T_RF [s].
    walk_std_rad : float
        sigma_w, the walking Tx's bearing change per step [rad].
    level_memory_s : float
        Memory of the walking Tx's level estimate [s].
    walk_prior : float
        Prior probability that the Tx walks.
    """

    def __init__(self, circle: CircleGrid, response: RxDirModel, noise_db: float, rf_period_s: float,
                 walk_std_rad: float = math.radians(2.0), level_memory_s: float = 0.5, walk_prior: float = 0.3,
                 tail_dof: float | None = 4.0) -> None:
        self.circle = circle
        self.response = response
        self.noise_var = max(float(noise_db), 0.1) ** 2
        self.walk_prior = float(walk_prior)
        self.tail_dof = tail_dof
        M = circle.size
        self._log_m = math.log(M)
        self._lam = math.exp(-rf_period_s / level_memory_s)
        # the walking model's transition: a wrapped Gaussian kernel on the grid, applied by FFT
        steps = np.minimum(np.arange(M), M - np.arange(M)) * circle.step
        kernel = np.exp(-0.5 * (steps / max(walk_std_rad, 1e-6)) ** 2)
        self._kernel_fft = np.fft.rfft(kernel / kernel.sum())
        self.n = 0
        self.rho = 0.0  # AR(1) correlation of the noise, from Rx(iso)
        self._iso_sum = self._iso_sq = self._iso_diff_sq = 0.0
        self._iso_prev: float | None = None
        self._level_walk = 0.0
        self._prev: tuple[np.ndarray, float] | None = None  # (antenna gain over the grid, z_dir) of the previous sample
        self._static = np.zeros(M)  # sum of the static model's sample log-likelihoods minus the baseline
        self._walk = np.full(M, -self._log_m)  # log posterior of the walking model (normalised)
        self.ll_stand = np.zeros(M)  # this step's sample log-likelihood (relative), standing level
        self.ll_walk = np.zeros(M)  # ... walking level
        self._evidence: dict[int, float] = {}  # track id -> trajectory evidence (relative to the baseline)
        self._read: dict = {}  # what the step's readers share (``_reading``), as of (samples, walk prior) = _posterior_key
        self._posterior_key: tuple[int, float] | None = None

    # -- updating -------------------------------------------------------------------------------
    def add(self, pan_rad: float, iso_dbm: float, dir_dbm: float) -> None:
        """Take the sample of one step: the pan and the two RSSI values."""
        self.n += 1
        n = self.n
        self._iso_sum += iso_dbm
        self._iso_sq += iso_dbm * iso_dbm
        if self._iso_prev is not None:
            self._iso_diff_sq += (iso_dbm - self._iso_prev) ** 2
        self._iso_prev = iso_dbm
        self._level_walk = iso_dbm if n == 1 else self._lam * self._level_walk + (1.0 - self._lam) * iso_dbm
        level_stand = self._iso_sum / n
        self.rho = self._noise_correlation()
        gain = self.response.gain_over(pan_rad, self.circle)
        ll_stand, ll_walk = self._sample_logliks(dir_dbm, gain, (level_stand, self._level_walk), (self._level_var(False), self._level_var(True)))
        self._prev = (gain, dir_dbm)
        self._absorb(ll_stand, ll_walk)

    def _absorb(self, ll_stand: np.ndarray, ll_walk: np.ndarray, steps: int = 1) -> None:
        """One update of the walking filter (predict: diffuse over ``steps`` steps of T_RF since
        the last update; update with ``ll_walk``, the log-likelihood over the grid), its
        normaliser the baseline of this update's relative log-likelihoods, and the standing
        model's evidence accumulated."""
        # the walking filter: predict (diffuse), update; its normaliser is the baseline. The arithmetic of
        # prior = exp(walk - max walk), predicted = max(irfft(rfft(prior) kernel), 0) / its sum,
        # joint = predicted exp(ll_walk - max ll_walk) in compiled passes, the exps, logs and FFTs numpy's
        # (the exps and the log in place: elementwise, the same doubles as into new arrays)
        shifted = np.empty(self._walk.size)
        _kernels.less_max(self._walk, shifted)
        kernel = self._kernel_fft if steps == 1 else self._kernel_fft**steps  # k steps: k times the variance
        predicted = convolve_periodic(np.exp(shifted, out=shifted), kernel)
        top = _kernels.clip_normalise(predicted, ll_walk, shifted)
        joint = np.exp(shifted, out=shifted)
        c = _kernels.times_sum_floored(predicted, joint, 1e-300)  # joint = np.maximum(predicted joint / c, 1e-300), c its sum
        log_c = top + math.log(max(c, 1e-300))
        self._walk = np.log(joint, out=joint)
        # ll_stand - log_c, ll_walk - log_c, and the first added to _static (one compiled pass)
        self.ll_stand, self.ll_walk = np.empty(ll_stand.size), np.empty(ll_walk.size)
        _kernels.rebase(ll_stand, ll_walk, float(log_c), self._static, self.ll_stand, self.ll_walk)

    def _noise_correlation(self) -> float:
        """rho from Rx(iso): for AR(1) noise Var(z_t - z_{t-1}) = 2 sigma^2 (1 - rho) (a walking
        Tx's drift reads as correlation, which only makes each sample count less)."""
        n = self.n
        if n < 10:
            return 0.0
        mean = self._iso_sum / n
        var = max(self._iso_sq / n - mean * mean, 1e-9) * n / (n - 1)
        rho = 1.0 - (self._iso_diff_sq / (n - 1)) / (2.0 * var)
        return min(max(rho, 0.0), 0.95)

    def _level_var(self, walking: bool) -> float:
        """Variance of the level estimate: sigma^2 / n_eff, n_eff shrunk by the correlation."""
        rho = self.rho
        inflate = (1.0 + rho) / (1.0 - rho)
        if walking:
            lam = self._lam
            return min(self.noise_var * (1.0 - lam) / (1.0 + lam) * inflate, self.noise_var)
        return min(self.noise_var * inflate / self.n, self.noise_var)

    def _slope_term(self, gain: np.ndarray) -> np.ndarray:
        """What ``_sample_loglik``'s variance adds per unit of level variance, (dE z / dL)^2
        quasi-differenced: the same for the standing and the walking level (computed once a sample)."""
        resp = self.response
        slope = resp.level_slope(gain)
        if self._prev is not None and self.rho > 0.0:
            return (slope - self.rho * resp.level_slope(self._prev[0])) ** 2
        return slope * slope

    def _sample_logliks(self, z: float, gain: np.ndarray, levels: tuple[float, float],
                        level_vars: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """The sample's log-likelihood over the grid at the standing and at the walking level. For the
        paper response with Student-t innovations the arithmetic of ``_slope_term`` and
        ``_sample_loglik`` for both levels in compiled passes (``_kernels.t_innovations``,
        ``t_combine``) with one numpy log1p and one log over both: the same doubles."""
        rho = self.rho
        if self.response.model == "paper" and self.tail_dof is not None:
            nu = self.tail_dof
            differenced = self._prev is not None and rho > 0.0
            gain0, z0 = self._prev if differenced else (gain, 0.0)
            M = gain.size
            var, q = np.empty(2 * M), np.empty(2 * M)  # the standing level's cells, then the walking one's
            _kernels.t_innovations(gain, gain0, float(z), float(z0), float(levels[0]), float(levels[1]), float(rho),
                                   float(self.noise_var), float(level_vars[0]), float(level_vars[1]), float(nu), differenced, var, q)
            # the log1p and the log in place (elementwise: the same doubles), combined into q
            _kernels.t_combine(np.log1p(q, out=q), np.log(var, out=var), -0.5 * (nu + 1.0), _t_const(nu), q)
            return q[:M], q[M:]
        shared = self._slope_term(gain)  # the same for both levels
        return tuple(self._sample_loglik(z, gain, level, level_var, shared) for level, level_var in zip(levels, level_vars))

    def _sample_loglik(self, z: float, gain: np.ndarray, level: float, level_var: float,
                       slope_term: np.ndarray) -> np.ndarray:
        """One sample's log-likelihood over the grid at ``level`` (the responses and innovations
        ``_sample_logliks`` does not compile); ``slope_term``: ``_slope_term(gain)``."""
        resp = self.response
        rho = self.rho
        mean = resp.mean(level, gain)
        if self._prev is not None and rho > 0.0:
            gain0, z0 = self._prev  # the previous sample's antenna gain over the grid, and its reading
            resid = (z - rho * z0) - (mean - rho * resp.mean(level, gain0))
            var = self.noise_var * (1.0 - rho * rho) + slope_term * level_var
        else:
            resid = z - mean
            var = self.noise_var + slope_term * level_var
        if self.tail_dof is None:
            return -0.5 * (resid * resid / var + np.log(2.0 * math.pi * var))
        nu = self.tail_dof  # Student-t: a rare large innovation (fading, a body passing) is not a reason to move gamma
        return -0.5 * (nu + 1.0) * np.log1p(resid * resid / (nu * var)) - 0.5 * np.log(var) + _t_const(nu)

    def follow(self, ids, means: np.ndarray, sds: np.ndarray, weights: np.ndarray) -> None:
        """After ``add``: add this sample's evidence to each camera track's trajectory evidence.

        ``means``, ``sds``, ``weights`` (n, 2) are the tracks' IMM components (standing,
        walking) predicted to this step. The sample is scored where each component puts the
        track (smeared over its uncertainty, with the standing or walking level); a track met
        for the first time gets the standing filter's evidence at its bearing for the samples
        before it (it may have stood there all along) or none (it walked in), by its weights."""
        evidence: dict[int, float] = {}
        circle = self.circle
        step = np.empty(len(ids))
        means, sds, weights, windows = smear_windows(means, sds, weights, circle)
        _kernels.track_sample_loglik(self.ll_stand, self.ll_walk, means, sds, weights, circle.step, *windows, step)
        for i, (tid, s) in enumerate(zip(ids, step.tolist())):
            if tid in self._evidence:
                evidence[tid] = self._evidence[tid] + s
            else:
                evidence[tid] = self._first_evidence(means[i], weights[i])
        self._evidence = evidence

    def follow_tracks(self, ids, means: np.ndarray, weights: np.ndarray) -> None:
        """``follow`` for a step without a sample: the tracks followed so far keep their
        evidence, a new one gets its first (``follow``), the others are forgotten."""
        self._evidence = {tid: self._evidence[tid] if tid in self._evidence else self._first_evidence(means[i], weights[i])
                          for i, tid in enumerate(ids)}

    def _first_evidence(self, means: np.ndarray, weights: np.ndarray) -> float:
        """A track met for the first time: its past is unknown, it stood where it is (the standing
        filter) or walked here (the walking filter), by its IMM weights."""
        circle = self.circle  # circle.interp at one angle, compiled (the same arithmetic)
        stood = float(_kernels._interp_periodic(self._static, float(means[0]), circle.step))
        walked = float(_kernels._interp_periodic(self._walk, float(means[1]), circle.step)) + self._log_m
        w0 = min(max(float(weights[0]), 1e-6), 1.0 - 1e-6)
        return _logsumexp_list([math.log(w0) + stood, math.log(1.0 - w0) + walked])

    # -- reading --------------------------------------------------------------------------------
    @property
    def log_joint_stand(self) -> np.ndarray:
        """log P(stands, gamma = cell) + const (the standing model's evidence included)."""
        return self._joints()[0].copy()

    @property
    def log_joint_walk(self) -> np.ndarray:
        """log P(walks, gamma_t = cell) + the same const."""
        return self._joints()[1].copy()

    def _reading(self) -> dict:
        """What the readers of one step share, computed once per sample and walk prior however many
        readers ask (the answer, J_RF, the probe, the tracks' scores): each entry is computed
        lazily, by the same expression as before it was kept."""
        key = (self.n, self.walk_prior)
        if self._posterior_key != key:
            self._read = {}
            self._posterior_key = key
        return self._read

    def _joint(self) -> tuple[np.ndarray, float]:
        """logaddexp(log_joint_stand, log_joint_walk) and its logsumexp (kept: ``_reading``)."""
        read = self._reading()
        joint = read.get("joint")
        if joint is None:
            joints = self._joints()
            joint = read["joint"] = np.logaddexp(joints[0], joints[1])
            shifted = np.empty(joint.size)
            top = _kernels.less_max(joint, shifted)  # logsumexp(joint): the exps numpy's, the sum and log compiled
            posterior = np.empty(joint.size)  # log_posterior's joint - logsumexp(joint), in the same pass
            read["joint_lse"] = _kernels.log_normalise(joint, np.exp(shifted, out=shifted), top, posterior)
            posterior.flags.writeable = False
            read["posterior"] = posterior
        return joint, read["joint_lse"]

    def _joints(self) -> np.ndarray:
        """(log_joint_stand, log_joint_walk) as the rows of one (2, M) array, read-only: (_static -
        log M) + log(1 - walk prior) and _walk + log(walk prior), with each row less its max for the
        logsumexps of ``p_walk`` (kept: ``_reading``; compiled, ``_kernels.joint_logs``)."""
        read = self._reading()
        joints = read.get("joints")
        if joints is None:
            M = self._static.size
            joints, shifted = np.empty((2, M)), np.empty((2, M))
            read["tops"] = _kernels.joint_logs(self._static, self._log_m, math.log(1.0 - self.walk_prior), self._walk,
                                               math.log(self.walk_prior), joints, shifted)
            joints.flags.writeable = False
            read["joints"], read["joints_shifted"] = joints, shifted
        return joints

    def log_posterior(self) -> np.ndarray:
        """log P(gamma_t = cell | samples), normalised over the grid: read-only, computed once per
        sample and walk prior however many readers ask in a step (the answer, J_RF, the probe)."""
        read = self._reading()
        posterior = read.get("posterior")
        if posterior is None:
            self._joint()  # joint - logsumexp(joint), made with the logsumexp
            posterior = read["posterior"]
        return posterior

    def posterior(self) -> np.ndarray:
        """exp(log_posterior()), read-only (kept: ``_reading``)."""
        read = self._reading()
        post = read.get("post")
        if post is None:
            post = read["post"] = np.exp(self.log_posterior())
            post.flags.writeable = False
        return post

    def _posterior_support(self, mass: float) -> tuple[np.ndarray, np.ndarray]:
        """(cells, their probabilities renormalised) of the posterior of gamma where it is at least
        ``mass`` of its largest: the cells worth a column in a (pans x cells) product."""
        read = self._reading()
        support = read.get(("support", mass))
        if support is None:  # np.flatnonzero(post >= mass * post.max()) and post[keep] / post[keep].sum(), compiled
            post = self.posterior()
            keep, p = np.empty(post.size, dtype=np.int64), np.empty(post.size)
            n = _kernels.support(post, mass, keep, p)
            support = read[("support", mass)] = (keep[:n], p[:n])
        return support

    @property
    def p_walk(self) -> float:
        """P(the Tx walks | samples)."""
        read = self._reading()
        p = read.get("p_walk")
        if p is None:
            self._joints()  # logsumexp of each row: its max plus the log of its shifted row's exps summed (as numpy sums a row)
            top_s, top_w = read["tops"]
            total_s, total_w = _kernels.row_totals(np.exp(read["joints_shifted"]))
            s, w = top_s + math.log(total_s), top_w + math.log(total_w)
            p = read["p_walk"] = 1.0 / (1.0 + math.exp(min(max(s - w, -50.0), 50.0)))
        return p

    def most_informative_pan(self, stride: int = 2, mass: float = 1e-3) -> float:
        """The pan whose next Rx(dir) sample the current posterior is least sure of: the largest
        predictive variance Var_gamma[E z_dir(s, gamma)] over the posterior of gamma (for Gaussian
        noise, the sample with the largest mutual information with gamma; MacKay 1992). Cells of
        posterior below ``mass`` of the largest are left out; pans every ``stride`` grid cells."""
        keep, p = self._posterior_support(mass)
        pans = self.circle.angles[::stride]
        walking = self.p_walk > 0.5
        # gain(pans[:, None] - angles[keep][None, :]): those rows and columns of the grid's table
        mean = self.response.mean(self._level_now(walking), _columns(self.response.gain_table(self.circle, stride), keep))  # (S, K)
        offset = self._probe_offset(walking)
        if offset is not None:
            mean += offset[keep][None, :]
        first = mean @ p
        var = (mean * mean) @ p - first * first
        return float(pans[int(var.argmax())])

    def _level_now(self, walking: bool) -> float:
        """The level L Rx(iso) reads now: the walking model's recent one, or the standing mean."""
        return self._level_walk if walking else self._iso_sum / max(self.n, 1)

    def _probe_offset(self, walking: bool) -> np.ndarray | None:
        """Rx(dir)'s offset per cell as ``most_informative_pan`` reads it (None: 0, known, as for the 1.0 pair)."""
        return None

    def predicted_gain(self, mass: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation over the posterior of gamma of the antenna gain
        rho(s - gamma) at every grid pan s: the normalised lobe J_RF(s) the fused objective's
        GP-UCB reads (paper eq. 24-25), and how unsure the filter is of it there."""
        keep, p = self._posterior_support(mass)
        # gain(angles[:, None] - angles[keep][None, :]) @ p, (M, K) @ (K,), and the same with the gains squared
        first = _columns(self.response.gain_table(self.circle), keep) @ p
        second = _columns(self.response.gain_table(self.circle, squared=True), keep) @ p
        sd = np.empty(first.size)
        _kernels.spread(first, second, sd)  # np.sqrt(np.maximum(second - first * first, 0.0)), compiled
        return first, sd

    def track_evidence(self, ids, less: float | None = None) -> np.ndarray:
        """log P(the Tx is track id, its trajectory) + the same const as ``log_joint_*``: the
        track's trajectory evidence per grid cell (less log M, like an untracked bearing); ``less``:
        that minus ``less`` (one compiled pass, the same doubles as subtracting it after)."""
        values = np.fromiter(map(self._evidence.__getitem__, ids), dtype=float, count=len(ids))
        if less is None:
            return values - self._log_m
        _kernels.less_twice(values, self._log_m, float(less))
        return values


class PacketBearingFilter(RFBearingFilter):
    """``RFBearingFilter`` that also reads BLE advertisements (protocol 1.3): 0..n packets per
    receiver and step, at irregular times, with whole-dBm RSSI, on advertising channels whose
    offsets differ (frequency-selective fading). ``add`` (the 1.0 pair) is the parent's, unchanged;
    ``add_packets`` takes a step's packets.

    The packet likelihood (one term per packet; a lost packet is no term, a step without a
    Rx(dir) packet leaves the bearing as it was):

    * **Level.** L is what Rx(iso) reads: the standing model's mean of every Rx(iso) packet; the
      walking model's exponential average over *time* (weight exp(-dt / level memory), dt the time
      since the previous Rx(iso) packet), each packet less its channel's estimated offset.
    * **Channel offsets** are random effects, marginalised: Rx(dir)'s packets on advertising channel
      c share an unknown offset b_c ~ N(0, sigma_ch^2) (null channel: one group, prior
      ``receiver_offset_db``). Per
      grid cell the offset's posterior given the channel's earlier residuals is Gaussian, so packet
      k's predictive residual is z_k - E z_dir(gamma) - E[b_c | earlier] with variance sigma_e^2 +
      Var[b_c | earlier] + (dE z / dL)^2 Var L: the exact sequential marginal of a Gaussian random
      effect (a Kalman filter on a constant), Student-t tails as the parent's. Rx(iso)'s offsets
      are estimated the same way (shrunk means) and removed from the walking level.
    * **The standing model reads every Rx(dir) packet against today's level** (``batch_standing``,
      the built-ins' default): a standing Tx at gamma gives packet k the mean a_k(gamma) + b_k(gamma) L
      (db-gain: a the gain in dB, b = 1; eq. 6: a = 0, b = rho). Its evidence is the batch marginal
      of all of Rx(dir)'s packets so far, at the current level estimate L (Rx(iso)'s mean): per
      channel group an offset ~ N(0, kappa_c sigma^2) (``channel_offset_db`` or ``receiver_offset_db``,
      plus the level's own variance: exact when b = 1, as if b = 1 for eq. 6), and the spread sigma^2
      itself unknown, scaled-inverse-chi^2 with ``prior_dof`` degrees of freedom about sigma_e^2
      (normal-inverse-gamma: Gelman et al., *Bayesian Data Analysis*, 3rd ed., Sec. 3.3). Each step's
      term is the change of that evidence, so a cell's terms add up to it. The sequential form (each
      packet scored once, against the level as it stood then) never revises a residual when Rx(iso)'s
      mean moves: on a recorded channel, whose level jumps 3-25 dB, its standing model named the Tx
      0.900 of the time on seed 1 where the same likelihood in one batch names it 0.955
      (docs/radio.md). With the spread unknown, packets spread wider than sigma_e lower every bearing
      alike instead of counting for the walking model. The walking model stays sequential (its level
      moves).
    * **Whole dBm.** Quantisation to a step q adds q^2 / 12 to the per-packet variance (a uniform
      rounding error, independent of the noise), rather than an interval likelihood: with
      sigma_e ~ 1.6 dB and q = 1 dB the two differ by under 1 % in log-likelihood.
    * **Fading over irregular times.** The per-packet noise is AR(1) in continuous time, lag
      correlation exp(-dt / tau); tau is estimated from consecutive Rx(iso) packets on one channel
      (Var(z_k - z_{k-1}) = 2 sigma_e^2 (1 - rho) at their mean gap). With ``temper_fading``
      packet k's term is tempered by (1 - rho_k) / (1 + rho_k), rho_k = exp(-dt_k / tau), dt_k
      the time since the previous Rx(dir) packet: the share of independent information it
      brings. Off by default: a walker's level changes read as correlation and the tempering
      then throws away most of the evidence (ble-dynamic, 100 tests: DR 0.66 / 0.45 with it,
      0.73 / 0.62 without, seeds 1 / 2).
    * **Innovation law.** ``packet_tail_dof`` (0: Gaussian, the built-in's) sets the packets' own,
      apart from the pair path's Student-t (``tail_dof``), once the walking model has its rate
      (``engage_rates``: people walk; always without a rate model): heavy tails bound what one packet can
      say, so when a walker starts to cross the packets that put it ahead of the estimate count as
      outliers and the estimate lags behind it (ble-dynamic, docs/radio.md).
    * sigma_e, the white per-packet spread, is the pooled within-channel spread of Rx(iso),
      shrunk to the learner's estimate with ``prior_dof`` pseudo-samples.
    * **Where to probe.** The probe pan is the one of largest predictive variance of the next
      Rx(dir) packet over the posterior of gamma (MacKay 1992, as the parent's), but the offset is
      unknown, not 0: given bearing gamma, the packets so far estimate it (the offset's posterior
      mean, per channel group, averaged by their counts), and the next packet's mean at pan s is
      a_s(gamma) + b_s(gamma) L + E[offset | packets, gamma]. At a pan where many packets were heard
      every bearing then predicts what was heard there, so another packet there says next to
      nothing about gamma; with the offset taken as 0 the variance is the same at every pan of a
      flat posterior and a probe could return to one pan for the whole test, its packets telling
      the offset but not the bearing (``ble-recorded``, docs/radio.md).
    * **A walking Tx between packets.** The walking model diffuses for every step of T_RF since
      its last update (k steps: the kernel's k-th power, k times the variance), not one.

    Parameters
    ----------
    channel_offset_db : float
        sigma_ch, the prior spread of a receiver's per-channel offset [dB].
    receiver_offset_db : float
        The same for packets that do not say their channel: one offset for all of Rx(dir)'s, the
        difference between two receivers' readings at one range (a recorded channel hears Rx(dir)
        through another receiver) [dB].
    rssi_step_db : float
        q, the receivers' RSSI step [dB] (1: whole dBm).
    prior_dof : float
        Pseudo-samples of the learner's noise estimate in sigma_e.
    temper_fading : bool
        Temper each packet's term by its AR(1) correlation with the previous one.
    batch_standing : bool
        The standing model's evidence in one batch at the current level (above); False: each
        packet scored once, sequentially, like the walking model.
    probe_offsets : bool
        The probe's predictive variance (``most_informative_pan``) reads each bearing's mean with
        Rx(dir)'s offset as its packets so far estimate it for that bearing (below); False: with
        the offset taken as known (0), as on the pair path.
    (others as ``RFBearingFilter``)
    """

    def __init__(self, circle: CircleGrid, response: RxDirModel, noise_db: float, rf_period_s: float,
                 walk_std_rad: float = math.radians(2.0), level_memory_s: float = 0.5, walk_prior: float = 0.3,
                 tail_dof: float | None = 4.0, channel_offset_db: float = 3.0, rssi_step_db: float = 1.0,
                 prior_dof: float = 5.0, receiver_offset_db: float = 8.0, temper_fading: bool = False,
                 walk_rate_std_rad_s: float = 0.0, walk_rate_change_rad_s: float = 0.2, walk_rate_cells: int = 21,
                 packet_tail_dof: float = -1.0, batch_standing: bool = False, probe_offsets: bool = False) -> None:
        super().__init__(circle, response, noise_db, rf_period_s, walk_std_rad, level_memory_s, walk_prior, tail_dof)
        # the packets' innovations: Student-t with this many degrees of freedom (negative: ``tail_dof``, 0: Gaussian)
        self.packet_tail_dof = tail_dof if packet_tail_dof < 0.0 else (float(packet_tail_dof) or None)
        self.rf_period_s = float(rf_period_s)
        self.level_memory_s = float(level_memory_s)
        self.offset_var = float(channel_offset_db) ** 2
        self.receiver_offset_var = float(receiver_offset_db) ** 2
        self.temper_fading = bool(temper_fading)
        self.quant_var = float(rssi_step_db) ** 2 / 12.0
        self.prior_dof = float(prior_dof)
        self.tau_s = 0.0  # fading correlation time, from Rx(iso)
        self.packets = 0  # Rx(iso) packets taken
        self._p_sum = 0.0
        self._iso_groups: dict[object, list[float]] = {}  # channel -> [n, sum, sum of squares]
        self._iso_last: tuple[float, float, object] | None = None  # (time, rssi, channel)
        self._pair_sq = self._pair_dt = 0.0  # consecutive same-channel Rx(iso) packets: squared differences, gaps
        self._pairs = 0
        self._walk_time: float | None = None
        self._dir_groups: dict[object, list] = {}  # channel -> [n, residual sums (standing), (walking)]
        self.batch_standing = bool(batch_standing)
        self.probe_offsets = bool(probe_offsets)
        # the standing model's batch (``batch_standing``): channel -> [n, sums over its Rx(dir) packets of (z - a),
        # (z - a)^2, b, b^2, (z - a) b per cell]; and the evidence as of the last update
        self._stand_groups: dict[object, list] = {}
        self._stand_evidence = np.zeros(circle.size)
        self._dir_last: float | None = None
        self._update_time: float | None = None  # when the bearing was last updated (its packets' mean time)
        # the walking Tx with a bearing rate (walk_rate_std_rad_s > 0): a grid over (rate, bearing), on packets, once
        # ``engage_rates`` is called (the built-ins: once the camera has seen someone walk)
        self._rates = self._rate_joint = self._rate_prior = None
        if walk_rate_std_rad_s > 0.0:
            top = 3.0 * float(walk_rate_std_rad_s)
            self._rates = np.linspace(-top, top, max(int(walk_rate_cells), 3))
            prior = np.exp(-0.5 * (self._rates / walk_rate_std_rad_s) ** 2)
            self._rate_prior = prior / prior.sum()
            self._rate_change = float(walk_rate_change_rad_s)
            self._walk_var_rad2 = float(walk_std_rad) ** 2
            self._freqs = np.fft.rfftfreq(circle.size)  # cycles per cell
            self._transitions: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def rates_engaged(self) -> bool:
        """Whether the walking model has a bearing rate now."""
        return self._rate_joint is not None

    def engage_rates(self) -> None:
        """From now on the walking model has a bearing rate (``walk_rate_std_rad_s`` > 0; else
        nothing changes): the walker's posterior of gamma so far times the rates' prior."""
        if self._rates is None or self._rate_joint is not None:
            return
        post = np.exp(self._walk - self._walk.max())
        self._rate_joint = self._rate_prior[:, None] * (post / post.sum())[None, :]

    # -- Rx(iso) ----------------------------------------------------------------------------------
    def white_var(self) -> float:
        """sigma_e^2: the pooled within-channel variance of Rx(iso)'s packets, shrunk to the
        learner's, plus the rounding's q^2 / 12."""
        ss, df = 0.0, 0
        for n, total, sq in self._iso_groups.values():
            if n > 1:
                ss += max(sq - total * total / n, 0.0)
                df += int(n) - 1
        return (self.prior_dof * self.noise_var + ss) / (self.prior_dof + df) + self.quant_var

    def _iso_offset(self, channel: object) -> float:
        """Rx(iso)'s offset on ``channel``: its packets' mean less the overall mean, shrunk."""
        n, total, _ = self._iso_groups.get(channel, (0, 0.0, 0.0))
        if not n or self.offset_var <= 0.0:
            return 0.0
        mean = self._p_sum / self.packets
        return (total - n * mean) / (n + self.white_var() / self.offset_var)

    def _take_iso(self, time_s: float, z: float, channel: object) -> None:
        self.packets += 1
        self._p_sum += z
        group = self._iso_groups.setdefault(channel, [0, 0.0, 0.0])
        group[0] += 1
        group[1] += z
        group[2] += z * z
        last = self._iso_last
        if last is not None and last[2] == channel and time_s > last[0]:
            self._pair_sq += (z - last[1]) ** 2
            self._pair_dt += time_s - last[0]
            self._pairs += 1
        self._iso_last = (time_s, z, channel)
        level = z - self._iso_offset(channel)
        if self._walk_time is None:
            self._level_walk = level
        else:
            lam = math.exp(-max(time_s - self._walk_time, 0.0) / self.level_memory_s)
            self._level_walk = lam * self._level_walk + (1.0 - lam) * level
        self._walk_time = time_s
        if self._pairs >= 8:
            rho = 1.0 - (self._pair_sq / self._pairs) / (2.0 * self.white_var())
            rho = min(max(rho, 0.0), 0.95)
            self.tau_s = -(self._pair_dt / self._pairs) / math.log(rho) if rho > 0.0 else 0.0

    def _level_now(self, walking: bool) -> float:
        if not self.packets:
            return super()._level_now(walking)
        return self._level_walk if walking else self._p_sum / self.packets

    def _offset_prior_var(self, channel: object) -> float:
        """Prior variance of Rx(dir)'s offset on ``channel``: sigma_ch^2, or ``receiver_offset_db``^2 for
        packets that do not say their channel."""
        return self.offset_var if channel is not None else self.receiver_offset_var

    def _packet_level_var(self, walking: bool, white: float) -> float:
        if walking:
            lam = math.exp(-self._pair_dt / self._pairs / self.level_memory_s) if self._pairs else 0.5
            return min(white * (1.0 - lam) / (1.0 + lam), white)
        return min(white / max(self.packets, 1), white)

    # -- a step's packets ---------------------------------------------------------------------------
    def add_packets(self, pan_rad: float, iso: list[tuple[float, float, object]], dir_: list[tuple[float, float, object]]) -> bool:
        """Take one step's packets: ``iso`` and ``dir_`` lists of (time [s], RSSI [dBm], channel or
        None), the pan they were heard at. Returns whether the bearing was updated (a Rx(dir) packet
        and a level to read it against)."""
        for time_s, z, channel in sorted(iso, key=lambda p: p[0]):
            self._take_iso(time_s, z, channel)
        if not dir_ or not self.packets:
            return False
        self.n += 1
        white = self.white_var()
        resp = self.response
        gain = resp.gain_over(pan_rad, self.circle)
        slope = resp.level_slope(gain)
        slope2 = slope * slope  # (in every packet's variance)
        level = self._level_now(False)
        means = (resp.mean(level, gain), resp.mean(self._level_walk, gain))
        level_vars = (self._packet_level_var(False, white), self._packet_level_var(True, white))
        total = [np.zeros(self.circle.size), np.zeros(self.circle.size)]
        models = (1,) if self.batch_standing else (0, 1)  # the standing model's term is then the batch's (below)
        for time_s, z, channel in sorted(dir_, key=lambda p: p[0]):
            rho = 0.0
            if self.temper_fading and self.tau_s > 0.0 and self._dir_last is not None:
                rho = math.exp(-max(time_s - self._dir_last, 0.0) / self.tau_s)
            self._dir_last = time_s
            weight = (1.0 - rho) / (1.0 + rho)
            group = self._dir_groups.get(channel)
            if group is None:
                group = self._dir_groups[channel] = [0, np.zeros(self.circle.size), np.zeros(self.circle.size)]
            n_c = group[0]
            prior_var = self._offset_prior_var(channel)
            if prior_var > 0.0:
                shrink = prior_var / (white + n_c * prior_var)
                offset_var = white * shrink
            else:
                shrink = offset_var = 0.0
            for j in models:
                resid = z - means[j]
                pred = resid - shrink * group[1 + j]
                var = white + offset_var + slope2 * level_vars[j]
                total[j] += weight * self._packet_loglik(pred, var)
                group[1 + j] += resid
            group[0] = n_c + 1
        if self.batch_standing:
            total[0] = self._standing_batch_term(dir_, gain, white, level, level_vars[0])
        now = sum(p[0] for p in dir_) / len(dir_)
        steps = 1 if self._update_time is None else max(int(round((now - self._update_time) / self.rf_period_s)), 1)
        self._update_time = now
        if self._rate_joint is not None:
            self._absorb_rates(total[0], total[1], steps * self.rf_period_s)
        else:
            self._absorb(total[0], total[1], steps)  # the walker moved for every step since the last update
        return True

    def _standing_batch_term(self, dir_: list[tuple[float, float, object]], gain: np.ndarray, white: float, level: float,
                             level_var: float) -> np.ndarray:
        """The standing model's term for this step's Rx(dir) packets (``batch_standing``): the batch
        evidence of every Rx(dir) packet so far at the current level, less the evidence as of the
        last update.

        With L = ``level`` (Rx(iso)'s mean) and Var L = ``level_var`` (sigma_e^2 / its packets), packet k's residual
        r_k = z_k - a_k - b_k L; per channel group c (n_c packets) an offset ~ N(0, kappa_c sigma^2),
        kappa_c = (sigma_c^2 + Var L) / sigma_e^2, the spread sigma^2 ~ scaled-inv-chi^2(nu0 = prior_dof,
        sigma_e^2); with RSS = sum_c [sum r^2 - (sum r)^2 kappa_c / (1 + n_c kappa_c)] over n packets,
        log p = lgamma((nu0 + n) / 2) - lgamma(nu0 / 2) - (n / 2) log pi + (nu0 / 2) log(nu0 sigma_e^2)
        - ((nu0 + n) / 2) log(nu0 sigma_e^2 + RSS) - sum_c log(1 + n_c kappa_c) / 2
        (the normal-inverse-gamma marginal; Gelman et al., BDA 3rd ed., Sec. 3.3)."""
        resp = self.response
        a = resp.mean(0.0, gain)
        b = resp.level_slope(gain)
        for _time, z, channel in dir_:
            group = self._stand_groups.get(channel)
            if group is None:
                group = self._stand_groups[channel] = [0, np.zeros((5, self.circle.size))]
            x = z - a
            sums = group[1]
            sums[0] += x
            sums[1] += x * x
            sums[2] += b
            sums[3] += b * b
            sums[4] += x * b
            group[0] += 1
        nu0 = self.prior_dof
        rss = np.zeros(self.circle.size)
        evidence = np.zeros(self.circle.size)
        n_total = 0
        for n, sums, kappa, r1 in self._batch_groups(white, level, level_var):
            r2 = sums[1] - 2.0 * level * sums[4] + level * level * sums[3]
            rss += r2 - r1 * r1 * (kappa / (1.0 + n * kappa))
            evidence -= 0.5 * math.log1p(n * kappa)
            n_total += n
        prior = nu0 * white
        evidence += (math.lgamma(0.5 * (nu0 + n_total)) - math.lgamma(0.5 * nu0) - 0.5 * n_total * math.log(math.pi)
                     + 0.5 * nu0 * math.log(prior)) - 0.5 * (nu0 + n_total) * np.log(prior + np.maximum(rss, 0.0))
        term = evidence - self._stand_evidence
        self._stand_evidence = evidence
        return term

    def _probe_offset(self, walking: bool) -> np.ndarray | None:
        """``most_informative_pan`` reads each bearing's mean with Rx(dir)'s offset as the packets so
        far estimate it for that bearing (``probe_offsets``; ``_offset_estimate``). Before a Rx(dir)
        packet, or on the 1.0 pair: the parent's (0)."""
        if not self.probe_offsets or not self._dir_groups:
            return None
        return self._offset_estimate(walking)

    def _offset_estimate(self, walking: bool) -> np.ndarray:
        """E[Rx(dir)'s offset | its packets so far, gamma] per cell: per channel group c the
        posterior mean of a Gaussian random effect, sum_k r_k(gamma) kappa_c / (1 + n_c kappa_c)
        (r_k packet k's residual given gamma; kappa_c the offset's prior variance over the packet
        spread), averaged over the groups by their packets (the next packet's channel is not known).
        The standing model's from its batch (``batch_standing``) at the current level, the walking
        model's from its sequential residuals."""
        white = self.white_var()
        out = np.zeros(self.circle.size)
        total = 0
        if self.batch_standing and not walking:
            for n, _sums, kappa, r1 in self._batch_groups(white, self._level_now(False), self._packet_level_var(False, white)):
                out += r1 * (n * kappa / (1.0 + n * kappa))
                total += n
        else:
            j = 2 if walking else 1
            for channel, group in self._dir_groups.items():
                n, prior_var = group[0], self._offset_prior_var(channel)
                if prior_var > 0.0:
                    out += group[j] * (n * prior_var / (white + n * prior_var))
                total += n
        return out / max(total, 1)

    def _batch_groups(self, white: float, level: float, level_var: float):
        """Per channel group of the standing model's batch at level L = ``level``: (n, its sums,
        kappa_c = (offset prior variance + Var L) / sigma_e^2, sum_k r_k = sum (z_k - a_k) - L sum b_k)."""
        for channel, (n, sums) in self._stand_groups.items():
            yield n, sums, (self._offset_prior_var(channel) + level_var) / white, sums[0] - level * sums[2]

    def standing_batch_evidence(self) -> np.ndarray:
        """log p(Rx(dir)'s packets so far | the Tx stands at each cell), as of the last update
        (``batch_standing``; zeros before a packet), read-only."""
        evidence = self._stand_evidence.view()
        evidence.flags.writeable = False
        return evidence

    def _predict_rates(self, joint: np.ndarray, dt: float) -> np.ndarray:
        """The (rates x grid) walking state ``joint`` predicted over dt [s]: each rate's row shifted
        by omega dt (a phase shift of its FFT) and spread by the random walk (``walk_std_rad`` per
        T_RF), then the rates mixed (omega changes by N(0, change^2 dt)); normalised."""
        if dt <= 0.0:
            return joint
        phase, mix = self._rate_transition(dt)
        moved = np.maximum(np.fft.irfft(np.fft.rfft(joint, axis=1) * phase, n=self.circle.size, axis=1), 0.0)
        predicted = mix @ moved
        return predicted / predicted.sum()

    def _rate_transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(the rows' FFT multipliers, the rates' mixing matrix) over dt, kept per dt (packets come
        a whole number of steps apart: a few values per episode)."""
        key = round(dt, 9)
        cached = self._transitions.get(key)
        if cached is not None:
            return cached
        step = self.circle.step
        shift = self._rates * dt / step  # cells each rate moves in dt
        cells_var = self._walk_var_rad2 * (dt / self.rf_period_s) / step**2
        diffusion = np.exp(-2.0 * (math.pi * self._freqs) ** 2 * cells_var)
        phase = np.exp(-2j * math.pi * shift[:, None] * self._freqs[None, :]) * diffusion[None, :]
        d = self._rates[:, None] - self._rates[None, :]
        mix = np.exp(-0.5 * d * d / max(self._rate_change**2 * dt, 1e-12))
        mix /= mix.sum(axis=0, keepdims=True)
        if len(self._transitions) < 64:
            self._transitions[key] = (phase, mix)
        return phase, mix

    def _absorb_rates(self, ll_stand: np.ndarray, ll_walk: np.ndarray, dt: float) -> None:
        """``_absorb`` with a walker whose bearing has a rate: the walking model's state is
        (omega, gamma) on (rates x grid); over dt, gamma moves by omega dt plus a random walk,
        omega by N(0, change^2 dt) (a person turns, their range changes): ``_predict_rates``. The
        update multiplies every rate's row by the packet likelihood over gamma; ``_walk`` stays
        the log posterior of gamma (summed over omega), so everything that reads the walking
        model is unchanged."""
        predicted = self._predict_rates(self._rate_joint, dt)
        top = ll_walk.max()
        post = predicted * np.exp(ll_walk - top)[None, :]
        c = float(post.sum())
        log_c = top + math.log(max(c, 1e-300))
        self._rate_joint = post / c
        self._walk = np.log(np.maximum(self._rate_joint.sum(axis=0), 1e-300))
        self.ll_stand = ll_stand - log_c
        self.ll_walk = ll_walk - log_c
        self._static += self.ll_stand

    def _packet_loglik(self, resid: np.ndarray, var: np.ndarray) -> np.ndarray:
        nu = self.packet_tail_dof if self._rate_joint is not None or self._rates is None else self.tail_dof
        if nu is None:
            return -0.5 * (resid * resid / var + np.log(2.0 * math.pi * var))
        return -0.5 * (nu + 1.0) * np.log1p(resid * resid / (nu * var)) - 0.5 * np.log(var) + _t_const(nu)


@functools.lru_cache(maxsize=64)
def _t_const(nu: float) -> float:
    return math.lgamma(0.5 * (nu + 1.0)) - math.lgamma(0.5 * nu) - 0.5 * math.log(nu * math.pi)


def logsumexp(values: np.ndarray) -> float:
    """log(sum(exp(values))) without overflow."""
    top = float(values.max())
    return top + math.log(float(np.exp(values - top).sum()))


def _logsumexp_list(values: list[float]) -> float:
    if not values:
        return -1e300
    top = max(values)
    return top + math.log(sum(math.exp(v - top) for v in values))
