"""A rig whose sensors and controller share one process, one Zenoh session and one worker
(``ra2vipas rig``, ``up``'s default layout; issue 22): a command and a measurement reach the
other node through the session's own delivery, on the worker, never inside the publisher's
handler; every one of them still goes on the network under its documented key, once; the
campaign equals ``simulate`` value for value; both liveliness tokens are the session's."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, Measurement
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import key_matches
from ra2vipas.services.transport.runtime import EventLoop
from ra2vipas.services.transport.zenoh_bus import ZenohBus
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end

SMALL = {"steps": 20, "n_train": 200, "n_targets": 8}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _SessionBus:
    """A bus that, like a Zenoh session, delivers a put to its own inline subscribers inside
    ``publish`` on the publisher's thread, and a message ``from_network`` on another thread."""

    def __init__(self) -> None:
        self.subs: list = []

    def subscribe_inline(self, key, callback):
        self.subs.append((key, callback))
        return self

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        for pattern, callback in list(self.subs):
            if key_matches(pattern, key):
                callback(key, payload)

    def from_network(self, key: str, payload: bytes) -> None:
        t = threading.Thread(target=self.publish, args=(key, payload))
        t.start()
        t.join()

    def undeclare(self) -> None:
        self.subs.clear()


def test_an_inline_delivery_runs_after_the_publishing_handler_on_the_same_worker():
    bus, loop = _SessionBus(), EventLoop("rig-inline", inline=True)
    trace: list[str] = []
    threads: set[str] = set()
    done = threading.Event()

    def on_a(payload: bytes) -> None:  # the "controller": answers b with a
        threads.add(threading.current_thread().name)
        n = int(payload)
        trace.append(f"a{n}<")
        if n < 50:
            bus.publish("data/r/b", f"{n + 1}".encode())
        else:
            done.set()
        trace.append(f"a{n}>")

    def on_b(payload: bytes) -> None:  # the "sensors"
        threads.add(threading.current_thread().name)
        trace.append(f"b{int(payload)}<")
        bus.publish("data/r/a", payload)
        trace.append(f"b{int(payload)}>")

    try:
        loop.feed(bus, "data/r/a", on_a)
        loop.feed(bus, "data/r/b", on_b)
        loop.post(bus.publish, "data/r/a", b"0")
        assert done.wait(5)
        assert loop.wait_idle(5)
        # never re-entered: each handler ends before the next one starts, in the messages' order
        assert trace[::2] == ["a0<"] + [s for n in range(1, 51) for s in (f"b{n}<", f"a{n}<")]
        assert all(enter[:-1] == leave[:-1] for enter, leave in zip(trace[::2], trace[1::2]))
        assert threads == {"rig-inline"}
        # a message from another thread (the network) is posted to the same worker
        bus.from_network("data/r/b", b"99")
        assert loop.wait_idle(5)
        assert "b99<" in trace and threads == {"rig-inline"}
    finally:
        loop.stop()


def test_a_one_session_rig_publishes_every_step_on_the_network_and_equals_simulate(tmp_path):
    port = _free_port()
    base = {"multicast_scouting": False}
    rig_bus = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    hub = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    loop = EventLoop("rig-rig-7", inline=True)
    seen: Counter = Counter()
    store = Store(str(tmp_path / "rig.db"))
    nodes: list = []
    scheduler = None
    try:
        # what anyone else on the network sees of the rig's step traffic
        hub.subscribe(keys.measurement("rig-7"), lambda _k, p: seen.update([("m", *_step(Measurement, p))]))
        hub.subscribe(keys.command("rig-7"), lambda _k, p: seen.update([("c", *_step(Command, p))]))
        nodes += [ControllerNode(rig_bus, "rig-7", loop=loop), SensorsNode(rig_bus, "rig-7", loop=loop), LearnerNode(hub)]
        deadline = time.monotonic() + 20
        alive: list[str] = []
        while time.monotonic() < deadline:
            alive = sorted(str(r.ok.key_expr) for r in hub.session.liveliness().get(keys.alive_all(), timeout=2.0) if r.ok)
            if keys.alive("controller", "rig-7") in alive and keys.alive("sensors", "rig-7") in alive:
                break
            time.sleep(0.1)
        assert {keys.alive("controller", "rig-7"), keys.alive("sensors", "rig-7")} <= set(alive), alive
        scheduler = Scheduler(hub, store, window=3)
        algorithms = ["ra2vipas", "rapas", "sweep"]
        c = run_to_end(store, scheduler, "paper", SMALL, 3, 21, algorithms)
        assert c["status"] == "done", c["error"]
        assert untimed(c["results"]) == untimed(run_campaign("paper", build_scenario("paper", SMALL), 3, 21, algorithms))
        episodes = {eid for _, eid, _ in seen}
        assert len(episodes) == 3 * len(algorithms)
        time.sleep(0.2)  # the last publications are on their way to the observer
        for eid in episodes:  # every command and every measurement went out once, under its key
            assert sorted(s for kind, e, s in seen if kind == "c" and e == eid) == list(range(SMALL["steps"]))
            assert sorted(s for kind, e, s in seen if kind == "m" and e == eid) == list(range(SMALL["steps"]))
        assert set(seen.values()) == {1}, "a message seen twice"
    finally:
        if scheduler is not None:
            scheduler.close()
        for n in nodes:
            n.close()
        loop.stop()
        rig_bus.close()
        hub.close()


def _step(schema, payload: bytes) -> tuple[str, int]:
    m = schema.model_validate_json(payload)
    return m.episode_id, m.step
