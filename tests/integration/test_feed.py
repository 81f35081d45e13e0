"""A node's per-step traffic taken by its own worker thread (``EventLoop.feed``, issue 22):
every fed message is handled once, in order, on the worker; posted events are not starved by a
busy feed and still wake a worker blocked on it; a closed feed falls back to posts; and over
Zenoh the wake-up never leaves the session (another subscriber of the key sees none)."""

from __future__ import annotations

import socket
import threading
import time

from ra2vipas.services.transport.bus import FeedClosed, MemoryBus
from ra2vipas.services.transport.runtime import EventLoop
from ra2vipas.services.transport.zenoh_bus import ZenohBus
from ra2vipas.services.transport.zenoh_config import ZenohSettings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_fed_messages_run_in_order_on_the_worker_and_posts_still_wake_it():
    bus, loop = MemoryBus(), EventLoop("feed-test")
    got: list[tuple[str, bytes]] = []
    threads: set[str] = set()

    def on_step(payload: bytes) -> None:
        threads.add(threading.current_thread().name)
        got.append(("fed", payload))

    try:
        handle = loop.feed(bus, "data/rig/step", on_step)
        assert loop.wait_idle(5)
        for i in range(300):
            bus.publish("data/rig/step", f"{i}".encode())
        assert bus.wait_idle(5)
        assert loop.wait_idle(5)  # a post wakes the worker blocked in the feed's recv
        assert got == [("fed", f"{i}".encode()) for i in range(300)] and threads == {"feed-test"}
        # the worker is blocked on an empty feed: a post alone must run, at once
        ran = threading.Event()
        loop.post(ran.set)
        assert ran.wait(5)
        handle.undeclare()  # a closed feed: posts keep working
        loop.post(got.append, ("posted", b"after"))
        assert loop.wait_idle(5) and got[-1] == ("posted", b"after")
    finally:
        loop.stop()
        bus.close()


def test_a_busy_feed_does_not_starve_posted_events():
    """Fed messages and posted events take turns: a control message (an EpisodeStart) is not
    held back until the per-step traffic stops."""
    bus, loop = MemoryBus(), EventLoop("feed-turns")
    order: list[str] = []
    gate = threading.Event()

    def on_step(payload: bytes) -> None:
        gate.wait(5)
        order.append(payload.decode())

    try:
        loop.feed(bus, "data/rig/step", on_step)
        assert loop.wait_idle(5)
        for i in range(5):
            bus.publish("data/rig/step", f"s{i}".encode())
        assert bus.wait_idle(5)
        loop.post(order.append, "p0")
        loop.post(order.append, "p1")
        gate.set()
        assert loop.wait_idle(5)
        deadline = time.monotonic() + 5
        while len(order) < 7 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sorted(order) == ["p0", "p1", "s0", "s1", "s2", "s3", "s4"]
        assert [o for o in order if o.startswith("s")] == ["s0", "s1", "s2", "s3", "s4"]  # each source in order
        assert order.index("p1") < order.index("s4"), f"posted events waited for the whole feed: {order}"
    finally:
        gate.set()
        loop.stop()
        bus.close()


def test_a_stopped_loop_ends_while_blocked_on_its_feed():
    bus, loop = MemoryBus(), EventLoop("feed-stop")
    try:
        loop.feed(bus, "data/rig/step", lambda p: None)
        assert loop.wait_idle(5)
        loop.stop(5)
        assert not loop._thread.is_alive()
    finally:
        bus.close()


def test_memory_feed_reports_wake_ups_and_closing():
    bus = MemoryBus()
    try:
        feed = bus.feed("a/b")
        assert feed.try_recv() is None
        bus.publish("a/b", b"x")
        assert bus.wait_idle(5)
        assert feed.recv() == ("a/b", b"x")
        feed.wake()
        assert feed.recv() is None
        feed.undeclare()
        for _ in range(2):
            try:
                feed.recv()
            except FeedClosed:
                pass
            else:
                raise AssertionError("recv on an undeclared feed returned")
    finally:
        bus.close()


def test_zenoh_feed_over_the_network_and_its_wake_up_stays_in_the_session():
    port = _free_port()
    base = {"multicast_scouting": False}
    publisher = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    receiver = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    loop = EventLoop("zenoh-feed")
    fed: list[bytes] = []
    seen_by_publisher: list[bytes] = []
    try:
        loop.feed(receiver, "data/rig-1/command", fed.append)
        publisher.subscribe("data/rig-1/command", lambda _k, p: seen_by_publisher.append(p))
        deadline = time.monotonic() + 10
        while not fed and time.monotonic() < deadline:  # until the subscription is routed
            publisher.publish("data/rig-1/command", b"probe")
            time.sleep(0.05)
        assert fed, "no route between the two peers"
        assert loop.wait_idle(5)
        fed.clear()
        for i in range(200):
            publisher.publish("data/rig-1/command", f"{i}".encode())
            if i % 50 == 0:
                loop.post(lambda: None)  # wake-ups in between
        deadline = time.monotonic() + 10
        while len(fed) < 200 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert fed == [f"{i}".encode() for i in range(200)]
        time.sleep(0.3)
        assert b"" not in seen_by_publisher, "a wake-up left the session"
    finally:
        loop.stop()
        receiver.close()
        publisher.close()


def test_a_zenoh_feed_whose_wake_up_cannot_arrive_falls_back_to_a_subscription(monkeypatch):
    """If a session-local put cannot reach the feed (say the client's own configuration denies
    it), a worker blocked in ``recv`` would never see its posted events: the bus checks the
    wake-up when it declares the feed, and the node subscribes the usual way instead."""
    from ra2vipas.services.transport import zenoh_bus

    port = _free_port()
    base = {"multicast_scouting": False}
    publisher = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    receiver = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    loop = EventLoop("no-wake")
    got: list[bytes] = []
    try:
        monkeypatch.setattr(zenoh_bus._ZenohFeed, "wake", lambda self: None)
        assert receiver.feed("data/rig-1/command") is None
        loop.feed(receiver, "data/rig-1/command", got.append)
        assert loop._feed is None  # subscribed instead
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            publisher.publish("data/rig-1/command", b"probe")
            time.sleep(0.05)
        assert got and loop.wait_idle(5)
        ran = threading.Event()
        loop.post(ran.set)
        assert ran.wait(5)
    finally:
        loop.stop()
        receiver.close()
        publisher.close()
