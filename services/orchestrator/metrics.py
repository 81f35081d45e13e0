"""Scoring: the discovery rate by the paper's association rule, and what we report beside it.

* î_t = argmin_i |wrap(gamma_hat_t - gamma_i)| (paper eq. 11) and
  DR_t = mean over tests of [î_t = i*] (eq. 28). This is the headline metric. When targets
  walk, gamma_i is the bearing of target i at step t (bearings of shape (T, N)).
* The Wilson 95 % score interval of DR_t at every t.
* Time to DR >= 0.9: the earliest time after which DR_t stays at or above 0.9 until the end.
* "Tx in FoV at gamma_hat_t": the rate at which the true Tx would be inside the field of view
  if the camera pointed at the estimate. The authors' code reports this instead of DR; we
  report it beside DR, labelled as what it is.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ra2vipas.services.protocol.messages import EpisodeTruth

Z95 = 1.959963984540054


def wrap(angle):
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def _per_step(bearings_rad, steps: int) -> np.ndarray:
    """Target bearings broadcastable to (T, N): static ones (N,) as one row, per-step ones
    (T', N) with T' >= T cut to their first T rows (an episode that ended early)."""
    b = np.asarray(bearings_rad, dtype=float)
    if b.ndim == 1:
        return b[None, :]
    if b.ndim != 2 or b.shape[0] < steps:
        raise ValueError(f"bearings must have shape (N,) or (T, N) with T >= {steps}, got {b.shape}")
    return b[:steps]


def associate(estimates_rad: np.ndarray, bearings_rad: np.ndarray) -> np.ndarray:
    """î_t for every estimate (eq. 11): index of the target whose bearing is nearest.

    ``bearings_rad`` is (N,) for static targets or (T, N), the targets' bearings at each step t
    of the T estimates (moving targets: the association at time t against the bearings at t).
    """
    est = np.asarray(estimates_rad, dtype=float)
    diff = np.abs(wrap(est[:, None] - _per_step(bearings_rad, est.shape[0])))
    return np.argmin(diff, axis=1)


def score_test(estimates_rad, bearings_rad, tx_index: int, fov_half_angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Per step: whether the association picked the Tx, and whether the Tx is in the FoV at
    gamma_hat_t. ``bearings_rad``: (N,) static or (T, N) per step, as in ``associate``."""
    est = np.asarray(estimates_rad, dtype=float)
    hits = associate(est, bearings_rad) == tx_index
    in_fov = np.abs(wrap(est - _per_step(bearings_rad, est.shape[0])[:, tx_index])) <= fov_half_angle_rad
    return hits, in_fov


def truth_bearings(truth: "EpisodeTruth", steps: int) -> np.ndarray | None:
    """The bearings an episode is scored against, from its ``EpisodeTruth``: (N,) when it
    carries no trajectories (a static world, or a v1 node), else (steps, N) with each walking
    target's column taken from its trajectory. None if the truth is inconsistent (Tx or a
    trajectory's index out of range, a repeated index, a trajectory not ``steps`` long)."""
    n = len(truth.bearings_rad)
    if not 0 <= truth.tx_index < n or len(truth.ranges_m) != n:
        return None
    static = np.asarray(truth.bearings_rad, dtype=float)
    if not truth.trajectories:
        return static
    seen: set[int] = set()
    out = np.repeat(static[None, :], steps, axis=0)
    for tr in truth.trajectories:
        if tr.index >= n or tr.index in seen or len(tr.bearings_rad) != steps or len(tr.ranges_m) != steps:
            return None
        seen.add(tr.index)
        out[:, tr.index] = tr.bearings_rad
    return out


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
