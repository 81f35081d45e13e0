"""Fitting the controllers' confidence maps (``ra2vipas bench calibrate``).

Each algorithm reports a raw confidence: the posterior probability of the target it names,
under its own model. Models are approximations (tempered likelihoods, a POD model learned
from noisy labels), so the raw number is over- or under-confident by an amount that depends
on the algorithm. Platt scaling (Platt 1999; Guo et al. 2017 for its use as "temperature
scaling" of posteriors), with covariates the controller measures itself (how likely the Tx
walks, the fading correlation rho from Rx(iso), the tracker's clutter density, how close the
nearest other track is to the answer), fits per algorithm
sigmoid((A + G tx_walks) logit(raw) + B + C tx_walks + D rho + E clutter + F crowding) to the hit of every step of
simulated tests over a mix of scenarios, with seeds that no benchmark uses. The fitted maps ship,
one named coefficient each (``confidence.ConfidenceMap``), in
``services/controller/data/confidence_maps.json``; this module is how they were made and how to
remake them (``ra2vipas bench calibrate --write``).
"""

from __future__ import annotations

from typing import Any, Callable, Iterable

import numpy as np

from ra2vipas.services.controller.confidence import ADVERTS_MAP_SUFFIX
from ra2vipas.services.controller.policy import RAW_CONFIDENCE_CLIP, Controller, sensor_config_from_scenario, tuned_settings
from ra2vipas.services.orchestrator.metrics import expected_calibration_error, score_test
from ra2vipas.services.orchestrator.simulate import train_pod
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.world import SimulatedPlatform

# A spread of worlds: the paper's, crowds, noise, antenna shapes, cameras, and the dynamic one.
SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("paper", {}),
    "paper-uniform": ("paper-uniform", {}),
    "crowd-40": ("paper-uniform", {"n_targets": 40, "rf_noise_db": 4.0}),
    "noise-6dB": ("paper", {"rf_noise_db": 6.0}),
    "db-gain": ("paper", {"antenna_model": "db-gain"}),
    "wide-lobe": ("paper", {"antenna_curvature": 0.1}),
    "fov-45": ("paper-uniform", {"fov_half_angle_deg": 45.0}),
    "nu-3": ("paper", {"frames_per_rf": 3}),
    "dynamic": ("dynamic", {}),
    "dynamic-static": ("dynamic", {"walking_fraction": 0.0}),
}

# The maps of a rig of BLE advertisements (``bench calibrate --adverts``, named ALGORITHM-adverts,
# ``confidence.ADVERTS_MAP_SUFFIX``): sparse whole-dBm packets give raw confidences that the RSSI
# pairs' map does not describe (Ra²ViPAS on `ble-dynamic`: final confidence 0.92 for a DR of 0.75
# with it). The BLE presets, their uniform placement, and the dynamic one without walkers.
PACKET_SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    "ble": ("ble", {}),
    "ble-uniform": ("ble", {"placement": "uniform"}),
    "ble-dynamic": ("ble-dynamic", {}),
    "ble-dynamic-static": ("ble-dynamic", {"walking_fraction": 0.0}),
    "ble-recorded": ("ble-recorded", {}),
}
_WORLDS = {**SCENARIOS, **PACKET_SCENARIOS}


Samples = tuple[np.ndarray, np.ndarray, np.ndarray]  # raw confidence, covariates (steps, 4), hit


def collect(algorithm: str, tests: int, seed: int, scenarios: Iterable[str] = SCENARIOS,
            progress: Callable[[str], None] | None = None, from_s: float = 0.0,
            workers: int = 1) -> Samples:
    """(raw confidence, covariates (steps, 4): tx_walks, rho, clutter density, crowding, hit) at every
    step of ``tests`` tests of each scenario from ``from_s`` seconds on (the sample of step t is
    taken (t + 1) T_RF after the start), with the algorithm's tuning (its confidence map does not
    change the raw value); scenarios in order, one per worker process at a time (the same arrays
    whatever ``workers``)."""
    return collect_many({algorithm: from_s}, tests, seed, scenarios, progress, workers)[algorithm]


def collect_many(from_s: dict[str, float], tests: int, seed: int, scenarios: Iterable[str] = SCENARIOS,
                 progress: Callable[[str], None] | None = None, workers: int = 1) -> dict[str, Samples]:
    """``collect`` for several algorithms at once (``from_s``: each one's first second), each
    scenario's POD model trained once for all of them: the same arrays as one ``collect`` per
    algorithm (the model depends on the scenario and seed only), for a quarter of the training
    when the four built-ins are fitted."""
    names = list(scenarios)
    unknown = [n for n in names if n not in _WORLDS]
    if unknown:
        raise ValueError(f"unknown calibration scenario(s) {unknown}; known: {', '.join(_WORLDS)}")
    parts = _per_scenario(lambda name: (_collect_scenario, dict(from_s), name, tests, seed), names, workers, progress)
    if not parts:
        return {a: (np.zeros(0), np.zeros((0, 4)), np.zeros(0)) for a in from_s}
    return {a: tuple(np.concatenate([p[a][i] for p in parts]) for i in range(3)) for a in from_s}  # type: ignore[misc]


def _per_scenario(task: Callable[[str], tuple], names: list[str], workers: int,
                  progress: Callable[[str], None] | None) -> list:
    """Run ``task(name)`` (a function and its arguments, picklable) for each scenario, one per
    worker process at a time, and return the results in the scenarios' order (the same whatever
    ``workers``), calling ``progress(name)`` as each is collected."""
    from ra2vipas.services.orchestrator.engine import worker_pool

    parts = []
    with worker_pool(max(1, min(workers, len(names)))) as pool:
        futures = [pool.submit(*task(name)) for name in names]
        for name, future in zip(names, futures):
            parts.append(future.result())
            if progress:
                progress(name)
    return parts


def _collect_scenario(from_s: dict[str, float], name: str, tests: int, seed: int) -> dict[str, Samples]:
    """``collect_many`` for one scenario: its POD model trained once, then each algorithm's tests."""
    preset, overrides = _WORLDS[name]
    scenario = build_scenario(preset, overrides)
    pod = train_pod(scenario, seed)
    return {algorithm: _run_tests(algorithm, scenario, pod.model, tests, seed, first_s) for algorithm, first_s in from_s.items()}


def _run_tests(algorithm: str, scenario, pod_model, tests: int, seed: int, from_s: float) -> Samples:
    settings = tuned_settings(algorithm)
    raw, walks, hit = [], [], []
    for k in range(tests):
        platform = SimulatedPlatform(scenario, seed, k)
        controller = Controller(algorithm, sensor_config_from_scenario(scenario), pod_model, settings)
        pan, estimates = controller.first_pan(), []
        first = 0
        for t in range(scenario.steps):
            d = controller.step(platform.sense(t, pan))
            pan = d.next_pan_rad
            estimates.append(d.estimate_rad)
            if (t + 1) * scenario.rf_period_s < from_s - 1e-9:
                first = t + 1
                continue
            raw.append(d.raw_confidence)
            walks.append((d.tx_walks, d.noise_correlation, d.clutter_density, d.crowding))
        truth = platform.truth
        hits, _ = score_test(np.asarray(estimates), truth.step_bearings_rad(), truth.tx_index, scenario.fov_half_angle_rad)
        hit += hits[first:].tolist()
    return np.asarray(raw, dtype=float), np.asarray(walks, dtype=float).reshape(-1, 4), np.asarray(hit, dtype=float)


# Worlds with several tags (issue 21) for the joint searches' maps: the paper's with K = 3, its
# uniform placement, two tags that may share a person, and the ward (the dynamic world, K = 3).
JOINT_SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper-3": ("paper", {"n_tags": 3}),
    "paper-uniform-3": ("paper-uniform", {"n_tags": 3}),
    "paper-2-shared": ("paper", {"n_tags": 2, "one_tag_per_person": False}),
    "ward": ("ward", {}),
}
# ... and on BLE advertisements (``--joint --adverts``: ALGORITHM-joint-adverts): the same four
# kinds of world heard by the BLE radio
JOINT_PACKET_SCENARIOS: dict[str, tuple[str, dict[str, Any]]] = {
    "ble-3": ("ble", {"n_tags": 3}),
    "ble-uniform-3": ("ble", {"n_tags": 3, "placement": "uniform"}),
    "ble-2-shared": ("ble", {"n_tags": 2, "one_tag_per_person": False}),
    "ble-ward": ("ble-dynamic", {"n_tags": 3}),
}
_JOINT_WORLDS = {**JOINT_SCENARIOS, **JOINT_PACKET_SCENARIOS}


def joint_map_name(algorithm: str, adverts: bool = False) -> str:
    """The name of ``algorithm``'s map for searches of several tags at once in the maps file (on a
    rig of BLE advertisements: ALGORITHM-joint-adverts)."""
    return f"{algorithm}-joint" + (ADVERTS_MAP_SUFFIX if adverts else "")


def collect_joint(algorithm: str, tests: int, seed: int, scenarios: Iterable[str] = JOINT_SCENARIOS,
                  progress: Callable[[str], None] | None = None, from_s: float = 0.0,
                  workers: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``collect`` for the joint search of several tags (``builtins.joint_search``): at every
    step from ``from_s`` seconds on, every tag's raw confidence, covariates and hit (eq. 11
    against that tag's carrier), of ``tests`` tests of each of ``scenarios`` (of ``JOINT_SCENARIOS``
    or ``JOINT_PACKET_SCENARIOS``)."""
    names = list(scenarios)
    unknown = [n for n in names if n not in _JOINT_WORLDS]
    if unknown:
        raise ValueError(f"unknown joint calibration scenario(s) {unknown}; known: {', '.join(_JOINT_WORLDS)}")
    parts = _per_scenario(lambda name: (_collect_joint_scenario, algorithm, name, tests, seed, from_s), names, workers, progress)
    if not parts:
        return np.zeros(0), np.zeros((0, 4)), np.zeros(0)
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))  # type: ignore[return-value]


def _collect_joint_scenario(algorithm: str, name: str, tests: int, seed: int,
                            from_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``collect_joint`` for one scenario."""
    from ra2vipas.services.controller.builtins import joint_search
    from ra2vipas.services.controller.contract import episode_context

    preset, overrides = _JOINT_WORLDS[name]
    scenario = build_scenario(preset, overrides)
    pod = train_pod(scenario, seed)
    first = 0
    while (first + 1) * scenario.rf_period_s < from_s - 1e-9:
        first += 1
    raw, cov, hit = [], [], []
    for k in range(tests):
        platform = SimulatedPlatform(scenario, seed, k)
        context = episode_context(sensor_config_from_scenario(scenario), pod.model, scenario, seed, k)
        search = joint_search(algorithm, context, scenario.n_tags)
        pan, decisions = search.first_pan(), []
        for t in range(scenario.steps):
            d = search.step(platform.sense(t, pan))
            pan = d.next_pan_rad
            decisions.append(d.tags)
        truth = platform.truth
        for tag, carrier in enumerate(truth.carriers):
            estimates = np.asarray([step[tag].estimate_rad for step in decisions])
            hits, _ = score_test(estimates, truth.step_bearings_rad(), carrier, scenario.fov_half_angle_rad)
            hit += hits[first:].tolist()
            for step in decisions[first:]:
                c = step[tag].covariates
                raw.append(step[tag].raw_confidence)
                cov.append((c.tx_walks, c.noise_correlation, c.clutter_density, c.crowding))
    return np.asarray(raw, dtype=float), np.asarray(cov, dtype=float).reshape(-1, 4), np.asarray(hit, dtype=float)


def _design(raw: np.ndarray, covariates: np.ndarray) -> np.ndarray:
    """Columns: logit(raw clipped), 1, the covariates, and logit x the first covariate (tx_walks)."""
    p = np.clip(raw, RAW_CONFIDENCE_CLIP, 1.0 - RAW_CONFIDENCE_CLIP)
    cov = np.asarray(covariates, dtype=float).reshape(raw.size, -1)
    logit = np.log(p / (1.0 - p))
    return np.column_stack([logit, np.ones(raw.size), cov, logit * cov[:, 0]])


def fit_platt(raw: np.ndarray, covariates: np.ndarray, hit: np.ndarray) -> tuple[float, ...]:
    """(A, B, C, ..., G) maximising the Bernoulli likelihood of ``hit`` under
    sigmoid((A + G covariates[:, 0]) logit(raw) + B + C covariates[:, 0] + ...): a logistic
    regression (scikit-learn's, unpenalised) of the hit on the raw logit, the covariates and the
    logit times the first covariate."""
    from sklearn.linear_model import LogisticRegression

    X = _design(raw, covariates)
    model = LogisticRegression(C=np.inf, fit_intercept=False, max_iter=1000).fit(X, hit.astype(int))
    return tuple(float(v) for v in model.coef_[0])


def platt(raw: np.ndarray, covariates: np.ndarray, *coefficients: float) -> np.ndarray:
    X = _design(raw, covariates)
    return 1.0 / (1.0 + np.exp(-(X @ np.asarray(coefficients, dtype=float))))


# How far a shipped map may be from the map refitted now, by what it does on the fitting data
# (not by its coefficients' digits: an unpenalised logistic regression's coefficients move in
# their 2nd-3rd decimal when another CPU moves raw confidences in their last bits, while what
# the map does barely moves). The test is the likelihood: 2 x the excess negative log-likelihood
# is the likelihood-ratio statistic of the shipped map against the refit, and <= 4 (2 nats) lies
# deep inside the refit's own 7-parameter confidence region (chi-squared_7, p = 0.78). Measured
# on the four maps (~40 000 steps each): rounding the coefficients to 4 decimals costs <= 0.004
# nats; this machine reduced to its SSE baseline (tests/docs/test_other_cpus.py) 0.0-0.40 nats,
# confidences moved by <= 0.018, ECE by <= 0.0004; scaling the logit's coefficient by 5 % (a
# small real change of a controller) costs 6.9-103 nats. Confidences and ECE are bounded too, as
# sanity limits a few times what another CPU moved.
MAP_TOLERANCE = {"nll_nats": 2.0, "confidence": 0.05, "ece": 0.002}

# The joint search's map (``bench calibrate --joint``: 20 tests of 2-3 tags, ~20 000 tag-steps) is
# determined less sharply, and another CPU moves its data more: each step's confidence comes from
# three tags' chains of decisions, and a last-bit difference that flips one pan changes the rest
# of the episode for every tag. Measured on a 2-core AMD EPYC (Zen 4), against the map the
# previous machine fitted with the same command: 1.92 nats, confidences by <= 0.028, ECE by
# 0.0020 (the ECE's bootstrap standard deviation on those steps: 0.0015). Still within the
# refit's own confidence region (2 x 4 nats = 8: chi-squared_7, p = 0.33), and ECE within about
# 2.5 bootstrap standard deviations; the single-tag map, which the joint search used before, is
# 321 nats away on the same steps.
JOINT_MAP_TOLERANCE = {"nll_nats": 4.0, "confidence": 0.05, "ece": 0.004}

# The maps of a rig of BLE advertisements (``bench calibrate --adverts``) are determined far less
# sharply across machines: a packet world's episode hangs on a few sparse packets, so a last-bit
# difference that moves one pan changes the rest of the episode, and another CPU's fitting episodes
# are in part other episodes. Measured on a 2-core AMD EPYC (Zen 4), the shipped maps against the
# refit on numpy's, OpenBLAS's and numba's other kernels (ra2vipas, rapas, ravipas, sweep): all three
# as tests/docs/test_other_cpus.py sets them 29.4 / 35.6 / 0.03 / 0.37 nats (confidences by <= 0.20,
# ECE by <= 0.0037); numpy without X86_V4 alone 4.1 / 14.4 / 0.0 / 0.1 nats (ECE by <= 0.016);
# OpenBLAS on Haswell <= 0.0003 nats -- the refit's own spread, up to about a 15 % change of its
# logit coefficient. The check still tells these maps from the RSSI pairs' (386-1013 nats away on the
# same steps) and from the logit coefficient 30 % low or 50 % high (>= 135 nats on either kernels).
ADVERTS_MAP_TOLERANCE = {"nll_nats": 80.0, "confidence": 0.3, "ece": 0.03}
# The joint search's on BLE advertisements (``--joint --adverts``; three tags' chains of decisions
# over sparse packets): 137.7 nats from the refit with all three kernels changed (confidences by
# <= 0.31, ECE by 0.001), 10.8 without X86_V4, 3.0 on Haswell's OpenBLAS; the RSSI pairs' joint map
# is 1912-2026 nats away, the logit coefficient halved or doubled >= 520.
JOINT_ADVERTS_MAP_TOLERANCE = {"nll_nats": 300.0, "confidence": 0.5, "ece": 0.03}


def map_agreement(raw: np.ndarray, covariates: np.ndarray, hit: np.ndarray, shipped: Iterable[float],
                  refitted: Iterable[float]) -> dict[str, float]:
    """What separates two confidence maps on the same steps: the excess negative log-likelihood of
    ``shipped`` over ``refitted`` (nats; twice it is the likelihood-ratio statistic, so well
    under 1 nat is far inside the fit's own sampling noise), the largest difference of the
    confidences they give, and the difference of their ECE."""
    a, b = platt(raw, covariates, *shipped), platt(raw, covariates, *refitted)

    def nll(p: np.ndarray) -> float:
        p = np.clip(p, 1e-12, 1.0 - 1e-12)
        return float(-(hit * np.log(p) + (1.0 - hit) * np.log(1.0 - p)).sum())

    return {"nll_nats": nll(a) - nll(b), "confidence": float(np.max(np.abs(a - b), initial=0.0)),
            "ece": abs((expected_calibration_error(a, hit) or 0.0) - (expected_calibration_error(b, hit) or 0.0))}


def map_drift(agreement: dict[str, float], tolerance: dict[str, float] = MAP_TOLERANCE) -> list[str]:
    """The measures of ``map_agreement`` beyond ``tolerance`` (empty: the same map)."""
    return [f"{k} {agreement[k]:.4g} > {limit:g}" for k, limit in tolerance.items() if not agreement[k] <= limit]


def calibrate(algorithms: Iterable[str], tests: int, seed: int, progress: Callable[[str], None] | None = None,
              from_s: float = 0.0, workers: int = 1, scenarios: Iterable[str] | None = None, joint: bool = False,
              adverts: bool = False) -> dict[str, Any]:
    """Fit every algorithm's map on the steps from ``from_s`` seconds on of ``scenarios`` (default:
    all of ``SCENARIOS``, or of ``PACKET_SCENARIOS`` with ``adverts``; ``workers`` processes run the scenarios, each training its POD model once
    for every algorithm; the maps do not depend on it); report it with the ECE before and after on
    the fitting data. ``joint``: the maps of the searches for several tags at once, fitted on
    every tag's steps in ``JOINT_SCENARIOS`` (named ``joint_map_name(algorithm)``; ``scenarios``
    is not used). ``adverts``: the maps of a rig of BLE advertisements (named ALGORITHM-adverts),
    on ``PACKET_SCENARIOS`` (default) or the given subset of them; with ``joint``, the joint
    searches' (ALGORITHM-joint-adverts) on ``JOINT_PACKET_SCENARIOS``."""
    names = list(algorithms)
    table = PACKET_SCENARIOS if adverts else SCENARIOS
    joint_worlds = JOINT_PACKET_SCENARIOS if adverts else JOINT_SCENARIOS
    worlds = list(joint_worlds) if joint else list(table if scenarios is None else scenarios)
    foreign = [w for w in worlds if not joint and w not in table]
    if foreign:
        raise ValueError(f"unknown calibration scenario(s) {foreign}; known: {', '.join(table)}")
    out: dict[str, Any] = {"tests_per_scenario": tests, "seed": seed, "from_s": from_s, "scenarios": worlds, "algorithms": {}}
    if adverts:
        out["adverts"] = True
    if joint:
        out["joint"] = True
        samples = {a: collect_joint(a, tests, seed, worlds, progress=(lambda name, a=a: progress(f"{a}: {name}")) if progress else None,
                                    from_s=from_s, workers=workers) for a in names}
    else:
        samples = collect_many({a: from_s for a in names}, tests, seed, worlds, progress=progress, workers=workers)
    for algorithm in names:
        raw, walks, hit = samples[algorithm]
        coefficients = fit_platt(raw, walks, hit)
        name = joint_map_name(algorithm, adverts) if joint else algorithm + ADVERTS_MAP_SUFFIX if adverts else algorithm
        out["algorithms"][name] = {
            "map": [round(v, 4) for v in coefficients], "samples": int(raw.size),
            "ece_raw": round(expected_calibration_error(raw, hit), 4),
            "ece_fitted": round(expected_calibration_error(platt(raw, walks, *coefficients), hit), 4),
        }
    return out
