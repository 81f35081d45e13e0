"""The access control grants everything the real nodes do: a campaign on the in-memory bus,
each node behind a recorder of what it sends and declares, and every such action (and every
delivery it causes) checked against the policy of the node's identity."""

from __future__ import annotations

import time

import zenoh

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.acl import EGRESS, INGRESS, access_control, standard_identities
from ra2vipas.services.transport.bus import MemoryBus
from tests.unit.test_acl import allowed


class Recorder:
    """A ``Bus`` that records (message, key) for what its node does, then delegates."""

    def __init__(self, bus: MemoryBus, user: str, log: list) -> None:
        self.bus, self.user, self.log = bus, user, log

    def _note(self, message: str, key: str) -> None:
        self.log.append((self.user, message, key))

    def publish(self, key, payload, express=False):
        self._note("put", key)
        return self.bus.publish(key, payload, express)

    def subscribe(self, key, callback):
        self._note("declare_subscriber", key)
        return self.bus.subscribe(key, callback)

    def serve(self, key, handler):
        self._note("declare_queryable", key)
        return self.bus.serve(key, handler)

    def query(self, key, payload, timeout, callback):
        self._note("query", key)
        return self.bus.query(key, payload, timeout, callback)

    def announce(self, key):
        self._note("liveliness_token", key)
        return self.bus.announce(key)

    def watch_alive(self, key, callback):
        self._note("declare_liveliness_subscriber", key)
        return self.bus.watch_alive(key, callback)

    def close(self):
        pass


def _intersects(a: str, b: str) -> bool:
    return zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))


def test_a_campaign_needs_nothing_the_policy_does_not_grant(tmp_path):
    identities = standard_identities(["rig-1"])
    policy = access_control(identities)
    bus, log = MemoryBus(), []
    store = Store(str(tmp_path / "acl.db"))
    nodes = [SensorsNode(Recorder(bus, "rig-1", log), "rig-1"), ControllerNode(Recorder(bus, "rig-1", log), "rig-1"),
             LearnerNode(Recorder(bus, "learner", log))]
    scheduler = Scheduler(Recorder(bus, "orchestrator", log), store, window=2)
    try:
        overrides = {"steps": 10, "n_train": 150, "n_targets": 6}
        cid = store.create_campaign(preset="paper", overrides=overrides, scenario=build_scenario("paper", overrides).model_dump(mode="json"),
                                    algorithms=["ra2vipas", "rapas"], tests=2, seed=3, mode="fast")
        scheduler.submit(cid)
        deadline = time.monotonic() + 120
        while store.campaign(cid)["status"] not in ("done", "failed") and time.monotonic() < deadline:
            time.sleep(0.05)
        assert store.campaign(cid)["status"] == "done", store.campaign(cid)["error"]
    finally:
        scheduler.close()
        for n in nodes:
            n.close()
        bus.close()
        store.close()

    actions = sorted(set(log))
    messages = {m for _, m, _ in actions}
    assert {"put", "declare_subscriber", "declare_queryable", "query", "liveliness_token", "declare_liveliness_subscriber"} <= messages
    for user, message, key in actions:  # what each identity sends (ingress at the router)
        assert allowed(policy, user, INGRESS, message, key), (user, message, key)
        if message == "declare_queryable":  # its replies carry the queryable's key
            assert allowed(policy, user, INGRESS, "reply", key), (user, key)
    subs = [(u, k) for u, m, k in actions if m == "declare_subscriber"]
    servers = [(u, k) for u, m, k in actions if m == "declare_queryable"]
    watchers = [(u, k) for u, m, k in actions if m == "declare_liveliness_subscriber"]
    for sender, message, key in actions:  # what the router delivers to others (egress)
        if message == "put":
            for user, pattern in subs:
                if _intersects(pattern, key):
                    assert allowed(policy, user, EGRESS, "put", key), (user, key)
            assert any(_intersects(p, key) for _, p in subs), f"nobody subscribes to {key}"
        elif message == "query":
            reached = [(user, served) for user, served in servers if _intersects(served, key)]
            assert reached, f"no queryable for {key}"
            for user, served in reached:
                assert allowed(policy, user, EGRESS, "query", key), (user, key)
                assert allowed(policy, sender, EGRESS, "reply", served), (sender, served)
        elif message == "liveliness_token":
            for user, pattern in watchers:
                if _intersects(pattern, key):
                    assert allowed(policy, user, EGRESS, "liveliness_token", key), (user, key)
