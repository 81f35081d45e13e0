"""The narrow messaging interface every service adapter talks to, and an in-memory bus.

A service's node logic (``services/<name>/node.py``) only publishes, subscribes, serves and
sends queries, and announces or watches liveliness through a ``Bus``. ``ZenohBus``
(``zenoh_bus.py``) implements it over a Zenoh session; ``MemoryBus`` implements it inside one
process so node logic is tested without a network (the dora-rs "fake node" idea).

Callbacks may be called from any thread; nodes hand events to their own single worker thread
(``ra2vipas.services.transport.runtime.EventLoop``) so their state needs no locks. A bus may
also offer ``feed(key)``: a subscription whose messages that worker thread takes itself
(``Feed``), with no callback thread in between, for a node's per-step traffic.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from typing import Callable, Protocol


class QueryError(Exception):
    """Raised by a query handler to send an error reply; the message is the reply's text."""


@dataclass(frozen=True)
class Reply:
    """One reply to a query: ``ok`` False means an error reply whose text is in ``payload``;
    ``timed_out``: the error is the querier's own timeout (a node matched the key but no answer
    came in time, e.g. its link went down mid-query), not a node's answer."""

    key: str
    payload: bytes
    ok: bool = True
    timed_out: bool = False


def answered(replies: list[Reply]) -> list[Reply]:
    """The replies some node sent (``replies`` without the querier's own timeout): a query whose
    every matching node stayed silent until its timeout was answered by no node."""
    return [r for r in replies if not r.timed_out]


class Handle(Protocol):
    def undeclare(self) -> None: ...


class FeedClosed(Exception):
    """Raised by ``Feed.recv`` once the feed is undeclared (or its bus closed)."""


class Feed(Protocol):
    """A subscription read by its consumer's own thread (``Bus.feed``): messages queue in the
    bus, in arrival order, until taken; nothing runs on the bus's threads."""

    def recv(self) -> "tuple[str, bytes] | None":
        """The next ``(key, payload)``, blocking until one arrives; None when woken by ``wake``
        instead. Raises ``FeedClosed`` once undeclared."""

    def try_recv(self) -> "tuple[str, bytes] | None":
        """The next ``(key, payload)`` if one is waiting (a pending wake-up is consumed and
        reported as None too), without blocking."""

    def wake(self) -> None:
        """Make a ``recv`` blocked now (or the next one) return None: the consumer has other
        work (any thread may call it)."""

    def undeclare(self) -> None: ...


Callback = Callable[[str, bytes], None]
QueryHandler = Callable[[str, bytes], "bytes | None"]
AliveCallback = Callable[[str, bool], None]
RepliesCallback = Callable[[list[Reply]], None]


class Bus(Protocol):
    """What a node may do on the network."""

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        """Put ``payload`` (JSON bytes) on ``key``; ``express`` skips batching (latency first)."""

    def subscribe(self, key: str, callback: Callback) -> Handle:
        """Call ``callback(key, payload)`` for every sample on keys matching ``key``."""

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        """Answer queries on ``key``: ``handler(key, payload)`` returns the reply payload or raises
        ``QueryError``, or returns None to send no reply (a query that is not for it, e.g. the
        conformance kit's learner). Handlers run on a worker thread and may take long."""

    def query(self, key: str, payload: bytes, timeout: float, callback: RepliesCallback) -> None:
        """Send a query; ``callback(replies)`` is called once with every reply received before
        the timeout (possibly none). Never blocks the caller."""

    def announce(self, key: str) -> Handle:
        """Declare a liveliness token on ``key`` for as long as the handle lives."""

    def watch_alive(self, key: str, callback: AliveCallback) -> Handle:
        """Call ``callback(token_key, alive)`` for tokens matching ``key``, current ones included."""

    def close(self) -> None:
        """Undeclare everything and leave the network."""


def undeclare_all(handles) -> None:
    """Undeclare every handle, ignoring ones already gone (used by every node's ``close``)."""
    for h in handles:
        try:
            h.undeclare()
        except Exception:
            pass


def key_matches(pattern: str, key: str) -> bool:
    """Whether a concrete ``key`` matches a Zenoh key expression ``pattern`` (``*`` one chunk,
    ``**`` any number of chunks)."""
    p = pattern.split("/")
    k = key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        if p[i] == "*" or p[i] == k[j]:
            return match(i + 1, j + 1)
        return False

    return match(0, 0)


class _MemoryFeed:
    """``MemoryBus.feed``: a subscription whose callback queues what the consumer takes."""

    _WAKE = object()
    _CLOSED = object()

    def __init__(self, bus: "MemoryBus", key: str) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        self._handle = bus.subscribe(key, lambda k, p: self._queue.put((k, p)))

    def _take(self, item):
        if item is self._CLOSED:
            self._queue.put(item)  # every later call sees it too
            raise FeedClosed("feed undeclared")
        return None if item is self._WAKE else item

    def recv(self):
        return self._take(self._queue.get())

    def try_recv(self):
        try:
            return self._take(self._queue.get_nowait())
        except queue.Empty:
            return None

    def wake(self) -> None:
        self._queue.put(self._WAKE)

    def undeclare(self) -> None:
        if not self._closed:
            self._closed = True
            self._handle.undeclare()
            self._queue.put(self._CLOSED)


class _MemoryHandle:
    def __init__(self, registry: list, item) -> None:
        self._registry = registry
        self._item = item

    def undeclare(self) -> None:
        try:
            self._registry.remove(self._item)
        except ValueError:
            pass


class MemoryBus:
    """In-process bus shared by several nodes: the network, without the network.

    Publications are delivered in order by one dispatcher thread (so a chain of replies never
    recurses), queries are answered on their own threads (handlers may block, as with Zenoh),
    and liveliness tokens notify watchers. ``published`` records every publication.
    """

    def __init__(self) -> None:
        self._subs: list[tuple[str, Callback]] = []
        self._servers: list[tuple[str, QueryHandler]] = []
        self._tokens: list[str] = []
        self._watchers: list[tuple[str, AliveCallback]] = []
        self._lock = threading.RLock()
        self._queue: "queue.SimpleQueue[tuple[str, bytes] | None]" = queue.SimpleQueue()
        self._pending = 0
        self._idle = threading.Condition(self._lock)
        self.published: list[tuple[str, bytes]] = []
        self._thread = threading.Thread(target=self._dispatch, name="memory-bus", daemon=True)
        self._thread.start()

    def _dispatch(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            key, payload = item
            with self._lock:
                targets = [cb for pattern, cb in self._subs if key_matches(pattern, key)]
            for cb in targets:
                try:
                    cb(key, payload)
                except Exception:  # like Zenoh: a failing subscriber does not stop delivery
                    pass
            with self._lock:
                self._pending -= 1
                if self._pending == 0:
                    self._idle.notify_all()

    def wait_idle(self, timeout: float = 10.0) -> bool:
        """Block until every publication so far has been delivered."""
        with self._lock:
            return self._idle.wait_for(lambda: self._pending == 0, timeout)

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        with self._lock:
            self.published.append((key, payload))
            self._pending += 1
        self._queue.put((key, payload))

    def subscribe(self, key: str, callback: Callback) -> Handle:
        item = (key, callback)
        with self._lock:
            self._subs.append(item)
        return _MemoryHandle(self._subs, item)

    def feed(self, key: str) -> Feed:
        """Messages on keys matching ``key``, taken by the consumer (``Feed``; a bus may
        return None instead when it cannot offer one: the caller subscribes then)."""
        return _MemoryFeed(self, key)

    def serve(self, key: str, handler: QueryHandler) -> Handle:
        item = (key, handler)
        with self._lock:
            self._servers.append(item)
        return _MemoryHandle(self._servers, item)

    def query(self, key: str, payload: bytes, timeout: float, callback: RepliesCallback) -> None:
        def run() -> None:
            with self._lock:
                servers = [(pattern, h) for pattern, h in self._servers if key_matches(key, pattern)]
            replies: list[Reply] = []
            for pattern, handler in servers[:1]:
                try:
                    answer = handler(pattern, payload)
                    if answer is not None:
                        replies.append(Reply(pattern, answer))
                except QueryError as err:
                    replies.append(Reply(pattern, str(err).encode(), ok=False))
            callback(replies)

        threading.Thread(target=run, daemon=True).start()

    def announce(self, key: str) -> Handle:
        with self._lock:
            self._tokens.append(key)
            watchers = [cb for pattern, cb in self._watchers if key_matches(pattern, key)]
        for cb in watchers:
            cb(key, True)
        bus = self

        class _Token:
            def undeclare(self) -> None:
                with bus._lock:
                    if key not in bus._tokens:
                        return
                    bus._tokens.remove(key)
                    targets = [cb for pattern, cb in bus._watchers if key_matches(pattern, key)]
                for cb in targets:
                    cb(key, False)

        return _Token()

    def watch_alive(self, key: str, callback: AliveCallback) -> Handle:
        item = (key, callback)
        with self._lock:
            self._watchers.append(item)
            current = [t for t in self._tokens if key_matches(key, t)]
        for t in current:
            callback(t, True)
        return _MemoryHandle(self._watchers, item)

    def close(self) -> None:
        with self._lock:
            self._subs.clear()
            self._servers.clear()
            self._watchers.clear()
        self._queue.put(None)
