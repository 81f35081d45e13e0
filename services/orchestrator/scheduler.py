"""The orchestrator's node logic: run Monte Carlo campaigns across the rigs on the bus.

For each campaign it

1. asks the learner for the POD model of (scenario, seed) (``model/pod``) and the simulated
   sensors for that training episode's truth (``truth/*/training``) to score R^2 (eq. 23);
2. hands out episodes (test index x algorithm) to live rigs, a window of them per rig at a
   time (``control/<rig>/episode``): many episodes in flight keep both cores busy;
3. pairs each episode's ``EpisodeResult`` (from the controller) with its ``EpisodeTruth``
   (from the simulated sensors), scores it by the association rule and records it in one
   transaction;
4. when every episode is recorded, reduces them to the same results object as
   ``ra2vipas simulate --json``.

A rig is live while both its sensors and its controller hold their liveliness tokens (once both
have left it is forgotten: no longer listed in ``/rigs``); when
its sensors come up the scheduler asks the rig what it is (``rig/<rig>/info``, a
``RigDescriptor``; a v1 node answers nothing and the rig is *undescribed*), and when its
controller comes up which pointing policies that controller serves (``rig/<rig>/policies``, a
``ControllerInfo``; a 1.0 or 1.1 controller answers nothing and serves the four built-ins). A
campaign's episodes go only to the rigs it targets (``targeting``: named rigs or a rig kind)
whose descriptor its scenario does not contradict (``protocol.rig.conflicts``), and an episode
of policy P only to a rig whose controller serves P. If a
rig disappears, its unfinished episodes go back to the queue and are run again from scratch
elsewhere: every draw of test k depends only on (seed, k), so the rerun gives the result the
lost run would have given, and ``finish_episode`` never records a test twice. On start, the
scheduler resumes every campaign the database says is unfinished.

Trust (defence in depth, beside Zenoh's access control): an episode id carries an
unguessable nonce, and a result, truth or timing report is accepted only on the key of the
rig its episode was assigned to, for the attempt in flight. Anything else is dropped and
counted (``status()["rejected"]``, shown by ``/health``).

Storage faults (disk full, read-only file system): a write that fails leaves the scheduler's
memory as it was (a finished episode keeps its result until it is recorded, an episode that
could not be marked running goes back to the queue), stops handing out new episodes, and is
retried with exponential backoff; when the database takes writes again everything resumes by
itself, with nothing lost or recorded twice. ``Store.fault`` says why meanwhile (``/health``
is 503, campaigns show it in ``error``).
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from ra2vipas.services.controller.registry import SHIPPED_BASELINES
from ra2vipas.services.learner.trained import NO_SENSORS, TRAINING_DATA_ERROR, TrainedPOD, predict, r2_score
from ra2vipas.services.orchestrator.metrics import score_episode, truth_bearings
from ra2vipas.services.orchestrator.reduce import AlgorithmTally, LatencyTally, held, results_object
from ra2vipas.services.orchestrator.rigcheck import RigChecks
from ra2vipas.services.orchestrator.storage import EpisodeKey, StorageFault, Store
from ra2vipas.services.orchestrator.study_store import StudyStore
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    ControllerInfo,
    EpisodeResult,
    EpisodeStart,
    EpisodeStop,
    EpisodeTiming,
    EpisodeTruth,
    ErrorReply,
    Mode,
    PODRequest,
    PODResponse,
    TrainingRequest,
    TrainingTruth,
    dump,
)
from ra2vipas.services.protocol.rig import (
    DESCRIPTOR_REASK_S,
    DESCRIPTOR_TIMEOUT_S,
    SENSORS_SETTLED_S,
    RigDescriptor,
    conflicts,
    speaks,
)
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.protocol.versions import (
    BUILTIN_POLICIES,
    PROTOCOL_VERSION,
    campaign_features,
    describe_missing,
    missing_features,
)
from ra2vipas.services.transport.bus import Bus, Reply, answered, undeclare_all
from ra2vipas.services.transport.runtime import EventLoop, decode_or_drop, first_valid_reply

log = logging.getLogger(__name__)

# what the orchestrator asks of a rig: the key of the query, the message that answers it, and what the rig is taken
# for when no node answers (``_Rig.asked``)
_QUERIES = {"descriptor": (keys.rig_info, RigDescriptor, "undescribed"), "policies": (keys.rig_policies, ControllerInfo, "silent")}

MAX_ATTEMPTS = 5
MODEL_TIMEOUT_S = 600.0
MODEL_ATTEMPTS = 60  # retries (every 2-10 s) while no learner answers, or no rig's sensors are live to train on
MODEL_RETRY_S = (1.0, 8.0)  # first and longest wait before asking again after the learner failed (doubling)
MODEL_PATIENCE_S = 30.0  # how long the learner may keep failing (e.g. missing live sensors) before the campaign fails
EPISODE_TIMEOUT_S = 60.0  # plus twice the test's duration in realtime mode
TIMEOUT_CHECK_S = 2.0
HEAL_BACKOFF_S = (1.0, 30.0)  # first and longest wait between retries of a failed database write
# after the settled-token re-check (Scheduler._recheck_if_young) a node still silent is asked again after these waits,
# the last repeated while it stays up and silent
RECHECK_BACKOFF_S = (30.0, 60.0, 120.0, 300.0)

REJECTIONS = ("malformed", "not_in_flight", "wrong_rig")
"""Why a result-plane or truth-plane message was dropped: it did not validate; its episode id
is not one in flight (a guess, a replay, or a late duplicate); it came on another rig's key
(or names another rig) than the one the episode was assigned to."""


@dataclass
class _Flight:
    key: EpisodeKey
    rig: str
    attempt: int
    started: float
    result: EpisodeResult | None = None
    truth: EpisodeTruth | None = None
    timing: EpisodeTiming | None = None
    saving: bool = False  # complete: being (or waiting to be) recorded


@dataclass
class _Run:
    """A campaign being executed."""

    id: str
    scenario: Scenario
    seed: int
    mode: Mode
    pending: deque = field(default_factory=deque)
    pod: TrainedPOD | None = None
    running_since: float | None = None
    model_attempts: int = 0
    model_retry_at: float | None = None
    model_failing_since: float | None = None  # the learner answered with errors since then (None: it has not)
    model_failures: int = 0  # error answers since model_failing_since (the backoff's exponent)
    awaiting_sensors: bool = False  # the learner found no sensors and none is live: asked again when one comes up
    stop_confidence: float = 0.0
    algorithms: tuple = ()  # the policies it runs (a policy outside the built-ins needs protocol 1.2)
    study: str | None = None  # the study this campaign is a point of, if any
    point: int = 0  # its index in the study's grid
    tests: int = 0
    targeting: dict | None = None  # {"rigs": [...] | None, "rig_kind": ... | None, ...}; None: any rig
    eligible: dict = field(default_factory=dict)  # rig -> whether this campaign may run there (cleared when a descriptor changes)


@dataclass
class _Rig:
    sensors: bool = False
    controller: bool = False
    in_flight: set = field(default_factory=set)
    since: float = 0.0  # epoch seconds of the last change of ``live`` (for the dashboard's "live since" / "last seen")
    descriptor: RigDescriptor | None = None
    described: str = "unknown"  # unknown (sensors down) | asking | described | undescribed (a v1 node)
    controller_info: ControllerInfo | None = None
    announced: str = "unknown"  # unknown (controller down) | asking | announced | silent (a 1.0/1.1 controller)
    asks: dict = field(default_factory=dict)  # "descriptor" | "policies" -> (generation, empty answers so far)
    appeared: dict = field(default_factory=dict)  # "descriptor" | "policies" -> monotonic time its node's token last appeared

    @property
    def live(self) -> bool:
        return self.sensors and self.controller

    def asked(self, what: str) -> tuple[bool, str]:
        """(its node is up, what is known of it) for ``what`` = "descriptor" (its sensors) or "policies" (its controller)."""
        return (self.sensors, self.described) if what == "descriptor" else (self.controller, self.announced)

    @property
    def ready(self) -> bool:
        """Live, and its descriptor and its controller's policies (or their absence) are known:
        episodes may go there."""
        return self.live and self.described in ("described", "undescribed") and self.announced in ("announced", "silent")

    @property
    def policies(self) -> tuple[str, ...] | None:
        """The policies its controller serves (a silent controller: the built-ins); None while not known."""
        if self.announced == "announced" and self.controller_info is not None:
            return tuple(p.name for p in self.controller_info.policies)
        return BUILTIN_POLICIES if self.announced == "silent" else None


class Scheduler:
    """Campaign execution over the bus; every method runs on ``self.loop``'s thread."""

    def __init__(self, bus: Bus, store: Store, window: int = 8, name: str = "orchestrator",
                 heal_backoff_s: tuple[float, float] = HEAL_BACKOFF_S, tick_s: float = TIMEOUT_CHECK_S,
                 model_retry_s: tuple[float, float] = MODEL_RETRY_S, model_patience_s: float = MODEL_PATIENCE_S) -> None:
        self.bus = bus
        self._model_retry = model_retry_s
        self._model_patience = model_patience_s
        self.store = store
        self._studies = StudyStore(store)
        self.window = max(1, int(window))
        self.loop = EventLoop("scheduler")
        self.rigs: dict[str, _Rig] = {}
        self.learners: set[str] = set()
        self.runs: dict[str, _Run] = {}
        self.flights: dict[str, _Flight] = {}
        self.rejected: Counter = Counter({reason: 0 for reason in REJECTIONS})
        self._order: deque[str] = deque()  # campaigns in FIFO order
        self._deferred: list[tuple[str, Callable[[], None]]] = []  # writes to retry once the database takes them
        self._finished: list[tuple[str, EpisodeKey, dict[str, Any], _Run, bool]] = []  # complete, to record together
        self._heal_backoff = heal_backoff_s
        self._heal_wait = heal_backoff_s[0]
        self._heal_at: float | None = None
        self._resumed = False
        self._provenance: dict[str, dict[str, str]] = {}  # policy -> {package, version} as a controller announced it
        self._handles = [
            bus.watch_alive(keys.alive_all(), lambda k, up: self.loop.post(self._on_alive, k, up)),
            bus.subscribe(keys.episode_result_all(), lambda k, p: self.loop.post(self._on_result, k, p)),
            bus.subscribe(keys.episode_truth_all(), lambda k, p: self.loop.post(self._on_truth, k, p)),
            bus.subscribe(keys.episode_timing_all(), lambda k, p: self.loop.post(self._on_timing, k, p)),
            bus.subscribe(keys.episode_rejected_all(), lambda k, p: self.loop.post(self._on_rejected, k, p)),
            bus.announce(keys.alive("orchestrator", keys.check_chunk(name, "name"))),
        ]
        self.loop.post(self._resume)
        self._stop = threading.Event()
        self._tick_s = tick_s
        self._ticker = threading.Thread(target=self._tick, name="scheduler-timeouts", daemon=True)
        self._ticker.start()

    def _tick(self) -> None:
        while not self._stop.wait(self._tick_s):
            self.loop.post(self._check_timeouts)
            self.loop.post(self._heal)

    # -- storage faults -------------------------------------------------------------------------
    @property
    def degraded(self) -> bool:
        """Whether writes are waiting for the database (no new episodes are handed out meanwhile)."""
        return bool(self._deferred) or not self._resumed

    def _defer(self, what: str, op: Callable[[], None], err: StorageFault | None = None) -> None:
        """Keep a write that failed (``op`` redoes it and what follows it, raising
        ``StorageFault`` if the database still refuses) to retry with backoff, in order."""
        if err is not None:
            log.error("storage fault while %s: %s; retrying", what, err)
        if all(w != what for w, _ in self._deferred):
            self._deferred.append((what, op))
        if self._heal_at is None:
            self._heal_at = time.time() + self._heal_wait

    def _attempt(self, what: str, op: Callable[[], None]) -> None:
        """Run a write (``op``) now, or after the writes already waiting, so the database sees
        them in the order they were asked for; a failure defers it."""
        if self._deferred:
            self._defer(what, op)
            return
        try:
            op()
        except StorageFault as err:
            self._defer(what, op, err)

    def _heal(self) -> None:
        """Retry the deferred writes in order, with exponential backoff; resume when all pass.
        A fault seen elsewhere (an API write) with nothing deferred is probed the same way, so
        ``/health`` recovers by itself."""
        if self._heal_at is None and self.store.fault is not None and self._resumed:
            self._defer("checking the database", self.store.probe_write)
        if self._heal_at is None or time.time() < self._heal_at:
            return
        try:
            if not self.store.available:
                self.store.reopen()
            if not self._resumed:
                self._resume()
                if not self._resumed:
                    raise StorageFault("resume deferred")
            while self._deferred:
                what, op = self._deferred[0]
                op()
                self._deferred.pop(0)
        except StorageFault as err:
            self._heal_wait = min(self._heal_wait * 2.0, self._heal_backoff[1])
            self._heal_at = time.time() + self._heal_wait
            log.warning("database still failing (%s); next retry in %.0f s", err, self._heal_wait)
            return
        log.info("database writable again: resuming")
        self._heal_at = None
        self._heal_wait = self._heal_backoff[0]
        self._dispatch()
        for run in list(self.runs.values()):
            self._maybe_finish(run)

    def _check_timeouts(self) -> None:
        """Requeue episodes unfinished far too long after they were sent (a lost message, a hung
        rig); an episode that finished and only waits for the database is not one."""
        now = time.time()
        for run in list(self.runs.values()):
            if run.model_retry_at is not None and now >= run.model_retry_at:
                self._request_model(run)
        for eid, flight in list(self.flights.items()):
            run = self.runs.get(flight.key.campaign_id)
            if run is None:
                continue
            if flight.result is not None and flight.truth is not None:
                continue
            limit = EPISODE_TIMEOUT_S + (2.0 * run.scenario.steps * run.scenario.rf_period_s if run.mode is Mode.realtime else 0.0)
            if now - flight.started > limit:
                log.warning("episode %s on %s timed out after %.0f s; rerunning it", eid, flight.rig, now - flight.started)
                self._requeue(eid, count_attempt=True, reason="timed out")

    # -- public (thread-safe) -----------------------------------------------------------------
    def submit(self, campaign_id: str) -> None:
        """A campaign was stored as queued: start it."""
        self.loop.post(self._start, campaign_id)

    def cancel(self, campaign_id: str) -> None:
        self.loop.post(self._cancel, campaign_id)

    def live_rigs(self) -> list[str]:
        return sorted(r for r, st in list(self.rigs.items()) if st.live)

    def ready_rigs(self) -> list[str]:
        """The live rigs whose descriptor and controller's policies (or their absence: a v1 node)
        are known, i.e. that episodes may go to (``_Rig.ready``)."""
        return sorted(r for r, st in list(self.rigs.items()) if st.ready)

    def close(self) -> None:
        self._stop.set()
        undeclare_all(self._handles)
        self.loop.stop()

    # -- campaign lifecycle ---------------------------------------------------------------------
    def _resume(self) -> None:
        """Start every campaign the database says is unfinished (after a restart). If the
        database cannot be read or written yet, the healer calls this again later."""
        if self._resumed:
            return
        try:
            active = self.store.active_campaigns()
            for c in active:
                reset = self.store.reset_running(c["id"])
                if reset:
                    log.info("campaign %s: %d interrupted episodes requeued", c["id"], reset)
        except StorageFault as err:
            log.error("cannot resume campaigns yet: %s; retrying", err)
            if self._heal_at is None:
                self._heal_at = time.time() + self._heal_wait
            return
        self._resumed = True
        for c in active:
            self._start(c["id"])

    def _start(self, cid: str) -> None:
        if cid in self.runs or not self._resumed:
            return  # not resumed yet: _resume starts it (it is in the database as queued)
        self._attempt(f"starting campaign {cid}", lambda: self._start_now(cid))

    def _start_now(self, cid: str) -> None:
        if cid in self.runs:
            return
        c = self.store.campaign(cid)
        if c is None or c["status"] not in ("queued", "training", "running"):
            return
        scenario = Scenario.model_validate(c["scenario"])
        run = _Run(id=cid, scenario=scenario, seed=c["seed"], mode=Mode(c["mode"]), stop_confidence=c.get("stop_confidence") or 0.0,
                   tests=c["tests"], targeting=c.get("targeting"), algorithms=tuple(c["algorithms"]))
        membership = self._studies.membership(cid)
        if membership is not None:
            run.study, run.point = membership
        if c["pod_job"] is not None:  # resumed after a restart: the model was already trained and scored
            run.pod = TrainedPOD(model=None, r2=c["pod_r2"], train_seconds=c["pod_train_seconds"] or 0.0)
            self._go_now(run)
            self.runs[cid] = run
            self._order.append(cid)
            self._after_go(run)
            return
        self.store.set_campaign(cid, status="training", started_at=c["started_at"] or time.time())
        self.runs[cid] = run
        self._order.append(cid)
        self._request_model(run)

    def _request_model(self, run: _Run) -> None:
        run.model_attempts += 1
        run.model_retry_at = None
        request = dump(PODRequest(scenario=run.scenario, seed=run.seed, protocol=PROTOCOL_VERSION))
        self.bus.query(keys.pod_model(), request, MODEL_TIMEOUT_S, lambda replies: self.loop.post(self._on_model, run.id, replies))

    def _on_model(self, cid: str, replies: list[Reply]) -> None:
        run = self.runs.get(cid)
        if run is None:
            return
        if not replies and run.model_attempts < MODEL_ATTEMPTS:
            # no learner (yet): the timeout ticker asks again; a campaign waits for its learner
            run.model_retry_at = time.time() + min(2.0 * run.model_attempts, 10.0)
            return
        response, passed_over = first_valid_reply(replies, PODResponse, "PODResponse")
        if response is None:
            error = passed_over[-1] if passed_over else "no learner answered"
            verdict = self._model_failed(run, error) if replies else error
            if verdict is not None:
                self._fail(run, f"POD model unavailable: {verdict}")
            return
        request = dump(TrainingRequest(job_id=response.job_id, scenario=run.scenario, seed=run.seed))
        self.bus.query(keys.training_truth_any(), request, 120.0,
                       lambda replies: self.loop.post(self._on_training_truth, cid, response, replies))

    def _model_failed(self, run: _Run, error: str) -> str | None:
        """The learner answered ``error`` instead of a model: schedule another request and return
        None, or return why the campaign fails.

        One failed request does not fail a campaign, unless the training episode was too thin to
        learn from and every live sensors node is simulated or a recorded survey
        (``TRAINING_DATA_ERROR``: the same episode again would fail the same way). If the learner found no sensors and none is
        live, the campaign waits for a rig, as for a learner (``_on_alive`` asks again the moment
        a rig's sensors come up). Any other failure, including sensors this orchestrator sees live
        but the learner's training query does not reach, is retried with doubling waits
        (``model_retry_s``) for ``model_patience_s``; then the campaign fails saying what was seen."""
        now = time.time()
        live = sorted(name for name, st in self.rigs.items() if st.sensors)
        if error == NO_SENSORS and not live:
            if not run.awaiting_sensors:
                log.warning("campaign %s: waiting for a rig's sensors to train the POD model on (none is live)", run.id)
            run.model_failing_since, run.model_failures, run.awaiting_sensors = None, 0, True
            if run.model_attempts < MODEL_ATTEMPTS:
                run.model_retry_at = now + 10.0
                return None
            return (f"{error}: no rig's sensors came up while this campaign waited ({run.model_attempts} requests). Start a rig "
                    "(ra2vipas sensors, or ra2vipas rig), and check that every service joins the same Zenoh router "
                    "(--connect tcp/ROUTER:7447, client mode)")
        run.awaiting_sensors = False
        if error.startswith(TRAINING_DATA_ERROR) and live and all(
                (d := self.rigs[name].descriptor) is not None and d.kind in ("simulated", "survey") for name in live):
            return (f"{error} (every live rig is simulated or a recorded survey: its training episode of this scenario and seed "
                    "is the same each time)")
        if run.model_failing_since is None:
            run.model_failing_since, run.model_failures = now, 0
        run.model_failures += 1
        elapsed = now - run.model_failing_since
        if elapsed < self._model_patience:
            wait = min(self._model_retry[0] * 2.0 ** (run.model_failures - 1), self._model_retry[1],
                       self._model_patience - elapsed)  # the last request when the patience runs out
            run.model_retry_at = now + wait
            seen = f" although the sensors of {', '.join(live)} are live" if error == NO_SENSORS else ""
            log.warning("campaign %s: the learner could not give the POD model (%s)%s; asking again in %.1f s",
                        run.id, error, seen, wait)
            return None
        attempts = f"{run.model_failures} requests over {elapsed:.0f} s"
        if error != NO_SENSORS:
            return f"{error} ({attempts})"
        rigs = "rig" + ("s " if len(live) > 1 else " ") + ", ".join(live)
        return (f"the learner's training query reached no sensors ({attempts}), although this orchestrator sees the "
                f"sensors of {rigs} live: the learner cannot reach them. Likely cause: Zenoh peer mode on the learner's "
                "or the sensors' host (a router relays nothing between peers, and a peer listens on loopback only unless "
                "given --listen). Start them with --zenoh-mode client --connect tcp/ROUTER:7447 (RA2VIPAS_ZENOH_MODE="
                "client), or give every peer a --listen endpoint the others can reach (behind a router with access "
                "control, also check that the learner may query data/*/training)")

    def _on_training_truth(self, cid: str, response: PODResponse, replies: list[Reply]) -> None:
        run = self.runs.get(cid)
        if run is None:
            return
        r2 = None
        truth_data = None  # kept with the model for the POD figure (paper Fig. 3)
        truth, _ = first_valid_reply(replies, TrainingTruth, "TrainingTruth",
                                     accept=lambda t: t.job_id == response.job_id and len(t.rssi_dbm) == len(t.pod))
        if truth is not None:
            r2 = round(float(r2_score(np.asarray(truth.pod), predict(response.model, np.asarray(truth.rssi_dbm)))), 6)
            truth_data = {"rssi_dbm": list(truth.rssi_dbm), "pod": list(truth.pod)}
        else:
            log.info("campaign %s: no training truth answered (a hardware rig has none): POD R² is not scored", cid)

        def record() -> None:
            if cid not in self.runs:
                return
            self.store.set_pod_artifacts(cid, model=response.model.model_dump(mode="json"), truth=truth_data)
            self.store.set_campaign(cid, pod_job=response.job_id, pod_r2=r2, pod_train_seconds=response.train_seconds)
            run.pod = TrainedPOD(model=response.model, r2=r2, train_seconds=response.train_seconds)
            self._go_now(run)
            self._after_go(run)

        self._attempt(f"recording the POD model of campaign {cid}", record)

    def _go_now(self, run: _Run) -> None:
        """Load the campaign's pending episodes and mark it running (raises ``StorageFault``)."""
        run.pending = deque(self.store.pending_episodes(run.id))
        self.store.set_campaign(run.id, status="running")
        run.running_since = time.time()

    def _after_go(self, run: _Run) -> None:
        self._dispatch()
        self._maybe_finish(run)

    def _cancel(self, cid: str) -> None:
        # a no-op if it already finished (e.g. failed just before, or the API cancelled it)
        self._attempt(f"cancelling campaign {cid}", lambda: self.store.cancel_campaign(cid))
        run = self.runs.pop(cid, None)
        if cid in self._order:
            self._order.remove(cid)
        for eid, flight in list(self.flights.items()):
            if flight.key.campaign_id == cid:
                self._drop_flight(eid, stop_reason="campaign cancelled")
        if run is not None:
            log.info("campaign %s cancelled", cid)
        self._dispatch()

    def _fail(self, run: _Run, error: str) -> None:
        log.error("campaign %s failed: %s", run.id, error)

        def record() -> None:
            self.store.set_campaign(run.id, status="failed", error=error[:2000], finished_at=time.time())

        self._attempt(f"recording the failure of campaign {run.id}", record)
        self._cancel(run.id)

    # -- dispatch -------------------------------------------------------------------------------
    def _dispatch(self) -> None:
        """Fill every live rig up to its window. A realtime episode runs alone on its rig: a
        real platform can only point one way at a time. Nothing is handed out while database
        writes are waiting: an episode is marked running before it is sent."""
        if self.degraded:
            return
        for rig_name in self.live_rigs():
            rig = self.rigs[rig_name]
            if not rig.ready:
                continue
            if any(self._is_realtime(eid) for eid in rig.in_flight):
                continue
            picked: list[tuple[_Run, EpisodeKey]] = []
            while len(rig.in_flight) + len(picked) < self.window:
                item = self._next_episode(allow_realtime=not rig.in_flight and not picked, rig=rig_name)
                if item is None:
                    break
                picked.append(item)
                if item[0].mode is Mode.realtime:
                    break
            if not picked:
                continue
            try:
                attempts = self.store.mark_running_many([key for _, key in picked], rig_name)  # one transaction
            except StorageFault as err:
                for run, key in reversed(picked):
                    run.pending.appendleft(key)
                self._defer("handing out episodes", self.store.probe_write, err)
                return
            for (run, key), attempt in zip(picked, attempts):
                eid = episode_id(key, attempt)
                self.flights[eid] = _Flight(key=key, rig=rig_name, attempt=attempt, started=time.time())
                rig.in_flight.add(eid)
                self.bus.publish(keys.episode_control(rig_name), dump(EpisodeStart(
                    episode_id=eid, campaign_id=key.campaign_id, test_index=key.test_index, algorithm=key.algorithm,
                    seed=run.seed, scenario=run.scenario, mode=run.mode, stop_confidence=run.stop_confidence)))

    def _eligible(self, run: _Run, rig_name: str) -> bool:
        """Whether ``run`` may go to ``rig_name``: the rig is one the campaign targets, and its
        descriptor (if it has one) does not contradict the campaign's scenario or mode."""
        known = run.eligible.get(rig_name)
        if known is not None:
            return known
        rig = self.rigs.get(rig_name)
        target = run.targeting or {}
        ok = rig is not None
        if ok and target.get("rigs"):
            ok = rig_name in target["rigs"]
        if ok and target.get("rig_kind"):
            ok = rig.descriptor is not None and rig.descriptor.kind == target["rig_kind"]
        if ok and rig.descriptor is not None:
            found = conflicts(rig.descriptor, run.scenario, run.mode.value)
            if found:
                log.warning("campaign %s does not run on rig %s: %s", run.id, rig_name, "; ".join(c.describe(rig_name) for c in found))
                ok = False
        if ok:
            version = speaks(rig.descriptor)
            missing = missing_features(version, campaign_features(run.stop_confidence, run.algorithms, run.scenario))
            if missing:
                log.warning("campaign %s does not run on rig %s: %s", run.id, rig_name,
                            "; ".join(describe_missing(rig_name, version, f, v) for f, v in missing))
                ok = False
        run.eligible[rig_name] = ok
        return ok

    def _next_episode(self, allow_realtime: bool, rig: str | None = None) -> tuple[_Run, EpisodeKey] | None:
        studies: set[str] = set()
        for cid in list(self._order):
            run = self.runs.get(cid)
            if run is None:
                continue
            if rig is not None and not self._eligible(run, rig):
                continue
            if run.study is not None:  # a study's points are served together, interleaved
                if run.study not in studies:
                    studies.add(run.study)
                    item = self._next_of_study(run.study, allow_realtime, rig)
                    if item is not None:
                        return item
                continue
            if run.pod is None or not run.pending:
                continue
            if run.mode is Mode.realtime and not allow_realtime:
                continue
            at = self._servable(run, rig)
            if at is None:
                continue
            return run, _pop_at(run.pending, at)
        return None

    def _servable(self, run: _Run, rig: str | None) -> int | None:
        """The index in ``run.pending`` of its first episode whose policy the controller of
        ``rig`` serves (any rig: 0), or None if it has none."""
        if not run.pending:
            return None
        if rig is None:
            return 0
        st = self.rigs.get(rig)
        served = st.policies if st is not None else None
        if not served or (run.algorithms and set(run.algorithms).isdisjoint(served)):
            return None
        return next((i for i, k in enumerate(run.pending) if k.algorithm in served), None)

    def _next_of_study(self, study: str, allow_realtime: bool, rig: str | None = None) -> tuple[_Run, EpisodeKey] | None:
        """The next episode of a study: from the point whose next test is the earliest (then the
        first point), so the points advance test by test together and partial results are
        meaningful early; a point's last test waits until every point has its POD model (and so
        has been handed its first tests), so every point gets its first tests before any point
        gets its last."""
        members = [r for r in self.runs.values() if r.study == study]
        all_trained = all(r.pod is not None for r in members)
        best: _Run | None = None
        best_k = best_at = 0
        for r in members:
            if r.pod is None or not r.pending or (r.mode is Mode.realtime and not allow_realtime):
                continue
            if rig is not None and not self._eligible(r, rig):
                continue
            at = self._servable(r, rig)
            if at is None:
                continue
            k = r.pending[at].test_index
            if r.tests > 1 and k >= r.tests - 1 and not all_trained:
                continue
            if best is None or (k, r.point) < (best_k, best.point):
                best, best_k, best_at = r, k, at
        return None if best is None else (best, _pop_at(best.pending, best_at))

    def _is_realtime(self, eid: str) -> bool:
        flight = self.flights.get(eid)
        run = self.runs.get(flight.key.campaign_id) if flight else None
        return run is not None and run.mode is Mode.realtime

    # -- results --------------------------------------------------------------------------------
    def _accepted(self, schema, key: str, payload: bytes):
        """The message and its flight if it validates, its episode is in flight and it came on
        the key of the rig that episode was assigned to; else None after counting why."""
        msg = decode_or_drop(schema, payload, schema.__name__, log)
        if msg is None or getattr(msg, "episode_id", "") is None:
            self.rejected["malformed"] += 1
            return None
        flight = self.flights.get(msg.episode_id)
        if flight is None:
            self.rejected["not_in_flight"] += 1
            log.debug("dropping %s of episode %s: not in flight", schema.__name__, msg.episode_id)
            return None
        if keys.rig_of(key) != flight.rig or getattr(msg, "rig", flight.rig) != flight.rig:
            self.rejected["wrong_rig"] += 1
            log.warning("dropping %s of episode %s on %s: that episode runs on rig %s", schema.__name__, msg.episode_id, key,
                        flight.rig)
            return None
        return msg, flight

    def _on_result(self, key: str, payload: bytes) -> None:
        accepted = self._accepted(EpisodeResult, key, payload)
        if accepted is None:
            return
        msg, flight = accepted
        if msg.status == "failed":
            log.warning("episode %s failed on %s: %s", msg.episode_id, flight.rig, msg.error)
            self._requeue(msg.episode_id, count_attempt=True, reason=msg.error)
            return
        if flight.result is None:
            flight.result = msg
        self._complete(msg.episode_id)

    def _on_rejected(self, key: str, payload: bytes) -> None:
        """A node of the rig rejected a message of an episode in flight there: that attempt fails
        at once with the node's reason (rerun like any failed attempt; after ``MAX_ATTEMPTS`` the
        campaign fails naming it), rather than timing out in silence."""
        accepted = self._accepted(ErrorReply, key, payload)
        if accepted is None:
            return
        msg, flight = accepted
        if flight.saving:
            return  # finished: a late rejection of a repeated message changes nothing
        log.warning("episode %s rejected on %s: %s", msg.episode_id, flight.rig, msg.error)
        self._requeue(msg.episode_id, count_attempt=True, reason=f"rejected: {msg.error}")

    def _on_truth(self, key: str, payload: bytes) -> None:
        self._attach(EpisodeTruth, key, payload, "truth")

    def _on_timing(self, key: str, payload: bytes) -> None:
        self._attach(EpisodeTiming, key, payload, "timing")

    def _attach(self, schema: type[EpisodeTruth] | type[EpisodeTiming], key: str, payload: bytes, part: str) -> None:
        """Keep the episode's truth or timing report with its flight (the first one that
        arrives on the right key); complete it if that was the last part missing."""
        accepted = self._accepted(schema, key, payload)
        if accepted is None:
            return
        msg, flight = accepted
        if getattr(flight, part) is None:
            setattr(flight, part, msg)
        self._complete(msg.episode_id)

    def _complete(self, eid: str) -> None:
        flight = self.flights.get(eid)
        run = self.runs.get(flight.key.campaign_id) if flight else None
        if flight is None or flight.result is None or flight.truth is None or flight.saving:
            return
        if run is not None and run.mode is Mode.realtime and flight.timing is None:
            return
        if run is None:
            self._drop_flight(eid)
            return
        res, truth = flight.result, flight.truth
        steps = run.scenario.steps
        bearings = truth_bearings(truth, steps)  # (N,), or (steps, N) when targets walk
        decided = res.decided_step
        expected = steps if decided is None else decided + 1
        if (len(res.estimates_rad) != expected or expected > steps or bearings is None
                or (decided is not None and run.stop_confidence <= 0.0)
                or (res.confidences and len(res.confidences) != expected)):
            log.warning("episode %s: inconsistent result (%d estimates for %d steps); rerun", eid, len(res.estimates_rad), steps)
            self._requeue(eid, count_attempt=True, reason="inconsistent result")
            return
        hits, in_fov, chosen = score_episode(np.asarray(res.estimates_rad), bearings, truth.tx_index,
                                             run.scenario.fov_half_angle_rad, steps, decided)
        tags = score_tags(res, truth, bearings, run.scenario, decided)
        if tags is False:
            log.warning("episode %s: inconsistent per-tag result; rerun", eid)
            self._requeue(eid, count_attempt=True, reason="inconsistent result")
            return
        record = dict(
            hits=[bool(h) for h in hits], in_fov=[bool(f) for f in in_fov], estimates=list(res.estimates_rad),
            pans=list(res.pans_rad), rewards=list(res.rewards), chosen=[int(i) for i in chosen],
            tx_index=truth.tx_index, bearings=list(truth.bearings_rad), ranges=list(truth.ranges_m),
            latencies=list(flight.timing.latencies_ms) if flight.timing and run.mode is Mode.realtime else None,
            trajectories=[t.model_dump(mode="json") for t in truth.trajectories] or None,
            confidences=list(res.confidences) or None, decided_step=decided,
            model_check=None if res.model_check is None else res.model_check.model_dump(mode="json"),
            tags=tags,
        )

        flight.saving = True  # a duplicate result must not record it twice meanwhile
        self._finished.append((eid, flight.key, record, run, decided is not None))
        if len(self._finished) == 1:  # after what arrived meanwhile: the whole burst is recorded in one transaction
            self.loop.post(self._save_finished)

    def _save_finished(self) -> None:
        """Record the episodes completed since the last call in one transaction, then forget
        their flights and hand out what they freed (a failed write is retried whole, later)."""
        batch, self._finished = self._finished, []
        if not batch:
            return

        def save() -> None:
            self.store.finish_episodes([(key, record) for _, key, record, _, _ in batch])  # nothing twice
            runs: dict[str, _Run] = {}
            for eid, _, _, run, decided in batch:
                self._drop_flight(eid, stop_reason="decided early" if decided else None)  # the sensors forget it
                runs[run.id] = run
            if any(cid in self.runs for cid in runs):
                self._dispatch()
            for run in runs.values():
                self._maybe_finish(run)

        self._attempt(f"recording episode {batch[0][0]}" + (f" and {len(batch) - 1} more" if len(batch) > 1 else ""), save)

    def _maybe_finish(self, run: _Run) -> None:
        if run.id not in self.runs or run.pending or any(f.key.campaign_id == run.id for f in self.flights.values()):
            return
        self._attempt(f"finishing campaign {run.id}", lambda: self._finish_now(run))

    def _finish_now(self, run: _Run) -> None:
        """Reduce a campaign whose every episode is recorded to its results object (raises
        ``StorageFault``)."""
        if run.id not in self.runs or run.pending or any(f.key.campaign_id == run.id for f in self.flights.values()):
            return
        c = self.store.campaign(run.id)
        if c is None or c["progress"]["done"] < c["progress"]["total"]:
            return
        tallies, latencies, checks = reduce_recorded(self.store.episode_outcomes(run.id), c["algorithms"], run.scenario)
        finished = time.time()
        elapsed = finished - (run.running_since or finished)
        steps_run = sum(t.steps_run for t in tallies.values())
        sps = (steps_run / elapsed) if elapsed > 0 else None
        results = results_object(c["preset"], run.scenario, c["tests"], c["seed"], run.pod, tallies, sps, run.stop_confidence)
        announced = {name: self._provenance[name] for name in results["algorithms"] if name in self._provenance}
        if announced:  # the controllers that ran a policy know its package best (the orchestrator may not have it)
            results["policies"] = {**results.get("policies", {}), **announced}
        if latencies.count:
            results["latency_ms"] = latencies.summary()
        checks.notes(results)
        if results["pod"].get("r2") is None:
            results["pod"]["note"] = ("R² not scored: no rig served the training truth (truth/*/training) when the model was "
                                      "trained; a hardware rig cannot, a simulated one or an operator can")
        self.store.set_campaign(run.id, status="done", results=_json(results), finished_at=finished,
                                steps_per_second=results["steps_per_second"])
        self.runs.pop(run.id, None)
        if run.id in self._order:
            self._order.remove(run.id)
        log.info("campaign %s done", run.id)

    # -- rigs and failures -------------------------------------------------------------------------
    def _on_alive(self, key: str, up: bool) -> None:
        parsed = keys.parse_alive(key)
        if parsed is None:
            return
        role, name = parsed
        if role == "learner":
            (self.learners.add if up else self.learners.discard)(name)
            return
        if role not in ("sensors", "controller"):
            return
        rig = self.rigs.setdefault(name, _Rig())
        was_live = rig.live
        setattr(rig, role, up)
        if role == "sensors":
            self._forget_descriptor(name)
            if up:  # the token is declared after the queryables (docs/protocol.md): ask what the rig is
                rig.described, rig.appeared["descriptor"] = "asking", time.monotonic()
                self._ask(name, "descriptor", new=True)
                for run in list(self.runs.values()):  # campaigns waiting for sensors to train on: ask again now
                    if run.awaiting_sensors and run.pod is None and run.model_retry_at is not None:
                        self._request_model(run)
        if role == "controller":
            rig.controller_info, rig.announced = None, "unknown"
            if up:  # its token is declared after its queryable: ask which policies it serves
                rig.announced, rig.appeared["policies"] = "asking", time.monotonic()
                self._ask(name, "policies", new=True)
        if rig.live != was_live or not rig.since:
            rig.since = time.time()
        if was_live and not rig.live:
            log.warning("rig %s lost (%s gone); requeueing %d episodes", name, role, len(rig.in_flight))
            for eid in list(rig.in_flight):
                flight = self.flights.get(eid)
                if flight is not None and flight.saving:
                    continue  # finished: only waiting for the database
                self._requeue(eid, count_attempt=False, reason=f"rig {name} lost")
        if not rig.sensors and not rig.controller:  # both its nodes left: it is no longer a rig of the mesh
            self.rigs.pop(name, None)
            for run in self.runs.values():
                run.eligible.pop(name, None)
            log.info("rig %s left (no sensors, no controller)", name)
            return
        if rig.live:
            self._dispatch()

    def _forget_descriptor(self, name: str) -> None:
        rig = self.rigs.get(name)
        if rig is not None:
            rig.descriptor, rig.described = None, "unknown"
        self._reassess(name)

    def _take_descriptor(self, name: str, rig: _Rig, descriptor: RigDescriptor | None) -> None:
        rig.descriptor, rig.described = descriptor, ("described" if descriptor is not None else "undescribed")
        self._reassess(name)

    def _reassess(self, name: str) -> None:
        """Rig ``name``'s descriptor changed: every campaign decides again whether it may run there."""
        for run in self.runs.values():
            run.eligible.pop(name, None)

    def _ask(self, name: str, what: str, new: bool = False, generation: int | None = None) -> None:
        """Query rig ``name``'s descriptor (``what`` = "descriptor") or its controller's policies
        ("policies"); ``new``: a fresh round of asking (its node just came up). A re-ask
        (``generation``: the round it belongs to) is dropped if the node went down or came up
        again since, or was answered."""
        rig = self.rigs.get(name)
        if rig is None:
            return
        if new:
            rig.asks[what] = (rig.asks.get(what, (0, 0))[0] + 1, 0)
        elif generation != rig.asks.get(what, (None, 0))[0]:
            return
        up, state = rig.asked(what)
        if not up or state != "asking":
            return
        round_ = rig.asks[what][0]
        handler = self._on_descriptor if what == "descriptor" else self._on_controller_info
        self.bus.query(_QUERIES[what][0](name), b"", DESCRIPTOR_TIMEOUT_S, lambda replies: self.loop.post(handler, name, replies, round_))

    def _asked_again(self, name: str, what: str, replies: list[Reply], generation: int) -> bool:
        """Whether an answer with no reply at all (a timeout counts as none: ``answered``) is asked again later (``DESCRIPTOR_REASK_S``)
        rather than taken as the node's silence; True also for an answer to an old round."""
        rig = self.rigs[name]
        current, empty = rig.asks.get(what, (None, 0))
        if generation != current:
            return True
        if replies or empty >= len(DESCRIPTOR_REASK_S):
            return False
        rig.asks[what] = (current, empty + 1)
        self.loop.post_later(DESCRIPTOR_REASK_S[empty], self._ask, name, what, False, current)
        log.info("no node answered the %s query of rig %s; asking again in %.0f s", what, name, DESCRIPTOR_REASK_S[empty])
        return True

    def _on_descriptor(self, name: str, replies: list[Reply], generation: int) -> None:
        replies = answered(replies)  # a query that timed out (a link cut mid-query) was answered by no node
        rig = self.rigs.get(name)
        if rig is None or not rig.sensors or rig.described != "asking":
            return
        if self._asked_again(name, "descriptor", replies, generation):
            return
        descriptor, passed_over = first_valid_reply(replies, RigDescriptor, "RigDescriptor")
        if descriptor is not None and descriptor.rig != name:
            log.warning("rig %s describes itself as rig %s; treated as undescribed", name, descriptor.rig)
            descriptor = None
        self._take_descriptor(name, rig, descriptor)
        if descriptor is None:
            log.info("rig %s is undescribed%s: its campaigns are scored under their scenarios' assumptions", name,
                     f" ({passed_over[-1]})" if passed_over else "")
            self._recheck_if_young(name, "descriptor", replies, generation)
        self._dispatch()

    def _recheck_if_young(self, name: str, what: str, replies: list[Reply], generation: int) -> None:
        """After rig ``name`` was taken for undescribed (``what`` = "descriptor") or its controller for
        silent ("policies") on the silence of a node whose token had just appeared (its queryable may
        not be routed yet): the rig stays usable as it is (a v1 node's readiness is not delayed), and
        the node is asked again when its token has stood ``SENSORS_SETTLED_S``, and then after
        ``RECHECK_BACKOFF_S`` while it stays silent (``_on_recheck``)."""
        young = SENSORS_SETTLED_S - (time.monotonic() - self.rigs[name].appeared.get(what, 0.0))
        if not replies and young > 0.0:
            self.loop.post_later(young, self._recheck, name, what, generation)

    def _still_unknown(self, name: str, what: str, generation: int) -> "_Rig | None":
        """Rig ``name`` if its node is up and still undescribed (or its controller silent) from round ``generation``."""
        rig = self.rigs.get(name)
        if rig is None or rig.asks.get(what, (None,))[0] != generation:
            return None
        up, state = rig.asked(what)
        return rig if up and state == _QUERIES[what][2] else None

    def _recheck(self, name: str, what: str, generation: int, attempt: int = 0) -> None:
        if self._still_unknown(name, what, generation) is not None:
            self.bus.query(_QUERIES[what][0](name), b"", DESCRIPTOR_TIMEOUT_S,
                           lambda replies: self.loop.post(self._on_recheck, name, what, replies, generation, attempt))

    def _on_recheck(self, name: str, what: str, replies: list[Reply], generation: int, attempt: int = 0) -> None:
        """Only a valid answer for that rig, in the same round, changes anything; without one the node
        is asked again after ``RECHECK_BACKOFF_S`` (its last wait repeated) while it stays up and
        unknown from that round: a queryable unrouted for longer than the settle time (a router slow
        to learn the node's routes) is seen once it is routed, without its token having to change;
        a v1 node's silence costs one query every few minutes."""
        rig = self._still_unknown(name, what, generation)
        if rig is None:
            return
        schema = _QUERIES[what][1]
        answer, _ = first_valid_reply(answered(replies), schema, schema.__name__)
        if answer is None or answer.rig != name:
            wait = RECHECK_BACKOFF_S[min(attempt, len(RECHECK_BACKOFF_S) - 1)]
            self.loop.post_later(wait, self._recheck, name, what, generation, attempt + 1)
            return
        log.info("rig %s answered its %s once its token had settled", name, what)
        (self._take_descriptor if what == "descriptor" else self._take_policies)(name, rig, answer)
        self._dispatch()

    def _on_controller_info(self, name: str, replies: list[Reply], generation: int) -> None:
        replies = answered(replies)  # as for the descriptor
        rig = self.rigs.get(name)
        if rig is None or not rig.controller or rig.announced != "asking":
            return
        if self._asked_again(name, "policies", replies, generation):
            return
        info, passed_over = first_valid_reply(replies, ControllerInfo, "ControllerInfo")
        if info is not None and info.rig != name:
            log.warning("the controller of rig %s answers for rig %s; taken to serve the built-ins only", name, info.rig)
            info = None
        if info is None:
            rig.controller_info, rig.announced = None, "silent"
            log.info("the controller of rig %s says nothing of its policies%s: it serves the built-ins (%s)", name,
                     f" ({passed_over[-1]})" if passed_over else "", ", ".join(BUILTIN_POLICIES))
            self._recheck_if_young(name, "policies", replies, generation)
        else:
            self._take_policies(name, rig, info)
        self._dispatch()

    def _take_policies(self, name: str, rig: _Rig, info: ControllerInfo) -> None:
        rig.controller_info, rig.announced = info, "announced"
        log.info("the controller of rig %s serves %s", name, ", ".join(p.name for p in info.policies))
        for offer in info.policies:
            if offer.name not in BUILTIN_POLICIES and offer.name not in SHIPPED_BASELINES and offer.package:
                self._provenance[offer.name] = {"package": offer.package, "version": offer.version or "?"}

    def served(self) -> dict[str, tuple[str, ...] | None]:
        """The policies each live rig's controller serves (None: not known yet); thread-safe copy."""
        return {name: st.policies for name, st in list(self.rigs.items()) if st.live}

    def protocols(self) -> dict[str, str | None]:
        """The protocol version each known rig speaks (``rig.speaks``: 1.0 when undescribed; None
        while its descriptor is not known yet); thread-safe copy."""
        return {name: (speaks(st.descriptor) if st.described in ("described", "undescribed") else None)
                for name, st in list(self.rigs.items())}

    def descriptors(self) -> dict[str, RigDescriptor | None]:
        """Each known rig's descriptor (None: undescribed or not known yet); thread-safe copy."""
        return {name: st.descriptor for name, st in list(self.rigs.items())}

    def _requeue(self, eid: str, count_attempt: bool, reason: str) -> None:
        flight = self.flights.get(eid)
        if flight is None:
            return
        self._drop_flight(eid, stop_reason=reason)
        run = self.runs.get(flight.key.campaign_id)
        if run is None:
            return
        if count_attempt and flight.attempt >= MAX_ATTEMPTS:
            self._fail(run, f"test {flight.key.test_index} ({flight.key.algorithm}) failed {flight.attempt} times: {reason}")
            return
        try:
            self.store.mark_pending(flight.key)
        except StorageFault as err:  # harmless: the row stays 'running' and is handed out again from memory
            log.warning("could not mark episode %s pending: %s", eid, err)
        run.pending.appendleft(flight.key)
        self._dispatch()

    def _drop_flight(self, eid: str, stop_reason: str | None = None) -> None:
        flight = self.flights.pop(eid, None)
        if flight is None:
            return
        rig = self.rigs.get(flight.rig)
        if rig is not None:
            rig.in_flight.discard(eid)
        if stop_reason is not None:
            self.bus.publish(keys.episode_control(flight.rig), dump(EpisodeStop(episode_id=eid, reason=stop_reason[:500])))

    def status(self) -> dict[str, Any]:
        """Snapshot for /health (read from another thread; copies only)."""
        return {
            "rigs": {name: {"sensors": st.sensors, "controller": st.controller, "in_flight": len(st.in_flight),
                            "since": st.since, "described": st.described,
                            "descriptor": None if st.descriptor is None else st.descriptor.model_dump(mode="json"),
                            "protocol": speaks(st.descriptor) if st.described in ("described", "undescribed") else None,
                            "announced": st.announced, "policies": _policies_public(st),
                            "controller_protocol": st.controller_info.protocol if st.controller_info is not None else None}
                     for name, st in list(self.rigs.items())},
            "learners": sorted(self.learners),
            "rejected": dict(self.rejected),
            "waiting_writes": len(self._deferred),
        }


def _policies_public(rig: _Rig) -> list[dict[str, str]] | None:
    """The policies a rig's controller serves, each ``{name, package, version}`` (a silent
    controller's built-ins with package ``ra2vipas`` and no version); None while not known."""
    if rig.controller_info is not None:
        return [p.model_dump(mode="json") for p in rig.controller_info.policies]
    if rig.policies is None:
        return None
    return [{"name": name, "package": "ra2vipas", "version": ""} for name in rig.policies]


def score_tags(res, truth, bearings, scenario: Scenario, decided: int | None) -> dict[str, Any] | None | bool:
    """An ``EpisodeResult`` that searched for several tags (``tags``, protocol 1.4) scored per tag
    against ``EpisodeTruth.tx_indices`` (eq. 11 per tag, held to the horizon after an early end,
    as ``simulate.score_tags``): the ``episodes.tags`` record; None for a single-tag result (or a
    one-tag scenario), False when the tags do not match the truth's (the result is rerun)."""
    if not res.tags or scenario.n_tags <= 1:
        return None
    carriers = truth.tx_indices or (truth.tx_index,)
    if sorted(t.tag for t in res.tags) != list(range(len(carriers))) or any(not 0 <= c < len(truth.bearings_rad) for c in carriers):
        return False
    steps = scenario.steps
    out: dict[str, Any] = {"hits": [], "in_fov": [], "confidences": [], "decided": []}
    for tag in sorted(res.tags, key=lambda t: t.tag):
        h, f, _ = score_episode(np.asarray(tag.estimates_rad), bearings, carriers[tag.tag], scenario.fov_half_angle_rad, steps, decided)
        out["hits"].append([int(x) for x in h])
        out["in_fov"].append([int(x) for x in f])
        out["confidences"].append(held(list(tag.confidences), steps) if tag.confidences else None)
        out["decided"].append(tag.decided_step)
    if any(c is None for c in out["confidences"]):
        out["confidences"] = None
    return out


def reduce_recorded(rows: Iterable[dict[str, Any]], algorithms: Iterable[str],
                    scenario: Scenario) -> tuple[dict[str, AlgorithmTally], LatencyTally, RigChecks]:
    """A campaign's recorded episodes (``Store.episode_outcomes``: read a page at a time)
    reduced as they stream past, in memory that does not grow with tests x steps: per
    algorithm its running sums (``reduce.AlgorithmTally``), the realtime latencies as a
    histogram (``reduce.LatencyTally``) and the controllers' model checks as counts
    (``rigcheck.RigChecks``)."""
    steps = scenario.steps
    tallies = {a: AlgorithmTally(steps, scenario.rf_period_s) for a in algorithms}
    latencies = LatencyTally()
    checks = RigChecks()
    for row in rows:
        tallies[row["algorithm"]].add(row["hits"], row["in_fov"], held(row.get("confidences") or [], steps) or None,
                                      row.get("decided_step"), row["n_estimates"], test_index=row.get("test_index"))
        tags = row.get("tags")
        if tags:
            tallies[row["algorithm"]].add_tags(np.asarray(tags["hits"], dtype=bool), np.asarray(tags["in_fov"], dtype=bool),
                                               None if tags.get("confidences") is None else np.asarray(tags["confidences"]),
                                               tags["decided"])
        latencies.add(row.get("latencies") or ())
        checks.add(row.get("rig"), row.get("model_check"))
    return tallies, latencies, checks


def _pop_at(pending: deque, at: int) -> EpisodeKey:
    """Take the ``at``-th item out of ``pending`` (the first one in the usual case)."""
    if at == 0:
        return pending.popleft()
    key = pending[at]
    del pending[at]
    return key


def episode_id(key: EpisodeKey, attempt: int) -> str:
    """``campaign.test.algorithm.attempt.nonce``: readable, and unguessable thanks to the nonce
    (64 random bits), so nobody can answer for an episode they were not sent."""
    return f"{key.campaign_id}.{key.test_index}.{key.algorithm}.{attempt}.{secrets.token_hex(8)}"


def _json(obj: Any) -> str:
    import json

    return json.dumps(obj, separators=(",", ":"))
