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
from typing import Any, Callable, Iterable

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import ErrorReply, decode, dump, error_text

log = logging.getLogger(__name__)


class EventLoop:
    """Runs a node's handlers one at a time, in arrival order, on the node's own worker thread.

    Bus callbacks (Zenoh's threads) only ``post``: they enqueue and return at once, so a slow
    disk, a long SQLite transaction or a busy CPU in a handler can never stall message
    delivery (the zenoh-python docs: callbacks must not block). One FIFO queue per node keeps
    the order in which messages arrived, and node state needs no other locking.

    While a handler runs, ``posted_ns`` and ``started_ns`` (``time.perf_counter_ns``) say when
    it was posted and when the worker took it: its time queued (``services/transport/costs.py``).
    """

    def __init__(self, name: str) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.posted_ns = 0
        self.started_ns = 0
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def post(self, fn: Callable[..., None], *args) -> None:
        """Queue ``fn(*args)`` to run on the worker thread (dropped once the loop is stopped)."""
        if not self._stopped.is_set():
            self._queue.put((fn, args, time.perf_counter_ns()))

    def backlog(self) -> int:
        """Handlers queued and not yet run (approximate)."""
        return self._queue.qsize()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until everything posted before this call has run (tests and shutdown)."""
        if threading.current_thread() is self._thread:
            return True
        done = threading.Event()
        self.post(done.set)
        return done.wait(timeout)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, args, self.posted_ns = item
            self.started_ns = time.perf_counter_ns()
            try:
                fn(*args)
            except Exception:
                log.exception("event handler %s failed", getattr(fn, "__name__", fn))

    def stop(self, timeout: float = 5.0) -> None:
        self._stopped.set()
        self._queue.put(None)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)


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
