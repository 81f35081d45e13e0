"""The physical model of the simulated world (paper, Sec. II and Table I).

Pure functions of numpy arrays. These are the *truth* the simulator draws from; the
controller and the learner never call them.
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.protocol.scenario import AntennaModel, Scenario


def wrap(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle (or a difference of angles) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


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
