"""The oracle reference of the robustness benchmark: a bound computed in the scoring code.

The Bayes-MAP choice of the Tx among the N targets given the *true* model (path loss, antenna
pattern, RSSI noise with its AR(1) correlation, the shadowing field's law), the *true* target
positions at every step, and the measurements a non-active sweep would take in that test's
world. Never a controller input: it reads the simulator's ground truth.

Under "target i carries the Tx", the 2T RSSI values of a sweep are Gaussian (paper eqs. 5-8):
mean g(d_i(t)) (Rx(iso)) and the antenna response to s_t - gamma_i(t) (Rx(dir)); the shadowing
S along the Tx's path is a Gaussian process with covariance sigma_S^2 exp(-|p_t - p_u| / d_corr)
entering Rx(iso) with weight 1 and Rx(dir) through the antenna model's derivative in the level
(1 for a dB gain, rho for the paper's scaled dBm), and each receiver's noise is AR(1). The
camera says nothing about who carries the Tx (every target is detected the same way), so the
oracle uses the radio only. The MAP over a uniform prior picks the target whose Gaussian
likelihood is largest.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ra2vipas.services.protocol.scenario import AntennaModel, Scenario
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import SimulatedPlatform


def sweep_pans(scenario: Scenario) -> np.ndarray:
    """The pans of the non-active ``sweep`` algorithm: evenly round the circle from s_0."""
    n = scenario.steps
    return np.asarray(physics.wrap(scenario.initial_pan_rad + 2.0 * math.pi * np.arange(n) / max(n, 1)), dtype=float)


def _ar1_covariance(steps: int, sigma: float, phi: float) -> np.ndarray:
    lag = np.abs(np.subtract.outer(np.arange(steps), np.arange(steps)))
    return sigma * sigma * phi**lag if phi > 0.0 else sigma * sigma * np.eye(steps)


def oracle_choice(scenario: Scenario, seed: int, test_index: int) -> tuple[int, int]:
    """(MAP target index, true Tx index) for test ``test_index`` of a campaign seeded ``seed``."""
    sc = scenario
    if sc.radio.value == "recorded":
        raise ValueError("the recorded channel has no model to be an oracle of (radio=recorded)")
    if sc.radio.value == "adverts":
        return packet_oracle_choice(sc, seed, test_index)
    platform = SimulatedPlatform(sc, seed, test_index)
    truth = platform.truth
    pans = sweep_pans(sc)
    T = sc.steps
    z = np.empty(2 * T)
    for t, pan in enumerate(pans):
        m = platform.sense(t, float(pan))
        z[t], z[T + t] = m.rf.iso_rssi_dbm, m.rf.dir_rssi_dbm
    noise = cho_factor(_ar1_covariance(T, sc.rf_noise_db, physics.fading_coefficient(sc)), lower=True)
    logdet_noise = 2.0 * float(np.log(np.diag(noise[0])).sum())
    walkers = set(truth.walkers.tolist()) if not truth.static else set()
    positions = np.stack([truth.positions_at(t) for t in range(T)]) if walkers else None
    best, best_ll = 0, -np.inf
    for i in range(sc.n_targets):
        if i in walkers:
            path = positions[:, i, :]
        else:
            path = np.repeat(truth.positions_m[i][None, :], T, axis=0)
        d = np.hypot(path[:, 0], path[:, 1])
        gamma = np.arctan2(path[:, 1], path[:, 0])
        g = physics.path_loss_dbm(sc, d)
        delta = pans - gamma
        r = z - np.concatenate([g, _dir_mean(sc, g, delta)])
        w = physics.attenuation(sc, delta) if sc.antenna_model is AntennaModel.paper else np.ones(T)
        if sc.shadowing_db > 0.0 and i in walkers:  # S along a path: full covariance
            K = sc.shadowing_db**2 * np.exp(-np.hypot(*(path[:, None, :] - path[None, :, :]).transpose(2, 0, 1)) / sc.shadowing_corr_m)
            B = np.concatenate([np.eye(T), np.diag(w)])
            cov = B @ K @ B.T
            cov[:T, :T] += noise_matrix(noise)
            cov[T:, T:] += noise_matrix(noise)
            factor = cho_factor(cov + 1e-9 * np.eye(2 * T), lower=True)
            ll = -0.5 * float(r @ cho_solve(factor, r)) - float(np.log(np.diag(factor[0])).sum())
        else:  # a standing Tx: S is one number, a rank-one term (Sherman-Morrison, matrix determinant lemma)
            ri = cho_solve(noise, r[:T]), cho_solve(noise, r[T:])
            quad = float(r[:T] @ ri[0] + r[T:] @ ri[1])
            logdet = 2.0 * logdet_noise
            if sc.shadowing_db > 0.0:
                b = (np.ones(T), w)
                bi = cho_solve(noise, b[0]), cho_solve(noise, b[1])
                s2 = sc.shadowing_db**2
                btb = float(b[0] @ bi[0] + b[1] @ bi[1])
                btr = float(b[0] @ ri[0] + b[1] @ ri[1])
                quad -= s2 * btr * btr / (1.0 + s2 * btb)
                logdet += math.log1p(s2 * btb)
            ll = -0.5 * quad - 0.5 * logdet
        if ll > best_ll:
            best, best_ll = i, ll
    return best, truth.tx_index


def packet_oracle_choice(scenario: Scenario, seed: int, test_index: int) -> tuple[int, int]:
    """``oracle_choice`` on BLE advertisements (``radio: adverts``, docs/radio.md): the sweep's
    packets, each z_k = level of its receiver at its step under "target i is the Tx" + that
    receiver's offset on the packet's channel (N(0, sigma_ch^2), shared by its packets) + the
    per-packet spread (AR(1) over the packets' times with tau = ``fading_corr_s``) + the rounding
    (variance q^2 / 12), + the shadowing along the Tx's path (weighted as in ``oracle_choice``):
    jointly Gaussian, the MAP over a uniform prior. Packets lost below the sensitivity are not
    modelled (a censoring the ble presets hardly reach)."""
    sc = scenario
    platform = SimulatedPlatform(sc, seed, test_index)
    truth = platform.truth
    pans = sweep_pans(sc)
    rows = []  # (step, receiver 0 iso | 1 dir, channel, time, rssi)
    for t, pan in enumerate(pans):
        m = platform.sense(t, float(pan))
        for a in m.adverts:
            rows.append((t, 0 if a.receiver == "iso" else 1, a.channel or 0, t * sc.rf_period_s + a.offset_s, a.rssi_dbm))
    if not rows:
        return 0, truth.tx_index
    step = np.array([r[0] for r in rows])
    rx = np.array([r[1] for r in rows])
    channel = np.array([r[2] for r in rows])
    times = np.array([r[3] for r in rows])
    z = np.array([r[4] for r in rows])
    same_rx = rx[:, None] == rx[None, :]
    base = np.where(same_rx & (channel[:, None] == channel[None, :]), sc.channel_offset_db**2, 0.0)
    lag = np.abs(times[:, None] - times[None, :])
    fade = np.exp(-lag / sc.fading_corr_s) if sc.fading_corr_s > 0.0 else (lag == 0.0).astype(float)
    base = base + np.where(same_rx, sc.rf_noise_db**2 * fade, 0.0) + np.eye(z.size) * sc.rssi_step_db**2 / 12.0
    T = sc.steps
    walkers = set(truth.walkers.tolist()) if not truth.static else set()
    positions = np.stack([truth.positions_at(t) for t in range(T)]) if walkers else None
    best, best_ll = 0, -np.inf
    for i in range(sc.n_targets):
        path = positions[:, i, :] if i in walkers else np.repeat(truth.positions_m[i][None, :], T, axis=0)
        d = np.hypot(path[:, 0], path[:, 1])
        gamma = np.arctan2(path[:, 1], path[:, 0])
        g = physics.path_loss_dbm(sc, d)
        delta = pans - gamma
        level = np.where(rx == 0, g[step], _dir_mean(sc, g, delta)[step])
        r = z - level
        cov = base
        if sc.shadowing_db > 0.0:
            w_step = physics.attenuation(sc, delta) if sc.antenna_model is AntennaModel.paper else np.ones(T)
            w = np.where(rx == 0, 1.0, w_step[step])
            p = path[step]
            K = sc.shadowing_db**2 * np.exp(-np.hypot(*(p[:, None, :] - p[None, :, :]).transpose(2, 0, 1)) / sc.shadowing_corr_m)
            cov = base + w[:, None] * K * w[None, :]
        factor = cho_factor(cov + 1e-9 * np.eye(z.size), lower=True)
        ll = -0.5 * float(r @ cho_solve(factor, r)) - float(np.log(np.diag(factor[0])).sum())
        if ll > best_ll:
            best, best_ll = i, ll
    return best, truth.tx_index


def noise_matrix(factor) -> np.ndarray:
    """The covariance back from its Cholesky factor."""
    L = np.tril(factor[0])
    return L @ L.T


def _dir_mean(sc: Scenario, g: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Noiseless Rx(dir) for per-step levels ``g`` and misalignments ``delta`` (paper eq. 6 or dB gain)."""
    rho = physics.attenuation(sc, delta)
    if sc.antenna_model is AntennaModel.paper:
        return g * rho
    return g + 10.0 * np.log10(np.maximum(rho, 10.0 ** (sc.antenna_floor_db / 10.0)))
