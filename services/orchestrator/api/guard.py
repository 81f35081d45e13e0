"""What one HTTP client can hold of the orchestrator (issue 18): slow clients must not take the
API down.

Connections that send one header line every 10 s once exhausted the orchestrator's file
descriptors: ``/health`` timed out for the whole attack and asyncio logged 380 927
``socket.accept() out of system resource`` tracebacks (170 MB in 38 s). The server now bounds
what a client can hold, below uvicorn's application, on the connections themselves:

- **a deadline for a request's head** (``header_timeout_s``, 10 s): from the moment a
  connection is accepted, or its previous response ends, the request line and headers must
  have arrived within it, else the connection is answered 408 and closed; a request's body
  must have arrived ``body_timeout_s`` (30 s) after its head;
- **a cap on connections** (``max_connections``, 1 000, and never more than the process's file
  descriptor limit allows, with a reserve for the database, Zenoh and the figure renderers)
  and **per client address** (``max_per_client``, 256): a new connection beyond either first
  evicts the connection of that client (or, at the global cap, of anyone) that has waited
  longest for its request head, if it has waited a second at least, so trickling connections
  make room for requests that arrive whole; otherwise the new one is answered 503 and closed.

So one address cannot hold more than ``max_per_client`` connections, the socket count stays
below the descriptor limit (accept() does not fail), and other clients' requests, ``/health``
included, keep being answered; a client that shares its address with an attacker shares its
limit. ``RepeatFilter`` rate-limits identical log lines (a flood of one error is logged a few
times per interval, then how many were suppressed).
"""

from __future__ import annotations

import asyncio
import logging
import resource
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Callable

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger("ra2vipas.orchestrator.guard")

FD_RESERVE = 256  # descriptors kept for SQLite, Zenoh, the renderers' pipes and the thread pool
SWEEP_EVERY_S = 0.5


def raise_fd_limit(target: int = 65536) -> int:
    """Raise the soft limit of open files towards the hard limit (at most ``target``); return
    the soft limit in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = target if hard == resource.RLIM_INFINITY else min(hard, target)
    if soft != resource.RLIM_INFINITY and soft < want:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
            soft = want
        except (ValueError, OSError):
            pass
    return soft if soft != resource.RLIM_INFINITY else target


@dataclass
class GuardLimits:
    max_connections: int = 1000
    max_per_client: int = 256
    header_timeout_s: float = 10.0
    body_timeout_s: float = 30.0
    eviction_grace_s: float = 1.0  # a connection is evicted for a newcomer only after waiting this long for its head
    backlog: int = 2048  # the listening socket's backlog, which is also how many connections asyncio accepts at once

    def within_fd_limit(self, fd_limit: int) -> "GuardLimits":
        """These limits lowered to fit ``fd_limit`` descriptors: asyncio accepts up to
        ``backlog`` connections in one go before any is admitted, and those it closes are
        closed on the next loop turn, so the connections held, two accept bursts and
        ``FD_RESERVE`` must fit."""
        room = max(64, fd_limit - FD_RESERVE)
        backlog = max(16, min(self.backlog, room // 8))
        cap = max(16, min(self.max_connections, room - 2 * backlog))
        return GuardLimits(cap, max(1, min(self.max_per_client, cap)), self.header_timeout_s, self.body_timeout_s,
                           self.eviction_grace_s, backlog)


_REFUSED = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\nretry-after: 1\r\nconnection: close\r\n"
            b"content-length: 53\r\n\r\n" + b'{"detail": "too many connections: retry in a second"}'.ljust(53))
_TIMED_OUT = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\nconnection: close\r\n"
              b"content-length: 50\r\n\r\n" + b'{"detail": "the request did not arrive in time"}'.ljust(50))


@dataclass
class ConnectionGuard:
    """The bookkeeping shared by every connection of one server (see the module docstring).
    Runs on the server's event loop only."""

    limits: GuardLimits = field(default_factory=GuardLimits)
    open: dict = field(default_factory=dict)  # protocol -> client address
    per_client: Counter = field(default_factory=Counter)
    waiting: "OrderedDict" = field(default_factory=OrderedDict)  # protocol -> since (loop time), oldest first
    receiving: dict = field(default_factory=dict)  # protocol -> when its head arrived (body may still be coming)
    counts: Counter = field(default_factory=Counter)  # refused, evicted, timed_out
    _sweeping: bool = False

    def protocol_class(self) -> type[H11Protocol]:
        """uvicorn's h11 protocol, bound to this guard (``uvicorn.Config(http=...)``)."""
        return type("GuardedH11Protocol", (GuardedH11Protocol,), {"guard": self})

    # -- events from the connections ---------------------------------------------------------
    def admit(self, proto: "GuardedH11Protocol") -> bool:
        """A connection was accepted: make room for it or refuse it (503, closed)."""
        client = proto.client[0] if proto.client else "?"
        if len(self.open) >= self.limits.max_connections and not self._evict_oldest(None):
            return self._refuse(proto)
        if self.per_client[client] >= self.limits.max_per_client and not self._evict_oldest(client):
            return self._refuse(proto)
        self.open[proto] = client
        self.per_client[client] += 1
        self.waiting[proto] = proto.loop.time()
        if not self._sweeping:
            self._sweeping = True
            proto.loop.call_later(SWEEP_EVERY_S, self._sweep, proto.loop)
        return True

    def head_received(self, proto: "GuardedH11Protocol") -> None:
        if self.waiting.pop(proto, None) is not None:
            self.receiving[proto] = proto.loop.time()

    def idle_again(self, proto: "GuardedH11Protocol") -> None:
        """Its response was sent and the connection stays open: the next request's head is due."""
        if proto in self.open:
            self.receiving.pop(proto, None)
            self.waiting[proto] = proto.loop.time()
            self.waiting.move_to_end(proto)

    def forget(self, proto: "GuardedH11Protocol") -> None:
        client = self.open.pop(proto, None)
        if client is not None:
            self.per_client[client] -= 1
            if self.per_client[client] <= 0:
                del self.per_client[client]
        self.waiting.pop(proto, None)
        self.receiving.pop(proto, None)

    # -- decisions ---------------------------------------------------------------------------
    def _evict_oldest(self, client: str | None) -> bool:
        """Close the connection (of ``client``, or anyone's) that has waited longest for its
        request head, if it has waited ``eviction_grace_s`` at least (a younger one may have
        its request in the socket, unread yet); False if there is none."""
        oldest_allowed = asyncio.get_running_loop().time() - self.limits.eviction_grace_s
        for proto, since in self.waiting.items():
            if since > oldest_allowed:
                return False
            if client is None or self.open.get(proto) == client:
                self._close(proto, _TIMED_OUT, "evicted")
                return True
        return False

    def _refuse(self, proto: "GuardedH11Protocol") -> bool:
        self.counts["refused"] += 1
        proto.transport.write(_REFUSED)
        proto.transport.close()
        return False

    def _close(self, proto: "GuardedH11Protocol", answer: bytes, why: str) -> None:
        self.counts[why] += 1
        self.forget(proto)
        if not proto.transport.is_closing():
            proto.transport.write(answer)
            proto.transport.close()

    def _sweep(self, loop: asyncio.AbstractEventLoop) -> None:
        now = loop.time()
        head_deadline = now - self.limits.header_timeout_s
        while self.waiting:
            proto, since = next(iter(self.waiting.items()))
            if since > head_deadline:
                break
            self._close(proto, _TIMED_OUT, "timed_out")
        body_deadline = now - self.limits.body_timeout_s
        for proto, since in list(self.receiving.items()):
            if since < body_deadline and proto.conn.their_state is h11.SEND_BODY:
                self._close(proto, _TIMED_OUT, "timed_out")
        if self.open:
            loop.call_later(SWEEP_EVERY_S, self._sweep, loop)
        else:
            self._sweeping = False


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, reporting to a ``ConnectionGuard`` (``guard``, set on the
    subclass ``ConnectionGuard.protocol_class`` makes)."""

    guard: ConnectionGuard

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.guard.admit(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.guard.forget(self)
        super().connection_lost(exc)

    def handle_events(self) -> None:
        super().handle_events()
        if self.conn.their_state is not h11.IDLE:  # the request's head has arrived (or the request was refused)
            self.guard.head_received(self)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self.guard.idle_again(self)


class RepeatFilter(logging.Filter):
    """Let a log line through at most ``burst`` times per ``interval_s`` (per logger, level and
    first line of the message as formatted: lines that differ there, e.g. naming another rig,
    are not the same line); the next one that passes says how many were suppressed."""

    def __init__(self, interval_s: float = 10.0, burst: int = 5, max_keys: int = 1024,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.interval_s, self.burst, self.max_keys = interval_s, burst, max_keys
        self.clock = clock  # time.monotonic; a test passes its own
        self._seen: dict[tuple, list] = {}  # key -> [window start, passed in window, suppressed]

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            first = record.getMessage().split("\n", 1)[0][:200]
        except Exception:  # noqa: BLE001 - a filter must never raise (a bad format is the handler's to report)
            return True
        key = (record.name, record.levelno, first)
        now = self.clock()
        state = self._seen.get(key)
        if state is None or now - state[0] >= self.interval_s:
            suppressed = state[2] if state else 0
            if len(self._seen) >= self.max_keys:
                self._seen.clear()
            self._seen[key] = [now, 1, 0]
            if suppressed:
                record.msg = f"{record.msg} ({suppressed} similar lines suppressed in the last {self.interval_s:g} s)"
            return True
        if state[1] < self.burst:
            state[1] += 1
            return True
        state[2] += 1
        return False


def rate_limit_logs(filter_: RepeatFilter | None = None, names: tuple[str, ...] = ("", "uvicorn", "uvicorn.error",
                                                                                    "uvicorn.access", "asyncio")) -> RepeatFilter:
    """Attach one ``RepeatFilter`` to every handler of the named loggers (root included)."""
    filter_ = filter_ or RepeatFilter()
    for name in names:
        for handler in logging.getLogger(name).handlers:
            if filter_ not in handler.filters:
                handler.addFilter(filter_)
    return filter_
