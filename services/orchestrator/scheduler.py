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

A rig is live while both its sensors and its controller hold their liveliness tokens. If a
rig disappears, its unfinished episodes go back to the queue and are run again from scratch
elsewhere: every draw of test k depends only on (seed, k), so the rerun gives the result the
lost run would have given, and ``finish_episode`` never records a test twice. On start, the
scheduler resumes every campaign the database says is unfinished.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ra2vipas.services.learner.pod import predict, r2_score
from ra2vipas.services.orchestrator.metrics import associate, score_test
from ra2vipas.services.orchestrator.simulate import TestOutcome, TrainedPOD, summarize
from ra2vipas.services.orchestrator.storage import EpisodeKey, Store
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    EpisodeResult, EpisodeStart, EpisodeStop, EpisodeTiming, EpisodeTruth, Mode, PODRequest, PODResponse,
    TrainingRequest, TrainingTruth, dump,
)
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.transport.bus import Bus, Reply, undeclare_all
from ra2vipas.services.transport.runtime import EventLoop, decode_or_drop, first_valid_reply

log = logging.getLogger(__name__)

MAX_ATTEMPTS = 5
MODEL_TIMEOUT_S = 600.0
MODEL_ATTEMPTS = 60  # retries (every 2-10 s) while no learner answers
EPISODE_TIMEOUT_S = 60.0  # plus twice the test's duration in realtime mode
TIMEOUT_CHECK_S = 2.0


@dataclass
class _Flight:
    key: EpisodeKey
    rig: str
    attempt: int
    started: float
    result: EpisodeResult | None = None
    truth: EpisodeTruth | None = None
    timing: EpisodeTiming | None = None


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


@dataclass
class _Rig:
    sensors: bool = False
    controller: bool = False
    in_flight: set = field(default_factory=set)

    @property
    def live(self) -> bool:
        return self.sensors and self.controller


class Scheduler:
    """Campaign execution over the bus; every method runs on ``self.loop``'s thread."""

    def __init__(self, bus: Bus, store: Store, window: int = 8, name: str = "orchestrator") -> None:
        self.bus = bus
        self.store = store
        self.window = max(1, int(window))
        self.loop = EventLoop("scheduler")
        self.rigs: dict[str, _Rig] = {}
        self.learners: set[str] = set()
        self.runs: dict[str, _Run] = {}
        self.flights: dict[str, _Flight] = {}
        self._order: deque[str] = deque()  # campaigns in FIFO order
        self._handles = [
            bus.watch_alive(keys.alive_all(), lambda k, up: self.loop.post(self._on_alive, k, up)),
            bus.subscribe(keys.episode_result_all(), lambda _k, p: self.loop.post(self._on_result, p)),
            bus.subscribe(keys.episode_truth_all(), lambda _k, p: self.loop.post(self._on_truth, p)),
            bus.subscribe(keys.episode_timing_all(), lambda _k, p: self.loop.post(self._on_timing, p)),
            bus.announce(keys.alive("orchestrator", keys.check_chunk(name, "name"))),
        ]
        self.loop.post(self._resume)
        self._stop = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="scheduler-timeouts", daemon=True)
        self._ticker.start()

    def _tick(self) -> None:
        while not self._stop.wait(TIMEOUT_CHECK_S):
            self.loop.post(self._check_timeouts)

    def _check_timeouts(self) -> None:
        """Requeue episodes unfinished far too long after they were sent (a lost message, a hung rig)."""
        now = time.time()
        for run in list(self.runs.values()):
            if run.model_retry_at is not None and now >= run.model_retry_at:
                self._request_model(run)
        for eid, flight in list(self.flights.items()):
            run = self.runs.get(flight.key.campaign_id)
            if run is None:
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

    def close(self) -> None:
        self._stop.set()
        undeclare_all(self._handles)
        self.loop.stop()

    # -- campaign lifecycle ---------------------------------------------------------------------
    def _resume(self) -> None:
        for c in self.store.active_campaigns():
            reset = self.store.reset_running(c["id"])
            if reset:
                log.info("campaign %s: %d interrupted episodes requeued", c["id"], reset)
            self._start(c["id"])

    def _start(self, cid: str) -> None:
        if cid in self.runs:
            return
        c = self.store.campaign(cid)
        if c is None or c["status"] not in ("queued", "training", "running"):
            return
        scenario = Scenario.model_validate(c["scenario"])
        run = _Run(id=cid, scenario=scenario, seed=c["seed"], mode=Mode(c["mode"]))
        self.runs[cid] = run
        self._order.append(cid)
        if c["pod_job"] is not None:  # resumed after a restart: the model was already trained and scored
            run.pod = TrainedPOD(model=None, r2=c["pod_r2"], train_seconds=c["pod_train_seconds"] or 0.0)
            self._go(run)
            return
        self.store.set_campaign(cid, status="training", started_at=c["started_at"] or time.time())
        self._request_model(run)

    def _request_model(self, run: _Run) -> None:
        run.model_attempts += 1
        run.model_retry_at = None
        request = dump(PODRequest(scenario=run.scenario, seed=run.seed))
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
            self._fail(run, f"POD model unavailable: {passed_over[-1] if passed_over else 'no learner answered'}")
            return
        request = dump(TrainingRequest(job_id=response.job_id, scenario=run.scenario, seed=run.seed))
        self.bus.query(keys.training_truth_any(), request, 120.0,
                       lambda replies: self.loop.post(self._on_training_truth, cid, response, replies))

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
        run.pod = TrainedPOD(model=response.model, r2=r2, train_seconds=response.train_seconds)
        self.store.set_campaign(cid, pod_job=response.job_id, pod_r2=r2, pod_train_seconds=response.train_seconds)
        self.store.set_pod_artifacts(cid, model=response.model.model_dump(mode="json"), truth=truth_data)
        self._go(run)

    def _go(self, run: _Run) -> None:
        run.pending = deque(self.store.pending_episodes(run.id))
        run.running_since = time.time()
        self.store.set_campaign(run.id, status="running")
        self._dispatch()
        self._maybe_finish(run)

    def _cancel(self, cid: str) -> None:
        self.store.cancel_campaign(cid)  # no-op if it already finished (e.g. failed just before)
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
        self.store.set_campaign(run.id, status="failed", error=error[:2000], finished_at=time.time())
        self._cancel(run.id)

    # -- dispatch -------------------------------------------------------------------------------
    def _dispatch(self) -> None:
        """Fill every live rig up to its window. A realtime episode runs alone on its rig: a
        real platform can only point one way at a time."""
        for rig_name in self.live_rigs():
            rig = self.rigs[rig_name]
            while len(rig.in_flight) < self.window:
                if any(self._is_realtime(eid) for eid in rig.in_flight):
                    break
                item = self._next_episode(allow_realtime=not rig.in_flight)
                if item is None:
                    break
                run, key = item
                attempt = self.store.attempt_of(key) + 1
                eid = f"{key.campaign_id}.{key.test_index}.{key.algorithm}.{attempt}"
                self.store.mark_running(key, rig_name, attempt)
                self.flights[eid] = _Flight(key=key, rig=rig_name, attempt=attempt, started=time.time())
                rig.in_flight.add(eid)
                self.bus.publish(keys.episode_control(rig_name), dump(EpisodeStart(
                    episode_id=eid, campaign_id=key.campaign_id, test_index=key.test_index, algorithm=key.algorithm,
                    seed=run.seed, scenario=run.scenario, mode=run.mode)))

    def _next_episode(self, allow_realtime: bool) -> tuple[_Run, EpisodeKey] | None:
        for cid in list(self._order):
            run = self.runs.get(cid)
            if run is None or run.pod is None or not run.pending:
                continue
            if run.mode is Mode.realtime and not allow_realtime:
                continue
            return run, run.pending.popleft()
        return None

    def _is_realtime(self, eid: str) -> bool:
        flight = self.flights.get(eid)
        run = self.runs.get(flight.key.campaign_id) if flight else None
        return run is not None and run.mode is Mode.realtime

    # -- results --------------------------------------------------------------------------------
    def _on_result(self, payload: bytes) -> None:
        msg = decode_or_drop(EpisodeResult, payload, "EpisodeResult", log)
        if msg is None:
            return
        flight = self.flights.get(msg.episode_id)
        if flight is None:
            return
        if msg.status == "failed":
            log.warning("episode %s failed on %s: %s", msg.episode_id, flight.rig, msg.error)
            self._requeue(msg.episode_id, count_attempt=True, reason=msg.error)
            return
        flight.result = msg
        self._complete(msg.episode_id)

    def _on_truth(self, payload: bytes) -> None:
        self._attach(EpisodeTruth, payload, "truth")

    def _on_timing(self, payload: bytes) -> None:
        self._attach(EpisodeTiming, payload, "timing")

    def _attach(self, schema: type[EpisodeTruth] | type[EpisodeTiming], payload: bytes, part: str) -> None:
        """Keep the episode's truth or timing report with its flight; complete it if that was
        the last part missing."""
        msg = decode_or_drop(schema, payload, schema.__name__, log)
        if msg is None:
            return
        flight = self.flights.get(msg.episode_id)
        if flight is not None:
            setattr(flight, part, msg)
            self._complete(msg.episode_id)

    def _complete(self, eid: str) -> None:
        flight = self.flights.get(eid)
        run = self.runs.get(flight.key.campaign_id) if flight else None
        if flight is None or flight.result is None or flight.truth is None:
            return
        if run is not None and run.mode is Mode.realtime and flight.timing is None:
            return
        steps = run.scenario.steps if run else len(flight.result.estimates_rad)
        res, truth = flight.result, flight.truth
        self._drop_flight(eid)
        if run is None:
            return
        if len(res.estimates_rad) != steps or truth.tx_index >= len(truth.bearings_rad):
            log.warning("episode %s: inconsistent result (%d estimates for %d steps); rerun", eid, len(res.estimates_rad), steps)
            self.store.mark_pending(flight.key)
            run.pending.appendleft(flight.key)
            self._dispatch()
            return
        bearings = np.asarray(truth.bearings_rad)
        estimates = np.asarray(res.estimates_rad)
        hits, in_fov = score_test(estimates, bearings, truth.tx_index, run.scenario.fov_half_angle_rad)
        self.store.finish_episode(
            flight.key, hits=[bool(h) for h in hits], in_fov=[bool(f) for f in in_fov], estimates=list(res.estimates_rad),
            pans=list(res.pans_rad), rewards=list(res.rewards), chosen=[int(i) for i in associate(estimates, bearings)],
            tx_index=truth.tx_index, bearings=list(truth.bearings_rad), ranges=list(truth.ranges_m),
            latencies=list(flight.timing.latencies_ms) if flight.timing else None,
        )
        self._dispatch()
        self._maybe_finish(run)

    def _maybe_finish(self, run: _Run) -> None:
        if run.pending or any(f.key.campaign_id == run.id for f in self.flights.values()):
            return
        c = self.store.campaign(run.id)
        if c is None or c["progress"]["done"] < c["progress"]["total"]:
            return
        rows = self.store.episode_rows(run.id)
        outcomes: dict[str, list[TestOutcome]] = {a: [] for a in c["algorithms"]}
        for row in rows:
            outcomes[row["algorithm"]].append(TestOutcome(
                algorithm=row["algorithm"], test_index=row["test_index"], hits=[bool(h) for h in row["hits"]],
                in_fov=[bool(f) for f in row["in_fov"]]))
        finished = time.time()
        elapsed = finished - (run.running_since or finished)
        sps = (len(rows) * run.scenario.steps / elapsed) if elapsed > 0 else None
        results = summarize(c["preset"], run.scenario, c["tests"], c["seed"], run.pod, outcomes, sps)
        latencies = [v for row in rows for v in (row.get("latencies") or [])]
        if latencies:
            results["latency_ms"] = {"p50": round(float(np.percentile(latencies, 50)), 4), "p99": round(float(np.percentile(latencies, 99)), 4)}
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
        if was_live and not rig.live:
            log.warning("rig %s lost (%s gone); requeueing %d episodes", name, role, len(rig.in_flight))
            for eid in list(rig.in_flight):
                self._requeue(eid, count_attempt=False, reason=f"rig {name} lost")
        if rig.live:
            self._dispatch()

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
        self.store.mark_pending(flight.key)
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
            "rigs": {name: {"sensors": st.sensors, "controller": st.controller, "in_flight": len(st.in_flight)} for name, st in list(self.rigs.items())},
            "learners": sorted(self.learners),
        }


def _json(obj: Any) -> str:
    import json

    return json.dumps(obj, separators=(",", ":"))
