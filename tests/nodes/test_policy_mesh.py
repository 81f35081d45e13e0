"""Policies over the mesh (issue 19): a controller announces the policies it serves
(``ControllerInfo`` on ``rig/{rig}/policies``), the orchestrator hands an episode only to a rig
whose controller serves its policy, and a controller that announces nothing (1.0, 1.1) still
gets the built-ins' episodes."""

from __future__ import annotations

import math
import time

import pytest

from ra2vipas import Policy, PolicyDecision
from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.controller.registry import BUILTINS, UnknownPolicy
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import ControllerInfo, EpisodeResult, EpisodeStart, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
from ra2vipas.services.transport.bus import MemoryBus
from tests.nodes.conftest import run_to_end, settle

SMALL = {"steps": 12, "n_train": 150, "n_targets": 6}
SPIN = f"{__name__}:Spin"


class Spin(Policy):
    """A policy no package registers: it turns a fixed step each sample and names where it looks."""

    name = "spin"

    def step(self, measurement) -> PolicyDecision:
        pan = float(measurement.pan_rad)
        return PolicyDecision(next_pan_rad=math.remainder(pan + 0.5, 2.0 * math.pi), estimate_rad=pan)


class Silent:
    """The bus as a 1.1 controller uses it: it serves no ``rig/{rig}/policies``."""

    def __init__(self, bus) -> None:
        self.bus = bus

    def serve(self, key, handler):
        if key.endswith("/policies"):
            return self
        return self.bus.serve(key, handler)

    def undeclare(self) -> None:
        pass

    def __getattr__(self, name):
        return getattr(self.bus, name)


def _run(store, scheduler, algorithms, tests=4, seed=3) -> dict:
    return run_to_end(store, scheduler, "paper", SMALL, tests, seed, algorithms)


def _rigs_by_policy(store, cid) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for row in store.episode_rows(cid):
        out.setdefault(row["algorithm"], set()).add(row["rig"])
    return out


def test_an_episode_goes_only_to_a_rig_whose_controller_serves_its_policy(mesh):
    """rig-a serves spin and rapas, rig-b every installed policy (not spin): every spin episode
    lands on rig-a at its first attempt (none is sent to rig-b and failed there)."""
    _, store, scheduler = mesh({"rig-a": {"controller": {"policies": [SPIN, "rapas"]}}, "rig-b": {}}, window=2)
    c = _run(store, scheduler, ["spin", "rapas"], tests=6)
    assert c["status"] == "done", c["error"]
    assert _rigs_by_policy(store, c["id"])["spin"] == {"rig-a"}
    assert all(row["attempt"] == 1 for row in store.episode_rows(c["id"]))
    rigs = scheduler.status()["rigs"]
    assert [p["name"] for p in rigs["rig-a"]["policies"]] == ["spin", "rapas"] and rigs["rig-a"]["announced"] == "announced"
    assert "spin" not in [p["name"] for p in rigs["rig-b"]["policies"]]
    assert rigs["rig-a"]["controller_protocol"] == PROTOCOL_VERSION
    # the orchestrator has no spin installed: the results name where rig-a's controller said it came from
    assert c["results"]["policies"] == {"spin": {"package": rigs["rig-a"]["policies"][0]["package"], "version": "?"}}
    assert c["results"]["policies"]["spin"]["package"] not in ("", "?")


def test_a_controller_that_announces_nothing_still_gets_the_builtins_episodes(mesh):
    """old-1's controller serves no rig/{rig}/policies (a 1.1 controller): it serves the four
    built-ins. new-1 serves only spin, so every ra2vipas episode runs on old-1 and every spin
    episode on new-1."""
    _, store, scheduler = mesh({"old-1": {"controller_bus": Silent}, "new-1": {"controller": {"policies": [SPIN]}}}, window=2)
    c = _run(store, scheduler, ["ra2vipas", "spin"], tests=3)
    assert c["status"] == "done", c["error"]
    assert _rigs_by_policy(store, c["id"]) == {"ra2vipas": {"old-1"}, "spin": {"new-1"}}
    old = scheduler.status()["rigs"]["old-1"]
    assert old["announced"] == "silent" and [p["name"] for p in old["policies"]] == list(BUILTINS)
    assert old["controller_protocol"] is None


def test_an_episode_no_live_controller_serves_waits_for_one(mesh):
    """Only spin is served: the rapas episodes are not handed out (nothing fails); the spin ones run."""
    bus, store, scheduler = mesh({"rig-a": {"controller": {"policies": [SPIN]}}}, window=2)
    scenario = build_scenario("paper", SMALL)
    cid = store.create_campaign(preset="paper", overrides=SMALL, scenario=scenario.model_dump(mode="json"),
                                algorithms=["spin", "rapas"], tests=2, seed=1, mode="fast")
    scheduler.submit(cid)
    deadline = time.monotonic() + 60
    while store.campaign(cid)["progress"]["done"] < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    c = store.campaign(cid)
    assert c["progress"]["done"] == 2 and c["status"] == "running", c
    assert {row["algorithm"] for row in store.episode_rows(cid)} == {"spin"}
    failed = [EpisodeResult.model_validate_json(p) for k, p in bus.published if k == keys.episode_result("rig-a")]
    assert all(r.status == "done" for r in failed)


def test_the_controller_answers_what_it_serves_and_fails_an_episode_of_another_naming_them():
    bus = MemoryBus()
    node = ControllerNode(bus, "rig-x", policies=["rapas", SPIN])
    try:
        replies = []
        bus.query(keys.rig_policies("rig-x"), b"", 5.0, replies.append)
        deadline = time.monotonic() + 5
        while not replies and time.monotonic() < deadline:
            time.sleep(0.01)
        info = ControllerInfo.model_validate_json(replies[0][0].payload)
        assert info.rig == "rig-x" and [p.name for p in info.policies] == ["rapas", "spin"] and info.protocol == PROTOCOL_VERSION
        assert info.policies[0].package == "ra2vipas"

        results = []
        bus.subscribe(keys.episode_result("rig-x"), lambda k, p: results.append(EpisodeResult.model_validate_json(p)))
        start = EpisodeStart(episode_id="c.0.ra2vipas.1.00", campaign_id="c", test_index=0, algorithm="ra2vipas", seed=1,
                             scenario=build_scenario("paper", SMALL))
        bus.publish(keys.episode_control("rig-x"), dump(start))
        settle(bus, node.loop)
        assert [r.status for r in results] == ["failed"]
        assert results[0].error == "controller of rig rig-x does not serve policy 'ra2vipas'; it serves: rapas, spin"
    finally:
        node.close()
        bus.close()


def test_a_controller_refuses_to_serve_a_policy_that_does_not_load():
    bus = MemoryBus()
    try:
        with pytest.raises(UnknownPolicy, match="unknown policy 'nope'"):
            ControllerNode(bus, "rig-x", policies=["nope"])
    finally:
        bus.close()
