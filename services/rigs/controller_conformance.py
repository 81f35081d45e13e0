"""The conformance kit for controllers: drive a live controller through scripted episodes and
say, rule by rule, whether it speaks the protocol of docs/protocol.md ("Writing your own
controller"; ``ra2vipas protocol check --controller RIG``).

The kit plays everyone else of one rig on any ``Bus``: the orchestrator (it publishes the
``EpisodeStart``/``EpisodeStop`` and reads the results), the sensors (it answers
``rig/{rig}/info`` with a small ``RigDescriptor`` and feeds ``Measurement`` s step by step) and
the learner (it answers ``model/pod`` with a small valid ``PODModel``, but only for its own
requests: those of its own, kit-specific seed; any other request gets no reply from it). It uses
its own episode ids (``conformance.*``). Run it while the rig's sensors node is down (it plays
the sensors) and no campaign uses the rig.

Every rule has a name (``RULES``) and ``check_controller`` returns one ``RuleResult`` per rule
(the result type of the sensors kit, ``services/rigs/conformance.py``): passed, failed (with
what was seen) or skipped (optional behaviour the controller does not show).
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from pydantic import ValidationError

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.measurements import CameraFrame, RFSample
from ra2vipas.services.protocol.messages import (
    Command,
    ControllerInfo,
    EpisodeResult,
    EpisodeStart,
    EpisodeStop,
    ErrorReply,
    Measurement,
    PODRequest,
    PODResponse,
    dump,
    training_job_id,
)
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.rig import RigDescriptor
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.rigs.conformance import RuleResult, _first
from ra2vipas.services.transport.bus import Bus

RULES: dict[str, str] = {
    "liveliness": "the controller holds the liveliness token alive/controller/{rig}, declared last: as soon as it appears, an "
                  "episode's start is answered (and rig/{rig}/policies, if it serves it)",
    "policies": "rig/{rig}/policies answers a valid ControllerInfo naming the rig (protocol 1.2; skip: a 1.0/1.1 controller "
                "serves none)",
    "command-0": "after an EpisodeStart it sends one valid Command(0) with a finite pan in [-pi, pi] within the timeout",
    "lockstep": "each Measurement(t) is answered by one valid Command(t+1) of the same episode with a finite pan in [-pi, pi]; "
                "none after the last step",
    "duplicate-measurement": "a repeated, an older or a future Measurement gets no Command (the episode does not advance)",
    "duplicate-start": "a repeated EpisodeStart does not restart the episode (no second Command(0); the next step is answered)",
    "result": "after the last step, exactly one valid EpisodeResult: status done, naming the rig, one estimate and one pan "
              "per step",
    "stop-mid-episode": "after an EpisodeStop, a Measurement of that episode gets no Command and no EpisodeResult",
    "unserved-policy": "an EpisodeStart of a policy it does not serve gets an EpisodeResult with status failed naming the "
                       "policy, and no Command",
    "malformed": "malformed control and measurement messages are dropped: the node stays up and runs the next episode",
    "rejects-malformed": "a malformed EpisodeStart naming an episode is rejected with an ErrorReply of that episode on "
                         "result/{rig}/rejected (protocol 1.1, optional: skip if none)",
    "concurrent": "two episodes in flight at once, their measurements interleaved, each get their own commands and their own "
                  "result",
}

TARGETS_RAD = (0.5, -1.0, 2.0, -2.6)
"""The kit's scene: the bearings of the targets its measurements show (the first carries the Tx)."""
UNSERVED = "conformance-unserved"


@dataclass
class _Seen:
    key: str
    payload: bytes
    parsed: dict | None
    at: float


def _wrap(angle: float) -> float:
    return float(wrap(angle))


def measurement(eid: str, step: int, pan: float, scenario: Scenario) -> Measurement:
    """What the kit's sensors sense at ``pan``: the targets of ``TARGETS_RAD`` in view (bearings
    relative to the optical axis, sorted) in each of nu frames, and an RSSI pair that is
    strongest towards the first target."""
    half = math.radians(scenario.fov_half_angle_deg)
    rel = sorted(_wrap(b - pan) for b in TARGETS_RAD if abs(_wrap(b - pan)) <= half)
    misalign = abs(_wrap(TARGETS_RAD[0] - pan))
    frames = tuple(CameraFrame(box_bearings_rad=tuple(rel)) for _ in range(scenario.frames_per_rf))
    rf = RFSample(iso_rssi_dbm=-45.0, dir_rssi_dbm=-40.0 - 10.0 * misalign)
    return Measurement(episode_id=eid, step=step, pan_rad=_wrap(pan), rf=rf, frames=frames)


def pod_model(scenario: Scenario) -> PODModel:
    """A small valid POD model (what the kit's learner serves)."""
    return PODModel(rssi_grid_dbm=(-80.0, -60.0, -40.0, -20.0), mean=(0.05, 0.3, 0.7, 0.95), std=(0.1, 0.1, 0.1, 0.1),
                    rf_noise_db=3.0, n_train=scenario.n_train, frames_per_rf=scenario.frames_per_rf)


class ControllerKit:
    """One run of the kit against the controller of ``rig`` on ``bus``. ``timeout``: how long to
    wait for any single answer [s]; ``policy``: the policy its episodes name (default: ``ra2vipas``
    if the controller serves it, else the first it announces)."""

    def __init__(self, bus: Bus, rig: str, timeout: float = 5.0, policy: str | None = None, clock=time.monotonic) -> None:
        self.bus, self.rig, self.timeout, self.clock = bus, keys.check_chunk(rig), timeout, clock
        self.policy = policy
        self.results: dict[str, RuleResult] = {}
        self.seen: list[_Seen] = []  # commands, results and rejections, in arrival order
        self._lock = threading.Condition()
        self._nonce = f"{int(time.time() * 1000) % 10**9}"
        self.seed = 1_000_000_000 + int(self._nonce)  # the kit's learner answers only requests of this seed
        self.model_requests = 0
        self.descriptor_queries = 0
        self._token_up = threading.Event()
        self._handles = [
            bus.subscribe(keys.command(rig), self._note),
            bus.subscribe(keys.episode_result(rig), self._note),
            bus.subscribe(keys.episode_rejected(rig), self._note),
            bus.serve(keys.rig_info(rig), self._on_info),
            bus.serve(keys.pod_model(), self._on_model),
        ]
        self._handles.append(bus.watch_alive(keys.alive("controller", rig), lambda _k, up: self._token_up.set() if up else None))

    # -- the kit's sensors and learner -----------------------------------------------------------
    def _on_info(self, _key: str, _payload: bytes) -> bytes:
        self.descriptor_queries += 1
        return dump(RigDescriptor(rig=self.rig, kind="simulated", modes=("fast",), training=False))

    def _on_model(self, _key: str, payload: bytes) -> bytes | None:
        try:
            request = PODRequest.model_validate_json(payload)
        except ValidationError:
            return None
        if request.seed != self.seed:
            return None  # not the kit's: let the mesh's learner answer it
        self.model_requests += 1
        return dump(PODResponse(job_id=training_job_id(request.scenario, request.seed), model=pod_model(request.scenario),
                                train_seconds=0.0), request.protocol)

    # -- plumbing ----------------------------------------------------------------------------------
    def _note(self, key: str, payload: bytes) -> None:
        try:
            parsed = json.loads(payload)
        except ValueError:
            parsed = None
        with self._lock:
            self.seen.append(_Seen(key, payload, parsed if isinstance(parsed, dict) else None, self.clock()))
            self._lock.notify_all()

    def _mark(self) -> int:
        with self._lock:
            return len(self.seen)

    def _matching(self, key: str, eid: str, since: int = 0, step: int | None = None) -> list[_Seen]:
        with self._lock:
            return [s for s in self.seen[since:] if s.key == key and s.parsed and s.parsed.get("episode_id") == eid
                    and (step is None or s.parsed.get("step") == step)]

    def _wait(self, pick: Callable[[], list[_Seen]], timeout: float | None = None) -> _Seen | None:
        deadline = self.clock() + (self.timeout if timeout is None else timeout)
        with self._lock:
            while True:
                found = pick()
                if found:
                    return found[0]
                left = deadline - self.clock()
                if left <= 0:
                    return None
                self._lock.wait(left)

    def _command(self, eid: str, step: int, since: int = 0, timeout: float | None = None) -> _Seen | None:
        return self._wait(lambda: self._matching(keys.command(self.rig), eid, since, step), timeout)

    def _result_of(self, eid: str, since: int = 0, timeout: float | None = None) -> _Seen | None:
        return self._wait(lambda: self._matching(keys.episode_result(self.rig), eid, since), timeout)

    def _id(self, what: str) -> str:
        return f"conformance.{self._nonce}.{what}"

    def _scenario(self, steps: int) -> Scenario:
        return Scenario(steps=steps, n_train=25, n_targets=len(TARGETS_RAD), frames_per_rf=3)

    def _start(self, eid: str, steps: int, algorithm: str | None = None, index: int = 0) -> bytes:
        payload = dump(EpisodeStart(episode_id=eid, campaign_id=f"conformance-{self._nonce}", test_index=index,
                                    algorithm=algorithm or self.policy or "ra2vipas", seed=self.seed,
                                    scenario=self._scenario(steps)))
        self._started_at = self.clock()
        self.bus.publish(keys.episode_control(self.rig), payload)
        return payload

    def _stop(self, eid: str, reason: str) -> None:
        self.bus.publish(keys.episode_control(self.rig), dump(EpisodeStop(episode_id=eid, reason=reason)))

    def _measure(self, eid: str, step: int, pan: float, steps: int) -> None:
        self.bus.publish(keys.measurement(self.rig), dump(measurement(eid, step, pan, self._scenario(steps))), express=True)

    def _result(self, rule: str, ok: bool | None, detail: str = "") -> None:
        if rule in self.results and self.results[rule].status == "fail":
            return  # the first failure stands
        self.results[rule] = RuleResult(rule, "skip" if ok is None else ("pass" if ok else "fail"), detail)

    def _pan(self, seen: _Seen, rule: str, what: str) -> float | None:
        """The pan of a valid Command, or None after failing ``rule``."""
        try:
            cmd = Command.model_validate_json(seen.payload)
        except ValidationError as err:
            self._result(rule, False, f"{what}: invalid Command: {_first(err)}")
            return None
        if not (math.isfinite(cmd.pan_rad) and -math.pi <= cmd.pan_rad <= math.pi):
            self._result(rule, False, f"{what}: pan_rad {cmd.pan_rad!r} is not in [-pi, pi]")
            return None
        return cmd.pan_rad

    def close(self) -> None:
        for h in self._handles:
            try:
                h.undeclare()
            except Exception:
                pass

    # -- the script ----------------------------------------------------------------------------------
    def run(self, steps: int = 6, wait: float | None = None) -> list[RuleResult]:
        """Run every rule; return the results in ``RULES`` order. ``wait``: how long to wait for
        the controller's liveliness token [s] (default: ``timeout``)."""
        if steps < 5:
            raise ValueError("the kit's episodes need at least 5 steps (it repeats measurements after step 2 and the start "
                             "after step 3)")
        self._liveliness_and_policies(self.timeout if wait is None else wait)
        self._episode(steps)
        self._stop_mid_episode()
        self._unserved()
        self._malformed()
        self._concurrent(steps)
        return [self.results.get(rule, RuleResult(rule, "fail", "not checked")) for rule in RULES]

    def _query_policies(self, got: list, done: threading.Event) -> None:
        def back(replies: list) -> None:
            got.extend(replies)
            done.set()

        self.bus.query(keys.rig_policies(self.rig), b"", self.timeout, back)

    def _liveliness_and_policies(self, wait: float) -> None:
        """On first seeing the token the kit at once asks rig/{rig}/policies and starts a probe
        episode: a controller that declares its token before its subscriptions and queryables
        misses them, as it would miss the orchestrator's."""
        alive = self._token_up.wait(wait)
        at_token: list = []
        probed = None
        if alive:
            done = threading.Event()
            self._query_policies(at_token, done)
            eid = self._id("at-token")
            mark = self._mark()
            self._start(eid, 2, index=4)
            # a Command(0), or a failed result if it does not serve the probe's policy: either way it heard the start
            probed = self._wait(lambda: self._matching(keys.command(self.rig), eid, mark, 0)
                                or self._matching(keys.episode_result(self.rig), eid, mark))
            self._stop(eid, "conformance: probe done")
            done.wait(self.timeout + 5.0)
        later: list = []
        done = threading.Event()
        self._query_policies(later, done)
        done.wait(self.timeout + 5.0)
        info, why = self._info(later)
        if info is None and not later:
            self._result("policies", None, "no reply: a 1.0 or 1.1 controller (it serves the four built-ins)")
        else:
            self._result("policies", info is not None, why)
        if self.policy is None:
            offered = [p.name for p in info.policies] if info is not None else []
            self.policy = "ra2vipas" if not offered or "ra2vipas" in offered else offered[0]
        self.info = info
        if not alive:
            self._result("liveliness", False, f"no token alive/controller/{self.rig} within {wait:g} s")
            return
        problems = []
        if probed is None:
            problems.append(f"an EpisodeStart sent as soon as the token appeared got no Command(0) within {self.timeout:g} s")
        if info is not None and not any(r.ok for r in at_token):
            problems.append(f"rig/{self.rig}/policies did not answer when the token appeared (it does later)")
        if problems:
            self._result("liveliness", False,
                         "; ".join(problems) + ": declare the token only after every subscription and queryable")
        else:
            self._result("liveliness", True,
                         "a probe episode (and the policies query) were answered as soon as the token was seen")

    def _info(self, replies: list) -> tuple[ControllerInfo | None, str]:
        why = "no reply"
        for reply in replies:
            if not reply.ok:
                why = f"error reply: {reply.payload[:200].decode(errors='replace')}"
                continue
            try:
                info = ControllerInfo.model_validate_json(reply.payload)
            except ValidationError as err:
                why = f"invalid ControllerInfo: {_first(err)}"
                continue
            if info.rig != self.rig:
                why = f"the ControllerInfo names rig {info.rig!r}"
                continue
            return info, f"serves {', '.join(p.name for p in info.policies)} (protocol {info.protocol})"
        return None, why

    def _episode(self, steps: int) -> None:
        """command-0, lockstep, duplicate-measurement and result on one episode of ``steps`` steps."""
        eid = self._id("lockstep")
        mark = self._mark()
        start = self._start(eid, steps)
        first = self._command(eid, 0, mark, self.timeout + 5.0)  # the first episode may wait for the model
        if first is None:
            self._result("command-0", False, f"no Command(0) within {self.timeout + 5.0:g} s of the EpisodeStart")
            for rule in ("lockstep", "duplicate-measurement", "result"):
                self._result(rule, False, "could not run: no Command(0)")
            return
        pan = self._pan(first, "command-0", "Command(0)")
        if pan is None:
            pan = 0.0
        else:
            self._result("command-0", True, f"after {(first.at - self._started_at) * 1e3:.0f} ms (it asked the kit's sensors "
                         f"for the descriptor {self.descriptor_queries} time(s) and its learner for the POD model "
                         f"{self.model_requests} time(s) so far)")
        for t in range(steps):
            self._measure(eid, t, pan, steps)
            if t + 1 == steps:
                break
            sent = self._mark()
            nxt = self._command(eid, t + 1, mark)
            if nxt is None:
                got = [s.parsed.get("step") for s in self._matching(keys.command(self.rig), eid, sent)]
                self._result("lockstep", False, f"Measurement({t}) got no Command({t + 1}) within {self.timeout:g} s"
                             + (f" (it sent commands of steps {got})" if got else ""))
                self._result("result", False, "could not run: the episode did not reach its last step")
                return
            pan = self._pan(nxt, "lockstep", f"Command({t + 1})")
            if pan is None:
                self._result("result", False, "could not run: the episode did not reach its last step")
                return
            if t == 2:
                self._duplicates(eid, steps, pan, mark)
            if t == 3:
                self._duplicate_start(eid, start, mark)
        result = self._result_of(eid, mark)
        time.sleep(0.5)
        commands = self._matching(keys.command(self.rig), eid, mark)
        counts = {}
        for s in commands:
            counts[s.parsed.get("step")] = counts.get(s.parsed.get("step"), 0) + 1
        extra = {k: n for k, n in counts.items() if n > 1 or not (isinstance(k, int) and 0 <= k < steps)}
        self._result("lockstep", not extra, f"commands per step beyond one per step 0..{steps - 1}: {extra}" if extra else
                     f"{steps} steps")
        self._check_result(eid, mark, result, steps, "result")

    def _duplicates(self, eid: str, steps: int, pan: float, mark: int) -> None:
        """After Command(3): Measurement(2) again, Measurement(1) (older) and Measurement(5) (future)."""
        before = len(self._matching(keys.command(self.rig), eid, mark))
        for step in (2, 1, 5):
            self._measure(eid, step, pan, steps)
        time.sleep(0.5)
        after = self._matching(keys.command(self.rig), eid, mark)
        if len(after) > before:
            self._result("duplicate-measurement", False, "a repeated Measurement(2), an older Measurement(1) or a future "
                         "Measurement(5) "
                         f"got a Command (steps {[s.parsed.get('step') for s in after[before:]]})")
        else:
            self._result("duplicate-measurement", True)

    def _duplicate_start(self, eid: str, start: bytes, mark: int) -> None:
        """After Command(4): the episode's EpisodeStart again. No second Command(0); the rest of
        the episode (lockstep, result) shows it was not restarted."""
        self.bus.publish(keys.episode_control(self.rig), start)
        time.sleep(0.5)
        zeros = self._matching(keys.command(self.rig), eid, mark, 0)
        self._result("duplicate-start", len(zeros) == 1, "" if len(zeros) == 1 else
                     f"a repeated EpisodeStart got another Command(0) ({len(zeros)} in all)")

    def _check_result(self, eid: str, mark: int, result: _Seen | None, steps: int, rule: str) -> bool:
        if result is None:
            self._result(rule, False, f"{eid}: no EpisodeResult within {self.timeout:g} s of the last Measurement")
            return False
        time.sleep(0.3)
        count = len(self._matching(keys.episode_result(self.rig), eid, mark))
        try:
            msg = EpisodeResult.model_validate_json(result.payload)
        except ValidationError as err:
            self._result(rule, False, f"{eid}: invalid EpisodeResult: {_first(err)}")
            return False
        problems = []
        if count != 1:
            problems.append(f"{count} EpisodeResults")
        if msg.status != "done":
            problems.append(f"status {msg.status} ({msg.error[:200]})")
        if msg.rig != self.rig:
            problems.append(f"rig {msg.rig!r}")
        if len(msg.estimates_rad) != steps or len(msg.pans_rad) != steps:
            problems.append(f"{len(msg.estimates_rad)} estimates and {len(msg.pans_rad)} pans for {steps} steps")
        if not all(math.isfinite(x) for x in msg.estimates_rad):
            problems.append("estimates that are not finite")
        self._result(rule, not problems, f"{eid}: " + "; ".join(problems) if problems else "")
        return not problems

    def _stop_mid_episode(self) -> None:
        eid = self._id("stop")
        mark = self._mark()
        self._start(eid, 6, index=1)
        first = self._command(eid, 0, mark)
        if first is None:
            self._result("stop-mid-episode", False, "could not run: no Command(0)")
            return
        self._measure(eid, 0, 0.0, 6)
        if self._command(eid, 1, mark) is None:
            self._result("stop-mid-episode", False, "could not run: Measurement(0) got no Command(1)")
            return
        self._stop(eid, "conformance: stop mid-episode")
        time.sleep(0.3)
        late = self._mark()
        self._measure(eid, 1, 0.0, 6)
        time.sleep(1.0)
        after = self._matching(keys.command(self.rig), eid, late) + self._matching(keys.episode_result(self.rig), eid, late)
        got = ("a Command" if after[0].key == keys.command(self.rig) else "an EpisodeResult") if after else ""
        self._result("stop-mid-episode", not after, f"Measurement(1) after EpisodeStop got {got}" if after else "")

    def _unserved(self) -> None:
        if self.info is not None and any(p.name == UNSERVED for p in self.info.policies):
            self._result("unserved-policy", None, f"the controller serves {UNSERVED}")
            return
        eid = self._id("unserved")
        mark = self._mark()
        self._start(eid, 3, algorithm=UNSERVED, index=5)
        got = self._result_of(eid, mark)
        commands = self._matching(keys.command(self.rig), eid, mark)
        if got is None:
            self._result("unserved-policy", False,
                         f"no EpisodeResult within {self.timeout:g} s" + (" (it sent a Command)" if commands else ""))
            return
        try:
            msg = EpisodeResult.model_validate_json(got.payload)
        except ValidationError as err:
            self._result("unserved-policy", False, f"invalid EpisodeResult: {_first(err)}")
            return
        if msg.status != "failed" or UNSERVED not in msg.error:
            self._result("unserved-policy", False,
                         f"status {msg.status}, error {msg.error[:200]!r} (expected failed, naming {UNSERVED})")
        else:
            self._result("unserved-policy", not commands, "it also sent a Command" if commands else "")

    def _malformed(self) -> None:
        control, meas = keys.episode_control(self.rig), keys.measurement(self.rig)
        bad = self._id("malformed")
        start = json.loads(dump(EpisodeStart(episode_id=bad, campaign_id=f"conformance-{self._nonce}", test_index=0,
                                             algorithm=self.policy or "ra2vipas", seed=self.seed, scenario=self._scenario(3))))
        start["scenario"]["steps"] = "many"
        mark = self._mark()
        garbage = [
            (control, b"not json"), (control, b"[]"), (control, b'{"kind": "start"}'), (control, b'{"kind": "stop"}'),
            (control, json.dumps(start).encode()),
            (meas, b"\xff\xfe"), (meas, b"{}"), (meas, b'{"episode_id": "x", "step": "one"}'),
        ]
        for key, payload in garbage:
            self.bus.publish(key, payload)
        rejected = self._wait(lambda: self._matching(keys.episode_rejected(self.rig), bad, mark), timeout=self.timeout)
        if rejected is None:
            self._result("rejects-malformed", None,
                         "no ErrorReply on the rejected key (optional: a 1.0 controller drops it silently)")
        else:
            try:
                ErrorReply.model_validate_json(rejected.payload)
                self._result("rejects-malformed", True, f"error: {rejected.parsed.get('error', '')[:200]}")
            except ValidationError as err:
                self._result("rejects-malformed", False, f"invalid ErrorReply: {_first(err)}")
        eid = self._id("after-garbage")
        mark2 = self._mark()
        self._start(eid, 2, index=2)
        got = self._command(eid, 0, mark2)
        alive = threading.Event()
        handle = self.bus.watch_alive(keys.alive("controller", self.rig), lambda _k, up: alive.set() if up else None)
        alive.wait(2.0)
        handle.undeclare()
        self._stop(eid, "conformance: done")
        ran_bad = self._matching(keys.command(self.rig), bad, mark)
        if not alive.is_set():
            self._result("malformed", False, "the liveliness token is gone after malformed messages (the node died?)")
        elif ran_bad:
            self._result("malformed", False, "the malformed EpisodeStart got a Command(0)")
        else:
            self._result("malformed", got is not None, "" if got else "after malformed messages, a new episode got no Command(0)")

    def _concurrent(self, steps: int) -> None:
        """Episodes A (``steps``) and B (``steps + 2``) in flight at once, measurements interleaved."""
        lengths = {self._id("concurrent-a"): steps, self._id("concurrent-b"): steps + 2}
        mark = self._mark()
        for i, eid in enumerate(lengths):
            self._start(eid, lengths[eid], index=6 + i)
        pans = {}
        for eid in lengths:
            got = self._command(eid, 0, mark)
            if got is None:
                self._result("concurrent", False, f"{eid}: no Command(0)")
                return
            pans[eid] = self._pan(got, "concurrent", f"{eid} Command(0)")
            if pans[eid] is None:
                return
        for t in range(max(lengths.values())):
            live = [eid for eid, n in lengths.items() if t < n]
            for eid in (live if t % 2 == 0 else live[::-1]):  # B's first on odd steps: the order must not matter
                self._measure(eid, t, pans[eid], lengths[eid])
            for eid in live:
                if t + 1 == lengths[eid]:
                    continue
                got = self._command(eid, t + 1, mark)
                if got is None:
                    self._result("concurrent", False, f"{eid}: Measurement({t}) got no Command({t + 1})")
                    return
                pans[eid] = self._pan(got, "concurrent", f"{eid} Command({t + 1})")
                if pans[eid] is None:
                    return
        for eid, n in lengths.items():
            if not self._check_result(eid, mark, self._result_of(eid, mark), n, "concurrent"):
                return
        self._result("concurrent", True, f"{len(lengths)} episodes of {', '.join(str(n) for n in lengths.values())} steps")


def check_controller(bus: Bus, rig: str, timeout: float = 5.0, steps: int = 6, wait: float | None = None,
                     policy: str | None = None) -> list[RuleResult]:
    """Run the kit against the controller of ``rig``; one ``RuleResult`` per rule of ``RULES``."""
    kit = ControllerKit(bus, rig, timeout, policy)
    try:
        return kit.run(steps=steps, wait=wait)
    finally:
        kit.close()


def report(results: list[RuleResult]) -> dict[str, Any]:
    """The JSON report: every rule's result and whether the controller passed (no rule failed)."""
    return {"passed": all(r.status != "fail" for r in results),
            "rules": [{"rule": r.rule, "status": r.status, "detail": r.detail, "what": RULES[r.rule]} for r in results]}
