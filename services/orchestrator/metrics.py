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

from ra2vipas.services.protocol.angles import wrap

if TYPE_CHECKING:
    from ra2vipas.services.protocol.messages import EpisodeTruth

Z95 = 1.959963984540054


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


def score_episode(estimates_rad, bearings_rad, tx_index: int, fov_half_angle_rad: float, steps: int,
                  decided_step: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per step of a whole test (``steps`` long): whether the association picked the Tx, whether
    the Tx is in the FoV at gamma_hat_t, and î_t.

    An episode that ended early with a decision at step d (``decided_step``; ``estimates_rad``
    then holds d + 1 estimates) keeps its answer: the target it named at d is its answer at
    every later step, so î_t = î_d, and the hit and in-FoV flags of step d hold to the end.
    """
    est = np.asarray(estimates_rad, dtype=float)
    chosen = associate(est, bearings_rad)
    hits, in_fov = score_test(est, bearings_rad, tx_index, fov_half_angle_rad)
    if decided_step is not None and est.shape[0] < steps:
        pad = steps - est.shape[0]
        chosen = np.concatenate([chosen, np.full(pad, chosen[-1])])
        hits = np.concatenate([hits, np.full(pad, hits[-1])])
        in_fov = np.concatenate([in_fov, np.full(pad, in_fov[-1])])
    return hits, in_fov, chosen


def expected_calibration_error(confidence, correct, bins: int = 10) -> float | None:
    """ECE: sum over equal-width confidence bins of (share of the samples in the bin) x |mean
    confidence - accuracy| in it (Guo et al. 2017; 10 bins, the last one closed). None without
    samples."""
    conf = np.asarray(confidence, dtype=float).ravel()
    ok = np.asarray(correct, dtype=float).ravel()
    if conf.size == 0:
        return None
    idx = np.minimum((conf * bins).astype(int), bins - 1)
    total = 0.0
    for b in range(bins):
        inside = idx == b
        if inside.any():
            total += inside.mean() * abs(_mean(conf[inside]) - _mean(ok[inside]))
    return float(total)


def ece_sampling_floor(confidence, bins: int = 10, exact_up_to: int = 2000) -> float | None:
    """The ECE a perfectly calibrated confidence would show on average with these confidences:
    each sample's hit drawn as Bernoulli(its confidence), the expectation over the draws of
    ``expected_calibration_error`` (same bins). With a few hundred tests it is not small (about
    0.03 for confidences near 0.9, 0.06 near 0.5 at 200 tests), so an ECE near it is sampling
    noise, not miscalibration. Per bin, E|mean confidence - share of hits| from the exact
    Poisson-binomial distribution of the hits (confidences sorted, so the value does not depend
    on their order) up to ``exact_up_to`` samples, from its normal approximation (mean absolute
    deviation sqrt(2 / pi) x std) above. None without finite samples."""
    conf = np.asarray(confidence, dtype=float).ravel()
    conf = np.clip(conf[np.isfinite(conf)], 0.0, 1.0)
    if conf.size == 0:
        return None
    idx = np.minimum((conf * bins).astype(int), bins - 1)
    total = 0.0
    for b in range(bins):
        c = np.sort(conf[idx == b])
        n = c.size
        if n == 0:
            continue
        mean = _mean(c)
        if n <= exact_up_to:
            pmf = np.ones(1)
            for p in c.tolist():  # the distribution of the number of hits, one sample at a time
                nxt = np.empty(pmf.size + 1)
                nxt[0] = pmf[0] * (1.0 - p)
                nxt[1:-1] = pmf[1:] * (1.0 - p) + pmf[:-1] * p
                nxt[-1] = pmf[-1] * p
                pmf = nxt
            deviation = math.fsum((pmf * np.abs(np.arange(n + 1) / n - mean)).tolist())
        else:
            deviation = math.sqrt(2.0 / math.pi) * math.sqrt(math.fsum((c * (1.0 - c)).tolist())) / n
        total += (n / conf.size) * deviation
    return float(total)


def reliability_bins(confidence, correct, bins: int = 10) -> list[dict[str, Any]]:
    """The reliability diagram's data: per equal-width bin, its range, how many samples fell in
    it, their mean confidence and their accuracy (None for an empty bin)."""
    conf = np.asarray(confidence, dtype=float).ravel()
    ok = np.asarray(correct, dtype=float).ravel()
    idx = np.minimum((conf * bins).astype(int), bins - 1)
    out = []
    for b in range(bins):
        inside = idx == b
        n = int(inside.sum())
        out.append({"lo": b / bins, "hi": (b + 1) / bins, "n": n,
                    "confidence": round(_mean(conf[inside]), 6) if n else None,
                    "accuracy": round(_mean(ok[inside]), 6) if n else None})
    return out


def rate_curve(successes, tests: int, rf_period_s: float) -> dict[str, Any]:
    """A DR-shaped block from the per-step count of successful tests (T,): the rate at every step
    (DR_t of eq. 11, or "every tag found"), its final value, the Wilson 95 % band at the end and at
    every step, and the time after which the rate stays >= 0.9."""
    successes = np.asarray(successes, dtype=np.float64)
    rate = successes / tests
    bands = [wilson_interval(float(k), tests) for k in successes]
    return {
        "dr": [round(float(v), 6) for v in rate],
        "dr_final": round(float(rate[-1]), 6),
        "ci95": [round(bands[-1][0], 6), round(bands[-1][1], 6)],
        "dr_ci95": [[round(lo, 6), round(hi, 6)] for lo, hi in bands],
        "time_to_dr90_s": time_to_level(rate, 0.9, rf_period_s),
    }


def decision_times(decided_steps, tests: int, rf_period_s: float) -> dict[str, Any]:
    """The median and 90th percentile of the time to decision over the tests that decided (a step
    index each, None for a test that did not), and the share of the ``tests`` still undecided."""
    times = np.asarray([(d + 1) * rf_period_s for d in decided_steps if d is not None], dtype=float)
    return {
        "median_s": round(float(np.median(times)), 6) if times.size else None,
        "p90_s": round(float(np.percentile(times, 90)), 6) if times.size else None,
        "undecided": round(1.0 - times.size / tests, 6) if tests else None,
    }


def decision_summary(final_hits, decided_steps, rf_period_s: float) -> dict[str, Any]:
    """The early-decision block: accuracy of the final answers with its Wilson interval, and
    ``decision_times``."""
    hits = np.asarray(final_hits, dtype=float)
    lo, hi = wilson_interval(float(hits.sum()), hits.size)
    return {
        "accuracy": round(float(hits.mean()), 6) if hits.size else None,
        "accuracy_ci95": [round(lo, 6), round(hi, 6)],
        **decision_times(decided_steps, hits.size, rf_period_s),
    }


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


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar test of two algorithms scored on the same tests: under H0 (equal
    discovery rates) each discordant test (one found the Tx, the other did not) is equally
    likely to favour either, so ``only_a`` ~ Binomial(only_a + only_b, 1/2); the p-value is the
    exact binomial test's (1 with no discordant test).

    Binomial(n, 1/2) is symmetric, so the two-sided p-value (the probability of every outcome no
    likelier than the one seen) is twice the tail up to min(only_a, only_b), at most 1: summed in
    integers, C(n, 0) + ... + C(n, k), and divided by 2^n once (Python rounds an int / int
    correctly). Equal to scipy.stats.binomtest's to its rounding (``_rounded``: 6 decimals, checked
    in tests/unit/test_paired.py), without importing scipy.stats (~1 s of CPU) in every process
    that scores a campaign."""
    a, b = int(only_a), int(only_b)
    n, k = a + b, min(a, b)
    if n == 0:
        return 1.0
    term = tail = 1  # C(n, 0)
    for i in range(k):
        term = term * (n - i) // (i + 1)  # C(n, i + 1), exactly
        tail += term
    return min(1.0, 2 * tail / 2**n)


def paired_comparison(name_a: str, hits_a, name_b: str, hits_b) -> dict[str, Any]:
    """Two algorithms' final hits (1/0 per test index, None where a test was not recorded)
    compared on the tests both ran: the 2 x 2 counts, the difference of their DR on those tests
    and the exact McNemar p-value (``mcnemar_exact``)."""
    pairs = [(bool(x), bool(y)) for x, y in zip(hits_a, hits_b) if x is not None and y is not None]
    both = sum(1 for x, y in pairs if x and y)
    only_a = sum(1 for x, y in pairs if x and not y)
    only_b = sum(1 for x, y in pairs if y and not x)
    n = len(pairs)
    return {"a": name_a, "b": name_b, "tests": n, "both": both, "only_a": only_a, "only_b": only_b,
            "neither": n - both - only_a - only_b, "dr_difference": round((only_a - only_b) / n, 6) if n else None,
            "p_value": _rounded(mcnemar_exact(only_a, only_b)) if n else None}


def paired_comparisons(outcomes: dict[str, list]) -> list[dict[str, Any]]:
    """``paired_comparison`` of every pair of algorithms, in the order given (a before b)."""
    names = list(outcomes)
    return [paired_comparison(a, outcomes[a], b, outcomes[b]) for i, a in enumerate(names) for b in names[i + 1:]]


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


def summarize_algorithm(hits: np.ndarray, in_fov: np.ndarray, rf_period_s: float, confidences: np.ndarray | None = None,
                        decided_steps: list | None = None) -> dict[str, Any]:
    """The per-algorithm block of the results object from per-test, per-step outcomes (tests, T).

    With per-step ``confidences`` (tests, T) it carries ``calibration``: the expected calibration
    error of the final confidence against the final hit (``ece_final``) and of every step's
    confidence against that step's hit (``ece_all``); with ``decided_steps`` (early decisions,
    None for a test that did not decide) it carries ``decision`` (``decision_summary``).
    """
    hits = np.asarray(hits, dtype=float)
    in_fov = np.asarray(in_fov, dtype=float)
    extra: dict[str, Any] = {}
    if confidences is not None and np.size(confidences):
        conf = np.asarray(confidences, dtype=float)
        extra["calibration"] = {"ece_final": _rounded(expected_calibration_error(conf[:, -1], hits[:, -1])),
                                "ece_final_floor": _rounded(ece_sampling_floor(conf[:, -1])),
                                "ece_all": _rounded(expected_calibration_error(conf, hits)),
                                "confidence_final": round(_mean(conf[:, -1]), 6),
                                "reliability": reliability_bins(conf[:, -1], hits[:, -1])}
    if decided_steps is not None:
        extra["decision"] = decision_summary(hits[:, -1], decided_steps, rf_period_s)
    return {
        **rate_curve(hits.sum(axis=0), hits.shape[0], rf_period_s),
        "in_fov_final": round(float(in_fov[:, -1].mean()), 6),
        **extra,
    }


def summarize_tags(hits, in_fov, rf_period_s: float, confidences=None, decided_steps=None) -> dict[str, Any]:
    """The results block of a search for K tags at once, from per-test, per-tag, per-step outcomes.

    ``hits`` and ``in_fov`` have shape (tests, K, T): whether the target named for tag k at step t
    carries tag k (the association rule of eq. 11, applied per tag), with a decided tag's final
    answer repeated up to the horizon. ``confidences`` (tests, K, T) and ``decided_steps``
    (tests x K, None where a tag was not decided) are optional.

    Returns ``per_tag`` (one ``summarize_algorithm`` block per tag: DR_t with its Wilson band,
    calibration, decision), ``mean_tag_dr_final``, ``all_found`` (the rate at which every tag's
    named target is its carrier, DR-shaped, with its Wilson band and time to 0.9) and, with
    ``decided_steps``, ``all_decided``: the time until all K tags are decided (median and 90th
    percentile over the tests where all were, and the share where some tag never was).
    """
    hits = np.asarray(hits, dtype=float)
    in_fov = np.asarray(in_fov, dtype=float)
    if hits.ndim != 3 or hits.shape != in_fov.shape:
        raise ValueError(f"hits and in_fov must have one shape (tests, K, T); got {hits.shape} and {in_fov.shape}")
    tests, tags, _ = hits.shape
    conf = None if confidences is None or not np.size(confidences) else np.asarray(confidences, dtype=float)
    per_tag = [summarize_algorithm(hits[:, k, :], in_fov[:, k, :], rf_period_s,
                                   None if conf is None else conf[:, k, :],
                                   None if decided_steps is None else [row[k] for row in decided_steps])
               for k in range(tags)]
    everyone = hits.min(axis=1)  # (tests, T): 1 where every tag's answer is right
    out: dict[str, Any] = {
        "per_tag": per_tag,
        "mean_tag_dr_final": round(_mean([block["dr_final"] for block in per_tag]), 6),
        "all_found": rate_curve(everyone.sum(axis=0), tests, rf_period_s),
    }
    if decided_steps is not None:
        last = [None if any(d is None for d in row) else max(row) for row in decided_steps]
        out["all_decided"] = decision_times(last, tests, rf_period_s)
    return out


def _mean(values) -> float:
    """The mean with an exactly rounded sum (``math.fsum``): the same value whatever the order
    of the tests, so a campaign whose episodes finished in another order (other rigs, a rerun
    after a kill) reports the same results to the last digit."""
    flat = np.asarray(values, dtype=float).ravel()
    return math.fsum(flat.tolist()) / flat.size


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 6)
