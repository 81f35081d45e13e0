"""The mesh without the network: the four services' node logic wired on one in-memory bus.

``mesh()`` builds sensors and a controller per rig, a learner and the scheduler on a
``MemoryBus`` with a store in the test's folder, and closes them all after the test;
``run_to_end`` submits a campaign and waits for it to finish; ``settle`` waits until the bus and
the nodes' loops have handled everything so far.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus

Wrap = Callable[[MemoryBus], Any]


def run_to_end(store: Store, scheduler: Scheduler, preset: str, overrides: dict, tests: int, seed: int, algorithms: list[str],
               *, mode: str = "fast", stop_confidence: float = 0.0, timeout: float = 120.0) -> dict:
    """Create a campaign, submit it and return it once it is done or failed (an AssertionError
    naming its state after ``timeout`` seconds)."""
    scenario = build_scenario(preset, overrides)
    cid = store.create_campaign(preset=preset, overrides=overrides, scenario=scenario.model_dump(mode="json"),
                                algorithms=algorithms, tests=tests, seed=seed, mode=mode, stop_confidence=stop_confidence)
    scheduler.submit(cid)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        c = store.campaign(cid)
        if c["status"] in ("done", "failed"):
            return c
        time.sleep(0.02)
    raise AssertionError(f"campaign not finished after {timeout:.0f} s: {store.campaign(cid)}")


def settle(bus: MemoryBus, *loops, rounds: int = 3) -> None:
    """Wait until the bus and the nodes' event loops have handled everything so far (a
    handler may publish, whose delivery may post to a loop again)."""
    for _ in range(rounds):
        bus.wait_idle()
        for loop in loops:
            assert loop.wait_idle()


@pytest.fixture()
def mesh(tmp_path):
    """``mesh(rigs, window=3) -> (bus, store, scheduler)``: for each rig of ``rigs`` (default
    ``{"rig-1": {}}``) a sensors node and a controller node, then a learner and the scheduler, on
    one in-memory bus. A rig's options: ``sensors`` / ``controller``, keyword arguments of its
    node; ``sensors_bus`` / ``controller_bus``, a wrapper of the bus that node is given (an older
    or stricter node's view of it). Everything built is closed after the test."""
    made: list[tuple[MemoryBus, Store, Scheduler, list]] = []

    def build(rigs: dict[str, dict] | None = None, window: int = 3):
        bus = MemoryBus()
        store = Store(str(tmp_path / f"mesh-{len(made)}.db"))
        nodes: list = []
        for rig, options in (rigs or {"rig-1": {}}).items():
            unknown = set(options) - {"sensors", "controller", "sensors_bus", "controller_bus"}
            assert not unknown, f"no such rig option: {sorted(unknown)}"
            nodes.append(SensorsNode(options.get("sensors_bus", _same)(bus), rig, **options.get("sensors", {})))
            nodes.append(ControllerNode(options.get("controller_bus", _same)(bus), rig, **options.get("controller", {})))
        nodes.append(LearnerNode(bus))
        scheduler = Scheduler(bus, store, window=window)
        made.append((bus, store, scheduler, nodes))
        return bus, store, scheduler

    yield build
    for bus, store, scheduler, nodes in made:
        scheduler.close()
        for n in nodes:
            n.close()
        bus.close()
        store.close()


def _same(bus: MemoryBus) -> MemoryBus:
    return bus
