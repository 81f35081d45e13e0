"""Process plumbing shared by the services: one worker thread per node, and shutdown on
SIGINT/SIGTERM that closes the Zenoh session before the process exits."""

from __future__ import annotations

import logging
import queue
import signal
import sys
import threading
from typing import Any, Callable, Iterable

from ra2vipas.services.protocol.messages import decode, error_text

log = logging.getLogger(__name__)


class EventLoop:
    """Runs callables one at a time, in arrival order, so node state needs no other locking.

    With ``inline`` (the default) a posted callable runs at once on the posting thread under
    the loop's lock: a bus callback does its work on Zenoh's thread without a thread hop,
    which matters at thousands of messages per second. Without it, callables run on a
    dedicated thread.
    """

    def __init__(self, name: str, inline: bool = True) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._stopped = threading.Event()
        self._inline = inline
        self._lock = threading.RLock()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def post(self, fn: Callable[..., None], *args) -> None:
        if self._stopped.is_set():
            return
        if self._inline:
            with self._lock:
                try:
                    fn(*args)
                except Exception:
                    log.exception("event handler %s failed", getattr(fn, "__name__", fn))
            return
        self._queue.put((fn, args))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            fn, args = item
            try:
                with self._lock:
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
