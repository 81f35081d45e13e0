"""The controller conformance kit (``ra2vipas protocol check --controller RIG``): our controller
passes every rule, on the in-memory bus and as a real process behind a Zenoh router; a
deliberately broken controller fails, and the report names the rule it breaks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from ra2vipas.cli.stack import free_port
from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.rigs.controller_conformance import RULES, check_controller
from ra2vipas.services.transport.bus import MemoryBus
from tests.integration.conftest import ROOT, wait_for_line
from tests.rigs import broken_controller
from tests.rigs.test_conformance import Scripts

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


def test_a_controller_that_ignores_stop_fails_that_rule_only():
    results = run_kit(broken_controller.IgnoresStop)
    failed = {k: r.detail for k, r in results.items() if r.status == "fail"}
    assert failed == {"stop-mid-episode": "Measurement(1) after EpisodeStop got a Command"}


def test_a_controller_that_answers_with_step_t_fails_lockstep():
    results = run_kit(broken_controller.StepT)
    assert results["command-0"].status == "pass"
    assert results["lockstep"].status == "fail"
    assert results["lockstep"].detail.startswith("Measurement(0) got no Command(1)"), results["lockstep"]
