"""A Zenoh query that a matched node does not answer in time ends with the querier's own
"Timeout" error, which the bus marks ``timed_out``: the descriptor and policies logic (issue 18's
re-asks and the controller's fallback) count it as no answer, as they count a query that matched
no node, and unlike an error a node sent (a CI failure: a 3 s link cut to the controller right as
a campaign's descriptor query went out made the whole campaign undescribed)."""

from __future__ import annotations

import socket
import threading
import time

from ra2vipas.services.transport.bus import QueryError, answered
from ra2vipas.services.transport.zenoh_bus import ZenohBus
from ra2vipas.services.transport.zenoh_config import ZenohSettings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _query(bus: ZenohBus, key: str, timeout: float) -> list:
    done, out = threading.Event(), []
    bus.query(key, b"", timeout, lambda replies: (out.extend(replies), done.set()))
    assert done.wait(timeout + 10)
    return out


def test_a_query_a_node_does_not_answer_in_time_is_marked_timed_out_and_an_error_it_sends_is_not():
    port = _free_port()
    base = {"multicast_scouting": False}
    node = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    asker = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    release = threading.Event()

    def slow(_key, _payload):
        release.wait(5)  # answers after the querier gave up
        return b"{}"

    def failing(_key, _payload):
        raise QueryError("sensors busy")

    try:
        node.serve("rig/slow/info", slow)
        node.serve("rig/failing/info", failing)
        deadline = time.monotonic() + 10
        while not answered(_query(asker, "rig/failing/info", 1.0)):  # the queryables are routed to the asker
            assert time.monotonic() < deadline
        timed_out = _query(asker, "rig/slow/info", 0.5)
        release.set()
        assert [(r.ok, r.timed_out) for r in timed_out] == [(False, True)] and answered(timed_out) == []
        failed = _query(asker, "rig/failing/info", 2.0)
        assert [(r.ok, r.timed_out, r.payload) for r in failed] == [(False, False, b"sensors busy")] and answered(failed) == failed
        assert _query(asker, "rig/nobody/info", 0.5) == []  # no queryable: no reply at all
    finally:
        release.set()
        asker.close()
        node.close()
