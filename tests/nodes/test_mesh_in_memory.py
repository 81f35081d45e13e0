"""The four services' node logic wired on the in-memory bus: the mesh without the network."""

from __future__ import annotations

import json
import time

import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, EpisodeStart, Measurement, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus

SMALL = {"steps": 25, "n_train": 200, "n_targets": 8}


@pytest.fixture()
def mesh(tmp_path):
    bus = MemoryBus()
    store = Store(str(tmp_path / "mesh.db"))
    nodes = [SensorsNode(bus, "rig-1"), ControllerNode(bus, "rig-1"), LearnerNode(bus)]
    scheduler = Scheduler(bus, store, window=3)
    yield bus, store, scheduler
    scheduler.close()
    for n in nodes:
        n.close()
    bus.close()
    store.close()


def _run(store, scheduler, preset, overrides, tests, seed, algorithms, mode="fast", timeout=120.0):
    scenario = build_scenario(preset, overrides)
    cid = store.create_campaign(preset=preset, overrides=overrides, scenario=scenario.model_dump(mode="json"),
                                algorithms=algorithms, tests=tests, seed=seed, mode=mode)
    scheduler.submit(cid)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        c = store.campaign(cid)
        if c["status"] in ("done", "failed"):
            return c
        time.sleep(0.05)
    raise AssertionError(f"campaign did not finish: {store.campaign(cid)}")


def _untimed(results):
    out = json.loads(json.dumps(results))
    out.pop("steps_per_second", None)
    out["pod"].pop("train_seconds", None)
    return out


def test_campaign_over_the_bus_equals_the_in_process_simulation(mesh):
    _, store, scheduler = mesh
    algorithms = ["ra2vipas", "rapas", "ravipas", "sweep"]
    c = _run(store, scheduler, "paper", SMALL, 4, 11, algorithms)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("paper", build_scenario("paper", SMALL), 4, 11, algorithms)
    assert _untimed(c["results"]) == _untimed(expected)
    assert c["progress"] == {"done": 16, "running": 0, "pending": 0, "total": 16}


def test_every_test_is_recorded_once_with_its_trace(mesh):
    _, store, scheduler = mesh
    c = _run(store, scheduler, "paper", SMALL, 3, 2, ["ra2vipas"])
    rows = store.episode_rows(c["id"])
    assert sorted(r["test_index"] for r in rows) == [0, 1, 2]
    for r in rows:
        assert len(r["estimates"]) == len(r["hits"]) == len(r["pans"]) == SMALL["steps"]
        assert r["attempt"] == 1


def test_only_measurements_reach_the_controller(mesh):
    """The controller subscribes to control and data keys of its rig; nothing it listens to is
    on the truth plane, and every measurement on the wire validates as a Measurement."""
    bus, store, scheduler = mesh
    _run(store, scheduler, "paper", SMALL, 1, 3, ["ra2vipas"])
    controller_keys = [k for k, _ in bus.published if k in (keys.measurement("rig-1"), keys.episode_control("rig-1"))]
    assert controller_keys and all("/truth/" not in k for k in controller_keys)
    for key, payload in bus.published:
        if key == keys.measurement("rig-1"):
            m = Measurement.model_validate_json(payload)
            assert set(json.loads(payload)) == {"episode_id", "step", "pan_rad", "rf", "frames"}
            assert all(list(f.box_bearings_rad) == sorted(f.box_bearings_rad) for f in m.frames)


def test_a_command_that_overtakes_its_episode_start_is_kept():
    bus = MemoryBus()
    sensors = SensorsNode(bus, "rig-9")
    got = []
    bus.subscribe(keys.measurement("rig-9"), lambda k, p: got.append(Measurement.model_validate_json(p)))
    sc = build_scenario("paper", SMALL)
    start = EpisodeStart(episode_id="c.0.ra2vipas.1", campaign_id="c", test_index=0, algorithm="ra2vipas", seed=1, scenario=sc)
    bus.publish(keys.command("rig-9"), dump(Command(episode_id=start.episode_id, step=0, pan_rad=0.0)))
    bus.wait_idle()
    assert got == []
    bus.publish(keys.episode_control("rig-9"), dump(start))
    bus.wait_idle()
    assert [m.step for m in got] == [0]
    sensors.close()
    bus.close()


@pytest.mark.parametrize("payload", [b"", b"not json", b"{}", b'{"episode_id": "x", "step": -1, "pan_rad": 0}',
                                     b'{"episode_id": "x", "step": 0, "pan_rad": NaN}', b"[" * 10000, b'{"kind": "start"}'])
def test_malformed_messages_are_dropped_and_the_mesh_still_works(mesh, payload):
    bus, store, scheduler = mesh
    for key in (keys.command("rig-1"), keys.measurement("rig-1"), keys.episode_control("rig-1"),
                keys.episode_result("rig-1"), keys.episode_truth("rig-1")):
        bus.publish(key, payload)
    bus.wait_idle()
    c = _run(store, scheduler, "paper", SMALL, 1, 4, ["rapas"])
    assert c["status"] == "done"
