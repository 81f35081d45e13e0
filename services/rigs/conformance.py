"""The conformance kit: drive a live sensors node through scripted episodes and say, rule by
rule, whether it speaks the protocol of docs/protocol.md (``ra2vipas protocol check``).

The kit plays the orchestrator and the controller of one rig on any ``Bus`` (Zenoh, or the
in-memory bus in tests). It uses its own episode ids (``conformance.*``), so it never touches a
campaign's episodes, but it does move the rig: run it on a rig no campaign is using.

Every rule has a name (``RULES``), and ``check_rig`` returns one ``RuleResult`` per rule:
passed, failed (with what was seen), or skipped (the rig's descriptor says it does not do that,
e.g. realtime).
"""

from __future__ import annotations

import json
import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    Command,
    EpisodeStart,
    EpisodeStop,
    EpisodeTiming,
    EpisodeTruth,
    Measurement,
    TrainingRequest,
    TrainingStream,
    dump,
)
from ra2vipas.services.protocol.rig import RigDescriptor, apply_rig_values, speaks
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.protocol.versions import V1_3, V1_4, newer
from ra2vipas.services.transport.bus import Bus

RULES: dict[str, str] = {
    "liveliness": "the sensors hold the liveliness token alive/sensors/{rig}, declared last: as soon as it appears, rig/{rig}/info "
                  "and an episode's start and Command(0) are answered",
    "descriptor": "rig/{rig}/info answers a valid RigDescriptor naming the rig",
    "fast-lockstep": "fast mode: each Command(t) is answered by one Measurement(t) with the same episode_id, valid against its schema",
    "frames": "every Measurement carries nu frames whose box bearings are sorted ascending",
    "rf-evidence": "every Measurement's RF evidence is the 1.0 rf pair or, from a node that speaks 1.3, the adverts heard since the "
                   "previous step in arrival order (maybe none: then no rf either), never both; a tag or address (1.4) only from a "
                   "node that speaks 1.4, only the tags the episode searches for (the kit's: tag 0), one address per tag",
    "pan-wrapped": "Measurement.pan_rad is the commanded pan, wrapped to [-pi, pi)",
    "command-before-start": "a Command(0) that arrives before its EpisodeStart is answered once the start arrives",
    "duplicate-command": "a repeated Command(t) does not advance the episode (at most the same sample again)",
    "duplicate-start": "a repeated EpisodeStart does not restart the episode",
    "stop-mid-episode": "after an EpisodeStop, commands of that episode get no measurement",
    "malformed": "malformed control and command messages are dropped: the node stays up and runs the next episode",
    "realtime-sample-0": "realtime: sample 0 is taken when Command(0) arrives, not T_RF later",
    "realtime-grid": "realtime: sample k arrives at t0 + k T_RF (within max(30 ms, T_RF/4))",
    "realtime-pan": "realtime: each sample is taken at the last commanded pan",
    "realtime-timing": "realtime: one EpisodeTiming after the last sample, at most steps-1 latencies, no late command when every "
                       "command came at once",
    "tags": "a node that says how many tags it hears (1.5: descriptor tags = N > 1) runs an episode that searches for all N, at "
            "T_RF pace (4 s, and on while a tag is unheard, up to --tags-seconds): its advertisements name only tags 0 .. N-1, "
            "each tag heard, each with one address of its own",
    "training": "data/{rig}/training answers a TrainingStream of n_train samples (indices 0..n-1, nu frames each, job_id echoed); "
                "from a rig whose radio is adverts, each sample carries what Rx(iso) heard (maybe nothing), never an rf pair",
    "truth": "a rig that says it publishes EpisodeTruth does so for every episode; one that says it does not, publishes none",
}


@dataclass
class RuleResult:
    rule: str
    status: str  # pass | fail | skip
    detail: str = ""

    def as_dict(self) -> dict[str, str]:
        return {"rule": self.rule, "status": self.status, "detail": self.detail, "what": RULES[self.rule]}


@dataclass
class _Seen:
    key: str
    payload: bytes
    at: float


class ConformanceKit:
    """One run of the kit against ``rig`` on ``bus``. ``timeout``: how long to wait for any
    single answer [s]."""

    def __init__(self, bus: Bus, rig: str, timeout: float = 5.0, clock=time.monotonic,
                 grid_tolerance_s: float | None = None, tags_seconds: float = 20.0) -> None:
        self.bus, self.rig, self.timeout, self.clock = bus, keys.check_chunk(rig), timeout, clock
        # the tags rule's episode runs TAGS_SECONDS, and on up to this long while a tag is still unheard
        # (a battery beacon may advertise every few seconds, and a receiver misses some of them)
        self.tags_seconds = max(float(tags_seconds), self.TAGS_SECONDS)
        # how far a realtime sample may arrive from t0 + k T_RF (None: max(30 ms, T_RF/4)); the
        # kit's own receipt is part of it, so a loaded machine (a CI running other work) needs more
        self.grid_tolerance_s = grid_tolerance_s
        self.results: dict[str, RuleResult] = {}
        self.measurements: list[tuple[_Seen, dict | None]] = []  # (seen, parsed JSON)
        self._lock = threading.Condition()
        self._timing: list[_Seen] = []
        self._truth: list[_Seen] = []
        self._nonce = f"{int(time.time() * 1000) % 10**9}"
        self.episodes: list[str] = []
        self._token_up = threading.Event()
        self._handles = [
            bus.subscribe(keys.measurement(rig), lambda k, p: self._note(self.measurements, k, p)),
            bus.subscribe(keys.episode_timing(rig), lambda k, p: self._note(self._timing, k, p)),
            bus.subscribe(keys.episode_truth(rig), lambda k, p: self._note(self._truth, k, p)),
        ]
        # watched from now on (after the kit's own subscriptions): when the node comes up after
        # the kit, the kit probes it the moment its token appears
        self._handles.append(bus.watch_alive(keys.alive("sensors", rig), self._on_token))

    def _on_token(self, _key: str, alive: bool) -> None:
        if alive:
            self._token_up.set()

    # -- plumbing ------------------------------------------------------------------------------
    def _note(self, target: list, key: str, payload: bytes) -> None:
        seen = _Seen(key, payload, self.clock())
        with self._lock:
            if target is self.measurements:
                try:
                    parsed = json.loads(payload)
                except ValueError:
                    parsed = None
                target.append((seen, parsed if isinstance(parsed, dict) else None))
            else:
                target.append(seen)
            self._lock.notify_all()

    def _wait_measurement(self, episode_id: str, step: int, since: int, timeout: float | None = None) -> tuple[_Seen, dict] | None:
        """The first measurement of (episode, step) at index >= ``since`` of the log."""
        deadline = self.clock() + (self.timeout if timeout is None else timeout)
        with self._lock:
            while True:
                for seen, parsed in self.measurements[since:]:
                    if parsed and parsed.get("episode_id") == episode_id and parsed.get("step") == step:
                        return seen, parsed
                left = deadline - self.clock()
                if left <= 0:
                    return None
                self._lock.wait(left)

    def _of(self, episode_id: str, step: int | None = None) -> list[tuple[_Seen, dict]]:
        with self._lock:
            return [(s, p) for s, p in self.measurements if p and p.get("episode_id") == episode_id and (step is None or p.get("step") == step)]

    def _id(self, what: str) -> str:
        eid = f"conformance.{self._nonce}.{what}"
        self.episodes.append(eid)
        return eid

    def _start(self, eid: str, scenario: Scenario, mode: str = "fast", index: int = 0) -> bytes:
        payload = dump(EpisodeStart(episode_id=eid, campaign_id=f"conformance-{self._nonce}", test_index=index, algorithm="rapas",
                                    seed=7, scenario=scenario, mode=mode))
        self.bus.publish(keys.episode_control(self.rig), payload)
        return payload

    def _command(self, eid: str, step: int, pan: float) -> None:
        self.bus.publish(keys.command(self.rig), dump(Command(episode_id=eid, step=step, pan_rad=pan)), express=True)

    def _result(self, rule: str, ok: bool | None, detail: str = "") -> None:
        if rule in self.results and self.results[rule].status == "fail":
            return  # the first failure stands
        self.results[rule] = RuleResult(rule, "skip" if ok is None else ("pass" if ok else "fail"), detail)

    def close(self) -> None:
        for h in self._handles:
            try:
                h.undeclare()
            except Exception:
                pass

    # -- the script ----------------------------------------------------------------------------
    def run(self, steps: int = 6, realtime_steps: int = 8, wait: float | None = None) -> list[RuleResult]:
        """Run every rule; return the results in ``RULES`` order. ``wait``: how long to wait for
        the node's liveliness token [s] (default: ``timeout``); a node started while the kit
        waits is probed the moment its token appears, which checks that it declares it last."""
        descriptor = self._liveliness_and_descriptor(self.timeout if wait is None else wait)
        self._speaks = speaks(descriptor)
        self._rf_seen = {"pair": 0, "adverts": 0, "empty": 0, "packets": 0}
        self._addresses: dict[int, str] = {}  # each tag's first address (1.4)
        base = Scenario(steps=steps, n_train=25, n_targets=6)
        scenario = apply_rig_values(descriptor, base) if descriptor is not None else base
        nu = scenario.frames_per_rf
        self._fast(scenario, nu, steps)
        self._early_duplicates_stop(scenario)
        self._malformed(scenario)
        modes = descriptor.modes if descriptor is not None else ("fast", "realtime")
        if "realtime" in modes:
            self._realtime(scenario.model_copy(update={"steps": realtime_steps}), realtime_steps)
        else:
            for rule in ("realtime-sample-0", "realtime-grid", "realtime-pan", "realtime-timing"):
                self._result(rule, None, "the rig does not run realtime episodes (its descriptor's modes)")
        self._tags(scenario, descriptor)
        if descriptor is None or descriptor.training:
            self._training(scenario, nu)
        else:
            self._result("training", None, "the rig serves no training episode (its descriptor)")
        self._truth_rule(descriptor)
        return [self.results.get(rule, RuleResult(rule, "fail", "not checked")) for rule in RULES]

    def _liveliness_and_descriptor(self, wait: float) -> RigDescriptor | None:
        """The liveliness rule and the descriptor rule. On first seeing the token the kit at once
        asks rig/{rig}/info and sends a probe episode (EpisodeStart and Command(0)): a node that
        declares its token before its subscriptions and queryables (docs/protocol.md, "Liveliness
        last") misses them, as the orchestrator's first query and episode would be missed."""
        self._alive = self._token_up.wait(wait)
        at_token: list | None = None
        probed = None
        if self._alive:
            got: "queue.Queue[list]" = queue.Queue()
            self.bus.query(keys.rig_info(self.rig), b"", self.timeout, got.put)
            eid = f"conformance.{self._nonce}.at-token"
            mark = len(self.measurements)
            self._start(eid, Scenario(steps=2, n_train=25, n_targets=6), index=4)
            self._command(eid, 0, 0.0)
            probed = self._wait_measurement(eid, 0, mark)
            self.bus.publish(keys.episode_control(self.rig), dump(EpisodeStop(episode_id=eid, reason="conformance: probe done")))
            if probed is not None:
                self.episodes.append(eid)  # the truth rule holds it to this episode only if it ran
            try:
                at_token = got.get(timeout=self.timeout + 5.0)
            except queue.Empty:
                at_token = []
        descriptor, why = self._descriptor(self._info(self.timeout))
        self._result("descriptor", descriptor is not None, "" if descriptor is not None else why)
        if not self._alive:
            self._result("liveliness", False, f"no token alive/sensors/{self.rig} within {wait:g} s")
            return descriptor
        problems = []
        if probed is None:
            problems.append(f"an EpisodeStart and Command(0) sent as soon as the token appeared got no Measurement within "
                            f"{self.timeout:g} s")
        if descriptor is not None and not any(r.ok for r in at_token or []):
            problems.append(f"rig/{self.rig}/info did not answer when the token appeared (it does later)")
        if problems:
            self._result("liveliness", False, "; ".join(problems) + ": declare the token only after every subscription and queryable")
            return descriptor
        self._result("liveliness", True, f"rig/{self.rig}/info and a probe episode were answered as soon as the token was seen "
                                          "(which shows the token is declared last if the kit was started before the node)")
        return descriptor

    def _info(self, timeout: float) -> list:
        """The replies to a query of rig/{rig}/info."""
        got: "queue.Queue[list]" = queue.Queue()
        self.bus.query(keys.rig_info(self.rig), b"", timeout, got.put)
        try:
            return got.get(timeout=timeout + 5.0)
        except queue.Empty:
            return []

    def _descriptor(self, replies: list) -> tuple[RigDescriptor | None, str]:
        """The first valid descriptor naming this rig among ``replies``, else None and why not."""
        why = "no reply (a v1 node serves no descriptor)"
        for reply in replies:
            if not reply.ok:
                why = f"error reply: {reply.payload[:200].decode(errors='replace')}"
                continue
            try:
                descriptor = RigDescriptor.model_validate_json(reply.payload)
            except ValidationError as err:
                why = f"invalid RigDescriptor: {_first(err)}"
                continue
            if descriptor.rig != self.rig:
                why = f"the descriptor names rig {descriptor.rig!r}"
                continue
            return descriptor, ""
        return None, why

    def _check_measurement(self, parsed: dict, raw: bytes, nu: int, pan: float) -> None:
        try:
            Measurement.model_validate_json(raw)
        except ValidationError as err:
            self._result("fast-lockstep", False, f"step {parsed.get('step')}: invalid Measurement: {_first(err)}")
            return
        frames = parsed["frames"]
        if len(frames) != nu:
            self._result("frames", False, f"step {parsed['step']}: {len(frames)} frames, expected nu = {nu}")
        elif any(list(f["box_bearings_rad"]) != sorted(f["box_bearings_rad"]) for f in frames):
            self._result("frames", False, f"step {parsed['step']}: box bearings not sorted ascending")
        else:
            self._result("frames", True)
        self._check_rf(parsed)
        reported = float(parsed["pan_rad"])
        expected = (pan + math.pi) % (2.0 * math.pi) - math.pi
        if not -math.pi <= reported < math.pi:
            self._result("pan-wrapped", False, f"step {parsed['step']}: pan_rad {reported:.4f} is outside [-pi, pi)")
        elif abs((reported - expected + math.pi) % (2.0 * math.pi) - math.pi) > 0.05:
            self._result("pan-wrapped", False, f"step {parsed['step']}: pan_rad {reported:.4f}, commanded {pan:.4f}")
        else:
            self._result("pan-wrapped", True)

    def _check_rf(self, parsed: dict) -> None:
        """The rf-evidence rule on one (schema-valid) Measurement."""
        step, adverts = parsed.get("step"), parsed.get("adverts") or []
        if "rf" in parsed and parsed["rf"] is not None:
            self._rf_seen["pair"] += 1
        else:
            if newer(V1_3, self._speaks):
                what = "adverts" if adverts else "no RF evidence (neither rf nor adverts)"
                self._result("rf-evidence", False, f"step {step}: {what}, but the node speaks protocol {self._speaks} "
                                                   "(adverts and empty steps need 1.3: say so in the descriptor)")
                return
            offsets = [a.get("offset_s", 0.0) for a in adverts]
            if offsets != sorted(offsets):
                self._result("rf-evidence", False, f"step {step}: adverts not in arrival order (offsets {offsets})")
                return
            if not self._check_tags(step, adverts):
                return
            self._rf_seen["adverts" if adverts else "empty"] += 1
            self._rf_seen["packets"] += len(adverts)
        seen = self._rf_seen
        self._result("rf-evidence", True, f"{seen['pair']} steps with an rf pair, {seen['adverts']} with adverts "
                                          f"({seen['packets']} advertisements), {seen['empty']} with none")

    def _check_tags(self, step, adverts: list) -> bool:
        """The rf-evidence rule's 1.4 part (docs/tags.md): ``tag``/``address`` only from a node that speaks
        1.4; the kit's episodes search for one tag (n_tags = 1), so every advertisement is tag 0's; a tag's
        address never changes. False (the rule failed) or True."""
        if any("tag" in a or "address" in a for a in adverts) and newer(V1_4, self._speaks):
            self._result("rf-evidence", False, f"step {step}: adverts name a tag or an address, but the node speaks protocol "
                                               f"{self._speaks} (1.4 fields: say so in the descriptor)")
            return False
        others = sorted({int(a.get("tag", 0)) for a in adverts} - {0})
        if others:
            self._result("rf-evidence", False, f"step {step}: advertisements of tag {', '.join(map(str, others))} in an episode "
                                               "whose scenario searches for one tag (n_tags = 1: send tags 0 .. n_tags - 1 only)")
            return False
        for a in adverts:
            changed = _address_changed(self._addresses, a)
            if changed:
                self._result("rf-evidence", False, f"step {step}: {changed}")
                return False
        return True

    def _fast(self, scenario: Scenario, nu: int, steps: int) -> None:
        eid = self._id("fast")
        self._start(eid, scenario)
        time.sleep(0.2)
        pans = [0.0, 1.0, 3.5, -2.0, -3.6, 2.9] * (steps // 6 + 1)  # 3.5 and -3.6: the node must wrap them
        for t in range(steps):
            mark = len(self.measurements)
            self._command(eid, t, pans[t])
            got = self._wait_measurement(eid, t, mark)
            if got is None:
                self._result("fast-lockstep", False, f"no Measurement for step {t} within {self.timeout:g} s")
                return
            self._check_measurement(got[1], got[0].payload, nu, pans[t])
        time.sleep(0.3)
        counts = [len(self._of(eid, t)) for t in range(steps)]
        if any(c != 1 for c in counts):
            self._result("fast-lockstep", False, f"measurements per step {counts}, expected one each")
        others = [p.get("step") for _, p in self._of(eid) if p.get("step") not in range(steps)]
        if others:
            self._result("fast-lockstep", False, f"measurements for steps never commanded: {others}")
        self._result("fast-lockstep", True)
        self._fast_id = eid

    def _early_duplicates_stop(self, scenario: Scenario) -> None:
        eid = self._id("early")
        mark = len(self.measurements)
        self._command(eid, 0, 0.5)
        time.sleep(0.3)
        start = self._start(eid, scenario, index=1)
        got = self._wait_measurement(eid, 0, mark)
        self._result("command-before-start", got is not None,
                     "" if got else f"Command(0) sent 0.3 s before its EpisodeStart got no Measurement within {self.timeout:g} s")
        if got is None:
            for rule in ("duplicate-command", "duplicate-start", "stop-mid-episode"):
                self._result(rule, False, "could not run: the episode did not start")
            return
        # duplicate command
        mark = len(self.measurements)
        self._command(eid, 1, 0.7)
        if self._wait_measurement(eid, 1, mark) is None:
            self._result("duplicate-command", False, "no Measurement for step 1")
            return
        self._command(eid, 1, 0.7)
        time.sleep(0.3)
        again = self._of(eid, 1)
        mark = len(self.measurements)
        self._command(eid, 2, 0.9)
        two = self._wait_measurement(eid, 2, mark)
        if len(again) > 2 or any(p != again[0][1] for _, p in again):
            self._result("duplicate-command", False, f"a repeated Command(1) gave {len(again)} different samples")
        elif two is None:
            self._result("duplicate-command", False, "after a repeated Command(1), Command(2) got no Measurement (the episode advanced?)")
        else:
            self._result("duplicate-command", True)
        # duplicate start
        self.bus.publish(keys.episode_control(self.rig), start)
        time.sleep(0.3)
        mark = len(self.measurements)
        self._command(eid, 3, 1.1)
        three = self._wait_measurement(eid, 3, mark)
        restarted = self._wait_measurement(eid, 0, mark, timeout=0.0)
        self._result("duplicate-start", three is not None and restarted is None,
                     "" if three is not None else "after a repeated EpisodeStart, Command(3) got no Measurement (restarted?)")
        # stop mid-episode
        self.bus.publish(keys.episode_control(self.rig), dump(EpisodeStop(episode_id=eid, reason="conformance: stop mid-episode")))
        time.sleep(0.3)
        mark = len(self.measurements)
        self._command(eid, 4, 1.3)
        late = self._wait_measurement(eid, 4, mark, timeout=1.0)
        self._result("stop-mid-episode", late is None, "" if late is None else "Command(4) after EpisodeStop got a Measurement")

    def _malformed(self, scenario: Scenario) -> None:
        control, command = keys.episode_control(self.rig), keys.command(self.rig)
        garbage = [
            (control, b"not json"), (control, b"[]"), (control, b'{"kind": "start"}'), (control, b'{"episode_id": "x"}'),
            (control, json.dumps({"kind": "start", "episode_id": "bad", "campaign_id": "c", "test_index": -1, "algorithm": "rapas",
                                  "seed": 1, "scenario": {"steps": "many"}}).encode()),
            (command, b"\xff\xfe"), (command, b"{}"), (command, b'{"episode_id": "x", "step": "one", "pan_rad": 0}'),
            (command, json.dumps({"episode_id": self._fast_id if hasattr(self, "_fast_id") else "x", "step": 0, "pan_rad": 1e9}).encode()),
        ]
        for key, payload in garbage:
            self.bus.publish(key, payload)
        time.sleep(0.5)
        eid = self._id("after-garbage")
        self._start(eid, scenario.model_copy(update={"steps": 2}), index=2)
        time.sleep(0.2)
        mark = len(self.measurements)
        self._command(eid, 0, 0.0)
        got = self._wait_measurement(eid, 0, mark)
        alive = threading.Event()
        handle = self.bus.watch_alive(keys.alive("sensors", self.rig), lambda _k, up: alive.set() if up else None)
        alive.wait(2.0)
        handle.undeclare()
        if not alive.is_set() and self._alive:
            self._result("malformed", False, "the liveliness token is gone after malformed messages (the node died?)")
        else:
            self._result("malformed", got is not None, "" if got else "after malformed messages, a new episode got no Measurement")

    def _realtime(self, scenario: Scenario, steps: int) -> None:
        period = scenario.rf_period_s
        eid = self._id("realtime")
        self._start(eid, scenario, mode="realtime", index=3)
        time.sleep(0.3)
        pans = [0.1 * (k + 1) * (-1) ** k for k in range(steps)]
        mark = len(self.measurements)
        sent0 = self.clock()
        self._command(eid, 0, pans[0])
        arrivals, reported = [], []
        for k in range(steps):
            got = self._wait_measurement(eid, k, mark, timeout=self.timeout + period)
            if got is None:
                self._result("realtime-grid", False, f"no Measurement for step {k}")
                break
            arrivals.append(got[0].at)
            reported.append(float(got[1]["pan_rad"]))
            try:  # a second of real time: a BLE node's advertisements are in these (fast steps take ms)
                Measurement.model_validate_json(got[0].payload)
            except ValidationError:
                pass  # whether a Measurement is valid is fast-lockstep's rule
            else:
                self._check_rf(got[1])
            if k + 1 < steps:
                self._command(eid, k + 1, pans[k + 1])
        if arrivals:
            first = arrivals[0] - sent0
            self._result("realtime-sample-0", first < max(0.5 * period, 0.05),
                         f"sample 0 came {first * 1e3:.0f} ms after Command(0)")
        if len(arrivals) == steps:
            tolerance = max(0.03, period / 4.0) if self.grid_tolerance_s is None else self.grid_tolerance_s
            off = [a - arrivals[0] - k * period for k, a in enumerate(arrivals)]
            worst = max(off, key=abs)
            self._result("realtime-grid", abs(worst) <= tolerance,
                         f"worst offset from t0 + k T_RF: {worst * 1e3:+.1f} ms (tolerance {tolerance * 1e3:.0f} ms)")
            # sample k is taken at the last commanded pan: pans[k] (sent as soon as sample k-1 arrived)
            wrong = [k for k in range(steps) if abs(reported[k] - pans[k]) > 0.05]
            self._result("realtime-pan", not wrong, f"samples at another pan than the last commanded: steps {wrong}" if wrong else "")
        else:
            self._result("realtime-pan", False, "the episode did not run to its end")
        deadline = self.clock() + period * 2 + self.timeout
        timing = None
        while self.clock() < deadline and timing is None:
            with self._lock:
                for seen in self._timing:
                    try:
                        msg = EpisodeTiming.model_validate_json(seen.payload)
                    except ValidationError as err:
                        self._result("realtime-timing", False, f"invalid EpisodeTiming: {_first(err)}")
                        return
                    if msg.episode_id == eid:
                        timing = msg
                if timing is None:
                    self._lock.wait(0.05)
        if timing is None:
            self._result("realtime-timing", False, "no EpisodeTiming")
        elif len(timing.latencies_ms) > steps - 1:
            self._result("realtime-timing", False, f"{len(timing.latencies_ms)} latencies for {steps} steps (at most {steps - 1})")
        elif timing.late_commands:
            self._result("realtime-timing", False, f"late_commands = {timing.late_commands} though every command came at once")
        else:
            self._result("realtime-timing", True, f"{len(timing.latencies_ms)} latencies, p50 "
                         f"{sorted(timing.latencies_ms)[len(timing.latencies_ms) // 2]:.2f} ms" if timing.latencies_ms else "")

    TAGS_SECONDS = 4.0
    """How long the ``tags`` rule's episode lasts: at ~2 advertisements a second per tag and receiver
    (docs/radio.md) a tag in range is heard several times over."""

    def _tags(self, scenario: Scenario, descriptor: RigDescriptor | None) -> None:
        """The ``tags`` rule: an episode that searches for every tag the node says it hears, commanded
        at T_RF pace in fast mode (a BLE node's advertisements arrive in real time), whose
        advertisements must name those tags only, every one of them, each with its own address. It
        runs ``TAGS_SECONDS``, and on while a tag is still unheard, up to ``tags_seconds`` (then an
        EpisodeStop ends it early)."""
        n = descriptor.tags if descriptor is not None else None
        if n is None or n < 2:
            self._result("tags", None, "the descriptor says no number of tags (1.5)" if n is None else
                         "the node hears one tag: rf-evidence checks it")
            return
        period = scenario.rf_period_s
        least = max(int(round(self.TAGS_SECONDS / period)), 2)
        steps = max(int(round(self.tags_seconds / period)), least)
        episode = scenario.model_copy(update={"steps": steps, "n_tags": n, "one_tag_per_person": n <= scenario.n_targets})
        eid = self._id("tags")
        self._start(eid, episode)
        time.sleep(0.2)
        heard: dict[int, int] = {}
        addresses = dict(self._addresses)  # tag 0's address from the one-tag episodes: the same here
        ran = 0
        for t in range(steps):
            if t >= least and len(heard) == n:  # every tag heard, for at least TAGS_SECONDS: enough
                self.bus.publish(keys.episode_control(self.rig), dump(EpisodeStop(episode_id=eid, reason="conformance: every tag heard")))
                break
            mark = len(self.measurements)
            self._command(eid, t, math.remainder(0.3 * t, 2.0 * math.pi))
            got = self._wait_measurement(eid, t, mark)
            if got is None:
                self._result("tags", False, f"no Measurement for step {t} of an episode with n_tags = {n} within {self.timeout:g} s")
                return
            ran = t + 1
            parsed = got[1]
            evidence = list(parsed.get("adverts") or [])  # 1.3 adverts; the 1.0 pair is tag 0's, rf_tags (1.4) the others'
            evidence += ([parsed["rf"]] if parsed.get("rf") else []) + list(parsed.get("rf_tags") or [])
            for a in evidence:
                tag = int(a.get("tag", 0))
                if tag >= n:
                    self._result("tags", False, f"step {t}: RF evidence of tag {tag}, though the node says it hears {n} tags "
                                                f"(0 .. {n - 1}) and the episode searches for those")
                    return
                heard[tag] = heard.get(tag, 0) + 1
                changed = _address_changed(addresses, a)
                if changed:
                    self._result("tags", False, f"step {t}: {changed}")
                    return
            time.sleep(period)
        by_address: dict[str, list[int]] = {}
        for tag, address in sorted(addresses.items()):
            by_address.setdefault(address, []).append(tag)
        shared = sorted((address, tags) for address, tags in by_address.items() if len(tags) > 1)
        if shared:
            self._result("tags", False, f"tags {shared[0][1]} share the address {shared[0][0]}: each tag has its own")
            return
        counts = ", ".join(f"tag {k}: {heard.get(k, 0)}" for k in range(n))
        silent = [k for k in range(n) if not heard.get(k)]
        seconds = f"{round(ran * period, 1):g}"
        self._result("tags", not silent, (f"tag {', '.join(map(str, silent))} never heard in {seconds} s of an episode "
                                          f"with n_tags = {n} ({counts}): are they in range and advertising? (a beacon that "
                                          f"advertises less often needs a longer --tags-seconds)") if silent else
                     f"pieces of RF evidence per tag in {seconds} s: {counts}")

    def _training(self, scenario: Scenario, nu: int) -> None:
        job = f"conformance-{self._nonce}"
        request = dump(TrainingRequest(job_id=job, scenario=scenario, seed=3))
        got: "queue.Queue[list]" = queue.Queue()
        self.bus.query(keys.training(self.rig), request, max(self.timeout, 60.0), got.put)
        try:
            replies = got.get(timeout=max(self.timeout, 60.0) + 5.0)
        except queue.Empty:
            replies = []
        ok = [r for r in replies if r.ok]
        if not ok:
            self._result("training", False, "no reply" if not replies else f"error reply: {replies[0].payload[:200].decode(errors='replace')}")
            return
        try:
            stream = TrainingStream.model_validate_json(ok[0].payload)
        except ValidationError as err:
            self._result("training", False, f"invalid TrainingStream: {_first(err)}")
            return
        n = scenario.n_train
        problems = []
        if stream.job_id != job:
            problems.append(f"job_id {stream.job_id!r}, expected {job!r}")
        if [s.index for s in stream.samples] != list(range(n)):
            problems.append(f"{len(stream.samples)} samples, expected indices 0..{n - 1}")
        if any(len(s.frames) != nu for s in stream.samples):
            problems.append(f"samples whose frames are not nu = {nu}")
        if scenario.radio.value == "adverts":  # the rig's descriptor says so (apply_rig_values)
            paired = [s.index for s in stream.samples if s.iso_rssi_dbm is not None]
            if paired:
                problems.append(f"{len(paired)} samples (the first: {paired[0]}) carry an Rx(iso) RSSI value though the rig's radio is "
                                "adverts: send the advertisements Rx(iso) heard in each sample, maybe none, never a made-up value")
        self._result("training", not problems, "; ".join(problems))

    def _truth_rule(self, descriptor: RigDescriptor | None) -> None:
        time.sleep(0.2)
        with self._lock:
            truths = {}
            for seen in self._truth:
                try:
                    msg = EpisodeTruth.model_validate_json(seen.payload)
                except ValidationError as err:
                    self._result("truth", False, f"invalid EpisodeTruth: {_first(err)}")
                    return
                truths[msg.episode_id] = msg
        says = descriptor.episode_truth if descriptor is not None else None
        if says is None:
            self._result("truth", None, "undescribed rig: nothing to hold it to")
        elif says:
            missing = [e for e in self.episodes if e not in truths]
            self._result("truth", not missing, f"no EpisodeTruth for {missing}" if missing else "")
        else:
            self._result("truth", not truths, f"published EpisodeTruth for {sorted(truths)} though its descriptor says it does not"
                         if truths else "")


def _address_changed(addresses: dict[int, str], advert: dict) -> str | None:
    """Whether an advertisement's ``address`` (1.4) differs from the first its tag came from
    (``addresses``, tag -> first address, updated); the failure's words, or None."""
    address = advert.get("address")
    if address is None:
        return None
    tag = int(advert.get("tag", 0))
    first = addresses.setdefault(tag, address)
    return None if first == address else f"tag {tag} came from {first} and from {address}"


def _first(err: ValidationError) -> str:
    e = err.errors()[0] if err.errors() else {}
    return f"{'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg', 'invalid')}"


def check_rig(bus: Bus, rig: str, timeout: float = 5.0, steps: int = 6, realtime_steps: int = 8,
              wait: float | None = None, clock=time.monotonic, grid_tolerance_s: float | None = None,
              tags_seconds: float = 20.0) -> list[RuleResult]:
    """Run the kit against ``rig``; one ``RuleResult`` per rule of ``RULES``."""
    kit = ConformanceKit(bus, rig, timeout, clock=clock, grid_tolerance_s=grid_tolerance_s, tags_seconds=tags_seconds)
    try:
        return kit.run(steps=steps, realtime_steps=realtime_steps, wait=wait)
    finally:
        kit.close()


def report(results: list[RuleResult]) -> dict[str, Any]:
    """The JSON report: every rule's result and whether the rig passed (no rule failed)."""
    return {"passed": all(r.status != "fail" for r in results), "rules": [r.as_dict() for r in results]}
