"""A rig whose sensors and controller share one process, one Zenoh session and one worker
(``ra2vipas rig``, ``up``'s default layout; issue 22): a command and a measurement reach the
other node on the worker, never inside the publisher's handler, as the message itself
(``EventLoop.send``: no JSON, no validation again); one lockstep exchange runs depth first;
every one of them still goes on the network under its documented key, once, while anyone
there subscribes, and only then is it encoded; the campaign equals ``simulate`` value for value
either way; both liveliness tokens are the session's."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter

import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, Measurement, dump
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


class _RemoteBus(_SessionBus):
    """A ``_SessionBus`` that also puts for other sessions only (``publish_remote``), while
    ``matching`` (a subscriber elsewhere)."""

    def __init__(self) -> None:
        super().__init__()
        self.matching = False
        self.remote: list[tuple[str, bytes]] = []

    def publish_remote(self, key: str, encode, express: bool = False) -> bool:
        if self.matching:
            self.remote.append((key, encode()))
        return self.matching


def test_send_hands_the_other_node_the_message_itself_and_encodes_only_for_a_subscriber_elsewhere():
    bus, loop = _RemoteBus(), EventLoop("rig-send", inline=True)
    got: list = []
    threads: set[str] = set()
    inside: list[bool] = []
    sending = threading.local()

    def on_command(payload) -> None:
        threads.add(threading.current_thread().name)
        inside.append(getattr(sending, "now", False))
        got.append(payload)

    def send(message) -> None:
        sending.now = True
        loop.send(bus, "data/r/command", message)
        sending.now = False

    try:
        loop.feed(bus, "data/r/command", on_command)
        first = Command(episode_id="e", step=0, pan_rad=0.5)
        loop.post(send, first)
        assert loop.wait_idle(5)
        assert got == [first] and got[0] is first  # the object itself: nothing encoded, nothing decoded
        assert bus.remote == [] and threads == {"rig-send"} and inside == [False]
        bus.matching = True  # someone elsewhere subscribes: the JSON goes out too, once
        second = Command(episode_id="e", step=1, pan_rad=-0.5)
        loop.post(send, second)
        assert loop.wait_idle(5)
        assert got[-1] is second and bus.remote == [("data/r/command", dump(second))]
        # from another thread (not a handler of the loop), a send is an ordinary publication
        bus.matching = False
        send(first)
        assert loop.wait_idle(5)
        assert got[-1] == dump(first)
    finally:
        loop.stop()


def test_an_inline_exchange_runs_depth_first_and_a_new_one_waits_its_turn():
    """Each message a handler of an inline delivery sends runs next (one episode's steps back to
    back); what a posted event's handler sends (an episode's first command) queues behind the
    exchanges already running, so none of them waits behind episodes started after it."""
    bus, loop = _RemoteBus(), EventLoop("rig-depth", inline=True)
    trace: list[str] = []
    done = threading.Event()

    def on_step(message) -> None:
        name, n = message
        trace.append(f"{name}{n}")
        if n < 5:
            loop.send(bus, "data/r/step", (name, n + 1))
        elif name == "c":
            done.set()

    try:
        loop.feed(bus, "data/r/step", on_step)
        gate = threading.Event()
        loop.post(gate.wait, 5)  # the three starts queue while the worker is held
        for name in "abc":
            loop.post(loop.send, bus, "data/r/step", (name, 0))
        gate.set()
        assert done.wait(5)
        assert trace == [f"{name}{n}" for name in "abc" for n in range(6)]
    finally:
        loop.stop()


def test_publish_remote_reaches_other_sessions_only_and_only_while_one_subscribes():
    port = _free_port()
    base = {"multicast_scouting": False}
    a = ZenohBus(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{port}",), **base))
    b = ZenohBus(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",), **base))
    own: list[bytes] = []
    other: list[bytes] = []
    encoded: list[int] = []

    def encode(n: int):
        def payload() -> bytes:
            encoded.append(n)
            return f"{n}".encode()

        return payload

    try:
        a.subscribe("data/r/measurement", lambda _k, p: own.append(p))
        assert a.publish_remote("data/r/measurement", encode(1)) is False  # nobody elsewhere: not even encoded
        b.subscribe("data/r/measurement", lambda _k, p: other.append(p))
        deadline = time.monotonic() + 5
        while not a.publish_remote("data/r/measurement", encode(2)) and time.monotonic() < deadline:
            time.sleep(0.01)
        deadline = time.monotonic() + 5
        while not other and time.monotonic() < deadline:
            time.sleep(0.01)
        assert other == [b"2"] and encoded == [2]
        assert own == []  # never this session's own subscribers: the caller hands them the message itself
    finally:
        a.close()
        b.close()


def test_a_client_rig_puts_its_first_step_for_a_subscriber_that_was_there_before_its_token():
    """The rig as ``ra2vipas up`` runs it: a Zenoh client of a router. Whoever subscribed to its
    step keys before it announced itself (a recorder: ``campaign start --record``) gets the
    first message it sends once someone who saw its token starts it. A client's matching status
    says no subscriber until the router has answered the interest the publisher declared, so a
    publisher declared at the first put could skip it (a fresh-clone run: a recording without
    the first episode's step-0 measurement); the rig's publishers are declared when its node
    subscribes, before the token (``ZenohBus.prepare_remote``). Several fresh rig sessions: the
    skip was a race each of them could lose."""
    port = _free_port()
    base = {"multicast_scouting": False}
    router = ZenohBus(ZenohSettings(mode="router", listen=(f"tcp/127.0.0.1:{port}",), **base))
    client = {"mode": "client", "connect": (f"tcp/127.0.0.1:{port}",), **base}
    observer = ZenohBus(ZenohSettings(**client))
    seen: list[str] = []
    up: set[str] = set()
    try:
        observer.subscribe(f"{keys.PREFIX}/data/*/command", lambda _k, p: seen.append(Command.model_validate_json(p).episode_id))
        observer.watch_alive(keys.alive_all(), lambda k, alive: up.add(k) if alive else up.discard(k))
        for n in range(8):
            rig, eid = f"rig-{n}", f"c.{n}.rapas.1.first"
            rig_bus = ZenohBus(ZenohSettings(**client))
            loop = EventLoop(f"rig-{rig}", inline=True)
            try:
                got: list = []
                loop.feed(rig_bus, keys.command(rig), got.append)  # the "sensors"
                # the "controller": on the start, its first command (``ControllerNode._begin``)
                rig_bus.subscribe(keys.episode_control(rig), lambda _k, _p, rig=rig, eid=eid, loop=loop, bus=rig_bus: loop.post(
                    lambda: loop.send(bus, keys.command(rig), Command(episode_id=eid, step=0, pan_rad=0.0))))
                rig_bus.announce(keys.alive("sensors", rig))
                deadline = time.monotonic() + 10
                while keys.alive("sensors", rig) not in up and time.monotonic() < deadline:
                    time.sleep(0.005)
                assert keys.alive("sensors", rig) in up
                observer.publish(keys.episode_control(rig), b"start")  # the orchestrator, once it saw the token
                deadline = time.monotonic() + 10
                while eid not in seen and time.monotonic() < deadline:
                    time.sleep(0.005)
                assert len(got) == 1, "the rig's own node did not get the command"
                assert seen.count(eid) == 1, f"round {n}: the first command never reached the subscriber ({seen})"
            finally:
                loop.stop()
                rig_bus.close()
    finally:
        observer.close()
        router.close()


@pytest.mark.parametrize("observed", [True, False], ids=["observed", "unobserved"])
def test_a_one_session_rig_publishes_every_step_on_the_network_and_equals_simulate(tmp_path, observed):
    """Observed (another session subscribes to the rig's step keys), every command and
    measurement goes out once; unobserved, none is even encoded; the results are the same."""
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
        if observed:
            hub.subscribe(keys.measurement("rig-7"), lambda _k, p: seen.update([("m", *_step(Measurement, p))]))
            hub.subscribe(keys.command("rig-7"), lambda _k, p: seen.update([("c", *_step(Command, p))]))
        puts = Counter()
        remote = rig_bus.publish_remote

        def counted(key, encode, express=False):
            put = remote(key, encode, express)
            puts[key] += put
            return put

        rig_bus.publish_remote = counted
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
        if not observed:
            assert not seen and sum(puts.values()) == 0, puts
            return
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
