"""The controller conformance kit (``ra2vipas protocol check --controller RIG``): our controller
passes every rule, on the in-memory bus and as a real process behind a Zenoh router; a
deliberately broken controller fails, and the report names the rule it breaks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.rigs.controller_conformance import RULES, check_controller
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
    assert {k: r.status for k, r in results.items()} == dict.fromkeys(RULES, "pass"), [r for r in results.values() if r.status != "pass"]


def test_a_1_0_controller_passes_with_the_optional_rules_skipped():
    results = run_kit(broken_controller.V10)
    assert {k: r.status for k, r in results.items()} == {**dict.fromkeys(RULES, "pass"), "policies": "skip", "rejects-malformed": "skip"}
    assert results["policies"].detail == "no reply: a 1.0 or 1.1 controller (it serves the four built-ins)"


def test_a_controller_that_ignores_stop_fails_that_rule_only():
    results = run_kit(broken_controller.IgnoresStop)
    failed = {k: r.detail for k, r in results.items() if r.status == "fail"}
    assert failed == {"stop-mid-episode": "Measurement(1) after EpisodeStop got a Command"}


def test_a_controller_that_answers_with_step_t_fails_lockstep():
    results = run_kit(broken_controller.StepT)
    assert results["command-0"].status == "pass"
    assert results["lockstep"].status == "fail"
    assert results["lockstep"].detail.startswith("Measurement(0) got no Command(1)"), results["lockstep"]


def kit(endpoint: str, rig: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "protocol", "check", "--controller", rig, "--connect", endpoint,
                           "--zenoh-mode", "client", "--timeout", "5", *args], cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "200"})


def test_our_controller_process_passes_over_zenoh(router):
    """The kit started first (``--wait``), so it probes the controller the moment its token
    appears: the token is declared last."""
    registry, endpoint = router
    kit_proc = registry.start("protocol", "check", "--controller", "ctl-1", "--connect", endpoint, "--zenoh-mode", "client", "--json",
                              "--timeout", "5", "--wait", "120")
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
    for args in ((), ("--rig", "a", "--controller", "a"), ("--rig", "a", "--policy", "rapas")):
        out = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "protocol", "check", *args], cwd=ROOT, capture_output=True,
                             text=True, timeout=60)
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
