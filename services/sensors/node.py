"""The sensors service's node logic: a simulated platform on the bus.

It plays the part real hardware will play, through exactly the messages a hardware node
would use (docs/protocol.md):

* ``control/<rig>/episode``: an ``EpisodeStart`` builds the simulated world of that test and
  publishes its ground truth on the *truth* plane (for the orchestrator only), with the
  walkers' per-step trajectories when targets walk;
* ``data/<rig>/command``: each ``Command(step, pan)`` is answered by the ``Measurement`` taken
  at that pan: immediately in ``fast`` mode (lockstep), or on the wall clock every T_RF in
  ``realtime`` mode, where the platform samples at the last commanded pan and the node
  records how long each command took to come back;
* ``data/<rig>/training`` (queryable): runs the POD training episode and replies with its
  stream, publishing the training truth on the truth plane;
* ``rig/<rig>/info`` (queryable): the rig's ``RigDescriptor``. By default a simulated rig is
  *configurable*: it simulates whatever hardware each campaign's scenario describes. Given a
  descriptor with fixed values (``ra2vipas sensors --hardware antenna_model=db-gain``) it
  simulates that hardware whatever the scenario says, as a real platform would;
  ``describe=False`` serves no descriptor (a v1 node).
"""

from __future__ import annotations

import heapq
import logging
import math
import threading
import time
from dataclasses import dataclass, field

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.messages import (
    Command,
    EpisodeStart,
    EpisodeStop,
    EpisodeTiming,
    Measurement,
    Mode,
    TrainingRequest,
    TrainingStream,
    TrainingTruth,
    decode,
    dump,
    episode_control_adapter,
)
from ra2vipas.services.protocol.rig import RigDescriptor, apply_rig_values
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
from ra2vipas.services.sensors.world import SimulatedPlatform, TrainingEpisode, episode_truth
from ra2vipas.services.transport.bus import Bus, QueryError, undeclare_all
from ra2vipas.services.transport.costs import CostClock, now_ns
from ra2vipas.services.transport.runtime import EventLoop, decode_or_reject

log = logging.getLogger(__name__)

_measurement = builder(Measurement, "episode_id", "step", "pan_rad", "rf", "frames", "adverts", "rf_tags")


@dataclass
class _Episode:
    start: EpisodeStart
    platform: SimulatedPlatform
    last: Measurement | None = None
    # realtime pacing
    pan: float = 0.0
    ticking: bool = False
    next_step: int = 0
    t0: float = 0.0
    sent_at: dict[int, float] = field(default_factory=dict)
    latencies_ms: list[float] = field(default_factory=list)
    late: int = 0
    costs: CostClock = field(default_factory=CostClock)


class SensorsNode:
    """One rig's simulated sensors. All state lives on ``self.loop``'s thread (its own, or
    ``loop``, a loop it shares with its rig's controller on the same bus: ``ra2vipas rig``)."""

    def __init__(self, bus: Bus, rig: str, clock=time.monotonic, descriptor: RigDescriptor | None = None,
                 describe: bool = True, loop: EventLoop | None = None, realtime_priority: int = 0) -> None:
        self.bus = bus
        self.rig = keys.check_chunk(rig)
        self.descriptor = descriptor or simulated_descriptor(rig)
        if self.descriptor.rig != rig:
            raise ValueError(f"the descriptor names rig {self.descriptor.rig!r}, this node is rig {rig!r}")
        self.clock = clock
        self.report_costs = describe  # a node that serves no descriptor speaks 1.0: no StepCosts (1.2)
        self._own_loop = loop is None  # else shared with the rig's controller (``ra2vipas rig``), stopped by its owner
        self.loop = EventLoop(f"sensors-{rig}", realtime_priority=realtime_priority) if loop is None else loop
        self.episodes: dict[str, _Episode] = {}
        self._finished: dict[str, None] = {}
        self._early: dict[str, list[bytes]] = {}  # commands that overtook their EpisodeStart
        self._timers: list[tuple[float, str, int]] = []
        self._clocks: dict[str, tuple[float, float, int]] = {}  # realtime episodes' tick grids (``_schedule``)
        self._timer_cv = threading.Condition()
        self._closing = False
        self._timer_thread = threading.Thread(target=self._run_timers, name=f"sensors-timer-{rig}", daemon=True)
        self._timer_thread.start()
        self.loop.realtime.add_thread(self._timer_thread.native_id)  # it times the samples: realtime with the worker
        self._measurement_key = keys.measurement(rig)
        self._handles = [
            bus.subscribe(keys.episode_control(rig), lambda _k, p: self.loop.post(self._on_control, p)),
            self.loop.feed(bus, keys.command(rig), self._on_command),  # the worker takes them itself
            bus.serve(keys.training(rig), self._on_training),
            bus.serve(keys.training_truth(rig), self._on_training_truth),
        ]
        if describe:
            info = dump(self.descriptor)
            self._handles.append(bus.serve(keys.rig_info(rig), lambda _k, _p: info))
        # the token last: whoever sees the rig alive finds its subscriptions and queryables in place
        self._handles.append(bus.announce(keys.alive("sensors", rig)))

    # -- episodes ---------------------------------------------------------------------------
    def _on_control(self, payload: bytes) -> None:
        msg = decode_or_reject(episode_control_adapter, payload, "episode control message", log, self.bus, self.rig, "sensors")
        if msg is None:
            return
        if isinstance(msg, EpisodeStop):
            self._end(msg.episode_id)
            return
        if msg.episode_id in self.episodes:
            return  # duplicate start
        platform = SimulatedPlatform(self.hardware(msg.scenario), msg.seed, msg.test_index)
        self.episodes[msg.episode_id] = _Episode(start=msg, platform=platform, pan=msg.scenario.initial_pan_rad)
        self.loop.realtime.began(("sensors", msg.episode_id), msg.mode is Mode.realtime)
        self._finished.pop(msg.episode_id, None)
        self.bus.publish(keys.episode_truth(self.rig), dump(episode_truth(platform.truth, msg.episode_id)))
        for early in self._early.pop(msg.episode_id, []):
            self._on_command(early)

    def _on_command(self, payload: "bytes | Command") -> None:
        """A command: its JSON from the network, or the message itself from the rig's own
        controller on this loop (``EventLoop.send``)."""
        posted, started = self.loop.posted_ns, self.loop.started_ns
        cmd = payload if isinstance(payload, Command) else decode_or_reject(Command, payload, "command", log, self.bus, self.rig, "sensors")
        if cmd is None:
            return
        ep = self.episodes.get(cmd.episode_id)
        if ep is None:
            # The controller's first command can overtake the orchestrator's EpisodeStart (two
            # publishers, no ordering between them): keep it until the start arrives.
            if cmd.episode_id not in self._finished and cmd.step == 0:
                self._early.setdefault(cmd.episode_id, [])[:1] = [payload]
                while len(self._early) > 1000:
                    self._early.pop(next(iter(self._early)))
            return
        if ep.start.mode is Mode.realtime:
            ep.costs.queued += max(0, started - posted)
            ep.costs.decode += now_ns() - started
            self._realtime_command(ep, cmd)
            return
        steps = ep.start.scenario.steps
        if ep.last is not None and cmd.step == ep.last.step:
            self.loop.send(self.bus, self._measurement_key, ep.last)  # a repeated command: same sample again
            return
        expected = 0 if ep.last is None else ep.last.step + 1
        if cmd.step != expected or cmd.step >= steps:
            log.warning("episode %s: command for step %d, expected %d; dropped", cmd.episode_id, cmd.step, expected)
            return
        costs = ep.costs
        costs.mark_arrival(posted, started)
        costs.lap("decode")
        ep.last = self._sense(ep, cmd.step, cmd.pan_rad)
        costs.lap("compute")
        if cmd.step == steps - 1:
            if self.report_costs:  # just before the last sample, so they reach the orchestrator before the result
                costs.replied()
                self.bus.publish(keys.episode_timing(self.rig), dump(EpisodeTiming(episode_id=cmd.episode_id, costs=costs.report())))
            self.loop.send(self.bus, self._measurement_key, ep.last)
            self._end(cmd.episode_id)
            return
        self.loop.send(self.bus, self._measurement_key, ep.last, costs=costs)
        costs.lap("publish")
        costs.replied()

    def _sense(self, ep: _Episode, step: int, pan: float) -> Measurement:
        if not -math.pi <= pan < math.pi:  # the pan unit reaches the commanded angle, reported wrapped (docs/protocol.md)
            pan = float(wrap(pan))
        m = ep.platform.sense(step, pan)
        return _measurement(ep.start.episode_id, m.step, m.pan_rad, m.rf, m.frames, m.adverts, m.rf_tags)

    # -- realtime pacing --------------------------------------------------------------------
    def _realtime_command(self, ep: _Episode, cmd: Command) -> None:
        now = self.clock()
        ep.pan = cmd.pan_rad
        if not ep.ticking:
            if cmd.step != 0:
                return
            ep.ticking = True
            ep.t0 = now
            sc = ep.start.scenario
            self._schedule(now + sc.rf_period_s, ep.start.episode_id, 1 if sc.steps > 1 else -1, (now, sc.rf_period_s, sc.steps))
            self._tick(ep.start.episode_id, 0)
            return
        sent = ep.sent_at.pop(cmd.step - 1, None)
        if sent is not None:
            ep.latencies_ms.append((now - sent) * 1e3)
            if cmd.step < ep.next_step:
                ep.late += 1  # the sample of this step was already taken at the old pan

    def _tick(self, episode_id: str, step: int) -> None:
        ep = self.episodes.get(episode_id)
        if ep is None or step != ep.next_step:
            return
        ep.costs.begin(self.loop.started_ns)
        m = self._sense(ep, step, ep.pan)
        ep.costs.lap("compute")
        ep.sent_at[step] = self.clock()
        self.loop.send(self.bus, self._measurement_key, m, express=True, costs=ep.costs)
        ep.costs.lap("publish")
        ep.costs.replied()
        ep.next_step = step + 1

    def _finish_realtime(self, episode_id: str) -> None:
        ep = self.episodes.get(episode_id)
        if ep is None:
            return
        self.bus.publish(keys.episode_timing(self.rig), dump(EpisodeTiming(
            episode_id=episode_id, latencies_ms=tuple(round(v, 4) for v in ep.latencies_ms), late_commands=ep.late,
            costs=ep.costs.report() if self.report_costs else None)))
        self._end(episode_id)

    def _schedule(self, when: float, episode_id: str, step: int, clock: tuple[float, float, int]) -> None:
        """Tick ``step`` (-1: the end) of a realtime episode at ``when``; the timer thread schedules
        every later one itself, on the grid ``clock`` = (t0, T_RF, steps): the worker never wakes
        it again, so it never takes the GIL from the worker in the middle of a step."""
        with self._timer_cv:
            self._clocks[episode_id] = clock
            heapq.heappush(self._timers, (when, episode_id, step))
            self._timer_cv.notify()

    def _run_timers(self) -> None:
        while True:
            with self._timer_cv:
                while not self._closing and (not self._timers or self._timers[0][0] > self.clock()):
                    timeout = None if not self._timers else max(0.0, self._timers[0][0] - self.clock())
                    self._timer_cv.wait(timeout)
                if self._closing:
                    return
                _, episode_id, step = heapq.heappop(self._timers)
                clock = self._clocks.get(episode_id) if step >= 0 else self._clocks.pop(episode_id, None)
                if clock is not None and step >= 0:  # the next tick: sample k at t0 + k T_RF; the end one period after the last
                    t0, period, steps = clock
                    nxt = step + 1
                    heapq.heappush(self._timers, (t0 + nxt * period, episode_id, nxt if nxt < steps else -1))
            if step < 0:
                self.loop.post(self._finish_realtime, episode_id)
            else:
                self.loop.post(self._tick, episode_id, step)

    def _end(self, episode_id: str) -> None:
        self._early.pop(episode_id, None)
        if episode_id in self._clocks:
            with self._timer_cv:  # no more ticks (one already queued runs and finds no episode)
                self._clocks.pop(episode_id, None)
        if self.episodes.pop(episode_id, None) is not None:
            self.loop.realtime.ended(("sensors", episode_id))
            self._finished[episode_id] = None
            while len(self._finished) > 10000:
                self._finished.pop(next(iter(self._finished)))

    # -- training ---------------------------------------------------------------------------
    def _on_training(self, _key: str, payload: bytes) -> bytes:
        """Queryable handler (runs on the bus's worker pool, touches no episode state)."""
        req = _training_request(payload)
        samples = tuple(TrainingEpisode(self.hardware(req.scenario), req.seed).samples())
        return dump(TrainingStream.model_construct(job_id=req.job_id, samples=samples))

    def _on_training_truth(self, _key: str, payload: bytes) -> bytes:
        """Truth-plane queryable: the noiseless RSSI and POD behind the training episode of
        (scenario, seed), regenerated deterministically, for the orchestrator's R^2."""
        req = _training_request(payload)
        truth = TrainingEpisode(self.hardware(req.scenario), req.seed).truth
        return dump(TrainingTruth(job_id=req.job_id, rssi_dbm=tuple(float(v) for v in truth.rssi_dbm), pod=tuple(float(v) for v in truth.pod)))

    def hardware(self, scenario: Scenario) -> Scenario:
        """The world this rig simulates for ``scenario``: its own fixed hardware values in place of
        the campaign's (nothing changes for a configurable rig)."""
        return apply_rig_values(self.descriptor, scenario)

    def close(self) -> None:
        with self._timer_cv:
            self._closing = True
            self._timer_cv.notify()
        undeclare_all(self._handles)
        if self._own_loop:
            self.loop.stop()


def simulated_descriptor(rig: str, **fixed) -> RigDescriptor:
    """The descriptor of a simulated rig: every hardware field configurable unless ``fixed``
    (descriptor fields, e.g. ``rx_dir={"model": "db-gain"}``); it knows the truth."""
    return RigDescriptor.model_validate({"rig": rig, "kind": "simulated", "vendor": "ra2vipas", "model": "simulator",
                                         "episode_truth": True, "training_truth": True,
                                         "protocol": PROTOCOL_VERSION, **fixed})


HARDWARE_PARAMETERS = ("frames_per_rf", "rf_period_s", "fov_half_angle_deg", "box_bearing_noise_deg", "antenna_model",
                       "antenna_curvature", "antenna_floor_db", "n_tags")
"""The scenario parameters a simulated rig can pin (``ra2vipas sensors --hardware NAME=VALUE``); ``n_tags``
is how many tags its receivers hear (the descriptor's ``tags``, 1.5): a campaign searching for more is
refused, one searching for fewer runs as it is."""


def pinned_descriptor(rig: str, values: dict) -> RigDescriptor:
    """A simulated rig's descriptor with hardware ``values`` (scenario parameter names, typed) pinned.

    Raises
    ------
    ValueError
        A parameter that is not hardware, or a value out of range (one line naming it).
    """
    from pydantic import ValidationError

    fixed: dict = {}
    rx: dict = {}
    for name, value in values.items():
        if name not in HARDWARE_PARAMETERS:
            raise ValueError(f"{name!r} is not a hardware parameter; pin one of {', '.join(HARDWARE_PARAMETERS)}")
        if name.startswith("antenna_"):
            rx[{"antenna_model": "model", "antenna_curvature": "curvature", "antenna_floor_db": "floor_db"}[name]] = value
        elif name == "n_tags":
            fixed["tags"] = value
        else:
            fixed[name] = value
    if rx:
        rx.setdefault("model", "paper")
        fixed["rx_dir"] = rx
    try:
        return simulated_descriptor(rig, **fixed)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        raise ValueError(f"{'n_tags' if where == 'tags' else where}: {first.get('msg')}") from None  # the name the user gave


def _training_request(payload: bytes) -> TrainingRequest:
    """The request of a training queryable; a malformed one is answered with an error reply."""
    req, reason = decode(TrainingRequest, payload)
    if req is None:
        raise QueryError(f"malformed TrainingRequest: {reason}")
    return req
