"""What "same seed, same results" means, on one machine and across machines.

On one machine (one CPU model, the pinned libraries of ``constraints.txt``) a campaign is
reproducible to the last digit: every draw of test k depends only on (seed, k), whatever the
number of workers or the order in which they finish, and a campaign through the Zenoh mesh
equals ``simulate`` value for value when both run on the same CPU family.

Across machines it is not: numpy, OpenBLAS and numba pick SIMD kernels at run time (AVX-512,
AVX2, SSE, NEON), and those kernels may round ``log10``, ``arctan2``, ``exp`` or a dot product's
sum differently in the last bit. A draw moves by a few ulp; a maximum-likelihood fit (the POD
model's hyperparameters, a confidence map's logistic regression) stops wherever its optimiser's
tolerance lets it, so a fitted number can move in its 4th-6th decimal; and a choice at a
near-tie (two pans' acquisition values or two targets' posteriors equal to ~1e-12) can flip,
after which that test's trajectory is another one. So anything compared with numbers recorded
on another machine compares:

* **decisions exactly, except near-ties**: each test's sequence of choices (the target î_t named
  at every step, eq. 11, and the early-decision step) is compared whole; at most
  ``MAX_FLIPPED_SHARE`` of the (algorithm, test) trajectories compared may take another path,
  and at most ``MAX_CHANGED_HITS_SHARE`` of them may end with another final hit (so a DR moves
  well within its sampling noise), never one whose choices are unchanged. Measured on this
  project's documented campaigns (152 trajectories of their first tests): this machine with
  numpy's AVX-512 kernels off as the issue's emulation of another CPU, 1 took another path;
  with numpy reduced to its SSE baseline, OpenBLAS on Nehalem kernels and numba for a generic
  CPU (no FMA), 11 (7 %), 2 of them with another final hit (1.3 %). A change of behaviour
  sends most trajectories elsewhere;
* **numbers that count decisions** (DR_t, in-FoV, hit counts, Wilson bounds, time to DR 0.9)
  exactly where no test took another path; where f tests of an algorithm did, its DR and
  in-FoV within f / tests, and the rest of its numbers not at all (the other paths move them);
* **numbers that come out of a fit or pass through one** within the tolerances below, each with
  the reason next to it;
* **draws of the world** (RSSI values, box bearings, positions) rounded to ``DRAW_DECIMALS``
  before they are hashed.

The test suite checks the recorded numbers this way on every machine, and once more with the
CPU features reduced (tests/docs/test_other_cpus.py), so the difference another machine makes
is exercised wherever the suite runs.
"""

from __future__ import annotations

import hashlib
import json
import math
from typing import Any, Callable

# A draw of the world is a closed-form function of seeded normals (log10, hypot, arctan2):
# across CPUs it moves by a few ulp (< 1e-12 at these magnitudes: RSSI in dBm, bearings in
# rad, positions in m). Rounded to 1e-6 a value changes only if it lies within 1e-12 of a
# rounding boundary (probability ~1e-6 per value, ~1e-3 per digest of ~1 000 values), while
# any change to how the world draws (another stream, another formula) moves values by far more.
DRAW_DECIMALS = 6

# The POD model's hyperparameters come from a gradient-based maximisation of the log marginal
# likelihood that stops at a gradient tolerance; an ulp in its inputs moves where it stops, and
# R² (eq. 23) with it: observed |ΔR²| <= 1e-6 between an AVX-512 machine and the same one
# reduced to its SSE baseline; 1e-4 leaves two orders of magnitude for other CPUs.
POD_R2_TOLERANCE = 1e-4

# Confidences are the shipped map applied to a posterior computed with that POD model: they
# move with it (observed <= 1e-6 per confidence, 4e-5 on an ECE whose bins a confidence
# crossed). 1e-3 is 25 times the largest move observed and a tenth of an ECE bin's resolution.
CONFIDENCE_TOLERANCE = 1e-3

# Near-ties send some trajectories elsewhere (measured up to 7 %, see above); a change of
# behaviour sends most. Their final hits change far more rarely (measured 1.3 %).
MAX_FLIPPED_SHARE = 0.2
MAX_CHANGED_HITS_SHARE = 0.05

# results keys, by what they are
FITTED_KEYS = {"r2": POD_R2_TOLERANCE, "pod_r2": POD_R2_TOLERANCE, "confidence_final": CONFIDENCE_TOLERANCE,
               "ece_all": CONFIDENCE_TOLERANCE, "ece_final": CONFIDENCE_TOLERANCE,
               "ece_final_floor": CONFIDENCE_TOLERANCE, "confidence": CONFIDENCE_TOLERANCE}
# fractions of tests (DR_t, in-FoV): within one test's weight where a test flipped; every other
# number of that algorithm (Wilson bounds, first crossing of 0.9, the calibration bins, which
# its other trajectory moves freely) is then not compared: the maps from hits to them are unit-tested
DECISION_FRACTION_KEYS = {"dr", "dr_final", "in_fov", "in_fov_final"}


def canonical(value: Any, decimals: int = DRAW_DECIMALS) -> Any:
    """A JSON-like value with every float rounded to ``decimals`` (``-0.0`` read as ``0.0``)."""
    if isinstance(value, float):
        if not math.isfinite(value):
            return repr(value)
        return round(value, decimals) + 0.0
    if isinstance(value, dict):
        return {str(k): canonical(v, decimals) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v, decimals) for v in value]
    return value


def draw_digest(parts: list[Any], decimals: int = DRAW_DECIMALS) -> str:
    """The SHA-256 of a sequence of JSON-like draws, each canonicalised (floats rounded): equal on
    every CPU for the same draws, different for other draws."""
    h = hashlib.sha256()
    for part in parts:
        h.update(json.dumps(canonical(part, decimals), sort_keys=True, separators=(",", ":")).encode())
    return h.hexdigest()


def choices_digest(chosen: list[int], decided_step: int | None) -> str:
    """The digest of one test's decisions: the target named at every step and the early-decision step."""
    return hashlib.sha256(json.dumps([chosen, decided_step], separators=(",", ":")).encode()).hexdigest()[:12]


def decision_drift(campaigns: list[tuple[str, dict[str, Any], dict[str, Any]]]) -> tuple[list[str], list[tuple[str, str, int]]]:
    """Compare the decisions of several campaigns' tests, each given as (label, record now, record
    then) with ``choices_sha256`` ({algorithm: [digest per test]}) and ``final_hits``
    ({name: "0101..."}, the oracle's included). Returns the problems (beyond the bounds above,
    or a final hit changed where the choices did not) and every (label, algorithm, test) that
    took another path."""
    problems: list[str] = []
    flipped: list[tuple[str, str, int]] = []
    compared = changed_hits = 0
    for label, now, then in campaigns:
        paths = set(flipped_tests(now["choices_sha256"], then["choices_sha256"]))
        flipped += [(label, name, k) for name, k in sorted(paths)]
        compared += sum(len(v) for v in then["choices_sha256"].values())
        hits_now, hits_then = now["final_hits"], then["final_hits"]
        if set(hits_now) != set(hits_then):
            problems.append(f"{label}: final hits of {sorted(set(hits_now) ^ set(hits_then))} on one side only")
            continue
        for name in sorted(hits_now):
            for k in range(max(len(hits_now[name]), len(hits_then[name]))):
                if hits_now[name][k:k + 1] == hits_then[name][k:k + 1]:
                    continue
                if (name, k) in paths:
                    changed_hits += 1
                else:
                    problems.append(f"{label}: {name} test {k}: final hit {hits_now[name][k:k + 1]!r} != "
                                    f"{hits_then[name][k:k + 1]!r} with the same choices")
    if len(flipped) > MAX_FLIPPED_SHARE * compared:
        problems.append(f"{len(flipped)} of {compared} tests took another path (at most {MAX_FLIPPED_SHARE:.0%}): "
                        + ", ".join(f"{label} {name} test {k}" for label, name, k in flipped[:12]))
    if changed_hits > MAX_CHANGED_HITS_SHARE * compared:
        problems.append(f"{changed_hits} of {compared} final hits changed (at most {MAX_CHANGED_HITS_SHARE:.0%})")
    return problems, flipped


def flipped_tests(now: dict[str, list[str]], recorded: dict[str, list[str]]) -> list[tuple[str, int]]:
    """The (algorithm, test) pairs whose decision digests differ; an algorithm or a test missing
    on one side counts as all of its tests differing."""
    out: list[tuple[str, int]] = []
    for algorithm in sorted(set(now) | set(recorded)):
        a, b = now.get(algorithm, []), recorded.get(algorithm, [])
        out += [(algorithm, k) for k in range(max(len(a), len(b))) if k >= len(a) or k >= len(b) or a[k] != b[k]]
    return out


def _walk(x: Any, y: Any, at: str, key: str, rule: Callable[[str, str], float | None], out: list[str], limit: int) -> None:
    if len(out) >= limit:
        return
    if isinstance(x, dict) and isinstance(y, dict):
        for k in sorted(set(x) | set(y), key=str):
            if k not in x or k not in y:
                out.append(f"{at}/{k}: only on the {'right' if k not in x else 'left'}")
            else:
                _walk(x[k], y[k], f"{at}/{k}", str(k), rule, out, limit)
    elif isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
        for i, (u, v) in enumerate(zip(x, y)):
            _walk(u, v, f"{at}[{i}]", key, rule, out, limit)
    elif (isinstance(x, (int, float)) and isinstance(y, (int, float)) and not isinstance(x, bool)
          and not isinstance(y, bool)):
        tolerance = rule(at, key)
        if tolerance is None:
            return
        if x != y and not abs(x - y) <= tolerance:
            out.append(f"{at}: {x!r} != {y!r}" + (f" (tolerance {tolerance:g})" if tolerance else ""))
    elif x != y:
        out.append(f"{at}: {x!r} != {y!r}")


def differences(a: Any, b: Any, tolerance: Callable[[str, str], float | None] = lambda path, key: 0.0,
                limit: int = 20) -> list[str]:
    """The paths where two JSON-like objects differ (at most ``limit``). ``tolerance(path, key)``
    gives the absolute tolerance of a number at ``path`` (its last key ``key``; 0: exact, None: not
    compared); everything else is compared exactly."""
    out: list[str] = []
    _walk(a, b, "", "", tolerance, out, limit)
    return out


def results_tolerance(flipped: dict[str, int], tests: int) -> Callable[[str, str], float | None]:
    """The tolerance rule for two results objects of the same campaign computed on different
    CPUs, where ``flipped[algorithm]`` of its ``tests`` tests took another path."""
    def rule(path: str, key: str) -> float | None:
        parts = path.split("/")
        if len(parts) > 1 and parts[1].startswith("paired") and any(flipped.values()):
            return None  # McNemar blocks: functions of the per-test outcomes, unit-tested
        name = parts[2].split("[")[0] if len(parts) > 2 else ""
        count = flipped.get(name, 0) if parts[1] in ("algorithms", "outcomes") else 0
        if count:
            return count / tests + 1e-6 if key in DECISION_FRACTION_KEYS else None
        return FITTED_KEYS.get(key, 0.0)
    return rule
