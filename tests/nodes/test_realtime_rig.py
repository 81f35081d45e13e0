"""A rig's nodes drive the scheduling class of their loop (services/transport/realtime.py): its
threads under SCHED_FIFO through a realtime campaign, never through a fast one."""

from __future__ import annotations

import threading

from ra2vipas.services.transport.realtime import RealtimeClass
from ra2vipas.services.transport.runtime import EventLoop
from tests.nodes.conftest import run_to_end
from tests.unit.test_realtime_class import Calls


def test_a_rigs_loop_is_fifo_through_a_realtime_campaign_and_never_through_a_fast_one(mesh):
    """Both nodes of a rig drive the rule: its threads (the worker, the sensors' tick timer) go to
    SCHED_FIFO when a realtime episode starts and back when it ends; a fast campaign never asks."""
    calls = Calls()
    loops: list[EventLoop] = []

    class Loop(EventLoop):
        def __init__(self, name: str, inline: bool = False, realtime_priority: int = 0) -> None:
            super().__init__(name, inline)
            self.realtime = RealtimeClass(realtime_priority, calls)
            self.realtime.add_thread(self._thread.native_id)
            loops.append(self)

    import ra2vipas.services.controller.node as controller_node
    import ra2vipas.services.sensors.node as sensors_node

    original = (controller_node.EventLoop, sensors_node.EventLoop)
    controller_node.EventLoop = sensors_node.EventLoop = Loop
    try:
        _, store, scheduler = mesh({"rig-1": {"sensors": {"realtime_priority": 10}, "controller": {"realtime_priority": 10}}}, window=1)
    finally:
        controller_node.EventLoop, sensors_node.EventLoop = original
    assert len(loops) == 2
    # this mesh's threads (another test's nodes in this process may have threads of the same names)
    threads = {tid for loop in loops for tid in loop.realtime._threads}
    names = {t.name for t in threading.enumerate() if t.native_id in threads}
    assert len(threads) == 3 and names == {"sensors-rig-1", "controller-rig-1", "sensors-timer-rig-1"}, names
    small = {"steps": 6, "n_train": 200, "n_targets": 8}
    c = run_to_end(store, scheduler, "paper", small, 2, 5, ["ra2vipas"])
    assert c["status"] == "done", c["error"]
    assert calls.take() == [] and not any(loop.realtime.active for loop in loops)
    c = run_to_end(store, scheduler, "paper", {**small, "rf_period_s": 0.02}, 2, 5, ["ra2vipas"], mode="realtime")
    assert c["status"] == "done", c["error"]
    for loop in loops:
        assert loop.wait_idle()
    got = calls.take()
    assert {tid for tid, on, _ in got if on} == threads  # every thread on a realtime step's path
    assert all(p == 10 for tid, on, p in got if on)
    for tid in threads:  # each went to FIFO and back, as often as episodes started and ended, and ended ordinary
        mine = [on for t, on, _ in got if t == tid]
        assert mine and mine[0] is True and mine[-1] is False
        assert all(a != b for a, b in zip(mine, mine[1:]))
    assert not any(loop.realtime.active for loop in loops)
