"""Gaussian-process regression over the pan angle, on the circle, with an explicit lobe basis.

Rx(dir)'s RSSI as a function of the pan angle s is modelled as

    z(s) = c + A h(s - gamma) + f(s) + e,      f ~ GP(0, k),  e ~ N(0, sigma^2),

where e is the RSSI noise, white or AR(1) in time (Cov(e_t, e_u) = sigma^2 rho^|t - u|,
``noise_correlation``: fading correlated over successive samples), h(d) = exp(-2 sin^2(d/2) / w^2) is a generic lobe (no knowledge of the true antenna
pattern beyond "one main lobe aligned with the camera axis"), gamma is the lobe centre, i.e.
the Tx bearing, and f is a residual GP whose kernel is the squared exponential of the chordal
distance,

    k(s, s') = sf2 exp(-|e^{is} - e^{is'}|^2 / (2 l^2)) = sf2 exp(-2 sin^2((s - s')/2) / l^2),

scikit-learn's ``ExpSineSquared`` with period 2 pi: -pi and pi are the same point (a
kernel on the raw angle would put them 2 pi apart). For each candidate centre gamma on a grid,
(c, A) have the generalised-least-squares solution of a GP with explicit basis functions
(Rasmussen & Williams 2006, Sec. 2.7), and the profile log-likelihood -q(gamma)/2 scores gamma. Everything is kept incrementally: a new
sample appends one row to the Cholesky factor and to L^{-1}[K(X, grid), H(X, grid)], so a
control step costs O(n M) for n samples and M grid points, never an O(n^3) refit.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.grid import CircleGrid


def circular_kernel(a: np.ndarray, b: np.ndarray, length_scale: float, signal_var: float = 1.0) -> np.ndarray:
    """k(a_i, b_j) for angle arrays ``a`` (n,) and ``b`` (m,); returns (n, m)."""
    s = np.sin(0.5 * (np.asarray(a, dtype=float)[:, None] - np.asarray(b, dtype=float)[None, :]))
    return signal_var * np.exp(-2.0 * s * s / (length_scale * length_scale))


class LobeGP:
    """Incremental GP over pan angles with an explicit lobe basis, evaluated on ``grid``.

    Parameters
    ----------
    grid : ndarray of shape (M,)
        Pan angles (and candidate lobe centres) where everything is evaluated.
    noise_var : float
        sigma^2, RSSI noise variance [dB^2].
    lobe_width : float
        w of the lobe template h [rad].
    lobe_sign : {+1, -1}
        Sign A must have: +1 when a stronger signal reads higher (dB gain), -1 for the
        paper's model where |z| grows with alignment of a negative dBm value.
    residual_length_scale, residual_var : float
        l and sf2 of the residual GP f.
    capacity : int
        Largest number of samples.
    noise_correlation : float
        rho of AR(1) noise between successive samples (0: white); ``set_noise_correlation``
        changes it later (the samples are refitted).
    """

    def __init__(self, grid: "np.ndarray | CircleGrid", noise_var: float, lobe_width: float, lobe_sign: int,
                 residual_length_scale: float, residual_var: float, capacity: int, noise_correlation: float = 0.0) -> None:
        if not isinstance(grid, CircleGrid):
            angles = np.asarray(grid, dtype=float)
            grid = CircleGrid(angles.size)
            if not np.allclose(grid.angles, angles, atol=1e-9):
                raise ValueError("LobeGP needs the uniform grid -pi + 2 pi k / M (np.linspace(-pi, pi, M, endpoint=False))")
        self.circle = grid
        self.grid = grid.angles
        self.noise_var = float(noise_var)
        self.lobe_width = float(lobe_width)
        self.lobe_sign = 1 if lobe_sign >= 0 else -1
        self.residual_length_scale = float(residual_length_scale)
        self.residual_var = float(residual_var)
        self.capacity = int(capacity)
        self.noise_correlation = float(noise_correlation)
        self._reset()

    def _reset(self) -> None:
        M = self.grid.size
        self.n_ = 0
        self._allocate(min(self.capacity, 128))
        self._res_var = np.full(M, self.residual_var)
        self._hh = np.zeros(M)
        self._ho = np.zeros(M)
        self._hu = np.zeros(M)
        self._oo = self._ou = self._uu = 0.0

    def _allocate(self, size: int) -> None:
        """(Re)allocate storage for ``size`` samples, keeping the first ``n_`` (memory grows with
        the samples actually taken, not with the largest test allowed)."""
        M, n = self.grid.size, self.n_
        old = getattr(self, "_Li", None)
        x, z, Li, V, H, o, u = (np.empty(size), np.empty(size), np.zeros((size, size)), np.zeros((size, M)), np.zeros((size, M)),
                                np.zeros(size), np.zeros(size))
        if old is not None and n:
            x[:n], z[:n], Li[:n, :n], V[:n], H[:n], o[:n], u[:n] = (self.x_[:n], self.z_[:n], self._Li[:n, :n], self._V[:n], self._H[:n],
                                                                    self._o[:n], self._u[:n])
        # samples, L^{-1}, L^{-1}k(X,grid), L^{-1}h(X-grid), L^{-1}1, L^{-1}z
        self.x_, self.z_, self._Li, self._V, self._H, self._o, self._u = x, z, Li, V, H, o, u

    def set_noise_correlation(self, rho: float) -> None:
        """Make the noise AR(1) with lag-1 correlation ``rho`` and refit the samples taken so far
        (O(n^2 M), so callers change it rarely, e.g. in steps of 0.05)."""
        rho = float(rho)
        if rho == self.noise_correlation:
            return
        x, z = self.x_[:self.n_].copy(), self.z_[:self.n_].copy()
        self.noise_correlation = rho
        self._reset()
        for s_i, z_i in zip(x, z):
            self.add(float(s_i), float(z_i))

    def add(self, s: float, z: float) -> None:
        """Add the sample z (dBm) taken at pan angle s (rad). O(n M).

        With K = L L^T, the new row of L is (ell^T, d), ell = L^{-1} k(X, s),
        d^2 = k(s, s) + sigma^2 - ell^T ell, and the new row of L^{-1} is
        (-ell^T L^{-1} / d, 1 / d); every matrix kept as L^{-1} M gains the row
        (m(s) - ell^T L^{-1} M) / d.
        """
        n = self.n_
        if n >= self.capacity:
            raise ValueError(f"LobeGP holds at most {self.capacity} samples")
        if n >= self.x_.size:
            self._allocate(min(self.capacity, 2 * self.x_.size))
        k_grid = self.circle.kernel_row(s, self.residual_length_scale, self.residual_var)
        h_grid = self.circle.kernel_row(s, self.lobe_width)
        d2 = self.residual_var + self.noise_var
        if n:
            half = np.sin(0.5 * (self.x_[:n] - s))
            k_old = self.residual_var * np.exp(-2.0 * half * half / (self.residual_length_scale**2))
            if self.noise_correlation:  # AR(1) noise: Cov(e_n, e_i) = sigma^2 rho^(n - i)
                k_old += self.noise_var * self.noise_correlation ** np.arange(n, 0, -1, dtype=float)
            Li = self._Li[:n, :n]
            ell = Li @ k_old
            d2 -= ell @ ell
            v = k_grid - ell @ self._V[:n]
            h = h_grid - ell @ self._H[:n]
            o = 1.0 - ell @ self._o[:n]
            u = z - ell @ self._u[:n]
        else:
            v, h, o, u = k_grid, h_grid, 1.0, z
        d = math.sqrt(max(d2, 1e-12))
        if n:
            self._Li[n, :n] = -(ell @ Li) / d
        self._Li[n, n] = 1.0 / d
        v, h, o, u = v / d, h / d, o / d, u / d
        self._V[n], self._H[n], self._o[n], self._u[n] = v, h, o, u
        self._res_var -= v * v
        self._hh += h * h
        self._ho += o * h
        self._hu += u * h
        self._oo += o * o
        self._ou += o * u
        self._uu += u * u
        self.x_[n] = s
        self.z_[n] = z
        self.n_ = n + 1

    def extend(self, xs, zs) -> None:
        """Add the samples ``zs`` taken at pans ``xs``, in order: ``add`` one by one, or, into a
        GP that holds none yet, the same fit in one pass of matrix products, O(n^2 M) (K = L L^T
        at once and every row of L^{-1} k(X, grid), L^{-1} h(X - grid), L^{-1} 1, L^{-1} z;
        equal up to rounding, ~10x faster than n calls of ``add``)."""
        xs, zs = np.asarray(xs, dtype=float), np.asarray(zs, dtype=float)
        n = xs.size
        if self.n_ or n < 2 or n > self.capacity:
            for s, z in zip(xs.tolist(), zs.tolist()):
                self.add(s, z)
            return
        half = np.sin(0.5 * (xs[:, None] - xs[None, :]))
        K = self.residual_var * np.exp(-2.0 * half * half / (self.residual_length_scale**2))
        lag = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
        K += self.noise_var * (self.noise_correlation**lag if self.noise_correlation else np.eye(n))
        try:
            Li = np.tril(np.linalg.solve(np.linalg.cholesky(K), np.eye(n)))
        except np.linalg.LinAlgError:  # not positive definite in floating point: add's guarded rows
            for s, z in zip(xs.tolist(), zs.tolist()):
                self.add(s, z)
            return
        if n > self.x_.size:
            self._allocate(min(self.capacity, max(n, 2 * self.x_.size)))
        pans = xs.tolist()  # the rows ``add`` would take (a pan on the grid: a view of one cached row)
        V = Li @ np.array([self.circle.kernel_row(s, self.residual_length_scale, self.residual_var) for s in pans])
        H = Li @ np.array([self.circle.kernel_row(s, self.lobe_width) for s in pans])
        o, u = Li.sum(axis=1), Li @ zs
        self.x_[:n], self.z_[:n], self._Li[:n, :n], self._V[:n], self._H[:n], self._o[:n], self._u[:n] = xs, zs, Li, V, H, o, u
        self._res_var = self.residual_var - np.einsum("ij,ij->j", V, V)
        self._hh, self._ho, self._hu = np.einsum("ij,ij->j", H, H), o @ H, u @ H
        self._oo, self._ou, self._uu = float(o @ o), float(o @ u), float(u @ u)
        self.n_ = n

    def lobe_fit(self, sign: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every grid centre gamma: profile log-likelihood -q(gamma)/2, amplitude A, offset c.

        ``sign`` overrides ``lobe_sign`` for this call (the statistics do not depend on it: the
        opposite orientation's fit costs one more O(M) profile).

        (A, c) solve [[h.h, h.o], [h.o, o.o]] (A, c) = (h.u, o.u) with h = L^{-1} h(X - gamma),
        o = L^{-1} 1, u = L^{-1} z, and q = u.u - A h.u - c o.u. Centres whose best amplitude
        has the wrong sign get the likelihood of "no lobe".
        """
        M = self.grid.size
        if self.n_ == 0:
            return np.zeros(M), np.zeros(M), np.zeros(M)
        loglik, A, c = np.empty(M), np.empty(M), np.empty(M)
        best = _kernels.lobe_profile(self._hh, self._ho, self._hu, self._oo, self._ou, self._uu,
                                     float(self.lobe_sign if sign is None else (1 if sign >= 0 else -1)), loglik, A, c)
        if sign is None:
            self.best_ = best
        return loglik, A, c

    def posterior(self, centre_index: int, A: float, c: float) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean and standard deviation of z on the grid, given the lobe (gamma, A, c).

        mu = c + A h(s - gamma) + k(s, X) K^{-1} (z - c - A h(X - gamma)) (eq. 17 with an explicit mean).
        """
        mean = c + A * self.circle.kernel_row(float(self.grid[centre_index]), self.lobe_width)
        n = self.n_
        if n:
            r = self._u[:n] - c * self._o[:n] - A * self._H[:n, centre_index]
            mean = mean + r @ self._V[:n]
        return mean, np.sqrt(np.maximum(self._res_var, 0.0) + 1e-12)

    def mean_at(self, s: float, centre_index: int, A: float, c: float) -> float:
        """Posterior mean of z at one pan angle ``s`` (O(n^2), compiled), given the lobe (gamma, A, c)."""
        n = self.n_
        return float(_kernels.lobe_mean_at(s, self.x_[:n], self._Li[:n, :n], self._u[:n], self._o[:n],
                                           np.ascontiguousarray(self._H[:n, centre_index]), float(self.grid[centre_index]),
                                           A, c, self.lobe_width, self.residual_length_scale, self.residual_var))


class RecentLobe:
    """Rx(dir)'s lobe fitted to recent samples only: for a Tx that walks.

    The same model as ``LobeGP`` without the residual GP (white noise), each sample weighted by
    lambda^(age) with lambda = exp(-T_RF / tau): recursive weighted least squares with a
    forgetting factor (Ljung & Soederstroem 1983), kept as discounted sufficient statistics per
    candidate centre on the grid, so a step costs O(M). The profile log-likelihood over the
    centre then says where the Tx is *now*, not where it was on average.
    """

    def __init__(self, grid: CircleGrid, noise_var: float, lobe_width: float, lobe_sign: int, memory_s: float,
                 rf_period_s: float) -> None:
        self.circle = grid
        self.noise_var = float(noise_var)
        self.lobe_width = float(lobe_width)
        self.lobe_sign = 1 if lobe_sign >= 0 else -1
        self.forget = math.exp(-rf_period_s / memory_s)
        M = grid.size
        self._hh, self._h, self._hz = np.zeros(M), np.zeros(M), np.zeros(M)
        self._w = self._z = self._zz = 0.0
        # the recent samples (weights beyond exp(-6) dropped), to start a new track's statistics
        self._recent: deque = deque(maxlen=max(1, int(math.ceil(6.0 * memory_s / rf_period_s))))
        self._stats = np.zeros((0, 3))  # per followed track: discounted (sum h^2, sum h, sum h z)
        self._rows: dict[int, int] = {}  # track id -> row of _stats

    def add(self, s: float, z: float) -> None:
        """Add the sample z taken at pan s; older samples weigh lambda less each step. O(M)."""
        lam = self.forget
        h = self.circle.kernel_row(s, self.lobe_width)
        self._hh *= lam
        self._hh += h * h
        self._h *= lam
        self._h += h
        self._hz *= lam
        self._hz += h * z
        self._w = lam * self._w + 1.0
        self._z = lam * self._z + z
        self._zz = lam * self._zz + z * z
        self._recent.append((s, z))

    def follow(self, ids, bearings) -> None:
        """Update, after ``add``, the statistics of "the lobe follows track id": its centre was the
        track's bearing when each sample was taken (a track met for the first time is taken to
        have stood where it is over the recent samples). Tracks no longer listed are forgotten."""
        lam = self.forget
        s, z = self._recent[-1]
        g = np.asarray(bearings, dtype=float)
        inv_w2 = 1.0 / (self.lobe_width * self.lobe_width)
        a = np.sin(0.5 * (s - g))
        h = np.exp(-2.0 * a * a * inv_w2)
        rows = np.fromiter((self._rows.get(tid, -1) for tid in ids), dtype=np.int64, count=len(ids))
        stats = np.empty((len(ids), 3))
        old = rows >= 0
        stats[old] = lam * self._stats[rows[old]] + np.stack([h[old] * h[old], h[old], h[old] * z], axis=1)
        self._backfill(ids, g, rows, stats)

    def follow_tracks(self, ids, bearings) -> None:
        """``follow`` for a step without a sample: the tracks followed so far keep their
        statistics, a new one is backfilled over the recent samples, the others are forgotten."""
        rows = np.fromiter((self._rows.get(tid, -1) for tid in ids), dtype=np.int64, count=len(ids))
        stats = np.empty((len(ids), 3))
        old = rows >= 0
        stats[old] = self._stats[rows[old]]
        self._backfill(ids, np.asarray(bearings, dtype=float), rows, stats)

    def _backfill(self, ids, g: np.ndarray, rows: np.ndarray, stats: np.ndarray) -> None:
        new = np.flatnonzero(rows < 0)
        if new.size:  # backfill over the recent samples, newest first
            past = np.asarray(self._recent, dtype=float).reshape(-1, 2)[::-1]  # (R, 2): pan, z
            w = self.forget ** np.arange(past.shape[0])
            ah = np.sin(0.5 * (past[:, 0][:, None] - g[new][None, :]))
            hh = np.exp(-2.0 * ah * ah * (1.0 / (self.lobe_width * self.lobe_width)))  # (R, len(new))
            stats[new] = np.stack([w @ (hh * hh), w @ hh, (w * past[:, 1]) @ hh], axis=1)
        self._stats = stats
        self._rows = {tid: j for j, tid in enumerate(ids)}

    def follow_profile(self, ids) -> np.ndarray:
        """Profile log-likelihood of "the lobe followed track id" for each id (see ``follow``)."""
        stats = self._stats[[self._rows[tid] for tid in ids]].reshape(-1, 3)
        n = stats.shape[0]
        loglik, A, c = np.empty(n), np.empty(n), np.empty(n)
        if n:
            inv = 1.0 / self.noise_var
            _kernels.lobe_profile(stats[:, 0] * inv, stats[:, 1] * inv, stats[:, 2] * inv, self._w * inv, self._z * inv,
                                  self._zz * inv, float(self.lobe_sign), loglik, A, c)
        return loglik

    def profile(self) -> np.ndarray:
        """Profile log-likelihood over the grid of lobe centres (white noise of ``noise_var``);
        the best fit's centre index, amplitude and offset are kept in ``best_``."""
        M = self.circle.size
        loglik, A, c = np.empty(M), np.empty(M), np.empty(M)
        inv = 1.0 / self.noise_var
        j = _kernels.lobe_profile(self._hh * inv, self._h * inv, self._hz * inv, self._w * inv, self._z * inv, self._zz * inv,
                                  float(self.lobe_sign), loglik, A, c)
        self.best_ = (int(j), float(A[j]), float(c[j]))
        return loglik

    def mean(self) -> np.ndarray:
        """The best recent lobe over the grid of pans, c + A h(s - gamma)."""
        j, A, c = self.best_
        return c + A * self.circle.kernel_row(float(self.circle.angles[j]), self.lobe_width)
