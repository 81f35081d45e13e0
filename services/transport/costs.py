"""Where a node's time goes, step by step: cheap per-stage timers kept by the adapters.

A node's adapter (``services/<name>/node.py``, never the pure domain logic) times each step
message it handles with ``time.perf_counter_ns`` (tens of nanoseconds a call) and sums the
stages per episode in a ``CostClock``; when the episode ends it reports the sums as a
``StepCosts`` (the controller in its ``EpisodeResult``, the sensors in their ``EpisodeTiming``).
``ra2vipas bench mesh`` adds them up per step (``step_breakdown``).

The stages of one step, as one node sees them::

    ... its last reply published ─ outside ─> message arrives (bus callback: EventLoop.post)
        ─ queued ─> the worker thread takes it ─ decode ─ compute ─ encode ─ publish ─> replied

``decode`` is decode and validate (pydantic, from the bytes), ``compute`` the handler's own
work (the policy's step, the platform's sample, bookkeeping), ``encode`` the reply's JSON,
``publish`` the call that hands it to Zenoh. ``outside`` is everything the node waited for
between its reply and the next message of the same episode: the other node's whole step and
the transport both ways. The stages are contiguous, so per episode
``outside + queued + decode + compute + encode + publish`` covers the node's span from the
start of its first step message's handling to its last publication (for a paced node without
one, from its first publication); for a lockstep (fast) episode the controller's ``outside``
minus the sensors' in-process stages is the transport time. Neither node counts the wait for
its episode's first step message, on the wire or in its queue (the episode's set-up, not a
step): the two nodes' views of the transport then have the same edges, one step each.

All times are monotonic (``perf_counter_ns``) and never compared across processes.
"""

from __future__ import annotations

import time

from ra2vipas.services.protocol.messages import StepCosts

now_ns = time.perf_counter_ns

STAGES = ("queued", "decode", "compute", "encode", "publish")


class CostClock:
    """One episode's stage sums on one node [ns]; ``report`` turns them into a ``StepCosts``.

    Use per handled step: ``mark_arrival(posted_ns, started_ns)`` when the handler starts (the
    ``EventLoop``'s ``posted_ns``/``started_ns`` of the message), then ``lap(stage)`` after each
    stage; ``replied()`` once the reply is published.
    """

    __slots__ = ("steps", "queued", "decode", "compute", "encode", "publish", "outside", "first", "last", "_t")

    def __init__(self) -> None:
        self.steps = 0
        self.queued = self.decode = self.compute = self.encode = self.publish = self.outside = 0
        self.first = 0  # its first step message's handling began (or its first publication)
        self.last = 0   # end of its latest publication
        self._t = 0

    def mark_arrival(self, posted_ns: int, started_ns: int) -> None:
        """A step message arrived at ``posted_ns`` (bus callback) and its handler started at ``started_ns``."""
        if self.last:
            self.outside += max(0, posted_ns - self.last)
            self.queued += max(0, started_ns - posted_ns)
        elif not self.first:  # the span starts as the first one's handling does: the wait for it, on the wire or
            self.first = started_ns  # in the queue (behind the episode's set-up, or other episodes), is not a step
        self.steps += 1
        self._t = started_ns

    def begin(self, started_ns: int) -> None:
        """A step begins on the worker thread without a message to wait for (a paced sample)."""
        self.steps += 1
        self._t = started_ns

    def lap(self, stage: str) -> int:
        """Charge the time since the last mark to ``stage``; the current time [ns]."""
        t = now_ns()
        setattr(self, stage, getattr(self, stage) + (t - self._t))
        self._t = t
        return t

    def replied(self) -> None:
        """The step's reply is published (call right after ``lap("publish")``)."""
        self.last = self._t
        if not self.first:
            self.first = self._t

    def report(self) -> StepCosts:
        ms = 1e-6
        return StepCosts(steps=self.steps, queued_ms=round(self.queued * ms, 4), decode_ms=round(self.decode * ms, 4),
                         compute_ms=round(self.compute * ms, 4), encode_ms=round(self.encode * ms, 4),
                         publish_ms=round(self.publish * ms, 4), outside_ms=round(self.outside * ms, 4),
                         span_ms=round(max(0, self.last - self.first) * ms, 4))


def _per_step(costs: list[StepCosts]) -> dict[str, float]:
    steps = sum(c.steps for c in costs)
    out = {"episodes": len(costs), "steps": steps}
    for name in (*STAGES, "outside", "span"):
        out[f"{name}_ms"] = round(sum(getattr(c, f"{name}_ms") for c in costs) / steps, 4) if steps else None
    return out


def _own(part: dict) -> float:
    return sum(part[f"{s}_ms"] for s in STAGES)


def step_breakdown(controller: list[StepCosts], sensors: list[StepCosts], latencies_ms: list[float] | None = None) -> dict:
    """Per step [ms, mean over the episodes' steps]: each node's stages (``STAGES``), and the
    transport between them, from the costs both nodes reported for the same episodes.

    Lockstep (fast) episodes (``latencies_ms`` None): one step is, as the controller sees it,
    ``outside + queued + decode + compute + encode + publish``, and its ``outside`` is the
    sensors' in-process stages plus the transport both ways, so ``transport_ms`` =
    controller ``outside`` - sensors' stages. ``transport_ms_sensors_view`` is the same
    derived the other way round (sensors ``outside`` - the controller's stages): the two
    agree when both nodes' timers are right, to each episode's edges (the controller's view
    lacks the sensors' first step and the first measurement's transport, the sensors' view the
    controller's last step and the last measurement's transport: about one step per episode,
    visible only where the transport is ~0, as in a one-process rig). ``step_ms`` is the
    controller's span per step (from the start of its first measurement's handling: the
    episode's set-up is not a step),
    measured as one interval; ``parts_sum_ms`` the sum of the parts. With several episodes in
    flight per rig a step's ``queued`` time is mostly other episodes' steps: ``*_busy_ms`` (the
    stages but the queue) is what one step costs each node's worker thread.

    Realtime episodes (``latencies_ms``, the sensors' sample->command latencies): the
    latency is the sensors' publish, the transport both ways, the controller's stages and
    the sensors' queue and decode of the command; ``transport_ms`` is what the others leave.
    """
    ctl, sen = _per_step(controller), _per_step(sensors)
    out: dict = {"controller": ctl, "sensors": sen}
    if not ctl["steps"] or not sen["steps"]:
        return out
    if latencies_ms is None:
        transport = ctl["outside_ms"] - _own(sen)
        out["transport_ms"] = round(transport, 4)
        out["transport_ms_sensors_view"] = round(sen["outside_ms"] - _own(ctl), 4)
        out["step_ms"] = ctl["span_ms"]
        out["parts_sum_ms"] = round(_own(ctl) + _own(sen) + transport, 4)
        out["controller_busy_ms"] = round(_own(ctl) - ctl["queued_ms"], 4)
        out["sensors_busy_ms"] = round(_own(sen) - sen["queued_ms"], 4)
        # of the controller's worker-thread time, the share its policy's step takes: what a rig core
        # spends on the algorithm when the controller is the busy process (queueing is not work)
        out["controller_compute_share"] = round(ctl["compute_ms"] / out["controller_busy_ms"], 4) if out["controller_busy_ms"] else None
        return out
    latency = sum(latencies_ms) / len(latencies_ms) if latencies_ms else 0.0
    others = _own(ctl) + sen["publish_ms"] + sen["queued_ms"] + sen["decode_ms"]
    out["latency_ms"] = round(latency, 4)
    out["transport_ms"] = round(latency - others, 4)
    out["controller_compute_share"] = round(ctl["compute_ms"] / latency, 4) if latency else None
    return out
