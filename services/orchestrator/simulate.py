"""In-process Monte Carlo campaign: the same episodes the mesh runs, in one Python process.

``run_campaign`` trains the POD model once for (scenario, seed), then runs every test of every
algorithm, each with its own simulated platform seeded from (seed, test index), and reduces
the outcomes to the results object that ``ra2vipas simulate --json`` prints and the REST API
serves.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from ra2vipas.services.controller import registry
from ra2vipas.services.controller.contract import episode_context
from ra2vipas.services.controller.policy import ControllerSettings, sensor_config_from_scenario
from ra2vipas.services.learner.model_cache import CachedPOD, PODCache
from ra2vipas.services.learner.pod import LearnedPOD, LearnerSettings, TrainingDataError, fit_pod
from ra2vipas.services.learner.trained import TrainedPOD, predict, r2_score
from ra2vipas.services.orchestrator.envelope import add_provenance, overrides_of, summarize  # noqa: F401  (the results object)
from ra2vipas.services.orchestrator.metrics import score_episode
from ra2vipas.services.orchestrator.reduce import held
from ra2vipas.services.protocol.messages import training_job_id
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.scenario import Scenario, ScenarioError
from ra2vipas.services.sensors.world import SimulatedPlatform, TrainingEpisode


@dataclass
class TestOutcome:
    """One test of one algorithm: per step, what the controller did and how it scored."""

    algorithm: str
    test_index: int
    pans: list[float] = field(default_factory=list)
    estimates: list[float] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    hits: list[bool] = field(default_factory=list)
    in_fov: list[bool] = field(default_factory=list)
    chosen: list[int] = field(default_factory=list)
    confidences: list[float] = field(default_factory=list)  # per step of the whole test (held after a decision)
    decided_step: int | None = None  # the step of an early decision (stop_confidence), if any
    tags: TagOutcome | None = None  # a search for several tags (issue 21): per tag, what it named and how it scored


@dataclass
class TagOutcome:
    """Per tag of one test that searched for K tags: the estimates and confidences it named after
    each step, the step each tag was decided at, and, once scored, per step whether the target
    named for tag k carries tag k (eq. 11 per tag) and whether that carrier is in the FoV.
    Arrays are (K, T) over the whole test (an episode that ended early holds its answers)."""

    estimates: list[list[float]] = field(default_factory=list)  # per step, K values
    confidences: list[list[float]] = field(default_factory=list)  # per step, K values
    decided_steps: list[int | None] = field(default_factory=list)  # K values
    hits: np.ndarray | None = None  # (K, T) bool
    in_fov: np.ndarray | None = None  # (K, T) bool
    held_confidences: np.ndarray | None = None  # (K, T) float


def _from_cache(scenario: Scenario, seed: int, settings: LearnerSettings | None) -> tuple[PODCache | None, str, CachedPOD | None]:
    """The POD model cache in force (None: off), the training job id of (scenario, seed), and the
    scored model the cache holds for it (None: none; a learner service's model, unscored, is not one)."""
    # the key is (scenario, seed) and the settings given: what ``for_scenario`` adds is the scenario's
    store, job = PODCache.from_environment(settings or LearnerSettings()), training_job_id(scenario, seed)
    hit = store.load(job) if store is not None else None
    return store, job, (hit if hit is not None and hit.r2 is not None else None)


def pod_is_cached(scenario: Scenario, seed: int, settings: LearnerSettings | None = None) -> bool:
    """Whether ``train_pod(scenario, seed)`` will load the model from the cache rather than train it."""
    return _from_cache(scenario, seed, settings)[2] is not None


def train_pod(scenario: Scenario, seed: int, settings: LearnerSettings | None = None, cache: bool = True) -> TrainedPOD:
    """Run the training episode, fit the POD and score it by eq. (23) against the truth; or, with
    ``cache``, load the model this machine and this code already trained for (scenario, seed)
    (``services/learner/model_cache.py``: the same bytes, ``cached`` set)."""
    store, job, hit = _from_cache(scenario, seed, settings) if cache else (None, training_job_id(scenario, seed), None)
    if hit is not None:
        return TrainedPOD(model=hit.model, r2=hit.r2, train_seconds=hit.train_seconds, cached=True)
    episode = TrainingEpisode(scenario, seed)
    try:
        learned: LearnedPOD = fit_pod(list(episode.samples()), LearnerSettings.for_scenario(scenario, settings))
    except TrainingDataError as err:  # the scenario's training episode is too short for its radio: say which parameter
        raise ScenarioError(f"n_train = {scenario.n_train} is too short a training episode for this world: {err}; "
                            "raise n_train") from None
    r2 = r2_score(episode.truth.pod, predict(learned.model, episode.truth.rssi_dbm))
    pod = TrainedPOD(model=learned.model, r2=round(float(r2), 6), train_seconds=learned.train_seconds)
    if store is not None:
        store.store(job, CachedPOD(model=pod.model, r2=pod.r2, train_seconds=pod.train_seconds))
    return pod


def run_test(scenario: Scenario, seed: int, test_index: int, algorithm: str, pod_model: PODModel,
             settings: ControllerSettings | None = None, stop_confidence: float = 0.0) -> TestOutcome:
    """One episode: the platform senses, the policy ``algorithm`` (a registered name or
    ``module:Class``, ``services/controller/registry.py``) decides, n_test times, or until the
    first step whose confidence reaches ``stop_confidence`` (> 0): that answer is final. The
    policy sees the measurements only (``StepMeasurement``); truth scores it afterwards."""
    platform = SimulatedPlatform(scenario, seed, test_index)
    policy = new_policy(algorithm, scenario, seed, test_index, pod_model, settings, stop_confidence)
    outcome = TestOutcome(algorithm=algorithm, test_index=test_index)
    pan = policy.first_pan()
    says_confidence = True
    for t in range(scenario.steps):
        measurement = platform.sense(t, pan)
        decision = policy.step(measurement)
        tags = getattr(decision, "tags", None) if scenario.n_tags > 1 else None
        if tags:  # several tags (issue 21): the episode ends when every tag is decided
            outcome.tags = outcome.tags or TagOutcome()
            outcome.tags.estimates.append([float(d.estimate_rad) for d in tags])
            outcome.tags.confidences.append([float(d.confidence) for d in tags])
            outcome.tags.decided_steps = [d.decided_step for d in tags]
        outcome.pans.append(pan)
        outcome.estimates.append(float(decision.estimate_rad))
        reward = getattr(decision, "reward", None)
        outcome.rewards.append(0.0 if reward is None else float(reward))
        confidence = getattr(decision, "confidence", None)
        says_confidence = says_confidence and confidence is not None
        outcome.confidences.append(0.0 if confidence is None else float(confidence))
        pan = float(decision.next_pan_rad)
        if tags:
            if stop_confidence > 0.0 and getattr(decision, "all_decided", False):
                outcome.decided_step = t
                break
        elif stop_confidence > 0.0 and confidence is not None and confidence >= stop_confidence:
            outcome.decided_step = t
            break
    truth = platform.truth
    bearings = truth.step_bearings_rad()  # (N,), or (T, N) when targets walk: DR_t against the bearings at t
    hits, in_fov, chosen = score_episode(np.asarray(outcome.estimates), bearings, truth.tx_index, scenario.fov_half_angle_rad,
                                         scenario.steps, outcome.decided_step)
    outcome.hits = [bool(h) for h in hits]
    outcome.in_fov = [bool(f) for f in in_fov]
    outcome.chosen = [int(i) for i in chosen]
    outcome.confidences = held(outcome.confidences, scenario.steps) if says_confidence else []
    if outcome.tags is not None:
        score_tags(outcome.tags, bearings, truth.carriers, scenario, outcome.decided_step)
    return outcome


def score_tags(tags: TagOutcome, bearings, carriers, scenario: Scenario, decided_step: int | None) -> None:
    """Score each tag's estimates against its carrier (eq. 11 per tag), held to the horizon after
    an early end; fills ``tags.hits``, ``tags.in_fov`` and ``tags.held_confidences``."""
    estimates = np.asarray(tags.estimates, dtype=float)  # (t_run, K)
    hits, in_fov = [], []
    for k in range(estimates.shape[1]):
        h, f, _ = score_episode(estimates[:, k], bearings, carriers[k], scenario.fov_half_angle_rad, scenario.steps, decided_step)
        hits.append(h)
        in_fov.append(f)
    tags.hits = np.asarray(hits, dtype=bool)
    tags.in_fov = np.asarray(in_fov, dtype=bool)
    conf = np.asarray(tags.confidences, dtype=float)
    if conf.shape[0] < scenario.steps:
        conf = np.concatenate([conf, np.repeat(conf[-1:], scenario.steps - conf.shape[0], axis=0)])
    tags.held_confidences = conf.T.copy()


def new_policy(algorithm: str, scenario: Scenario, seed: int, test_index: int, pod_model: PODModel,
               settings: ControllerSettings | None = None, stop_confidence: float = 0.0):
    """The policy object of one simulated episode, given what the contract allows: the rig as
    the scenario describes it, the POD model, the public scenario, the seed and test index, and
    the campaign's early-decision level."""
    context = episode_context(sensor_config_from_scenario(scenario), pod_model, scenario, seed, test_index, stop_confidence)
    return registry.create(algorithm, context, settings)


def run_campaign(preset: str, scenario: Scenario, tests: int, seed: int, algorithms: Iterable[str] = registry.BUILTINS,
                 settings: ControllerSettings | None = None,
                 progress: Callable[[int, int], None] | None = None, stop_confidence: float = 0.0,
                 workers: int = 1, on_trained: Callable[[TrainedPOD], None] | None = None) -> dict[str, Any]:
    """Train once, run tests x algorithms episodes, return the results object.

    ``progress(done, total)`` is called as episodes finish, ``on_trained(pod)`` once the POD
    model is trained (before the first episode); ``stop_confidence`` > 0 ends each
    episode at its first step that confident (its answer final) and adds ``decision`` blocks.
    ``workers`` > 1 runs the tests on that many processes (``engine.run_points``), with results
    identical value for value to ``workers=1``; outcomes are reduced as they arrive, never
    held for every test at once.
    """
    from ra2vipas.services.orchestrator.engine import Point, run_points

    point = Point(preset=preset, scenario=scenario, tests=tests, seed=seed, algorithms=tuple(algorithms),
                  stop_confidence=stop_confidence)
    announce = None if on_trained is None else (lambda _i, pod: on_trained(pod))
    return run_points([point], workers=workers, progress=progress, settings=settings, on_trained=announce).results[0]
