"""API schemas (request and response bodies), distinct from wire messages and database rows.

Families: ``CampaignCreate`` (what a client sends), ``*Public`` (what the API shows), and
``*Page`` (one page of a list with its total).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, StringConstraints

from ra2vipas.services.controller.registry import BUILTINS
from ra2vipas.services.protocol.messages import MAX_TESTS, AlgorithmName

MAX_OVERRIDES = 64
MAX_PAGE = 200
MAX_OFFSET = 1_000_000_000

ALGORITHM_NAMES = BUILTINS  # the built-in policies, a campaign's default
MAX_POLICIES = 16
CampaignStatus = Literal["queued", "training", "running", "done", "failed", "cancelled"]
EpisodeStatus = Literal["pending", "running", "done", "cancelled"]

class PolicyPublic(BaseModel):
    """A pointing policy a campaign can name (GET /policies)."""

    name: str
    package: str = Field(description="the distribution that registered it")
    version: str
    builtin: bool
    summary: str = ""


ParameterName = Annotated[str, StringConstraints(min_length=1, max_length=64)]
OverrideValue = Union[StrictBool, StrictInt, StrictFloat, Annotated[str, StringConstraints(max_length=64)]]


# -- errors --------------------------------------------------------------------------------------

class ErrorItem(BaseModel):
    loc: list[Union[str, int]] = Field(description="where the error is, e.g. [\"body\", \"tests\"]")
    msg: str
    type: str


class ErrorPublic(BaseModel):
    """Body of every error response: one line naming the field and what is allowed."""

    detail: str
    errors: Optional[list[ErrorItem]] = Field(None, description="422 only: every invalid field")


# -- campaigns -----------------------------------------------------------------------------------

class CampaignCreate(BaseModel):
    """Body of ``POST /campaigns``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    preset: str = Field("paper", description="scenario preset (GET /presets)", max_length=64)
    overrides: dict[ParameterName, OverrideValue] = Field(
        default_factory=dict, max_length=MAX_OVERRIDES,
        description="scenario parameters to override, NAME: value (GET /presets/{name} lists them with their ranges)")
    algorithms: list[AlgorithmName] = Field(default_factory=lambda: list(ALGORITHM_NAMES), min_length=1, max_length=MAX_POLICIES,
                                            description="pointing policies (GET /policies): the built-ins ra2vipas, rapas, ravipas, "
                                                        "sweep, or any installed policy")
    tests: int = Field(50, ge=1, le=MAX_TESTS, strict=True, description="Monte Carlo tests per algorithm")
    seed: int = Field(1, ge=0, le=2**63 - 1, strict=True, description="campaign seed; fixes every random draw")
    mode: Literal["fast", "realtime"] = Field("fast", description="fast: lockstep as fast as possible; realtime: one sample every T_RF")
    name: Optional[str] = Field(None, max_length=100, strict=True, description="a label")
    stop_confidence: float = Field(0.0, ge=0.0, lt=1.0, strict=True, description="end each episode at the first step whose confidence "
                                   "reaches this, its answer final (0: off); results then carry `decision` per algorithm")
    rigs: Optional[list[Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_-]{1,64}$")]]] = Field(
        None, min_length=1, max_length=256, description="run only on these rigs (default: any live rig)")
    rig_kind: Optional[Literal["simulated", "hardware", "survey"]] = Field(None, description="run only on rigs of this kind")
    use_rig_values: bool = Field(False, strict=True, description="where the scenario contradicts a targeted rig's descriptor, take the "
                                 "rig's values (else such a campaign is refused with a 422 naming each conflicting field)")


class Targeting(BaseModel):
    rigs: Optional[list[str]] = Field(None, description="the rigs it may run on (null: any)")
    rig_kind: Optional[str] = Field(None, description="the kind of rig it may run on (null: any)")
    use_rig_values: bool = False
    rig_values: dict[str, Any] = Field(default_factory=dict, description="scenario parameters taken from the rigs' descriptors")


class Progress(BaseModel):
    done: int = Field(description="episodes (test x algorithm) recorded")
    running: int
    pending: int
    total: int


class PODSummary(BaseModel):
    r2: Optional[float] = Field(None, description="R^2 of the learned POD against the truth of its training episode (eq. 23)")
    train_seconds: Optional[float] = None


class ResultsPOD(PODSummary):
    note: Optional[str] = Field(None, description="why r2 is null (no rig served the training truth)")


class CampaignProgress(BaseModel):
    """What the progress stream sends (``event: progress``)."""

    id: str
    status: CampaignStatus
    progress: Progress
    started_at: Optional[float]
    finished_at: Optional[float]
    pod: PODSummary
    error: Optional[str]


class CampaignPublic(CampaignProgress):
    """A campaign as the API shows it: status, progress, timings, the scenario resolved in
    full (every parameter) and the POD fit."""

    name: Optional[str]
    preset: str
    overrides: dict[str, Any]
    scenario: dict[str, Any]
    algorithms: list[str]
    tests: int
    seed: int
    mode: str
    created_at: float
    elapsed_s: Optional[float] = Field(description="from start to finish (or to now while it runs)")
    steps_per_second: Optional[float]
    stop_confidence: float = Field(0.0, description="early decision threshold (0: off)")
    targeting: Optional[Targeting] = Field(None, description="which rigs it runs on (null: any live rig)")


class CampaignPage(BaseModel):
    items: list[CampaignPublic]
    total: int = Field(description="campaigns matching the filters")
    limit: int
    offset: int


# -- results -------------------------------------------------------------------------------------

class ReliabilityBin(BaseModel):
    lo: float
    hi: float
    n: int = Field(description="tests whose final confidence fell in [lo, hi)")
    confidence: Optional[float] = Field(description="their mean final confidence")
    accuracy: Optional[float] = Field(description="their share of final hits")


class Calibration(BaseModel):
    ece_final: Optional[float] = Field(description="expected calibration error (10 bins) of the final confidence against the final hit")
    ece_final_floor: Optional[float] = Field(None, description=(
        "the ece_final a perfectly calibrated confidence would show on average with these final confidences and this "
        "many tests (hits drawn as Bernoulli(confidence)): its sampling floor; an ece_final near it is noise"))
    ece_all: Optional[float] = Field(description="the same over every step's confidence and hit")
    confidence_final: Optional[float] = Field(None, description="mean final confidence")
    reliability: list[ReliabilityBin] = Field(default_factory=list, description="the reliability diagram of the final confidences (10 bins)")


class Decision(BaseModel):
    accuracy: Optional[float] = Field(description="share of tests whose final answer (decided early or at the horizon) is the Tx")
    accuracy_ci95: list[float] = Field(min_length=2, max_length=2, description="its Wilson 95 % interval")
    median_s: Optional[float] = Field(description="median time to decision over the tests that decided")
    p90_s: Optional[float] = Field(description="90th percentile of the time to decision")
    undecided: Optional[float] = Field(description="share of tests that never reached the confidence")


class AlgorithmResults(BaseModel):
    dr: list[float] = Field(description="DR_t at every step (association rule, eq. 11)")
    dr_final: float
    ci95: list[float] = Field(min_length=2, max_length=2, description="Wilson 95 % interval of the final DR")
    dr_ci95: list[list[float]] = Field(description="Wilson 95 % interval [lo, hi] at every step")
    time_to_dr90_s: Optional[float] = Field(description="time after which DR stays >= 0.9; null if it ends below")
    in_fov_final: float = Field(description="rate of tests with the Tx inside the FoV at the final estimate (secondary)")
    calibration: Optional[Calibration] = Field(None, description="how honest the confidences were (absent without confidences)")
    decision: Optional[Decision] = Field(None, description="early decision (campaigns with stop_confidence > 0)")
    tags: Optional["TagsResults"] = Field(None, description="a search for several tags (n_tags > 1): per tag and all found; "
                                                            "the fields above then describe tag 0")


class AllFound(BaseModel):
    dr: list[float] = Field(description="at every step, the share of tests in which every tag's named target carries it")
    dr_final: float
    ci95: list[float] = Field(min_length=2, max_length=2, description="Wilson 95 % interval of the final rate")
    dr_ci95: list[list[float]] = Field(description="Wilson 95 % interval [lo, hi] at every step")
    time_to_dr90_s: Optional[float] = Field(description="time after which the rate stays >= 0.9; null if it ends below")


class AllDecided(BaseModel):
    median_s: Optional[float] = Field(description="median time until every tag was decided, over the tests where all were")
    p90_s: Optional[float] = Field(description="its 90th percentile")
    undecided: Optional[float] = Field(description="share of tests in which some tag never reached the confidence")


class TagsResults(BaseModel):
    """A search for several tags (issue 21; docs/tags.md)."""

    per_tag: list[AlgorithmResults] = Field(description="per tag k, its block: DR_t against tag k's carrier (eq. 11 per tag), "
                                                        "calibration, decision")
    mean_tag_dr_final: float = Field(description="the mean over the tags of their final DR")
    all_found: AllFound
    all_decided: Optional[AllDecided] = Field(None, description="early decision (campaigns with stop_confidence > 0)")


class PairedComparison(BaseModel):
    """Two algorithms on the tests both ran (test k is the same world for each): the 2 x 2 counts
    of their final answers, the DR difference and McNemar's exact test."""

    a: str
    b: str
    tests: int = Field(description="tests both recorded")
    both: int = Field(description="tests both found the Tx in")
    only_a: int = Field(description="tests only a found the Tx in")
    only_b: int = Field(description="tests only b found the Tx in")
    neither: int
    dr_difference: Optional[float] = Field(description="DR of a minus DR of b on these tests: (only_a - only_b) / tests")
    p_value: Optional[float] = Field(description="two-sided exact McNemar p-value (binomial test of only_a among the "
                                                 "discordant tests, p = 1/2)")


class LatencySummary(BaseModel):
    p50: float
    p99: float


AlgorithmResults.model_rebuild()


class ResultsPublic(BaseModel):
    """The results object, the same as ``ra2vipas simulate --json`` prints."""

    id: Optional[str] = Field(None, description="the campaign's id (null for a campaign run in-process: `simulate`)")
    preset: str
    overrides: dict[str, Any] = Field(default_factory=dict, description="the scenario's parameters that differ from the preset's "
                                                                          "(what --set would say to rebuild it), typed")
    scenario: dict[str, Any]
    tests: int
    seed: int
    pod: ResultsPOD
    algorithms: dict[str, AlgorithmResults]
    steps_per_second: Optional[float]
    latency_ms: Optional[LatencySummary] = Field(None, description="realtime campaigns only: sample -> command latency")
    stop_confidence: Optional[float] = Field(None, description="early decision threshold, when the campaign had one")
    partial: Optional[bool] = Field(None, description="true for a cancelled or failed campaign: the reduction of the episodes "
                                                      "recorded before it stopped (tests_recorded says how many per algorithm)")
    tests_recorded: Optional[dict[str, int]] = Field(None, description="partial results only: tests recorded per algorithm")
    outcomes: Optional[dict[str, list[Optional[int]]]] = Field(None, description="per algorithm, the final hit (1/0) of every test "
                                                                                 "by index (null: not recorded)")
    paired: Optional[list[PairedComparison]] = Field(None, description="every pair of algorithms compared test by test (McNemar)")
    paired_all_found: Optional[list[PairedComparison]] = Field(None, description="several tags: the same comparison on whether "
                                                                                  "every tag's final answer was right")
    warnings: Optional[list[str]] = Field(None, description="what makes these numbers suspect, e.g. every radio algorithm far below "
                                                            "chance, or Rx(dir)'s samples contradicting the assumed antenna model")
    assumptions: Optional[dict[str, Any]] = Field(None, description="present when some episodes ran on undescribed rigs: they were "
                                                                    "modelled and scored under the scenario's assumptions")
    policies: Optional[dict[str, dict[str, str]]] = Field(None, description="policies outside the built-ins: the package and version "
                                                                            "each came from ({name: {package, version}})")


class OutcomePublic(BaseModel):
    """One test of one algorithm: how it ended (null fields until it is done)."""

    test_index: int
    algorithm: str
    status: EpisodeStatus
    rig: Optional[str]
    attempt: int
    tx_index: Optional[int] = Field(description="i*, the target carrying the Tx")
    final_choice: Optional[int] = Field(description="î at the last step (eq. 11)")
    final_hit: Optional[bool] = Field(description="î = i* at the last step")
    final_in_fov: Optional[bool]
    final_estimate_rad: Optional[float] = Field(description="gamma_hat at the last step")
    hit_rate: Optional[float] = Field(description="fraction of steps with î_t = i*")
    first_hit_s: Optional[float] = Field(description="time of the first step with î_t = i*")
    settled_s: Optional[float] = Field(description="time after which î_t = i* until the end; null if the test ends on a miss")
    final_confidence: Optional[float] = Field(None, description="the controller's confidence in its final answer")
    decided_s: Optional[float] = Field(None, description="time of an early decision (stop_confidence), else null")


class OutcomePage(BaseModel):
    items: list[OutcomePublic]
    total: int
    limit: int
    offset: int


class TargetPublic(BaseModel):
    index: int
    bearing_rad: float = Field(description="gamma_i at step 0 (always, for a static target)")
    range_m: float = Field(description="d_i at step 0")
    is_tx: bool
    bearings_rad: Optional[list[float]] = Field(None, description="walking targets only: gamma_i at every step")
    ranges_m: Optional[list[float]] = Field(None, description="walking targets only: d_i at every step")


class TraceStep(BaseModel):
    step: int
    time_s: float = Field(description="(step + 1) * T_RF")
    pan_rad: float = Field(description="pan angle s_t the sample was taken at")
    reward: float = Field(description="fused objective at s_t")
    gamma_hat_rad: float = Field(description="estimate gamma_hat_t after the sample")
    i_hat: int = Field(description="î_t, the target nearest to gamma_hat_t (eq. 11)")
    hit: bool = Field(description="î_t = i*")
    in_fov: bool = Field(description="the Tx is inside the FoV at gamma_hat_t")
    latency_ms: Optional[float] = Field(None, description="realtime only: sample -> command latency")
    confidence: Optional[float] = Field(None, description="the controller's confidence in the target it named")


class TracePublic(BaseModel):
    campaign_id: str
    test_index: int
    algorithm: str
    rig: Optional[str]
    attempt: int
    tx_index: int
    targets: list[TargetPublic]
    steps: list[TraceStep]
    decided_step: Optional[int] = Field(None, description="the step of an early decision (stop_confidence), else null")
    model_check: Optional[dict[str, Any]] = Field(None, description="how the controller modelled the rig (EpisodeResult.model_check; "
                                                                   "null from a v1 controller)")


# -- presets, rigs, health -----------------------------------------------------------------------

class PresetSummary(BaseModel):
    name: str
    description: str


class ParameterPublic(BaseModel):
    value: Union[StrictBool, StrictInt, StrictFloat, str]
    allowed: str = Field(description="what the parameter accepts, e.g. 'an integer in [1, 500]'")
    description: Optional[str]


class PresetPublic(PresetSummary):
    parameters: dict[str, ParameterPublic]


class ServedPolicy(BaseModel):
    name: str
    package: str = Field("", description="the distribution it comes from, as the controller says (empty: not said)")
    version: str = Field("", description="that distribution's version, as the controller says (empty: not said)")


class RigPublic(BaseModel):
    name: str
    live: bool = Field(description="both its sensors and its controller hold their Zenoh liveliness tokens")
    sensors: bool
    controller: bool
    in_flight: int = Field(description="episodes running on it now")
    described: str = Field("unknown", description="described (it serves its descriptor) | undescribed (a v1 node: modelled from "
                                                  "each campaign's scenario) | asking | unknown (its sensors are down)")
    descriptor: Optional[dict[str, Any]] = Field(None, description="its RigDescriptor (docs/protocol.md), when described")
    protocol: Optional[str] = Field(None, description="the protocol version its nodes speak: its descriptor's, 1.0 when undescribed, "
                                                      "null while not known (docs/protocol.md, \"Compatibility\")")
    announced: str = Field("unknown", description="announced (its controller serves its ControllerInfo on rig/{rig}/policies) | "
                                                  "silent (a 1.0 or 1.1 controller: it serves the four built-ins) | asking | "
                                                  "unknown (its controller is down)")
    policies: Optional[list[ServedPolicy]] = Field(None, description="the pointing policies its controller serves: only episodes "
                                                   "of these go there (null while not known)")
    controller_protocol: Optional[str] = Field(None, description="the protocol version its controller says it speaks (null: "
                                                                 "silent or not known)")


class SupervisedService(BaseModel):
    """A service of the local stack (``ra2vipas up``) that is down and waiting to be restarted."""

    name: str = Field(description="e.g. controller-rig-1, learner, orchestrator")
    state: str = Field(description="restarting (crashed; restarted after a delay doubling from 0.5 s) | backing off (a crash "
                                   "loop: crashed 5 times within a minute, restarted at the capped delay until it stays up)")
    crashes: int = Field(description="crashes within the last window_s seconds")
    window_s: float
    exit_code: Optional[int] = None
    next_restart_at: Optional[float] = Field(None, description="epoch seconds of the next restart (None: it is running)")


class RigsPublic(BaseModel):
    rigs: list[RigPublic]
    learners: list[str]
    services: list[SupervisedService] = Field(default_factory=list, description="under `ra2vipas up`: its services that crashed "
                                                                                "and are waiting to be restarted")


class Health(BaseModel):
    status: Literal["ok", "starting", "degraded"]
    ready: bool
    database: bool = Field(description="the database answers and takes writes")
    database_error: Optional[str] = Field(None, description="why not, e.g. 'not writable: database or disk is full (since 12:01:02)'")
    zenoh: bool
    rigs: list[str] = Field(description="the live rigs (sensors and controller both up)")
    ready_rigs: list[str] = Field(default_factory=list, description="the live rigs whose descriptor and controller's policies are known "
                                  "(a v1 node's silence counts): the ones episodes may go to; `ready` waits for `expected_rigs` of them")
    expected_rigs: int
    learners: list[str]
    rejected_messages: dict[str, int] = Field(
        default_factory=dict,
        description="result/truth-plane messages dropped, by reason: malformed, not_in_flight (unknown or stale episode id), "
                    "wrong_rig (not on the key of the rig the episode was assigned to)")
    waiting_writes: int = Field(0, description="database writes waiting to be retried")
    instance: str = Field("", description="this orchestrator process's instance id (a client can tell it from another one on the same address)")
