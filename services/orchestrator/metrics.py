"""Scoring: the discovery rate by the paper's association rule, and what we report beside it.

* î_t = argmin_i |wrap(gamma_hat_t - gamma_i)| (paper eq. 11) and
  DR_t = mean over tests of [î_t = i*] (eq. 28). This is the headline metric.
* The Wilson 95 % score interval of DR_t at every t.
* Time to DR >= 0.9: the earliest time after which DR_t stays at or above 0.9 until the end.
* "Tx in FoV at gamma_hat_t": the rate at which the true Tx would be inside the field of view
  if the camera pointed at the estimate. The authors' code reports this instead of DR; we
  report it beside DR, labelled as what it is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

Z95 = 1.959963984540054


def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def associate(estimates_rad: np.ndarray, bearings_rad: np.ndarray) -> np.ndarray:
    """î_t for every estimate (eq. 11): index of the target whose bearing is nearest."""
    diff = np.abs(wrap(np.asarray(estimates_rad)[:, None] - np.asarray(bearings_rad)[None, :]))
    return np.argmin(diff, axis=1)


def score_test(estimates_rad, bearings_rad, tx_index: int, fov_half_angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Per step: whether the association picked the Tx, and whether the Tx is in the FoV at gamma_hat_t."""
    est = np.asarray(estimates_rad, dtype=float)
    hits = associate(est, bearings_rad) == tx_index
    in_fov = np.abs(wrap(est - bearings_rad[tx_index])) <= fov_half_angle_rad
    return hits, in_fov


def wilson_interval(successes: float, trials: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion."""
    if trials <= 0:
        return 0.0, 1.0
    p = successes / trials
    den = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / den
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / den
    lo = 0.0 if successes <= 0 else max(0.0, centre - half)
    hi = 1.0 if successes >= trials else min(1.0, centre + half)
    return lo, hi


def time_to_level(dr: np.ndarray, level: float, rf_period_s: float) -> float | None:
    """Earliest time (s) after which DR_t >= level up to the end; None if the last DR is below."""
    dr = np.asarray(dr)
    below = np.flatnonzero(dr < level - 1e-12)
    if below.size == 0:
        return rf_period_s
    last = int(below[-1])
    if last == dr.size - 1:
        return None
    return round((last + 2) * rf_period_s, 10)


def summarize_algorithm(hits: np.ndarray, in_fov: np.ndarray, rf_period_s: float) -> dict[str, Any]:
    """The per-algorithm block of the results object from per-test, per-step outcomes (tests, T)."""
    hits = np.asarray(hits, dtype=float)
    in_fov = np.asarray(in_fov, dtype=float)
    tests = hits.shape[0]
    successes = hits.sum(axis=0)
    dr = successes / tests
    bands = [wilson_interval(float(k), tests) for k in successes]
    return {
        "dr": [round(float(v), 6) for v in dr],
        "dr_final": round(float(dr[-1]), 6),
        "ci95": [round(bands[-1][0], 6), round(bands[-1][1], 6)],
        "dr_ci95": [[round(lo, 6), round(hi, 6)] for lo, hi in bands],
        "time_to_dr90_s": time_to_level(dr, 0.9, rf_period_s),
        "in_fov_final": round(float(in_fov[:, -1].mean()), 6),
    }
