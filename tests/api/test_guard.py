"""What one HTTP client can hold (``api/guard.py``, issue 18): a deadline for a request's
head, a cap per client address that evicts the connection waiting longest for its head, a
503 when nothing can be evicted, limits that fit the descriptor limit, and repeated log lines
rate-limited. On a real uvicorn server in a thread with a trivial application."""

from __future__ import annotations

import logging
import socket
import threading
import time

import pytest
import uvicorn

from ra2vipas.services.orchestrator.api.guard import ConnectionGuard, GuardLimits, RepeatFilter


async def _app(scope, receive, send):
    if scope["type"] != "http":
        return
    while (await receive()).get("more_body"):  # the whole body first, as a route that parses it does
        pass
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"text/plain")]})
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.fixture()
def server():
    guard = ConnectionGuard(GuardLimits(max_connections=64, max_per_client=4, header_timeout_s=1.0, body_timeout_s=1.5,
                                      eviction_grace_s=0.3))
    config = uvicorn.Config(_app, host="127.0.0.1", port=0, log_level="warning", lifespan="off", http=guard.protocol_class())
    srv = uvicorn.Server(config)
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not srv.started and time.monotonic() < deadline:
        time.sleep(0.02)
    yield srv.servers[0].sockets[0].getsockname()[1], guard
    srv.should_exit = True
    thread.join(10)


def _trickle(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # and never the end of the headers
    return s


def _get(port: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        return s.recv(4096)


def _answer(s: socket.socket) -> bytes:
    s.settimeout(5)
    try:
        return s.recv(4096)
    except OSError:
        return b""


def test_a_request_head_that_does_not_arrive_in_time_is_answered_408(server):
    port, guard = server
    s = _trickle(port)
    start = time.monotonic()
    assert _answer(s).startswith(b"HTTP/1.1 408 ")
    assert time.monotonic() - start >= 0.9  # not before its deadline (1 s); a late one is a slow machine, and _answer waits 5 s
    assert _answer(s) == b""  # and closed
    s.close()
    assert guard.counts["timed_out"] == 1


def test_a_body_that_does_not_arrive_in_time_is_answered_408(server):
    port, guard = server
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.sendall(b"POST / HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n0123456789")  # 10 of 100 bytes, then nothing
    start = time.monotonic()
    assert _answer(s).startswith(b"HTTP/1.1 408 ")
    assert time.monotonic() - start >= 1.4  # not before its deadline (1.5 s)
    s.close()
    assert _get(port).startswith(b"HTTP/1.1 200 ")  # a whole request is served as before


def test_a_client_at_its_cap_loses_its_oldest_waiting_connection_to_a_whole_request(server):
    port, guard = server
    held = [_trickle(port) for _ in range(4)]
    time.sleep(0.4)  # older than the eviction grace
    assert _get(port).startswith(b"HTTP/1.1 200 ")  # a fifth connection: the oldest trickler makes room
    assert _answer(held[0]).startswith(b"HTTP/1.1 408 ")
    for s in held:
        s.close()
    assert guard.counts["evicted"] == 1


def test_a_client_whose_connections_are_all_young_is_refused_503(server):
    port, guard = server
    held = [_trickle(port) for _ in range(4)]
    answer = _get(port)  # the four have just connected: none is evicted, the newcomer is refused
    assert answer.startswith(b"HTTP/1.1 503 ") and b"retry-after: 1" in answer and b"too many connections" in answer
    for s in held:
        s.close()
    assert guard.counts["refused"] == 1


def test_the_limits_fit_the_descriptor_limit():
    limits = GuardLimits(max_connections=1000, max_per_client=256, backlog=2048)
    assert limits.within_fd_limit(20000) == GuardLimits(1000, 256, backlog=2048)
    small = limits.within_fd_limit(1024)  # e.g. a default soft limit that could not be raised
    assert small.max_connections + 2 * small.backlog + 256 <= 1024 and small.max_per_client <= small.max_connections


def test_repeated_log_lines_are_rate_limited():
    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    logger = logging.getLogger("test.guard.repeat")
    logger.propagate = False
    handler = Keep()
    now = [100.0]  # the filter's clock: the 10 000 lines fall in one window however slow the machine is
    handler.addFilter(RepeatFilter(interval_s=0.2, burst=3, clock=lambda: now[0]))
    logger.addHandler(handler)
    try:
        for fd in range(10_000):
            logger.error("socket.accept() out of system resource\nsocket: <fd=%d>", fd)
        logger.error("rig %s lost", "rig-1")
        logger.error("rig %s lost", "rig-2")  # another line: not suppressed
        assert len(records) == 5
        now[0] += 0.25
        logger.error("socket.accept() out of system resource\nsocket: <fd=%d>", 8)
        assert "(9997 similar lines suppressed in the last 0.2 s)" in records[-1]
    finally:
        logger.removeHandler(handler)
