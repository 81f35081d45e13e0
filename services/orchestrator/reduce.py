"""Streaming reduction of episode outcomes to the results object, in memory that does not grow
with the number of steps kept per test.

``summarize_algorithm`` (``metrics``) reduces a (tests, T) array of per-step hits at once: a
campaign of 10 000 tests would hold every test's per-step trace. ``AlgorithmTally`` takes one
episode at a time and keeps only running sums over steps and one scalar per test:

* DR_t (eq. 28): per step, how many tests hit (an integer per step), so DR_t and its Wilson
  interval at every t are exact whatever the order the tests arrive in;
* in-FoV at the last step: a count;
* calibration: per confidence bin, the number of (test, step) samples, their summed
  confidence and their hits (``ece_all``), and each test's final confidence and hit (the
  final-step ECE, mean confidence and reliability bins: O(tests) scalars, never O(tests x T));
* early decisions: each test's decided step.

``AlgorithmTally.summary()`` returns the same block, field for field, as
``summarize_algorithm`` on the whole array (a unit test checks it against it on random
outcomes): equal for everything but ``ece_all``, whose per-bin mean confidence is summed in
test order rather than numpy's pairwise order (equal to ~1e-15 before rounding to 6 digits).
The in-process engine and the orchestrator both reduce with it, tests fed in test order, so
the mesh and ``simulate`` agree value for value.
"""

from __future__ import annotations

from array import array
from typing import Any, Mapping

import numpy as np

from ra2vipas.services.orchestrator.metrics import (
    decision_summary, expected_calibration_error, reliability_bins, time_to_level, wilson_interval,
)

BINS = 10  # the calibration bins of metrics.expected_calibration_error


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
        self._with_conf = True  # every episode so far carried per-step confidences
        self._bin_n = np.zeros(BINS, dtype=np.int64)
        self._bin_conf = np.zeros(BINS, dtype=np.float64)
        self._bin_hits = np.zeros(BINS, dtype=np.int64)

    def add(self, hits, in_fov, confidences=None, decided_step: int | None = None, steps_run: int | None = None) -> None:
        """One episode: its per-step hits and in-FoV flags (``steps`` long), its per-step
        confidences (``steps`` long, or None/empty from a controller that sends none), the step
        it decided at (early decisions) and how many control steps it actually ran.

        Raises
        ------
        ValueError
            A series is not ``steps`` long.
        """
        h = np.asarray(hits, dtype=bool)
        f = np.asarray(in_fov, dtype=bool)
        if h.shape != (self.steps,) or f.shape != (self.steps,):
            raise ValueError(f"an episode's hits and in-FoV flags must have {self.steps} steps, got {h.shape} and {f.shape}")
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
            idx = np.clip((c * BINS).astype(int), 0, BINS - 1)  # metrics.expected_calibration_error's bins
            self._bin_n += np.bincount(idx, minlength=BINS)
            self._bin_conf += np.bincount(idx, weights=c, minlength=BINS)
            self._bin_hits += np.bincount(idx, weights=h, minlength=BINS).astype(np.int64)
            self._final_conf.append(float(c[-1]))

    def _ece_all(self) -> float | None:
        total_n = int(self._bin_n.sum())
        if total_n == 0:
            return None
        total = 0.0
        for b in range(BINS):
            n = int(self._bin_n[b])
            if n:
                total += (n / total_n) * abs(float(self._bin_conf[b]) / n - int(self._bin_hits[b]) / n)
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
        successes = self._hit_counts.astype(np.float64)
        dr = successes / tests
        bands = [wilson_interval(float(k), tests) for k in successes]
        final_hits = np.frombuffer(self._final_hits, dtype=np.int8).astype(np.float64)
        extra: dict[str, Any] = {}
        if self._with_conf and len(self._final_conf) == tests:
            conf = np.frombuffer(self._final_conf, dtype=np.float64)
            ece_all = self._ece_all()
            extra["calibration"] = {"ece_final": _rounded(expected_calibration_error(conf, final_hits)),
                                    "ece_all": _rounded(ece_all),
                                    "confidence_final": round(float(conf.mean()), 6),
                                    "reliability": reliability_bins(conf, final_hits)}
        if decisions:
            extra["decision"] = decision_summary(final_hits, list(self._decided), self.rf_period_s)
        return {
            "dr": [round(float(v), 6) for v in dr],
            "dr_final": round(float(dr[-1]), 6),
            "ci95": [round(bands[-1][0], 6), round(bands[-1][1], 6)],
            "dr_ci95": [[round(lo, 6), round(hi, 6)] for lo, hi in bands],
            "time_to_dr90_s": time_to_level(dr, 0.9, self.rf_period_s),
            "in_fov_final": round(self._final_in_fov / tests, 6),
            **extra,
        }


def results_object(preset: str, scenario, tests: int, seed: int, pod, tallies: Mapping[str, AlgorithmTally],
                   steps_per_second: float | None, stop_confidence: float = 0.0) -> dict[str, Any]:
    """The results object (``simulate.summarize``'s envelope: preset, scenario, tests, seed,
    POD fit, speed, and whatever else it carries) with the algorithms' blocks from ``tallies``."""
    from ra2vipas.services.orchestrator.simulate import summarize

    out = summarize(preset, scenario, tests, seed, pod, {}, steps_per_second, stop_confidence)
    out["algorithms"] = {name: tally.summary(decisions=stop_confidence > 0.0) for name, tally in tallies.items()}
    return out


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 6)
