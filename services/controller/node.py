"""The controller service's node logic: one rig's Ra²ViPAS controllers on the bus.

* ``control/<rig>/episode``: on ``EpisodeStart`` it asks its rig what it is
  (``rig/<rig>/info``, a ``RigDescriptor``; once per campaign) and fetches the POD model of
  (scenario, seed) from the learner (``model/pod`` query; cached here afterwards), builds a
  ``Controller`` whose sensor model is the rig's descriptor (the campaign's scenario only for
  an undescribed, v1 rig) and sends the step-0 ``Command`` with the initial pan angle;
* ``data/<rig>/measurement``: each ``Measurement`` of step t goes through
  ``Controller.step``; the node answers with the ``Command`` for step t+1, or, after the last
  step (or the first whose confidence reaches ``EpisodeStart.stop_confidence``: an early,
  final decision), publishes the episode's ``EpisodeResult`` on the result plane.

* ``rig/<rig>/policies`` (protocol 1.2): a queryable answering with the ``ControllerInfo``,
  the pointing policies this controller serves (``ra2vipas controller --policy NAME``; by
  default every installed one, ``services/controller/registry.py``). The orchestrator asks it
  when this node's liveliness token appears and hands the rig only episodes of those
  policies; an ``EpisodeStart`` naming another fails at once, naming the ones it serves.

Only measurements reach the controller: it subscribes to nothing on the truth plane.
Many episodes may be in flight at once; each has its own policy object. The liveliness token
is declared last, after the subscribers and the queryable.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Sequence

from ra2vipas.services.controller import registry
from ra2vipas.services.controller.builtins import BuiltinPolicy
from ra2vipas.services.controller.contract import Policy, episode_context
from ra2vipas.services.controller.policy import (
    Controller,
    ControllerSettings,
    SensorConfig,
    sensor_config_from_descriptor,
    sensor_config_from_scenario,
)
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.messages import (
    Command,
    ControllerInfo,
    EpisodeResult,
    EpisodeStart,
    EpisodeStop,
    Measurement,
    Mode,
    ModelCheck,
    PODRequest,
    PODResponse,
    PolicyOffer,
    TagResult,
    dump,
    episode_control_adapter,
    training_job_id,
)
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.rig import DESCRIPTOR_REASK_S, DESCRIPTOR_TIMEOUT_S, SENSORS_SETTLED_S, RigDescriptor
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
from ra2vipas.services.transport.bus import Bus, Reply, answered, undeclare_all
from ra2vipas.services.transport.costs import CostClock
from ra2vipas.services.transport.runtime import EventLoop, decode_or_drop, decode_or_reject, first_valid_reply

log = logging.getLogger(__name__)

MODEL_TIMEOUT_S = 300.0
MODEL_ATTEMPTS = 30  # about a minute of retries while no learner answers
DESCRIPTORS_KEPT = 64  # campaigns whose rig descriptor is remembered
_ASKING = object()
_new_command = builder(Command, "episode_id", "step", "pan_rad")
_PAN_LIMIT = Command.model_json_schema()["properties"]["pan_rad"]["maximum"]


def _command(episode_id: str, step: int, pan_rad: float) -> Command:
    """``Command(episode_id, step, pan_rad)`` without validating what this node knows is valid
    (its episode's id and the step it counts); the policy's pan is checked as ``Command`` would
    (finite, within its bounds), so a policy's bad pan still fails the step, as it did."""
    if not -_PAN_LIMIT <= pan_rad <= _PAN_LIMIT:  # NaN too
        raise ValueError(f"the policy's pan {pan_rad!r} is not a finite angle within +-{_PAN_LIMIT} rad")
    return _new_command(episode_id, step, pan_rad)


@dataclass
class _Episode:
    start: EpisodeStart
    policy: Policy | None = None
    sensors: SensorConfig | None = None
    next_step: int = 0
    estimates: list[float] = field(default_factory=list)
    pans: list[float] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    confidences: list[float] = field(default_factory=list)
    says_confidence: bool = True  # False once the policy gave a step no confidence
    costs: CostClock = field(default_factory=CostClock)
    tags: list = field(default_factory=list)  # several tags (1.4): each step's per-tag decisions (joint.TagDecision)


def warm_up() -> None:
    """Run a few controller steps on synthetic data so compiled kernels are loaded (or
    compiled) before the node accepts episodes: the first real step must not take seconds."""
    from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement
    from ra2vipas.services.protocol.scenario import Scenario

    sc = Scenario(steps=14)  # past the warm-up sweep, so UCB and probe kernels are loaded too
    model = PODModel(rssi_grid_dbm=(-60.0, -20.0), mean=(0.0, 0.5), std=(0.1, 0.1), rf_noise_db=3.0, n_train=2, frames_per_rf=sc.frames_per_rf)
    for algorithm in (a for a in registry.BUILTINS if a != "sweep"):  # the active built-ins load every kernel
        ctl = Controller(algorithm, sensor_config_from_scenario(sc), model)
        pan = ctl.first_pan()
        for t in range(sc.steps):
            frames = tuple(CameraFrame(box_bearings_rad=(0.01 * t, 0.2)) for _ in range(sc.frames_per_rf))
            pan = ctl.step(StepMeasurement(step=t, pan_rad=pan, rf=RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=-35.0), frames=frames)).next_pan_rad


def served_policies(policies: Sequence[str] | None = None) -> dict[str, str]:
    """What a controller serves: wire name -> what ``registry.create`` loads. ``policies``
    are installed names or ``module:Class`` (served under the class's ``name``, which must then
    be a valid wire name); None or empty: every installed policy that loads (one that does not
    is left out, with a warning). Raises ``registry.UnknownPolicy`` naming a given one that
    does not load or has no wire name."""
    if not policies:
        out = {}
        for name in registry.names():
            try:
                registry.load(name)
            except registry.UnknownPolicy as err:
                log.warning("not serving policy %s: %s", name, err)
                continue
            out[name] = name
        return out
    out: dict[str, str] = {}
    for spec in dict.fromkeys(policies):
        registry.load(spec)
        name = registry.result_name(spec)
        if not registry.is_valid_name(name):
            raise registry.UnknownPolicy(f"policy {spec!r} has no name to serve it under on the wire: give its class a "
                                         f"`name` matching {registry.NAME_PATTERN}, or register it (entry point "
                                         f"{registry.GROUP})")
        out.setdefault(name, spec)
    return out


def controller_info(rig: str, served: dict[str, str]) -> ControllerInfo:
    """The ``ControllerInfo`` of a controller serving ``served`` (``served_policies``)."""
    offers = []
    for name, spec in served.items():
        try:
            found = registry.info(spec)
            package, version = found.package, found.version
        except registry.UnknownPolicy:
            package, version = "", ""
        offers.append(PolicyOffer(name=name, package=package[:200] if package != "?" else "",
                                  version=version[:100] if version != "?" else ""))
    return ControllerInfo(rig=rig, policies=tuple(offers), protocol=PROTOCOL_VERSION)


class ControllerNode:
    """One rig's controller process. All state lives on ``self.loop``'s thread (its own, or
    ``loop``, shared with its rig's sensors on the same bus: ``ra2vipas rig``).

    ``policies``: the policies it serves (installed names or ``module:Class``; None: every
    installed policy). Raises ``registry.UnknownPolicy`` for one that does not load."""

    def __init__(self, bus: Bus, rig: str, settings: ControllerSettings | None = None,
                 policies: Sequence[str] | None = None, loop: EventLoop | None = None, realtime_priority: int = 0) -> None:
        self.bus = bus
        self.rig = keys.check_chunk(rig)
        self.settings = settings or ControllerSettings()
        self.served = served_policies(policies)
        self.info = controller_info(self.rig, self.served)
        info_payload = dump(self.info)
        self._own_loop = loop is None  # else shared with the rig's sensors (``ra2vipas rig``), stopped by its owner
        self.loop = EventLoop(f"controller-{rig}", realtime_priority=realtime_priority) if loop is None else loop
        self.episodes: dict[str, _Episode] = {}
        self.models: dict[str, PODModel] = {}
        self._waiting: dict[str, list[str]] = {}  # job id -> episodes waiting for that model
        # campaign id -> the rig's descriptor when its first episode arrived (None: undescribed), or
        # _ASKING while the query is out; one query per campaign, so a campaign sees one rig model
        self.descriptors: dict[str, object] = {}
        self._last_descriptor: RigDescriptor | None = None  # the last one this rig's sensors served (any campaign)
        # this rig's sensors' liveliness token: when it last appeared (monotonic; None while gone), how many times it
        # appeared, in which of those appearances the sensors served ``_last_descriptor``, and when each campaign's
        # round of descriptor queries began
        self._sensors_since: float | None = None
        self._sensors_presence = 0
        self._described_in = -1
        self._round_began: dict[str, float] = {}
        self._described: dict[str, list[str]] = {}  # campaign id -> episodes waiting for the descriptor
        self._command_key = keys.command(rig)
        warm_up()
        self._handles = [
            bus.subscribe(keys.episode_control(rig), lambda _k, p: self.loop.post(self._on_control, p)),
            self.loop.feed(bus, keys.measurement(rig), self._on_measurement),  # the worker takes them itself
            bus.serve(keys.rig_policies(rig), lambda _k, _p: info_payload),
            bus.watch_alive(keys.alive("sensors", rig), lambda _k, alive: self.loop.post(self._on_sensors_alive, alive)),
            bus.announce(keys.alive("controller", rig)),  # last: whoever sees it may query the policies
        ]

    def _on_sensors_alive(self, alive: bool) -> None:
        """This rig's sensors' liveliness token came or went (a node stopped, or its link was down
        past Zenoh's lease: they look alike from here). Only counted: ``_on_descriptor`` reads it."""
        if not alive:
            self._sensors_since = None
        elif self._sensors_since is None:
            self._sensors_since = time.monotonic()
            self._sensors_presence += 1

    # -- episode lifecycle ------------------------------------------------------------------
    def _on_control(self, payload: bytes) -> None:
        msg = decode_or_reject(episode_control_adapter, payload, "episode control message", log, self.bus, self.rig, "controller")
        if msg is None:
            return
        if isinstance(msg, EpisodeStop):
            self._drop(msg.episode_id)
            return
        if msg.episode_id in self.episodes:
            return
        self.episodes[msg.episode_id] = _Episode(start=msg)
        self.loop.realtime.began(("controller", msg.episode_id), msg.mode is Mode.realtime)
        if msg.algorithm not in self.served:
            self._fail(msg.episode_id, f"controller of rig {self.rig} does not serve policy {msg.algorithm!r}; it serves: "
                                       f"{', '.join(self.served)}")
            return
        if self.descriptors.get(msg.campaign_id, _ASKING) is not _ASKING:
            self._with_model(msg)
            return
        waiting = self._described.setdefault(msg.campaign_id, [])
        waiting.append(msg.episode_id)
        if len(waiting) == 1:
            self.descriptors[msg.campaign_id] = _ASKING
            while len(self.descriptors) > DESCRIPTORS_KEPT:
                self.descriptors.pop(next(iter(self.descriptors)))
            self._ask_descriptor(msg.campaign_id, 0)

    def _ask_descriptor(self, campaign_id: str, empty: int) -> None:
        """Query the rig's descriptor for a campaign; ``empty``: how many earlier queries no node answered."""
        if empty == 0:
            self._round_began[campaign_id] = time.monotonic()
        self.bus.query(keys.rig_info(self.rig), b"", DESCRIPTOR_TIMEOUT_S,
                       lambda replies: self.loop.post(self._on_descriptor, campaign_id, replies, empty))

    def _on_descriptor(self, campaign_id: str, replies: list[Reply], empty: int) -> None:
        """The descriptor's answer: a query no node answered at all is asked again after the waits of
        ``DESCRIPTOR_REASK_S`` (the router may not route it to the sensors' queryable yet: a link just
        back, a node just up) before the rig is taken for a v1 node and modelled from the scenario."""
        replies = answered(replies)  # a query that timed out (a link cut mid-query) was answered by no node
        if not replies and empty < len(DESCRIPTOR_REASK_S):
            log.info("rig %s: no node answered the descriptor query; asking again in %.0f s", self.rig, DESCRIPTOR_REASK_S[empty])
            self.loop.post_later(DESCRIPTOR_REASK_S[empty], self._ask_descriptor, campaign_id, empty + 1)
            return
        descriptor, passed_over = first_valid_reply(replies, RigDescriptor, "RigDescriptor")
        if descriptor is not None and descriptor.rig != self.rig:
            log.warning("rig %s: the descriptor names rig %s; ignored", self.rig, descriptor.rig)
            descriptor = None
        began = self._round_began.pop(campaign_id, None)
        if descriptor is not None:  # served in the token's current appearance (or the first, not seen here yet)
            self._last_descriptor = descriptor
            self._described_in = self._sensors_presence + (self._sensors_since is None)
        elif not replies and self._last_descriptor is not None and self._sensors_since is not None \
                and self._sensors_presence != self._described_in:
            # no node answered, and the sensors' token went and came back since they described the rig: the node now
            # under its name may be another (a v1 node serving no descriptor) or the same one just back, whose queryable
            # may not be routed yet. Silence counts only from a token that stood SENSORS_SETTLED_S before the round began
            settled_at = self._sensors_since + SENSORS_SETTLED_S
            if began is None or began < settled_at - 0.01:  # (a timer that fires a hair early does not ask twice)
                wait = max(settled_at - time.monotonic(), 0.0)
                log.info("rig %s: its sensors came back and answer no descriptor query yet; asking again in %.0f s", self.rig, wait)
                self.loop.post_later(wait, self._ask_descriptor, campaign_id, 0)
                return
            log.info("rig %s: the sensors node now under its name serves no descriptor (a v1 node); the one the node "
                     "before it served is forgotten", self.rig)
            self._last_descriptor = None
        elif not replies and self._last_descriptor is not None:
            # no node answered at all, again and again (a link cut across the re-asks), but this rig's sensors served a
            # descriptor before, and their token has not come back since (it may have gone: a cut past the lease):
            # a node that described its hardware is not a v1 node; use what it said
            log.info("rig %s: no node answered the descriptor query; using the one its sensors served last", self.rig)
            descriptor = self._last_descriptor
        if descriptor is None:
            log.info("rig %s is undescribed%s: modelling it from each campaign's scenario", self.rig,
                     f" ({passed_over[-1]})" if passed_over else "")
        self.descriptors[campaign_id] = descriptor
        for episode_id in self._described.pop(campaign_id, []):
            ep = self.episodes.get(episode_id)
            if ep is not None:
                self._with_model(ep.start)

    def _sensor_config(self, start: EpisodeStart) -> SensorConfig:
        descriptor = self.descriptors.get(start.campaign_id)
        if isinstance(descriptor, RigDescriptor):
            return sensor_config_from_descriptor(descriptor, start.scenario)
        return sensor_config_from_scenario(start.scenario)

    def _with_model(self, msg: EpisodeStart) -> None:
        job = training_job_id(msg.scenario, msg.seed)
        if job in self.models:
            self._begin(msg.episode_id, self.models[job])
            return
        waiting = self._waiting.setdefault(job, [])
        waiting.append(msg.episode_id)
        if len(waiting) == 1:
            self._request_model(job, dump(PODRequest(scenario=msg.scenario, seed=msg.seed, protocol=PROTOCOL_VERSION)), 1)

    def _request_model(self, job: str, request: bytes, attempt: int) -> None:
        self.bus.query(keys.pod_model(), request, MODEL_TIMEOUT_S,
                       lambda replies: self.loop.post(self._on_model, job, replies, request, attempt))

    def _on_model(self, job: str, replies: list[Reply], request: bytes = b"", attempt: int = MODEL_ATTEMPTS) -> None:
        if not replies and attempt < MODEL_ATTEMPTS and self._waiting.get(job):
            # no learner reachable right now (restarting?): ask again shortly instead of failing
            self.loop.post_later(min(0.5 * attempt, 5.0), self._request_model, job, request, attempt + 1)
            return
        waiting = self._waiting.pop(job, [])
        response, passed_over = first_valid_reply(replies, PODResponse, "PODResponse")
        if response is None:
            error = passed_over[-1] if passed_over else "no learner answered"
            for episode_id in waiting:
                self._fail(episode_id, f"POD model unavailable: {error}")
            return
        self.models[job] = response.model
        for episode_id in waiting:
            self._begin(episode_id, response.model)

    def _begin(self, episode_id: str, model: PODModel) -> None:
        ep = self.episodes.get(episode_id)
        if ep is None:
            return
        ep.sensors = self._sensor_config(ep.start)
        context = episode_context(ep.sensors, model, ep.start.scenario, ep.start.seed, ep.start.test_index, ep.start.stop_confidence)
        try:
            ep.policy = registry.create(self.served.get(ep.start.algorithm, ep.start.algorithm), context, self.settings)
        except registry.UnknownPolicy as err:
            self._fail(episode_id, f"controller of rig {self.rig}: {err}")
            return
        self.loop.send(self.bus, self._command_key, _command(episode_id, 0, float(ep.policy.first_pan())))

    def _drop(self, episode_id: str) -> "_Episode | None":
        """Forget an episode (ended, stopped or failed): its scheduling class no longer counts."""
        ep = self.episodes.pop(episode_id, None)
        if ep is not None:
            self.loop.realtime.ended(("controller", episode_id))
        return ep

    def _fail(self, episode_id: str, error: str) -> None:
        if self._drop(episode_id) is None:
            return
        log.error("episode %s failed: %s", episode_id, error)
        self.bus.publish(keys.episode_result(self.rig), dump(EpisodeResult(episode_id=episode_id, rig=self.rig, status="failed", error=error[:2000])))

    # -- stepping ---------------------------------------------------------------------------
    def _on_measurement(self, payload: "bytes | Measurement") -> None:
        """A measurement: its JSON from the network, or the message itself from the rig's own
        sensors on this loop (``EventLoop.send``)."""
        posted, started = self.loop.posted_ns, self.loop.started_ns
        m = payload if isinstance(payload, Measurement) else decode_or_drop(Measurement, payload, "measurement", log)
        if m is None:
            return
        ep = self.episodes.get(m.episode_id)
        if ep is None or ep.policy is None or m.step != ep.next_step:
            return  # not ours, not started, or a duplicate
        costs = ep.costs
        costs.mark_arrival(posted, started)
        costs.lap("decode")
        sc = ep.start.scenario
        if len(m.frames) != ep.sensors.frames_per_rf:
            log.warning("episode %s step %d: %d frames, expected %d; dropped", m.episode_id, m.step, len(m.frames),
                        ep.sensors.frames_per_rf)
            return
        decision = ep.policy.step(m)
        confidence = getattr(decision, "confidence", None)
        reward = getattr(decision, "reward", None)
        ep.estimates.append(float(decision.estimate_rad))
        ep.pans.append(m.pan_rad)
        ep.rewards.append(0.0 if reward is None else float(reward))
        if confidence is None:
            ep.says_confidence = False
        ep.confidences.append(0.0 if confidence is None else float(confidence))
        ep.next_step = m.step + 1
        stop = ep.start.stop_confidence
        tags = getattr(decision, "tags", None) if sc.n_tags > 1 else None
        if tags:  # several tags (issue 21): the episode ends when every tag is decided
            ep.tags.append(tags)
            decided = stop > 0.0 and bool(getattr(decision, "all_decided", False))
        else:
            decided = stop > 0.0 and confidence is not None and confidence >= stop
        if ep.next_step < sc.steps and not decided:
            command = _command(m.episode_id, ep.next_step, float(decision.next_pan_rad))
            costs.lap("compute")
            self.loop.send(self.bus, self._command_key, command, express=ep.start.mode is Mode.realtime, costs=costs)
            costs.lap("publish")
            costs.replied()
            return
        self._drop(m.episode_id)
        costs.lap("compute")
        costs.replied()  # the span ends here: the episode's model check and its result's encoding are no step's
        check = model_check(ep.sensors, ep.policy.controller if isinstance(ep.policy, BuiltinPolicy) else None)
        self.bus.publish(keys.episode_result(self.rig), dump(EpisodeResult(
            episode_id=m.episode_id, rig=self.rig, estimates_rad=tuple(ep.estimates), pans_rad=tuple(ep.pans), rewards=tuple(ep.rewards),
            confidences=tuple(ep.confidences) if ep.says_confidence else (), decided_step=m.step if decided else None,
            model_check=check, costs=costs.report(), tags=tag_results(ep.tags))))

    def close(self) -> None:
        undeclare_all(self._handles)
        if self._own_loop:
            self.loop.stop()


def tag_results(steps: list) -> tuple[TagResult, ...]:
    """The ``EpisodeResult.tags`` of a search for several tags: per tag, its estimate and
    confidence after each step and the step it was decided at (``steps``: each step's
    ``joint.TagDecision`` s; none: a single-tag episode, no tags)."""
    if not steps:
        return ()
    last = steps[-1]
    return tuple(TagResult(tag=d.tag, estimates_rad=tuple(float(row[k].estimate_rad) for row in steps),
                           confidences=tuple(min(max(float(row[k].confidence), 0.0), 1.0) for row in steps),
                           decided_step=d.decided_step) for k, d in enumerate(last))


def model_check(sensors: SensorConfig, controller: Controller | None = None) -> ModelCheck:
    """What the controller assumed about its rig in this episode (its sensor model: the rig's
    descriptor or the scenario) and, for a built-in with the generic lobe, whether Rx(dir) agreed."""
    evidence = controller.lobe_evidence() if controller is not None else None
    return ModelCheck(sensor_model="descriptor" if sensors.source == "descriptor" else "scenario",
                      rx_dir=sensors.rx_dir, lobe=controller.lobe if controller is not None else None,
                      lobe_evidence=None if evidence is None else round(evidence, 4))
