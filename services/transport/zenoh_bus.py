"""``Bus`` over a Zenoh session (eclipse-zenoh 1.x Python API).

Payloads are JSON bytes published with encoding ``application/json``. Queryable handlers run
on a small thread pool and reply from there (a Zenoh query stays open until its ``Query``
object is dropped), so a long handler such as a training episode never blocks Zenoh's own
threads.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import zenoh

from ra2vipas.services.transport.bus import AliveCallback, Callback, FeedClosed, QueryError, QueryHandler, RepliesCallback, Reply
from ra2vipas.services.transport.zenoh_config import ZenohSettings

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON
ZENOH_QUERY_TIMEOUT = b"Timeout"  # the error reply a Zenoh session gives its own query that timed out (eclipse-zenoh 1.x)

MAX_MESSAGE_BYTES = 1 << 20
"""Largest publication or query payload a node accepts (1 MiB; the largest legitimate message,
an EpisodeStart or a Measurement, is a few kB). Query replies, such as a training stream, are
not limited."""


FEED_CAPACITY = 1 << 16
"""Messages a feed holds before Zenoh's receiving thread waits for its consumer (a node's
per-step traffic is a few messages per episode in flight; a stuck consumer stalls the session's
delivery only after this many)."""

WAKE = b"ra2vipas-wake"
"""The attachment of a feed's wake-up: an empty sample put on the feed's own key, delivered to
this session only (``Locality.SESSION_LOCAL``: it never reaches the network)."""


class _ZenohFeed:
    """``ZenohBus.feed``: a subscriber with a FIFO channel that the consumer's thread reads
    (``recv`` waits without holding the GIL), so a sample goes from Zenoh's receiving thread
    to the node's worker with no Python callback thread in between."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self._session = session
        self._wake_key = key.replace("**", "_wake").replace("*", "_wake")  # a key the subscription matches
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(FEED_CAPACITY))
        self._early: deque = deque()  # messages that arrived while ``wakes`` checked the wake-up

    @staticmethod
    def _is_wake(sample: zenoh.Sample) -> bool:
        attachment = sample.attachment
        return attachment is not None and len(sample.payload) == 0 and attachment.to_bytes() == WAKE

    def wakes(self) -> bool:
        """Whether a wake-up reaches this feed (a session-local put is delivered before ``put``
        returns; a client configuration whose own access control forbade the put would leave
        the worker asleep, so the bus then subscribes the usual way instead)."""
        self.wake()
        for _ in range(3):
            sample = self._sub.try_recv()
            while sample is not None:
                if self._is_wake(sample):
                    return True
                self._early.append(sample)
                sample = self._sub.try_recv()
            time.sleep(0.01)
        return False

    def _take(self, sample: "zenoh.Sample | None"):
        if sample is None or self._is_wake(sample):
            return None
        payload = sample.payload
        if len(payload) > MAX_MESSAGE_BYTES:
            log.warning("dropping a %d-byte message on %s (limit %d)", len(payload), sample.key_expr, MAX_MESSAGE_BYTES)
            return None
        return str(sample.key_expr), payload.to_bytes()

    def recv(self):
        if self._early:
            return self._take(self._early.popleft())
        try:
            sample = self._sub.recv()
        except zenoh.ZError as err:  # undeclared: the channel is empty and closed
            raise FeedClosed(str(err)) from None
        return self._take(sample)

    def try_recv(self):
        if self._early:
            return self._take(self._early.popleft())
        try:
            return self._take(self._sub.try_recv())
        except zenoh.ZError as err:
            raise FeedClosed(str(err)) from None

    def wake(self) -> None:
        try:
            self._session.put(self._wake_key, b"", attachment=WAKE, allowed_destination=zenoh.Locality.SESSION_LOCAL)
        except Exception:  # the session is closing: nothing is waiting any more
            pass

    def undeclare(self) -> None:
        self._sub.undeclare()


class _RemotePublisher:
    """A publisher to other sessions only, and whether any subscriber there matches it now
    (kept by a matching listener: reading a flag costs a step nothing, asking Zenoh a call
    that releases and retakes the GIL).

    A client's matching status says no subscriber until the router has answered the interest
    the publisher declares with it (Zenoh 1.x, ``hat/client/pubsub.rs``: the status counts only
    finalized interests; the data route sends to the router while the interest is pending), so
    a status read right after the declaration can say False with a recorder subscribed, and a put
    skipped on it is lost. ``ZenohBus.prepare_remote`` declares it before the node's liveliness
    token: the router answers the interest before it sees the token, hence before anyone who
    waits for the token can start an episode; the first put reads the status once itself, from
    the routing tables, instead of the flag a listener task updates later."""

    def __init__(self, session: zenoh.Session, key: str, express: bool) -> None:
        self.pub = session.declare_publisher(
            key,
            encoding=JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=express,
            allowed_destination=zenoh.Locality.REMOTE,
        )
        self.matching = True  # until the listener is in place: put rather than miss someone
        self._listener = self.pub.declare_matching_listener(self._on_status)
        self.matching = self.pub.matching_status.matching
        self.checked = False  # the first put reads the status itself (class docstring)

    def _on_status(self, status: "zenoh.MatchingStatus") -> None:
        self.matching = status.matching

    def check(self) -> bool:
        """Whether a subscriber elsewhere matches, from Zenoh's tables (once; then the flag)."""
        self.checked = True
        self.matching = matching = self.pub.matching_status.matching
        return matching

    def undeclare(self) -> None:
        self._listener.undeclare()
        self.pub.undeclare()


class ZenohBus:
    """A ``Bus`` bound to one Zenoh session; ``close`` closes the session."""

    def __init__(self, settings: ZenohSettings, workers: int = 4) -> None:
        self.session = zenoh.open(settings.to_zenoh())
        self._publishers: dict[tuple[str, bool], zenoh.Publisher] = {}
        self._remote_publishers: dict[tuple[str, bool], _RemotePublisher] = {}  # ``publish_remote``'s
        self._declared: list = []
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="zenoh-query")
        self._lock = threading.Lock()
        self._closed = False

    # -- pub/sub -----------------------------------------------------------------------------
    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        """``express`` sends at once instead of waiting up to Zenoh's batching time limit
        (1 ms per hop): for latency-critical traffic such as realtime pan commands."""
        pub = self._publishers.get((key, express))
        if pub is None:
            with self._lock:
                pub = self._publishers.get((key, express))
                if pub is None:
                    pub = self.session.declare_publisher(key, encoding=JSON, congestion_control=zenoh.CongestionControl.BLOCK, express=express)
                    self._publishers[(key, express)] = pub
        pub.put(payload)

    def _remote(self, key: str, express: bool) -> _RemotePublisher:
        remote = self._remote_publishers.get((key, express))
        if remote is None:
            with self._lock:
                remote = self._remote_publishers.get((key, express))
                if remote is None:
                    remote = self._remote_publishers[(key, express)] = _RemotePublisher(self.session, key, express)
        return remote

    def prepare_remote(self, key: str) -> None:
        """Declare ``publish_remote``'s publishers of ``key`` (express or not) now, ahead of its
        first put: a node that will send on ``key`` calls it before its liveliness token
        (``EventLoop.feed``), so Zenoh knows who subscribes before any episode comes
        (``_RemotePublisher``)."""
        for express in (False, True):
            self._remote(key, express)

    def publish_remote(self, key: str, encode: Callable[[], bytes], express: bool = False) -> bool:
        """Put ``encode()`` on ``key`` for other sessions only (never this session's own
        subscribers: the caller hands its own process the message itself), and only while a
        subscriber elsewhere matches ``key`` (Zenoh's matching status, kept by the router's
        declarations; with none, ``encode`` is not even called: Zenoh would send nothing
        anyway). Returns whether it was put. A key not prepared (``prepare_remote``) has its
        publisher declared here: a subscriber may then miss the first puts while the router
        answers the publisher's interest."""
        remote = self._remote(key, express)
        if not (remote.matching if remote.checked else remote.check()):
            return False
        remote.pub.put(encode())
        return True

    @staticmethod
    def _on_sample(key: str, callback: Callback) -> Callable[[zenoh.Sample], None]:
        """``callback(key, payload)`` for each sample of at most ``MAX_MESSAGE_BYTES``; a failure
        is logged, never raised into Zenoh's thread (nor a publisher's ``put``)."""
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                payload = sample.payload
                if len(payload) > MAX_MESSAGE_BYTES:
                    log.warning("dropping a %d-byte message on %s (limit %d)", len(payload), sample.key_expr, MAX_MESSAGE_BYTES)
                    return
                callback(str(sample.key_expr), payload.to_bytes())
            except Exception:  # a bad message must never kill Zenoh's thread
                log.exception("subscriber callback on %s failed", key)

        return on_sample

    def subscribe(self, key: str, callback: Callback):
        sub = self.session.declare_subscriber(key, self._on_sample(key, callback))
        self._declared.append(sub)
        return sub

    def subscribe_inline(self, key: str, callback: Callback):
        """Like ``subscribe``, but ``callback(key, payload)`` runs on the thread that delivers
        the sample, with no Python callback thread in between: for a put by this same session
        (Zenoh 1.x delivers it to the session's own matching subscribers before ``put``
        returns, besides sending it to the network), the publisher's own thread, inside its
        ``put``; for a sample from the network, Zenoh's receiving thread. The callback must
        only hand the message on (``EventLoop.feed`` on an ``inline`` loop queues it)."""
        sub = self.session.declare_subscriber(key, zenoh.handlers.Callback(self._on_sample(key, callback), indirect=False))
        self._declared.append(sub)
        return sub

    def feed(self, key: str) -> "_ZenohFeed | None":
        """Samples on keys matching ``key`` for the caller's thread to take (``bus.Feed``);
        None if this session cannot wake its consumer (``_ZenohFeed.wakes``): subscribe then."""
        f = _ZenohFeed(self.session, key)
        if not f.wakes():
            log.warning("no wake-up reaches a feed on %s (the session's own access control?): subscribing instead", key)
            f.undeclare()
            return None
        self._declared.append(f)
        return f

    # -- query/reply -------------------------------------------------------------------------
    def serve(self, key: str, handler: QueryHandler):
        def answer(query: zenoh.Query) -> None:
            try:
                if query.payload is not None and len(query.payload) > MAX_MESSAGE_BYTES:
                    query.reply_err(b"query payload too large", encoding=zenoh.Encoding.TEXT_PLAIN)
                    return
                payload = query.payload.to_bytes() if query.payload is not None else b""
                try:
                    reply = handler(str(query.key_expr), payload)
                except QueryError as err:
                    query.reply_err(str(err).encode(), encoding=zenoh.Encoding.TEXT_PLAIN)
                except Exception as err:  # never leave a query unanswered
                    log.exception("query handler on %s failed", key)
                    query.reply_err(f"internal error: {type(err).__name__}".encode(), encoding=zenoh.Encoding.TEXT_PLAIN)
                else:
                    if reply is not None:  # None: not for this queryable, no reply
                        query.reply(key, reply, encoding=JSON)
            finally:
                query.drop()

        def on_query(query: zenoh.Query) -> None:
            if self._closed:
                query.drop()
                return
            self._pool.submit(answer, query)

        qbl = self.session.declare_queryable(key, on_query)
        self._declared.append(qbl)
        return qbl

    def query(self, key: str, payload: bytes, timeout: float, callback: RepliesCallback) -> None:
        def run() -> None:
            replies: list[Reply] = []
            try:
                for r in self.session.get(key, payload=payload, encoding=JSON, timeout=timeout, target=zenoh.QueryTarget.BEST_MATCHING):
                    if r.ok is not None:
                        replies.append(Reply(str(r.ok.key_expr), r.ok.payload.to_bytes(), True))
                    elif r.err is not None:
                        # Zenoh ends a query that a matched queryable did not answer in time with its own error "Timeout"
                        text = r.err.payload.to_bytes()
                        replies.append(Reply(key, text, False, timed_out=text == ZENOH_QUERY_TIMEOUT))
            except Exception:
                log.exception("query on %s failed", key)
            callback(replies)

        self._pool.submit(run)

    # -- liveliness --------------------------------------------------------------------------
    def announce(self, key: str):
        token = self.session.liveliness().declare_token(key)
        self._declared.append(token)
        return token

    def watch_alive(self, key: str, callback: AliveCallback):
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("liveliness callback on %s failed", key)

        sub = self.session.liveliness().declare_subscriber(key, on_sample, history=True)
        self._declared.append(sub)
        return sub

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for obj in reversed(self._declared):
            try:
                obj.undeclare()
            except Exception:
                pass
        for pub in (*self._publishers.values(), *self._remote_publishers.values()):
            try:
                pub.undeclare()
            except Exception:
                pass
        self._pool.shutdown(wait=False, cancel_futures=True)
        self.session.close()
