"""Wire messages: the JSON payloads that travel on the keys of ``ra2vipas.services.protocol.keys``.

Every payload is a JSON object (Zenoh encoding ``application/json``) validated by one of
these pydantic models; ``ra2vipas protocol schemas OUTDIR`` writes their JSON Schemas
(checked in under ``docs/schemas``). Angles are radians, RSSI dBm, times seconds.
A message that fails validation is logged and dropped by the receiver.
"""

from __future__ import annotations

import hashlib
import json
from enum import Enum
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from ra2vipas.services.protocol.measurements import (
    ADDRESS_PATTERN,
    Advertisement,
    CameraFrame,
    RFSample,
    StepMeasurement,
    TrainingSample,
)
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.rig import RigDescriptor, RxDirResponse
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.protocol.versions import V1_0, VERSION_PATTERN, wire_exclude

MAX_STEPS = 10000
MAX_TESTS = 10000  # Monte Carlo tests per algorithm in one campaign: the API's, the CLI's and the client's limit

ALGORITHMS: tuple[str, ...] = ("ra2vipas", "rapas", "ravipas", "sweep")
"""The built-in policies (paper Sec. IV-B plus the non-active sweep): every name a node of
protocol 1.0 or 1.1 knows (there ``algorithm`` was this closed list)."""
POLICY_NAME_PATTERN = r"^[a-z][a-z0-9_.-]{0,63}$"
"""A pointing policy's name (protocol 1.2: any registered policy, ``ra2vipas.policies``)."""
AlgorithmName = Annotated[str, Field(pattern=POLICY_NAME_PATTERN, min_length=1, max_length=64,
                                     description="the pointing policy: one of the built-ins ra2vipas, rapas, ravipas, sweep, "
                                                 "or (protocol 1.2) any policy name a controller serves")]
_ID = Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:-]+$")
SINCE_1_1 = {"since": "1.1"}
"""Schema mark of a field added in protocol 1.1 (``versions.since``): senders omit it at its default."""


class _Message(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Mode(str, Enum):
    """How an episode is paced: ``fast`` lockstep as fast as possible, ``realtime`` one RF
    sample every T_RF on the wall clock (hardware in the loop)."""

    fast = "fast"
    realtime = "realtime"


# -- control plane -----------------------------------------------------------------------------

class EpisodeStart(_Message):
    """Start one test of one algorithm on a rig (orchestrator -> sensors and controller)."""

    kind: Literal["start"] = "start"
    episode_id: str = _ID
    campaign_id: str = _ID
    test_index: int = Field(ge=0, le=1_000_000)
    algorithm: AlgorithmName
    seed: int = Field(ge=0, le=2**63 - 1)
    scenario: Scenario
    mode: Mode = Mode.fast
    stop_confidence: float = Field(0.0, ge=0.0, lt=1.0, description="end the episode at the first step whose confidence "
                                   "reaches this, its answer final (0: run every step; omitted); a 1.0 node does not know it",
                                   json_schema_extra=SINCE_1_1)


class EpisodeStop(_Message):
    """Abandon an episode (cancelled campaign, reassignment). Receivers drop its state."""

    kind: Literal["stop"] = "stop"
    episode_id: str = _ID
    reason: str = Field(default="", max_length=500)


EpisodeControl = Annotated[Union[EpisodeStart, EpisodeStop], Field(discriminator="kind")]
episode_control_adapter: TypeAdapter = TypeAdapter(EpisodeControl)


# -- data plane --------------------------------------------------------------------------------

class Command(_Message):
    """Point the camera at ``pan_rad`` and take sample ``step`` there (controller -> sensors).

    Step 0's command carries the initial pan s_0; after sample t the controller sends step t+1.
    """

    episode_id: str = _ID
    step: int = Field(ge=0, le=MAX_STEPS)
    pan_rad: float = Field(ge=-7.0, le=7.0)


class Measurement(StepMeasurement):
    """What the platform sensed at step t (sensors -> controller): the pan angle it was at,
    Rx(iso) and Rx(dir) RSSI (1.0: one ``rf`` pair; 1.3: the ``adverts`` each receiver heard
    since the previous step, possibly none), and the nu frames of box bearings (relative to the
    optical axis, sorted, no identities; since 1.3 optionally their angular heights and scores)."""

    episode_id: str = _ID


class TrainingRequest(_Message):
    """Run a POD training episode (learner -> sensors queryable): the Tx walks in view while
    the platform records iso RSSI and frames (paper Sec. III-A)."""

    job_id: str = _ID
    scenario: Scenario
    seed: int = Field(ge=0, le=2**63 - 1)


class TrainingStream(_Message):
    """The training episode's samples, in the order taken (sensors -> learner, query reply)."""

    job_id: str = _ID
    samples: tuple[TrainingSample, ...] = Field(min_length=1, max_length=100_000)


# -- model plane -------------------------------------------------------------------------------

class PODRequest(_Message):
    """Ask the learner for the POD model of (scenario, seed); it trains once and caches."""

    scenario: Scenario
    seed: int = Field(ge=0, le=2**63 - 1)
    protocol: str = Field(V1_0, pattern=VERSION_PATTERN, json_schema_extra=SINCE_1_1, description=(
        "the protocol version the asker speaks (absent: 1.0); the reply carries no field newer than that"))


class PODResponse(_Message):
    """The learner's answer: the model, the training job it came from, and how long fitting took."""

    job_id: str = _ID
    model: PODModel
    train_seconds: float = Field(ge=0.0)


class ErrorReply(_Message):
    """Payload of an error reply to any query."""

    error: str = Field(max_length=2000)
    episode_id: str | None = Field(None, min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.:-]+$", json_schema_extra=SINCE_1_1,
                                   description="on result/{rig}/rejected: the episode whose message the node rejected")


# -- rig plane (the controller's half) ----------------------------------------------------------

class PolicyOffer(_Message):
    """One pointing policy a controller serves: its wire name and where it comes from."""

    name: AlgorithmName
    package: str = Field("", max_length=200, description="the distribution that provides it (ra2vipas for the built-ins; "
                                                          "free text, empty if not known)")
    version: str = Field("", max_length=100, description="that distribution's version (free text, empty if not known)")


class ControllerInfo(_Message):
    """What a rig's controller serves (controller -> orchestrator, reply on ``rig/{rig}/policies``;
    protocol 1.2). The orchestrator hands this rig only episodes whose ``algorithm`` is one of
    ``policies``. A controller that serves no such queryable (1.0, 1.1) serves the four built-ins."""

    rig: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$", description="the rig's name (its key chunk)")
    policies: tuple[PolicyOffer, ...] = Field(min_length=1, max_length=1000, description="the policies it runs, by name")
    protocol: str = Field("1.2", pattern=VERSION_PATTERN, description="the protocol version the controller speaks (1.2: the "
                                                                      "version that introduced this message)")


# -- result plane ------------------------------------------------------------------------------

class ModelCheck(_Message):
    """How the controller modelled its rig in one episode, and whether the data agreed (optional
    part of ``EpisodeResult``; a v1 controller sends none, meaning ``sensor_model: scenario``)."""

    sensor_model: Literal["descriptor", "scenario"] = Field(
        description="where the controller's sensor model came from: the rig's descriptor, or the campaign's scenario "
                    "(an undescribed rig: the results say it was scored under the scenario's assumptions)")
    rx_dir: Literal["paper", "db-gain", "unknown"] = Field(description="the Rx(dir) response the controller assumed")
    lobe: Literal["peak", "dip"] | None = Field(None, description="the lobe orientation it used at the end: given by the response, "
                                                "or learned from the data when the response is unknown; null without Rx(dir)")
    lobe_evidence: float | None = Field(None, ge=-1e9, le=1e9, description=(
        "log-likelihood ratio of the lobe orientation used against the opposite one over the episode's Rx(dir) samples "
        "(positive: the data agree with it; strongly negative: the directional RSSI contradicts the assumed antenna model); "
        "null without Rx(dir)"))


_MS = Field(default=0.0, ge=0.0, le=1e9)
SINCE_1_2 = {"since": "1.2"}
"""Schema mark of a field added in protocol 1.2 that only our nodes send to the orchestrator."""


class StepCosts(_Message):
    """Where one node's time went in one episode, summed over its steps [ms] (optional part of
    ``EpisodeResult``, the controller's, and of ``EpisodeTiming``, the sensors'; for benchmarks).

    Per handled step message: ``queued`` on the node's event loop after it arrived,
    ``decode`` (and validate), ``compute`` (the handler's work), ``encode`` (the reply's JSON),
    ``publish`` (handing it to Zenoh); ``outside``: from the node's reply to the arrival of
    the episode's next message (the other node and the transport); ``span``: from the start
    of its handling of the episode's first step message (a paced node: its first publication)
    to its last publication; the wait for that first message, queue included, is in neither. The stages are contiguous, so
    ``outside + queued + decode + compute + encode + publish`` ~ ``span``.
    """

    steps: int = Field(default=0, ge=0, le=10 * MAX_STEPS, description="step messages handled")
    queued_ms: float = _MS
    decode_ms: float = _MS
    compute_ms: float = _MS
    encode_ms: float = _MS
    publish_ms: float = _MS
    outside_ms: float = _MS
    span_ms: float = _MS


SINCE_1_4 = {"since": "1.4"}
"""Schema mark of a field added in protocol 1.4 (many tags, issue 21; docs/tags.md)."""


class TagResult(_Message):
    """One tag's trace in an episode that searched for several (optional part of
    ``EpisodeResult``, protocol 1.4): what the controller named for tag k after each sample.

    ``estimates_rad[t]`` is the bearing it names for tag k after sample t (scored by the
    association rule, eq. 11, against tag k's carrier), ``confidences[t]`` its posterior
    probability that the target it names carries tag k, ``decided_step`` the step at which tag
    k's confidence reached ``stop_confidence`` (its answer final from then on; null: never).
    """

    tag: int = Field(ge=0, le=63, description="k, the tag's index (Advertisement.tag, RFSample.tag)")
    estimates_rad: tuple[float, ...] = Field(default=(), max_length=MAX_STEPS)
    confidences: tuple[Annotated[float, Field(ge=0.0, le=1.0)], ...] = Field(default=(), max_length=MAX_STEPS)
    decided_step: int | None = Field(default=None, ge=0, le=MAX_STEPS)

    @model_validator(mode="after")
    def _aligned(self) -> "TagResult":
        if self.confidences and len(self.confidences) != len(self.estimates_rad):
            raise ValueError(f"tag {self.tag}: {len(self.confidences)} confidences for {len(self.estimates_rad)} estimates")
        if self.decided_step is not None and self.decided_step >= len(self.estimates_rad):
            raise ValueError(f"tag {self.tag}: decided_step {self.decided_step} after its last estimate")
        return self


class EpisodeResult(_Message):
    """The controller's trace of one episode (controller -> orchestrator).

    ``estimates_rad[t]`` is gamma_hat_t after sample t; ``pans_rad[t]`` the pan angle sample t
    was taken at; ``rewards[t]`` the fused objective there; ``confidences[t]`` the controller's
    posterior probability that the target it names at t is the Tx (optional: a v1 controller
    sends none). ``decided_step`` = d when the episode ended early at step d because its
    confidence reached ``EpisodeStart.stop_confidence``: the lists then hold d + 1 values and the
    answer of step d is final. ``status`` is ``failed`` with an ``error`` if the controller
    could not run the episode.

    A controller that searched for several tags (protocol 1.4) adds ``tags``, one ``TagResult``
    per tag, each with as many estimates as ``pans_rad``; the top-level fields then describe tag 0
    and ``decided_step`` the step at which every tag was decided. A single-tag controller sends none.
    """

    episode_id: str = _ID
    rig: str = Field(min_length=1, max_length=64)
    status: Literal["done", "failed"] = "done"
    error: str = Field(default="", max_length=2000)
    estimates_rad: tuple[float, ...] = Field(default=(), max_length=MAX_STEPS)
    pans_rad: tuple[float, ...] = Field(default=(), max_length=MAX_STEPS)
    rewards: tuple[float, ...] = Field(default=(), max_length=MAX_STEPS)
    confidences: tuple[Annotated[float, Field(ge=0.0, le=1.0)], ...] = Field(default=(), max_length=MAX_STEPS,
                                                                            json_schema_extra=SINCE_1_1)
    decided_step: int | None = Field(default=None, ge=0, le=MAX_STEPS, json_schema_extra=SINCE_1_1)
    model_check: ModelCheck | None = Field(default=None, description="how the rig was modelled (optional; v1 controllers send none)",
                                           json_schema_extra=SINCE_1_1)
    costs: StepCosts | None = Field(default=None, json_schema_extra=SINCE_1_2,
                                    description="the controller's time per stage in this episode (optional; for benchmarks)")
    tags: tuple[TagResult, ...] = Field(default=(), max_length=64, json_schema_extra=SINCE_1_4,
                                        description="per tag, when the controller searched for several (optional)")

    @model_validator(mode="after")
    def _tags_aligned(self) -> "EpisodeResult":
        if self.tags:
            indices = [t.tag for t in self.tags]
            if len(set(indices)) != len(indices):
                raise ValueError(f"tags: a tag is listed twice: {indices}")
            bad = [t.tag for t in self.tags if len(t.estimates_rad) != len(self.pans_rad)]
            if bad:
                raise ValueError(f"tags: tag {bad[0]} has not one estimate per pan ({len(self.pans_rad)})")
        return self


class EpisodeTiming(_Message):
    """Realtime episodes: for each step, the time from the sensors publishing sample t to
    receiving the command for step t+1 [ms] (sensors -> orchestrator). Since 1.2 the
    simulated sensors also send one in fast mode, with ``costs`` only, just before the
    episode's last measurement (so it reaches the orchestrator before the result)."""

    episode_id: str = _ID
    latencies_ms: tuple[float, ...] = Field(default=(), max_length=MAX_STEPS)
    late_commands: int = Field(default=0, ge=0, description="commands that arrived after the next sample was taken")
    costs: StepCosts | None = Field(default=None, json_schema_extra=SINCE_1_2,
                                    description="the sensors' time per stage in this episode (optional; for benchmarks)")


# -- truth plane -------------------------------------------------------------------------------

class TargetTrajectory(_Message):
    """Where one walking target was at every step of an episode (truth plane only)."""

    index: int = Field(ge=0, le=999, description="i, the target's index in EpisodeTruth.bearings_rad")
    bearings_rad: tuple[float, ...] = Field(min_length=1, max_length=MAX_STEPS, description="gamma_i at step t = 0 ... steps-1 [rad]")
    ranges_m: tuple[float, ...] = Field(min_length=1, max_length=MAX_STEPS, description="d_i at step t [m]")


class EpisodeTruth(_Message):
    """Ground truth of a simulated episode, for scoring only (simulated sensors -> orchestrator).

    ``bearings_rad``/``ranges_m``: every target at step 0 (static targets stay there).
    ``trajectories`` (optional, added in v1.1): one entry per *walking* target with its
    bearing and range at every step; DR_t is then scored against the bearings at step t.
    A node that sends none describes a static world.
    ``tx_indices`` (optional, 1.4): with K > 1 tags, the target that carries tag k, k = 0..K-1
    (``tx_indices[0]`` is ``tx_index``; two tags may share a target unless the scenario says one
    person carries at most one); ``tag_addresses`` the tags' addresses in the same order. A node
    that sends none describes one tag, carried by ``tx_index``.
    """

    episode_id: str = _ID
    bearings_rad: tuple[float, ...] = Field(min_length=1, max_length=1000)
    ranges_m: tuple[float, ...] = Field(min_length=1, max_length=1000)
    tx_index: int = Field(ge=0)
    trajectories: tuple[TargetTrajectory, ...] = Field(default=(), max_length=1000)
    tx_indices: tuple[Annotated[int, Field(ge=0)], ...] = Field(default=(), max_length=64, json_schema_extra=SINCE_1_4,
                                                                description="the carrier of each tag k (K > 1)")
    tag_addresses: tuple[Annotated[str, Field(pattern=ADDRESS_PATTERN)], ...] = Field(
        default=(), max_length=64, json_schema_extra=SINCE_1_4, description="each tag's address, in the order of tx_indices")

    @model_validator(mode="after")
    def _carriers(self) -> "EpisodeTruth":
        if self.tx_indices:
            if self.tx_indices[0] != self.tx_index:
                raise ValueError(f"tx_indices[0] ({self.tx_indices[0]}) must be tx_index ({self.tx_index})")
            if max(self.tx_indices) >= len(self.bearings_rad):
                raise ValueError(f"tx_indices names target {max(self.tx_indices)} of {len(self.bearings_rad)}")
        if self.tag_addresses and len(self.tag_addresses) != max(1, len(self.tx_indices)):
            raise ValueError(f"{len(self.tag_addresses)} tag_addresses for {max(1, len(self.tx_indices))} tags")
        return self

    @property
    def carriers(self) -> tuple[int, ...]:
        """The carrier of each tag (one tag: ``(tx_index,)``)."""
        return self.tx_indices or (self.tx_index,)


class TrainingTruth(_Message):
    """Ground truth of a simulated training episode, to score the learned POD by R^2 (eq. 23):
    per sample the noiseless iso RSSI r_j (path loss plus shadowing) and the true POD at that
    RSSI, p_D(d_j) without shadowing, E[p_D(d) | r_j] with it (``world.TrainingTruth``)."""

    job_id: str = _ID
    rssi_dbm: tuple[float, ...] = Field(min_length=1, max_length=100_000)
    pod: tuple[float, ...] = Field(min_length=1, max_length=100_000)


WIRE_MESSAGES: tuple[type[BaseModel], ...] = (
    EpisodeStart, EpisodeStop, Command, Measurement, TrainingRequest, TrainingStream,
    PODRequest, PODResponse, ErrorReply, ControllerInfo, PolicyOffer, EpisodeResult, EpisodeTiming, EpisodeTruth, TrainingTruth,
    RFSample, Advertisement, CameraFrame, TrainingSample, TargetTrajectory, PODModel, Scenario, RigDescriptor, RxDirResponse, ModelCheck,
    StepCosts, TagResult,
)


def training_job_id(scenario: Scenario, seed: int) -> str:
    """Deterministic id of the training episode of (scenario, seed): the POD cache key. The
    scenario is hashed as it goes on the wire (``dump``: parameters added after 1.0 count only
    when set), so a scenario's id does not change when a version adds a parameter."""
    wire = scenario.model_dump(mode="json", exclude=wire_exclude(scenario) or None)
    canonical = json.dumps({"scenario": wire, "seed": seed}, sort_keys=True, separators=(",", ":"))
    return "pod-" + hashlib.sha256(canonical.encode()).hexdigest()[:16]


def decode(schema: "type[BaseModel] | TypeAdapter", payload: bytes):
    """``(message, None)`` if ``payload`` validates against ``schema``, else ``(None, reason)``
    with a one-line reason naming the first offending field."""
    try:
        if isinstance(schema, TypeAdapter):
            return schema.validate_json(payload), None
        return schema.model_validate_json(payload), None
    except ValidationError as err:
        errors = err.errors()
        first = errors[0] if errors else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        reason = f"{where}: {first.get('msg', 'invalid')}" if where else str(first.get("msg", "invalid"))
        return None, reason[:200]


def error_text(payload: bytes) -> str:
    """The text of an error reply (an ``ErrorReply`` or plain text)."""
    message, _ = decode(ErrorReply, payload)
    return message.error if message is not None else payload.decode(errors="replace")[:500]


def dump(message: BaseModel, version: str | None = None) -> bytes:
    """The message as compact JSON bytes, as it goes on the wire: without the fields added after
    protocol 1.0 that hold their defaults (so a message that uses no newer feature is byte for
    byte what a 1.0 sender sent), and, for a receiver that speaks ``version``, without any field
    newer than that (``versions.wire_exclude``). Every sender encodes with this function."""
    exclude = wire_exclude(message, version)
    return message.model_dump_json(exclude=exclude or None).encode()
