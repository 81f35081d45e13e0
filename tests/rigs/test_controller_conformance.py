"""The controller conformance kit (``ra2vipas protocol check --controller RIG``): our controller
passes every rule, on the in-memory bus and as a real process behind a Zenoh router; a
deliberately broken controller fails, and the report names the rule it breaks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

from ra2vipas.services.controller.node import ControllerNode, warm_up
from ra2vipas.services.rigs.controller_conformance import RULES, ControllerKit, check_controller
from ra2vipas.services.transport.bus import MemoryBus
from tests.integration.conftest import ROOT, wait_for_line
from tests.rigs import broken_controller

BROKEN = ROOT / "tests" / "rigs" / "broken_controller.py"


def run_kit(node_class, rig: str = "rig-1", **kw):
    bus = MemoryBus()
    node = node_class(bus, rig)
    try:
        return {r.rule: r for r in check_controller(bus, rig, timeout=3.0, **kw)}
    finally:
        node.close()
        bus.close()


def test_our_controller_passes_every_rule_on_the_in_memory_bus():
    results = run_kit(ControllerNode)
    assert list(results) == list(RULES)
    statuses = {k: r.status for k, r in results.items()}
    assert statuses == dict.fromkeys(RULES, "pass"), [r for r in results.values() if r.status != "pass"]


def test_a_1_0_controller_passes_with_the_optional_rules_skipped():
    results = run_kit(broken_controller.V10)
    statuses = {k: r.status for k, r in results.items()}
    assert statuses == {**dict.fromkeys(RULES, "pass"), "policies": "skip", "rejects-malformed": "skip"}
    assert results["policies"].detail == "no reply: a 1.0 or 1.1 controller (it serves the four built-ins)"


def test_a_controller_that_ignores_stop_fails_that_rule_only():
    results = run_kit(broken_controller.IgnoresStop)
    failed = {k: r.detail for k, r in results.items() if r.status == "fail"}
    assert failed == {"stop-mid-episode": "Measurement(1) after EpisodeStop got a Command"}


def test_a_controller_that_answers_with_step_t_fails_lockstep():
    results = run_kit(broken_controller.StepT)
    assert results["command-0"].status == "pass"
    assert results["lockstep"].status == "fail"
    assert results["lockstep"].detail == "Measurement(0) got no Command(1) within 3 s (it sent commands of steps [0])"
    assert results["result"].detail == "could not run: the episode did not reach its last step"


def test_a_controller_that_declares_its_token_first_fails_the_liveliness_rule():
    """The kit started first sends an episode and queries the policies the moment the token
    appears: a controller whose token comes before its subscriptions misses both."""
    import threading

    warm_up()  # compiled once in this process: the node's own warm-up is then quick, its set-up is SETUP_S
    bus = MemoryBus()
    kit = ControllerKit(bus, "rig-1", timeout=3.0)
    out = []
    runner = threading.Thread(target=lambda: out.extend(kit.run(wait=30)))
    runner.start()
    node = broken_controller.TokenFirst(bus, "rig-1")
    try:
        runner.join(120)
    finally:
        kit.close()
        node.close()
        bus.close()
    failed = {r.rule: r.detail for r in out if r.status == "fail"}
    assert failed == {"liveliness": "an EpisodeStart sent as soon as the token appeared got no Command(0) within 3 s; "
                                    "rig/rig-1/policies did not answer when the token appeared (it does later): declare the "
                                    "token only after every subscription and queryable"}, out


def test_a_query_handler_that_returns_none_sends_no_reply():
    """How the kit's learner lets every request but its own pass (``Bus.serve``)."""
    import threading

    bus = MemoryBus()
    bus.serve("a/b", lambda _k, p: p if p == b"mine" else None)
    got = {}
    try:
        for payload in (b"mine", b"theirs"):
            done = threading.Event()
            bus.query("a/b", payload, 1.0, lambda replies, p=payload: (got.__setitem__(p, replies), done.set()))
            assert done.wait(5)
    finally:
        bus.close()
    assert [r.payload for r in got[b"mine"]] == [b"mine"] and got[b"theirs"] == []


def kit(endpoint: str, rig: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "protocol", "check", "--controller", rig,
                           "--connect", endpoint, "--zenoh-mode", "client", "--timeout", "5", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, "COLUMNS": "200"})


def test_our_controller_process_passes_over_zenoh(router):
    """The kit started first (``--wait``), so it probes the controller the moment its token
    appears: the token is declared last."""
    registry, endpoint = router
    kit_proc = registry.start("protocol", "check", "--controller", "ctl-1", "--connect", endpoint, "--zenoh-mode", "client",
                              "--json", "--timeout", "5", "--wait", "120")
    wait_for_line(kit_proc, "watching for the controller of rig ctl-1", 60)
    node = registry.start("controller", "--rig", "ctl-1", "--connect", endpoint, "--zenoh-mode", "client")
    out, _ = kit_proc.communicate(timeout=300)
    body = json.loads(out.strip().splitlines()[-1])
    assert kit_proc.returncode == 0, out
    assert {r["rule"]: r["status"] for r in body["rules"]} == dict.fromkeys(RULES, "pass"), body
    os.killpg(node.pid, signal.SIGTERM)
    assert node.wait(30) == 0


def test_a_broken_controller_process_fails_naming_the_rule(router):
    registry, endpoint = router
    node = registry.script(BROKEN, "ignores-stop", "--rig", "bad-c1", "--connect", endpoint)
    wait_for_line(node, "up (zenoh", 120)
    out = kit(endpoint, "bad-c1", "--json")
    body = json.loads(out.stdout.strip().splitlines()[-1])
    assert out.returncode == 1, out.stderr
    assert {r["rule"]: r["detail"] for r in body["rules"] if r["status"] == "fail"} == {
        "stop-mid-episode": "Measurement(1) after EpisodeStop got a Command"}
    out = kit(endpoint, "bad-c1")
    assert out.returncode == 1 and "rule(s) failed: stop-mid-episode" in out.stdout, out.stdout


def test_check_takes_a_rig_or_a_controller():
    for args in ((), ("--rig", "a", "--controller", "a"), ("--rig", "a", "--policy", "rapas"),
                 ("--controller", "a", "--policy", "Bad!")):
        out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "protocol", "check", *args], cwd=ROOT,
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 2, (args, out.stderr)


def test_the_controller_kit_refuses_a_rig_whose_sensors_are_up(router):
    """The kit plays the rig's sensors: with the real ones up, both would answer the controller."""
    registry, endpoint = router
    node = registry.start("sensors", "--rig", "busy-1", "--connect", endpoint, "--zenoh-mode", "client")
    wait_for_line(node, "up (zenoh", 60)
    out = kit(endpoint, "busy-1")
    assert out.returncode == 2 and "the sensors node of rig busy-1 is up" in out.stderr, out.stderr
    os.killpg(node.pid, signal.SIGTERM)
    assert node.wait(30) == 0


def test_the_controller_kit_refuses_a_mesh_with_a_learner(router):
    """The kit plays the learner: a Zenoh query reaches one of two learners, so a controller's
    request for the kit's model could go to the real one (and another's to the kit)."""
    registry, endpoint = router
    node = registry.start("learner", "--connect", endpoint, "--zenoh-mode", "client")
    wait_for_line(node, "up (zenoh", 60)
    out = kit(endpoint, "free-1")
    os.killpg(node.pid, signal.SIGTERM)
    assert node.wait(30) == 0
    assert out.returncode == 2 and "a learner is up on this mesh" in out.stderr, out.stderr


def test_a_query_handler_that_returns_none_sends_no_reply_over_zenoh(router):
    """A request that is not the kit's gets no reply from the kit's learner: no error reply
    that a controller would take for the learner's answer."""
    import threading

    from ra2vipas.services.transport.zenoh_bus import ZenohBus
    from ra2vipas.services.transport.zenoh_config import ZenohSettings

    _registry, endpoint = router
    buses = [ZenohBus(ZenohSettings(mode="client", connect=(endpoint,), multicast_scouting=False)) for _ in range(2)]
    kit_side, asker = buses
    try:
        kit_side.serve("test/none/model", lambda _k, p: b'"kit"' if p == b"mine" else None)
        time.sleep(0.5)
        got = {}
        for payload in (b"mine", b"theirs"):
            done = threading.Event()
            asker.query("test/none/model", payload, 5.0, lambda replies, p=payload: (got.__setitem__(p, replies), done.set()))
            assert done.wait(15)
    finally:
        for bus in buses:
            bus.close()
    assert [(r.payload, r.ok) for r in got[b"mine"]] == [(b'"kit"', True)]
    assert got[b"theirs"] == []
