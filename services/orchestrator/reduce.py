"""Streaming reduction of episode outcomes to the results object, in memory that does not grow
with the number of steps kept per test.

``summarize_algorithm`` (``metrics``) reduces a (tests, T) array of per-step hits at once: a
campaign of 10 000 tests would hold every test's per-step trace. ``AlgorithmTally`` takes one
episode at a time and keeps only running sums over steps and one scalar per test:

* DR_t (eq. 28): per step, how many tests hit (an integer per step), so DR_t and its Wilson
  interval at every t are exact whatever the order the tests arrive in;
* in-FoV at the last step: a count;
* calibration: per confidence bin, the number of (test, step) samples, their summed
  confidence (summed exactly, see below) and their hits (``ece_all``), and each test's final
  confidence and hit (the final-step ECE, mean confidence and reliability bins: O(tests)
  scalars, never O(tests x T));
* early decisions: each test's decided step.

``LatencyTally`` does the same for a realtime campaign's sample-to-command latencies: a count
per 0.1 µs bin instead of every (test, step) latency, and the same p50/p99.

``AlgorithmTally.summary()`` returns the same block, value for value, as
``summarize_algorithm`` on the whole array, whatever order the episodes arrive in (unit tests
check both on random outcomes). Every sum it keeps is exact: counts are integers, and the
per-bin confidence sums are kept as integers in units of 2**-1074 (every double is a whole
multiple of it), so the per-bin mean is the correctly rounded sum divided by n, which is what
``metrics._mean`` (``math.fsum``) gives over all the samples at once. A float running sum
would depend on the arrival order (other workers, other rigs, a rerun after a kill) in the
last bits, and that moves a rounded 6th decimal now and then.
"""

from __future__ import annotations

import math
from array import array
from collections import Counter
from typing import Any, Iterable, Mapping

import numpy as np

from ra2vipas.services.orchestrator.metrics import (
    decision_summary,
    decision_times,
    ece_sampling_floor,
    expected_calibration_error,
    paired_comparisons,
    rate_curve,
    reliability_bins,
)

BINS = 10  # the calibration bins of metrics.expected_calibration_error
_ULP_EXP = 1074  # every finite double is a whole multiple of 2**-1074


def held(values: list[float], steps: int) -> list[float]:
    """A per-step series of an episode that may have ended early, its last value held to ``steps``."""
    return list(values) + [values[-1]] * (steps - len(values)) if values else list(values)


def _exact_units(value: float) -> int:
    """``value`` as an integer count of 2**-1074 (exact for every finite double)."""
    num, den = value.as_integer_ratio()  # den is a power of two, at most 2**1074
    return num << (_ULP_EXP - den.bit_length() + 1)


class AlgorithmTally:
    """Running sums of one algorithm's episodes over a campaign (see the module docstring).

    Parameters
    ----------
    steps : int
        n_test, the length of every episode's per-step series (an episode that decided early
        arrives padded to it, its answer held).
    rf_period_s : float
        T_RF, to turn steps into times.
    """

    def __init__(self, steps: int, rf_period_s: float) -> None:
        self.steps = int(steps)
        self.rf_period_s = float(rf_period_s)
        self.tests = 0
        self.steps_run = 0
        self._hit_counts = np.zeros(self.steps, dtype=np.int64)
        self._final_in_fov = 0
        self._final_hits = array("b")
        self._final_conf = array("d")
        self._decided: list[int | None] = []
        self._test_index = array("q")  # each episode's test index, in arrival order (its final hit: _final_hits)
        self._with_conf = True  # every episode so far carried per-step confidences
        self._bin_n = np.zeros(BINS, dtype=np.int64)
        self._bin_conf = [0] * BINS  # exact sums, in units of 2**-1074 (_exact_units)
        self._bin_special: list[list[float]] = [[] for _ in range(BINS)]  # inf/nan confidences, if ever
        self._samples = 0  # every (test, step) confidence, binned or not (metrics' denominator)
        self._bin_hits = np.zeros(BINS, dtype=np.int64)
        self.tags: TagTally | None = None  # a search for several tags (issue 21): per tag, and all found

    def add_tags(self, hits, in_fov, confidences=None, decided_steps=None) -> None:
        """One episode's per-tag outcomes (after ``add`` took its top-level series): (K, T) hits
        and in-FoV flags, (K, T) confidences or None, K decided steps (None: not decided)."""
        hits = np.asarray(hits, dtype=bool)
        if self.tags is None:
            self.tags = TagTally(self.steps, self.rf_period_s, hits.shape[0])
        self.tags.add(hits, in_fov, confidences, decided_steps)

    def add(self, hits, in_fov, confidences=None, decided_step: int | None = None, steps_run: int | None = None,
            test_index: int | None = None) -> None:
        """One episode: its per-step hits and in-FoV flags (``steps`` long), its per-step
        confidences (``steps`` long, or None/empty from a controller that sends none), the step
        it decided at (early decisions), how many control steps it actually ran and its test
        index (default: the episodes arrive in test order, 0, 1, ...).

        Raises
        ------
        ValueError
            A series is not ``steps`` long.
        """
        h = np.asarray(hits, dtype=bool)
        f = np.asarray(in_fov, dtype=bool)
        if h.shape != (self.steps,) or f.shape != (self.steps,):
            raise ValueError(f"an episode's hits and in-FoV flags must have {self.steps} steps, got {h.shape} and {f.shape}")
        self._test_index.append(self.tests if test_index is None else int(test_index))
        self.tests += 1
        self.steps_run += self.steps if steps_run is None else int(steps_run)
        self._hit_counts += h
        self._final_in_fov += bool(f[-1])
        self._final_hits.append(int(h[-1]))
        self._decided.append(decided_step)
        if confidences is None or len(confidences) == 0:
            self._with_conf = False
        elif self._with_conf:
            c = np.asarray(confidences, dtype=np.float64)
            if c.shape != (self.steps,):
                raise ValueError(f"an episode's confidences must have {self.steps} steps, got {c.shape}")
            with np.errstate(invalid="ignore"):
                idx = np.minimum((c * BINS).astype(int), BINS - 1)  # metrics.expected_calibration_error's bins
            self._samples += c.size
            binned = idx >= 0
            self._bin_n += np.bincount(idx[binned], minlength=BINS)
            self._bin_hits += np.bincount(idx[binned], weights=h[binned], minlength=BINS).astype(np.int64)
            for b, value in zip(idx[binned].tolist(), c[binned].tolist()):
                if math.isfinite(value):
                    self._bin_conf[b] += _exact_units(value)
                else:
                    self._bin_special[b].append(value)
            self._final_conf.append(float(c[-1]))

    def outcomes(self, tests: int) -> list[int | None]:
        """The final hit (1/0) of tests 0 .. ``tests`` - 1, None for a test not added."""
        out: list[int | None] = [None] * tests
        for k, hit in zip(self._test_index, self._final_hits):
            if 0 <= k < tests:
                out[k] = int(hit)
        return out

    def all_found_outcomes(self, tests: int) -> list[int | None]:
        """A search for several tags: whether every tag's final answer was right (1/0) in tests
        0 .. ``tests`` - 1, None for a test not added."""
        if self.tags is None:
            raise ValueError("no per-tag outcomes were added")
        return self.tags.all_found_outcomes(self._test_index, tests)

    def _bin_mean_confidence(self, b: int, n: int) -> float:
        """The mean confidence of bin ``b`` (n samples): its exact sum, correctly rounded (int / int
        is), divided by n: ``math.fsum`` over the bin's samples, divided by n."""
        exact = self._bin_conf[b] / (1 << _ULP_EXP)
        if self._bin_special[b]:
            exact = math.fsum([exact, *self._bin_special[b]])
        return exact / n

    def ece_all(self) -> float | None:
        """``metrics.expected_calibration_error`` over every (test, step) sample, bin by bin in
        the same order with the same operations."""
        total_n = self._samples
        if total_n == 0:
            return None
        total = 0.0
        for b in range(BINS):
            n = int(self._bin_n[b])
            if n:
                total += (n / total_n) * abs(self._bin_mean_confidence(b, n) - int(self._bin_hits[b]) / n)
        return float(total)

    def summary(self, decisions: bool = False) -> dict[str, Any]:
        """The per-algorithm block of the results object (``metrics.summarize_algorithm``'s
        fields); ``decisions`` adds the early-decision block (campaigns with stop_confidence).

        Raises
        ------
        ValueError
            No episode was added.
        """
        if self.tests == 0:
            raise ValueError("no episode to summarize")
        tests = self.tests
        final_hits = np.frombuffer(self._final_hits, dtype=np.int8).astype(np.float64)
        extra: dict[str, Any] = {}
        if self._with_conf and len(self._final_conf) == tests:
            conf = np.frombuffer(self._final_conf, dtype=np.float64)
            ece_all = self.ece_all()
            extra["calibration"] = {"ece_final": _rounded(expected_calibration_error(conf, final_hits)),
                                    "ece_final_floor": _rounded(ece_sampling_floor(conf)),
                                    "ece_all": _rounded(ece_all),
                                    "confidence_final": round(math.fsum(conf.tolist()) / conf.size, 6),  # metrics._mean
                                    "reliability": reliability_bins(conf, final_hits)}
        if decisions:
            extra["decision"] = decision_summary(final_hits, list(self._decided), self.rf_period_s)
        if self.tags is not None:
            extra["tags"] = self.tags.summary(decisions)
        return {
            **rate_curve(self._hit_counts, tests, self.rf_period_s),
            "in_fov_final": round(self._final_in_fov / tests, 6),
            **extra,
        }


class TagTally:
    """Running sums of one algorithm's searches for K tags (issue 21): one ``AlgorithmTally`` per
    tag, the per-step count of tests in which every tag's answer was right, and each test's step
    at which the last tag was decided. ``summary`` is ``metrics.summarize_tags``, value for value.

    Parameters
    ----------
    steps : int
        n_test.
    rf_period_s : float
        T_RF.
    n_tags : int
        K.
    """

    def __init__(self, steps: int, rf_period_s: float, n_tags: int) -> None:
        self.steps, self.rf_period_s, self.n_tags = int(steps), float(rf_period_s), int(n_tags)
        self.per_tag = [AlgorithmTally(steps, rf_period_s) for _ in range(self.n_tags)]
        self.tests = 0
        self._all_hits = np.zeros(self.steps, dtype=np.int64)
        self._all_decided: list[int | None] = []
        self._final_all = array("b")

    def add(self, hits, in_fov, confidences=None, decided_steps=None) -> None:
        """One episode: (K, T) hits and in-FoV flags, (K, T) confidences or None, K decided steps.

        Raises
        ------
        ValueError
            Not K tags, or a series not ``steps`` long.
        """
        h = np.asarray(hits, dtype=bool)
        f = np.asarray(in_fov, dtype=bool)
        if h.shape != (self.n_tags, self.steps) or f.shape != h.shape:
            raise ValueError(f"per-tag hits and in-FoV flags must be ({self.n_tags}, {self.steps}), got {h.shape} and {f.shape}")
        decided = list(decided_steps) if decided_steps is not None else [None] * self.n_tags
        for k, tally in enumerate(self.per_tag):
            tally.add(h[k], f[k], None if confidences is None else np.asarray(confidences)[k], decided[k])
        self.tests += 1
        everyone = h.min(axis=0)
        self._all_hits += everyone
        self._final_all.append(int(everyone[-1]))
        self._all_decided.append(None if any(d is None for d in decided) else max(decided))

    def summary(self, decisions: bool = False) -> dict[str, Any]:
        """The ``tags`` block of an algorithm (``metrics.summarize_tags``'s fields)."""
        if self.tests == 0:
            raise ValueError("no episode to summarize")
        per_tag = [t.summary(decisions=decisions) for t in self.per_tag]
        finals = [block["dr_final"] for block in per_tag]
        out: dict[str, Any] = {
            "per_tag": per_tag,
            "mean_tag_dr_final": round(math.fsum(finals) / len(finals), 6),  # metrics._mean
            "all_found": rate_curve(self._all_hits, self.tests, self.rf_period_s),
        }
        if decisions:
            out["all_decided"] = decision_times(self._all_decided, self.tests, self.rf_period_s)
        return out

    def all_found_outcomes(self, test_indices, tests: int) -> list[int | None]:
        """The final "every tag found" (1/0) of tests 0 .. ``tests`` - 1 (None: not added), given
        each added episode's test index in arrival order (its ``AlgorithmTally``'s)."""
        out: list[int | None] = [None] * tests
        for k, found in zip(test_indices, self._final_all):
            if 0 <= k < tests:
                out[k] = int(found)
        return out


class LatencyTally:
    """A realtime campaign's sample-to-command latencies [ms], reduced as they arrive: a count
    per bin of width 10**-DECIMALS ms (0.1 µs: the sensors report latencies rounded to it and
    the results print them so), kept sparse. Memory grows with the distinct latencies seen (at
    most one bin per 0.1 µs of the range they span), never with tests x steps, and
    ``percentile`` is ``np.percentile``'s (linear interpolation between order statistics,
    Hyndman & Fan's 7th method) of the latencies rounded to the bin width: exact, value for
    value, for the latencies the sensors send. Non-finite values are ignored (the protocol
    refuses them).
    """

    DECIMALS = 4

    def __init__(self) -> None:
        self.count = 0
        self._bins: Counter[int] = Counter()  # bin index (latency x 10**DECIMALS, rounded) -> samples

    @property
    def bins(self) -> int:
        """How many distinct bins are held (what the memory grows with)."""
        return len(self._bins)

    def add(self, latencies_ms: Iterable[float]) -> None:
        """One episode's latencies (or any batch of them), in any order."""
        scale = 10 ** self.DECIMALS
        bins = self._bins
        for value in latencies_ms:
            if math.isfinite(value):
                bins[round(value * scale)] += 1
                self.count += 1

    def _order_statistics(self, ranks: Iterable[int]) -> dict[int, float]:
        """The latencies at the given 0-based ranks of the sorted sample."""
        wanted = sorted(set(ranks))
        out: dict[int, float] = {}
        seen = 0
        i = 0
        for key in sorted(self._bins):
            seen += self._bins[key]
            while i < len(wanted) and wanted[i] < seen:
                out[wanted[i]] = key / 10 ** self.DECIMALS  # the nearest double to the rounded decimal, as round(v, 4) gives
                i += 1
            if i == len(wanted):
                break
        return out

    def percentiles(self, qs: Iterable[float]) -> list[float]:
        """``np.percentile(latencies, q)`` for each q in ``qs`` (percent), with numpy's operations
        in numpy's order: virtual index (n - 1) q / 100, gamma its fractional part, and the
        interpolation computed from the nearer neighbour (``numpy.lib._function_base_impl._lerp``).

        Raises
        ------
        ValueError
            No latency was added.
        """
        n = self.count
        if n == 0:
            raise ValueError("no latency to summarize")
        plan = []
        for q in qs:
            virtual = (n - 1) * (q / 100)
            below = math.floor(virtual)
            if virtual >= n - 1:
                lo = hi = n - 1
            elif virtual < 0:
                lo = hi = 0
            else:
                lo, hi = below, below + 1
            plan.append((lo, hi, virtual - below))
        values = self._order_statistics(r for lo, hi, _ in plan for r in (lo, hi))
        out = []
        for lo, hi, gamma in plan:
            a, b = values[lo], values[hi]
            diff = b - a
            out.append(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)
        return out

    def summary(self) -> dict[str, float] | None:
        """The results object's ``latency_ms`` block, ``{"p50", "p99"}`` rounded to 4 decimals;
        None if no latency was added."""
        if self.count == 0:
            return None
        p50, p99 = self.percentiles((50, 99))
        return {"p50": round(float(p50), 4), "p99": round(float(p99), 4)}


def results_object(preset: str, scenario, tests: int, seed: int, pod, tallies: Mapping[str, AlgorithmTally],
                   steps_per_second: float | None, stop_confidence: float = 0.0) -> dict[str, Any]:
    """The results object (``simulate.summarize``'s envelope: preset, scenario, tests, seed,
    POD fit, speed, and whatever else it carries) with the algorithms' blocks from ``tallies``."""
    from ra2vipas.services.orchestrator.envelope import add_provenance, summarize
    from ra2vipas.services.orchestrator.rigcheck import dr_warnings

    out = summarize(preset, scenario, tests, seed, pod, {}, steps_per_second, stop_confidence)
    out["algorithms"] = {name: tally.summary(decisions=stop_confidence > 0.0) for name, tally in tallies.items()}
    # per test, each algorithm's final hit, and every pair of algorithms compared on the tests
    # both ran (every algorithm meets the same world in test k: McNemar's exact test)
    out["outcomes"] = {name: tally.outcomes(tests) for name, tally in tallies.items()}
    out["paired"] = paired_comparisons(out["outcomes"])
    found = {name: tally.all_found_outcomes(tests) for name, tally in tallies.items() if tally.tags is not None}
    if found:  # several tags (issue 21): the same comparison on "every tag found" at the end
        out["paired_all_found"] = paired_comparisons(found)
    add_provenance(out)
    warnings = dr_warnings(out)
    if warnings:
        out["warnings"] = warnings
    return out


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 6)
