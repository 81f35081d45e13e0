"""The physical model of the simulated world (paper, Sec. II and Table I).

Pure functions of numpy arrays. These are the *truth* the simulator draws from; the
controller and the learner never call them.
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.scenario import AntennaModel, Scenario


def path_loss_dbm(sc: Scenario, distance_m: np.ndarray | float) -> np.ndarray:
    """g(d) = kappa - 10 n log10(d / delta), the log-distance path loss (eq. 5, Table I)."""
    d = np.maximum(np.asarray(distance_m, dtype=float), 1e-6)
    return sc.path_loss_ref_dbm - 10.0 * sc.path_loss_exponent * np.log10(d / sc.path_loss_ref_distance_m)


def range_from_rssi(sc: Scenario, rssi_dbm: np.ndarray | float) -> np.ndarray:
    """g^{-1}(r): the range at which the noiseless RSSI equals ``rssi_dbm``."""
    r = np.asarray(rssi_dbm, dtype=float)
    return sc.path_loss_ref_distance_m * 10.0 ** ((sc.path_loss_ref_dbm - r) / (10.0 * sc.path_loss_exponent))


def attenuation(sc: Scenario, misalignment_rad: np.ndarray | float) -> np.ndarray:
    """rho(s, gamma) = 1 - a * Delta^2 with Delta = wrap(s - gamma), clipped to [0, 1] (eq. 6)."""
    delta = wrap(misalignment_rad)
    return np.clip(1.0 - sc.antenna_curvature * delta * delta, 0.0, 1.0)


def directional_rssi_dbm(sc: Scenario, distance_m: float, misalignment_rad: np.ndarray | float) -> np.ndarray:
    """Noiseless RSSI at Rx(dir).

    ``paper``: g(d) * rho (eq. 6, a dBm value scaled by the attenuation factor).
    ``db-gain``: g(d) + 10 log10(max(rho, 10^(floor/10))), an antenna gain in dB.
    """
    rho = attenuation(sc, misalignment_rad)
    g = path_loss_dbm(sc, distance_m)
    if sc.antenna_model is AntennaModel.paper:
        return g * rho
    floor = 10.0 ** (sc.antenna_floor_db / 10.0)
    return g + 10.0 * np.log10(np.maximum(rho, floor))


def directional_rssi_scalar(sc: Scenario, path_loss: float, misalignment_rad: float) -> float:
    """``directional_rssi_dbm`` for one pan angle, given g(d) already computed (the hot path
    of the simulator; a test checks it equals the array version)."""
    delta = (misalignment_rad + math.pi) % (2.0 * math.pi) - math.pi
    rho = min(max(1.0 - sc.antenna_curvature * delta * delta, 0.0), 1.0)
    if sc.antenna_model is AntennaModel.paper:
        return path_loss * rho
    return path_loss + 10.0 * math.log10(max(rho, 10.0 ** (sc.antenna_floor_db / 10.0)))


def pod(sc: Scenario, distance_m: np.ndarray | float) -> np.ndarray:
    """p_D(d) = [(1 + e^{4(d-4.5)}) (1 + e^{-(d-2.5)})]^{-1} (eq. 22), parameterised."""
    d = np.asarray(distance_m, dtype=float)
    far = 1.0 + np.exp(np.clip(sc.pod_far_slope * (d - sc.pod_far_range_m), -700, 700))
    near = 1.0 + np.exp(np.clip(-sc.pod_near_slope * (d - sc.pod_near_range_m), -700, 700))
    return 1.0 / (far * near)


def pod_of_rssi(sc: Scenario, rssi_dbm: np.ndarray | float) -> np.ndarray:
    """The true POD as a function of the noiseless iso RSSI, p_D(g^{-1}(r)) (Sec. III-A)."""
    return pod(sc, range_from_rssi(sc, rssi_dbm))


# -- a cluttered, dynamic world (beyond the paper; issue 9) -------------------------------------


def angular_half_width(body_width_m: float, distance_m: np.ndarray | float) -> np.ndarray:
    """Half the angle a disc of diameter ``body_width_m`` subtends at range d:
    asin(min(1, (w/2) / d)) (pi/2 when the platform is inside the disc)."""
    d = np.maximum(np.asarray(distance_m, dtype=float), 1e-12)
    return np.arcsin(np.minimum(1.0, 0.5 * body_width_m / d))


_OCCLUSION_CHUNK = 2_000_000  # pairwise elements per block: bounds the memory of ``occluded``


def occluded(body_width_m: float, bearings_rad: np.ndarray, ranges_m: np.ndarray) -> np.ndarray:
    """Which targets the camera cannot see because a nearer one hides them.

    Every target is a disc of diameter ``body_width_m``; target i subtends the arc
    [gamma_i - alpha_i, gamma_i + alpha_i], alpha_i = asin(min(1, (w/2)/d_i)). It is occluded
    when a *nearer* target j (d_j < d_i) covers more than half of that arc: the LOS condition
    of eq. 10 fails for it. A nearer disc subtends a wider arc (alpha_j >= alpha_i), and then
    "more than half of i's arc is covered by j's" is exactly "j's arc contains i's centre",
    |wrap(gamma_i - gamma_j)| < alpha_j, which is what is computed.

    Parameters
    ----------
    bearings_rad, ranges_m : arrays of shape (..., N)
        One layout per leading index (e.g. per step).

    Returns
    -------
    ndarray of bool, shape (..., N)
    """
    b = wrap(np.asarray(bearings_rad, dtype=float))
    d = np.asarray(ranges_m, dtype=float)
    if body_width_m <= 0.0 or b.shape[-1] < 2:
        return np.zeros(b.shape, dtype=bool)
    lead = b.shape[:-1]
    n = b.shape[-1]
    b2, d2 = b.reshape(-1, n), d.reshape(-1, n)
    out = np.empty(b2.shape, dtype=bool)
    block = max(1, _OCCLUSION_CHUNK // (n * n))
    for lo in range(0, b2.shape[0], block):
        bb, dd = b2[lo:lo + block], d2[lo:lo + block]
        half = angular_half_width(body_width_m, dd)  # (K, N)
        delta = np.abs(bb[:, :, None] - bb[:, None, :])  # (K, N_i, N_j): angle between i's and j's centres
        delta = np.minimum(delta, 2.0 * np.pi - delta)  # = |wrap(gamma_i - gamma_j)| (bearings in [-pi, pi))
        covered = (delta < half[:, None, :]) & (dd[:, None, :] < dd[:, :, None])
        out[lo:lo + block] = covered.any(axis=2)
    return out.reshape(*lead, n)


def _reflect_step(sc: Scenario, x: float, y: float, heading: float, stride: float) -> tuple[float, float, float]:
    """One step of ``stride`` metres from (x, y) along ``heading``, reflected off the arena's
    walls and off the disc of radius ``min_target_range_m``; returns the new (x, y, heading)."""
    w, r_min = sc.arena_half_width_m, sc.min_target_range_m
    ux, uy = math.cos(heading), math.sin(heading)
    nx, ny = x + stride * ux, y + stride * uy
    for _ in range(8):  # a reflection off the disc can send it to a wall and back
        # walls: mirror at each of x = +-w, y = +-w as often as needed (triangle folding)
        for axis in (0, 1):
            c = nx if axis == 0 else ny
            u = c + w
            m = u % (4.0 * w)
            c = (m if m <= 2.0 * w else 4.0 * w - m) - w
            if math.floor(u / (2.0 * w)) % 2:
                if axis == 0:
                    ux = -ux
                else:
                    uy = -uy
            c = min(max(c, -w), w)
            if axis == 0:
                nx = c
            else:
                ny = c
        rad = math.hypot(nx, ny)
        if rad >= r_min:
            return nx, ny, math.atan2(uy, ux)
        # the disc around the platform: mirror radially, reflect the velocity about the tangent
        if rad > 1e-12:
            ex, ey = nx / rad, ny / rad
        else:
            r0 = math.hypot(x, y)
            ex, ey = x / r0, y / r0
        nx, ny = ex * (2.0 * r_min - rad), ey * (2.0 * r_min - rad)
        dot = ux * ex + uy * ey
        ux, uy = ux - 2.0 * dot * ex, uy - 2.0 * dot * ey
    return x, y, math.atan2(-uy, -ux)  # pathological geometry (disc nearly the arena): turn back


def walk(sc: Scenario, rng: np.random.Generator, start_m: np.ndarray, steps: int) -> np.ndarray:
    """Trajectories of walking targets, one position per RF sample (every T_RF).

    Each walker has a constant speed v_i ~ U(0.5, 1) * ``walk_speed_mps`` and a Brownian
    heading: theta_{t+1} = theta_t + N(0, sigma_theta^2 T_RF), theta_0 ~ U(-pi, pi); it moves
    v_i T_RF along its heading each step. It reflects off the arena's edges [-w, w]^2 like
    light off a mirror, and off the disc of radius ``min_target_range_m`` around the platform
    (mirrored radially, the velocity reflected about the tangent), so it never leaves the
    arena nor comes closer than that. Draws, in order: speeds, initial headings, heading
    increments (steps - 1, W): the whole trajectory is fixed by ``rng`` alone.

    Vectorised between reflections: the free path is integrated with ``cumsum`` up to the
    first step that would leave the allowed region, that step is reflected, and the walk
    continues from there.

    Parameters
    ----------
    start_m : ndarray, shape (W, 2)
        Positions at step 0 (inside the arena, at least ``min_target_range_m`` away).

    Returns
    -------
    ndarray, shape (steps, W, 2)
    """
    start = np.asarray(start_m, dtype=float).reshape(-1, 2)
    n_walk = start.shape[0]
    out = np.empty((steps, n_walk, 2))
    if steps == 0:
        return out
    out[0] = start
    speeds = sc.walk_speed_mps * rng.uniform(0.5, 1.0, size=n_walk)
    headings = rng.uniform(-math.pi, math.pi, size=n_walk)
    turns = rng.normal(0.0, sc.walk_turn_rad_per_sqrt_s * math.sqrt(sc.rf_period_s), size=(max(steps - 1, 0), n_walk))
    w, r_min = sc.arena_half_width_m, sc.min_target_range_m
    window = 256
    for k in range(n_walk):
        stride = float(speeds[k] * sc.rf_period_s)
        x, y = float(start[k, 0]), float(start[k, 1])
        heading = float(headings[k])
        t = 0  # out[t] is known; the next move uses turns[t]
        while t < steps - 1:
            stop = min(steps - 1, t + window)
            h = heading + np.cumsum(turns[t:stop, k])
            path = np.column_stack([x + np.cumsum(stride * np.cos(h)), y + np.cumsum(stride * np.sin(h))])
            bad = (np.abs(path) > w).any(axis=1) | (np.hypot(path[:, 0], path[:, 1]) < r_min)
            first = int(np.argmax(bad)) if bad.any() else path.shape[0]
            out[t + 1:t + 1 + first, k] = path[:first]
            if first == path.shape[0]:
                x, y, heading, t = float(path[-1, 0]), float(path[-1, 1]), float(h[-1]), stop
                continue
            if first > 0:
                x, y = float(path[first - 1, 0]), float(path[first - 1, 1])
            x, y, heading = _reflect_step(sc, x, y, float(h[first]), stride)
            t = t + first + 1
            out[t, k] = (x, y)
    return out


class ShadowingField:
    """Log-normal shadowing: a stationary Gaussian field S(p) in dB over the plane with
    std ``shadowing_db`` and Gudmundson's correlation exp(-|p - q| / d_corr).

    Random Fourier features (Rahimi & Recht 2007): S(p) = sigma_S sqrt(2/M) sum_m
    cos(omega_m . p + b_m), b_m ~ U(0, 2 pi), omega_m drawn from the spectral density of the
    exponential kernel in 2-D, proportional to (1 + d_corr^2 |omega|^2)^(-3/2): a bivariate
    Cauchy (Student-t with one degree of freedom) of scale 1/d_corr, i.e. omega = z / (d_corr |c|)
    with z ~ N(0, I_2), c ~ N(0, 1). Over draws, E[S(p) S(q)] = sigma_S^2 exp(-|p - q|/d_corr)
    exactly; with M features the marginal is a sum of M independent terms, Gaussian to
    within an excess kurtosis of -1.5/M. One draw is one real field: the same position gives
    the same value.
    """

    features = 512

    def __init__(self, std_db: float, corr_m: float, rng: np.random.Generator) -> None:
        m = self.features
        z = rng.standard_normal((m, 2))
        c = rng.standard_normal(m)
        self.omega = z / (corr_m * np.maximum(np.abs(c), 1e-300))[:, None]  # (M, 2) [rad/m]
        self.phase = rng.uniform(0.0, 2.0 * math.pi, size=m)
        self.amplitude = std_db * math.sqrt(2.0 / m)

    def __call__(self, positions_m: np.ndarray) -> np.ndarray:
        """S at each position of ``positions_m`` (K, 2) -> (K,) [dB]."""
        p = np.asarray(positions_m, dtype=float).reshape(-1, 2)
        out = np.empty(p.shape[0])
        block = 2048
        for lo in range(0, p.shape[0], block):
            arg = p[lo:lo + block] @ self.omega.T + self.phase
            out[lo:lo + block] = self.amplitude * np.cos(arg).sum(axis=1)
        return out


def fading_coefficient(sc: Scenario) -> float:
    """phi = exp(-T_RF / tau), the lag-1 correlation of the AR(1) RSSI noise (0: white)."""
    if sc.fading_corr_s <= 0.0:
        return 0.0
    return math.exp(-sc.rf_period_s / sc.fading_corr_s)


def ar1(innovations: np.ndarray, phi: float) -> np.ndarray:
    """Stationary AR(1) series with the marginal of ``innovations`` (iid along axis 0):
    x_0 = e_0, x_t = phi x_{t-1} + sqrt(1 - phi^2) e_t."""
    from scipy.signal import lfilter

    e = np.asarray(innovations, dtype=float)
    if phi == 0.0 or e.shape[0] == 0:
        return e.copy()
    x = np.empty_like(e)
    x[0] = e[0]
    if e.shape[0] > 1:
        x[1:], _ = lfilter([math.sqrt(1.0 - phi * phi)], [1.0, -phi], e[1:], axis=0, zi=phi * e[:1])
    return x
