"""Never block Zenoh's threads (issue 14): a node's handlers run on its own worker
(``runtime.EventLoop``), so a handler stuck on a slow disk or a long transaction neither delays
what the bus delivers to other nodes of the process nor loses or reorders what it delivers to
the stuck node itself."""

from __future__ import annotations

import socket
import threading
import time

from ra2vipas.services.transport.runtime import EventLoop
from ra2vipas.services.transport.zenoh_bus import ZenohBus
from ra2vipas.services.transport.zenoh_config import ZenohSettings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_post_returns_while_a_handler_blocks_and_order_is_kept():
    loop = EventLoop("test-loop")
    release, started = threading.Event(), threading.Event()
    ran: list[int] = []

    def stuck() -> None:
        started.set()
        release.wait(30)

    try:
        loop.post(stuck)
        assert started.wait(5)
        posted = threading.Event()

        def poster() -> None:  # what a Zenoh callback thread does: post and return
            for i in range(1000):
                loop.post(ran.append, i)
            posted.set()

        threading.Thread(target=poster, daemon=True).start()
        assert posted.wait(5), "posting waited for the stuck handler"
        assert ran == [] and loop.backlog() >= 1000  # nothing ran past the stuck handler...
        release.set()
        assert loop.wait_idle(10)
        assert ran == list(range(1000))  # ...and then everything, in arrival order
    finally:
        release.set()
        loop.stop()


def test_a_stuck_node_does_not_stall_delivery_to_another_over_zenoh():
    """Two nodes of one process share a Zenoh session (as the rig command's sensors and
    controller may); the first node's handler blocks. Zenoh keeps handing over every sample,
    the second node's are handled, the first node's wait in its queue, all of them, in order
    (a handler run on Zenoh's callback thread would hold the stuck node's later samples in
    Zenoh instead)."""
    port = _free_port()
    base = {"multicast_scouting": False}
    publisher = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    receiver = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    slow, fast = EventLoop("slow-node"), EventLoop("fast-node")
    release = threading.Event()
    slow_got: list[bytes] = []
    fast_got: list[bytes] = []
    try:
        def slow_handler(payload: bytes) -> None:
            release.wait(30)  # a full disk, a long SQLite transaction
            slow_got.append(payload)

        delivered: list[bytes] = []  # what Zenoh handed the slow node's subscription

        def on_slow(key: str, payload: bytes) -> None:
            delivered.append(payload)
            slow.post(slow_handler, payload)

        receiver.subscribe("test/slow", on_slow)
        receiver.subscribe("test/fast", lambda key, payload: fast.post(fast_got.append, payload))
        deadline = time.monotonic() + 10
        while not fast_got and time.monotonic() < deadline:  # until the subscriptions are routed
            publisher.publish("test/fast", b"hello")
            time.sleep(0.05)
        assert fast_got, "no route between the two peers"
        fast_got.clear()
        for i in range(20):
            publisher.publish("test/slow", f"{i}".encode())
        for i in range(200):
            publisher.publish("test/fast", f"{i}".encode())
        deadline = time.monotonic() + 10
        while len(fast_got) < 200 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert fast_got == [f"{i}".encode() for i in range(200)], "delivery to the other node stalled"
        while len(delivered) < 20 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert delivered == [f"{i}".encode() for i in range(20)], "delivery to the stuck node's subscription stalled"
        assert slow_got == []  # still stuck in its first handler
        release.set()
        assert slow.wait_idle(10)
        assert slow_got == [f"{i}".encode() for i in range(20)]
    finally:
        release.set()
        slow.stop()
        fast.stop()
        receiver.close()
        publisher.close()
