"""Process plumbing shared by the services: one worker thread per node, and shutdown on
SIGINT/SIGTERM that closes the Zenoh session before the process exits."""

from __future__ import annotations

import json
import logging
import queue
import re
import signal
import sys
import threading
import time
from collections import deque
from typing import Any, Callable, Iterable

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import ErrorReply, decode, dump, error_text
from ra2vipas.services.transport.realtime import RealtimeClass

log = logging.getLogger(__name__)


class EventLoop:
    """Runs a node's handlers one at a time, in arrival order, on the node's own worker thread.

    Bus callbacks (Zenoh's threads) only ``post``: they enqueue and return at once, so a slow
    disk, a long SQLite transaction or a busy CPU in a handler can never stall message
    delivery (the zenoh-python docs: callbacks must not block). One FIFO queue per node keeps
    the order in which messages arrived, and node state needs no other locking.

    A node's per-step traffic (the controller's measurements, the sensors' commands) comes
    through ``feed`` instead when the bus offers it (``Bus.feed``): the worker takes those
    messages from the bus itself, so a step's message reaches its handler with one thread
    hop (Zenoh's receiving thread to the worker) instead of two, no other thread takes the GIL
    for it, and a backlog of them is drained without a thread switch each. Posted events and
    fed messages take turns when both are waiting; each source keeps its own order.

    While a handler runs, ``posted_ns`` and ``started_ns`` (``time.perf_counter_ns``) say when
    it was posted and when the worker took it: its time queued (``services/transport/costs.py``).
    For a fed message ``posted_ns`` is when the worker started waiting for it, or, if it was
    already waiting in the bus, when the worker looked: the time it spent queued in the bus
    behind other messages is not seen (it counts as the time outside the node).

    ``inline=True`` makes a loop for several nodes on one bus session (``ra2vipas rig``: a
    rig's sensors and controller, one process, one Zenoh session, one worker). Their per-step
    traffic is then subscribed with ``Bus.subscribe_inline`` where the bus offers it: a message
    one of the nodes publishes is delivered by the session to the other's subscription inside
    the publisher's ``put``, on this worker, and queued there in a local deque (no lock, no
    wake-up, no other thread) to run once the publishing handler returns; a message from the
    network (another process) arrives on the bus's thread and is posted like any other.

    A node of an inline loop publishes its step messages with ``send``: where the bus offers
    ``publish_remote``, the other node's handler gets the message object itself, through the same
    local deque (no JSON encoding, no Zenoh delivery, no decoding and validating again: the
    message was made by this process), and the network gets its JSON only while a subscriber
    elsewhere wants it. A handler fed this way takes either the payload bytes (from the network)
    or the message.

    The local deque runs depth first: what a handler delivered while it ran an inline delivery
    (the next message of the same lockstep exchange) runs before the deliveries queued earlier
    (other episodes' exchanges), so one episode's steps run back to back, its state warm in the
    CPU's caches, and episodes finish one after another instead of all at once; what a posted
    event's handler delivers (an episode's first command) joins the back, so no exchange waits
    behind more than the ones queued before it started.

    ``realtime_priority`` (1-49; 0: off): while every episode its nodes have in flight is a realtime
    one (they say so through ``realtime``), the worker runs under ``SCHED_FIFO`` at that priority,
    where the process may (``services/transport/realtime.py``).
    """

    def __init__(self, name: str, inline: bool = False, realtime_priority: int = 0) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.posted_ns = 0
        self.started_ns = 0
        self._stopped = threading.Event()
        self._feed = None  # (Feed, handler) once ``feed`` found a bus that offers one
        self._waiting = False  # the worker may be blocked in the feed's recv: a post must wake it
        self._fed_last = False  # the last item came from the feed: posted events go first next
        self.inline = inline
        self._local: deque = deque()  # messages delivered on the worker itself (inline), in order
        self._local_last = False  # the last item came from ``_local``: a posted event goes first next
        self._handlers: dict[str, Callable] = {}  # inline feeds' handlers by key, for ``send``
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self._ident = self._thread.ident
        # SCHED_FIFO for the worker (and threads nodes add) while realtime episodes only are in flight
        self.realtime = RealtimeClass(realtime_priority)
        self.realtime.add_thread(self._thread.native_id)

    def post(self, fn: Callable[..., None], *args) -> None:
        """Queue ``fn(*args)`` to run on the worker thread (dropped once the loop is stopped)."""
        if not self._stopped.is_set():
            self._queue.put((fn, args, time.perf_counter_ns()))
            self._wake()

    def post_later(self, seconds: float, fn: Callable[..., None], *args) -> None:
        """``post(fn, *args)`` once ``seconds`` have passed (a daemon timer: it never keeps the
        process alive, and what it posts after ``stop`` is dropped)."""
        timer = threading.Timer(seconds, self.post, (fn, *args))
        timer.daemon = True
        timer.start()

    def _wake(self) -> None:
        # the worker sets ``_waiting`` before it last looks at the queue and then blocks: a post
        # that reads False was queued before that look (the GIL orders the two), so it is seen
        feed = self._feed
        if feed is not None and self._waiting:
            feed[0].wake()

    def feed(self, bus, key: str, handler: Callable[[bytes], None]):
        """Run ``handler(payload)`` on the worker thread for every message on ``key``, taken
        from ``bus.feed(key)`` by the worker itself; on a bus without feeds, through
        ``bus.subscribe`` and ``post`` like any other subscription. One feed per loop. The
        returned handle's ``undeclare`` ends it."""
        inline = getattr(bus, "subscribe_inline", None) if self.inline else None
        if inline is not None:
            self._handlers[key] = handler
            prepare = getattr(bus, "prepare_remote", None)
            if prepare is not None:  # another node of this loop sends on ``key`` (``send``): its network publishers now, before the tokens
                prepare(key)
            return inline(key, lambda _k, p: self._arrive(handler, p))
        make = getattr(bus, "feed", None)
        feed = make(key) if make is not None and self._feed is None else None
        if feed is None:
            return bus.subscribe(key, lambda _k, p: self.post(handler, p))
        self._feed = (feed, handler)
        self._queue.put((_nothing, (), time.perf_counter_ns()))  # the worker may be blocked on the queue: now it pulls
        return feed

    def send(self, bus, key: str, message, express: bool = False, costs=None) -> None:
        """Publish ``message`` (a protocol message) on ``key`` from a handler of this loop: to a
        handler of this loop fed ``key``, the message itself, run once the calling handler returns,
        and to the rest of the network its JSON, if anyone there subscribes (``publish_remote``);
        without both, its JSON through ``bus.publish`` as any message. ``costs`` (a
        ``CostClock``) gets an ``encode`` lap once the JSON is made, if it is."""

        def encode() -> bytes:
            payload = dump(message)
            if costs is not None:
                costs.lap("encode")
            return payload

        handler = self._handlers.get(key)
        remote = getattr(bus, "publish_remote", None) if handler is not None else None
        if remote is None or threading.get_ident() != self._ident:
            bus.publish(key, encode(), express)
            return
        self._local.append((handler, (message,), None))
        remote(key, encode, express)

    def _arrive(self, handler: Callable[[bytes], None], payload: bytes) -> None:
        """A message of an inline subscription (``feed`` on an ``inline`` loop): delivered on the
        worker itself (a put by a node of this loop), it waits in the local deque until the
        running handler returns; from any other thread (the network), it is posted."""
        if threading.get_ident() == self._ident:
            self._local.append((handler, (payload,), None))  # posted when the publishing handler returns (``_run``)
        else:
            self.post(handler, payload)

    def _next(self):
        """The next ``(fn, args, posted_ns)`` to run, None to stop."""
        local = self._local
        if local:  # inline deliveries and posted events take turns; each keeps its order
            if self._local_last and not self._queue.empty():
                self._local_last = False
                return self._queue.get_nowait()
            self._local_last = True
            return local.popleft()
        self._local_last = False
        while True:
            feed = self._feed
            if feed is None:
                return self._queue.get()
            source, handler = feed
            self._waiting = True
            if self._fed_last or self._stopped.is_set():
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    pass
                else:
                    self._waiting = self._fed_last = False
                    return item
            looked = time.perf_counter_ns()
            try:
                got = source.try_recv()
                if got is None:
                    try:
                        item = self._queue.get_nowait()
                    except queue.Empty:
                        got = source.recv()  # blocks without the GIL until a message or a wake-up
                        looked = time.perf_counter_ns()
                    else:
                        self._waiting = self._fed_last = False
                        return item
            except Exception:  # FeedClosed (undeclared, bus closed): back to the queue alone
                self._feed = None
                continue
            self._waiting = False
            if got is None:  # a wake-up: a posted event is waiting
                self._fed_last = True
                continue
            self._fed_last = True
            return handler, (got[1],), looked

    def backlog(self) -> int:
        """Handlers queued and not yet run (approximate)."""
        return self._queue.qsize() + len(self._local)

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until everything posted before this call has run (tests and shutdown)."""
        if threading.current_thread() is self._thread:
            return True
        done = threading.Event()
        self.post(done.set)
        return done.wait(timeout)

    def _run(self) -> None:
        while True:
            item = self._next()
            if item is None:
                return
            fn, args, self.posted_ns = item
            from_local = self._local_last
            self.started_ns = time.perf_counter_ns()
            try:
                fn(*args)
            except Exception:
                log.exception("event handler %s failed", getattr(fn, "__name__", fn))
            local = self._local
            if local and local[-1][2] is None:
                # delivered inline while ``fn`` ran (its put): posted now, as ``fn`` returns, since it
                # could not run before; the rest of that put is the publisher's time, not queueing
                ended, i = time.perf_counter_ns(), len(local) - 1
                while i >= 0 and local[i][2] is None:
                    local[i] = (*local[i][:2], ended)
                    i -= 1
                if from_local and i >= 0:  # depth first: the exchange ``fn`` continued goes on next
                    local.rotate(len(local) - 1 - i)

    def stop(self, timeout: float = 5.0) -> None:
        self._stopped.set()
        self._queue.put(None)
        feed = self._feed
        if feed is not None:
            feed[0].wake()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


def _nothing() -> None:
    """A no-op event: wakes a worker blocked on its queue (``EventLoop.feed``)."""


def decode_or_drop(schema, payload: bytes, what: str, logger: logging.Logger):
    """The validated message, or None after logging why it was dropped (log-and-drop at the edge)."""
    message, reason = decode(schema, payload)
    if message is None:
        logger.warning("dropping malformed %s (%d bytes): %s", what, len(payload), reason)
    return message


_EPISODE_ID = re.compile(r"^[A-Za-z0-9_.:-]{1,128}$")


def rejected_episode_id(payload: bytes) -> str | None:
    """The ``episode_id`` a message that did not validate names, if it is a JSON object with a
    well-formed one (what a rejection report can name); else None."""
    if len(payload) > 1 << 20:
        return None
    try:
        obj = json.loads(payload)
    except (ValueError, RecursionError):
        return None
    eid = obj.get("episode_id") if isinstance(obj, dict) else None
    return eid if isinstance(eid, str) and _EPISODE_ID.match(eid) else None


def decode_or_reject(schema, payload: bytes, what: str, logger: logging.Logger, bus, rig: str, role: str):
    """The validated message, or None after logging why it was dropped and, when the message
    names an episode, reporting the rejection on ``result/{rig}/rejected`` (an ``ErrorReply``
    with the episode id and the reason): the orchestrator then fails that attempt at once,
    saying why, instead of waiting for it to time out (docs/protocol.md, "Compatibility")."""
    message, reason = decode(schema, payload)
    if message is None:
        logger.warning("dropping malformed %s (%d bytes): %s", what, len(payload), reason)
        eid = rejected_episode_id(payload)
        if eid is not None:
            error = f"the {role} of rig {rig} rejected its {what}: {reason}"
            bus.publish(keys.episode_rejected(rig), dump(ErrorReply(error=error[:2000], episode_id=eid)))
    return message


def first_valid_reply(replies: Iterable, schema, what: str, accept: Callable[[Any], bool] | None = None) -> tuple[Any, list[str]]:
    """The first query reply that is not an error, validates against ``schema`` and passes
    ``accept`` (if given); else None. Also why earlier replies were passed over: an error
    reply's text, or ``malformed <what>: <first invalid field>`` (replies ``accept`` refuses,
    such as another job's, are skipped without a reason)."""
    passed_over: list[str] = []
    for reply in replies:
        if not reply.ok:
            passed_over.append(error_text(reply.payload))
            continue
        message, reason = decode(schema, reply.payload)
        if message is None:
            passed_over.append(f"malformed {what}: {reason}")
            continue
        if accept is None or accept(message):
            return message, passed_over
    return None, passed_over


def wait_for_shutdown_signal() -> int:
    """Block until SIGINT or SIGTERM; return the signal number."""
    got = threading.Event()
    received = {"signal": 0}

    def handler(signum, _frame) -> None:
        received["signal"] = signum
        got.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    while not got.wait(0.5):
        pass
    return received["signal"]


def configure_logging(level: str = "INFO") -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
