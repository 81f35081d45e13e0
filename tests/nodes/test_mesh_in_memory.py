"""The four services' node logic wired on the in-memory bus: the mesh without the network."""

from __future__ import annotations

import json
import time

import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, EpisodeStart, EpisodeStop, Measurement, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end, settle

SMALL = {"steps": 25, "n_train": 200, "n_targets": 8}


def test_campaign_over_the_bus_equals_the_in_process_simulation(mesh):
    _, store, scheduler = mesh()
    algorithms = ["ra2vipas", "rapas", "ravipas", "sweep"]
    c = run_to_end(store, scheduler, "paper", SMALL, 4, 11, algorithms)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("paper", build_scenario("paper", SMALL), 4, 11, algorithms)
    assert untimed(c["results"]) == untimed(expected)
    assert c["progress"] == {"done": 16, "running": 0, "pending": 0, "total": 16}


def test_every_test_is_recorded_once_with_its_trace(mesh):
    _, store, scheduler = mesh()
    c = run_to_end(store, scheduler, "paper", SMALL, 3, 2, ["ra2vipas"])
    rows = store.episode_rows(c["id"])
    assert sorted(r["test_index"] for r in rows) == [0, 1, 2]
    for r in rows:
        assert len(r["estimates"]) == len(r["hits"]) == len(r["pans"]) == SMALL["steps"]
        assert r["attempt"] == 1


def test_only_measurements_reach_the_controller(mesh):
    """The controller subscribes to control and data keys of its rig; nothing it listens to is
    on the truth plane, and every measurement on the wire validates as a Measurement."""
    bus, store, scheduler = mesh()
    run_to_end(store, scheduler, "paper", SMALL, 1, 3, ["ra2vipas"])
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
    settle(bus, sensors.loop)
    assert got == []
    bus.publish(keys.episode_control("rig-9"), dump(start))
    settle(bus, sensors.loop)
    assert [m.step for m in got] == [0]
    sensors.close()
    bus.close()


@pytest.mark.parametrize("payload", [b"", b"not json", b"{}", b'{"episode_id": "x", "step": -1, "pan_rad": 0}',
                                     b'{"episode_id": "x", "step": 0, "pan_rad": NaN}', b"[" * 10000, b'{"kind": "start"}'])
def test_malformed_messages_are_dropped_and_the_mesh_still_works(mesh, payload):
    bus, store, scheduler = mesh()
    for key in (keys.command("rig-1"), keys.measurement("rig-1"), keys.episode_control("rig-1"),
                keys.episode_result("rig-1"), keys.episode_truth("rig-1")):
        bus.publish(key, payload)
    bus.wait_idle()
    c = run_to_end(store, scheduler, "paper", SMALL, 1, 4, ["rapas"])
    assert c["status"] == "done"


# -- the dynamic world (issue 9): walkers, occlusion, clutter, shadowing, fading -------------------------

DYNAMIC_SMALL = {"steps": 30, "n_train": 200, "n_targets": 8}


def test_dynamic_campaign_over_the_bus_equals_the_in_process_simulation(mesh):
    """Walkers' per-step truth travels on the truth plane, is stored with each test and scores
    DR_t exactly as ``run_test`` does in process."""
    from ra2vipas.services.orchestrator.api.views import trace_public
    from ra2vipas.services.orchestrator.simulate import run_test, train_pod
    from ra2vipas.services.sensors.world import SimulatedPlatform

    _, store, scheduler = mesh()
    algorithms = ["ra2vipas", "rapas", "ravipas", "sweep"]
    scenario = build_scenario("dynamic", DYNAMIC_SMALL)
    c = run_to_end(store, scheduler, "dynamic", DYNAMIC_SMALL, 3, 5, algorithms)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("dynamic", scenario, 3, 5, algorithms)
    assert untimed(c["results"]) == untimed(expected)
    pod = train_pod(scenario, 5).model
    walked = 0
    for row in store.episode_rows(c["id"]):
        outcome = run_test(scenario, 5, row["test_index"], row["algorithm"], pod)
        assert row["hits"] == [int(h) for h in outcome.hits] and row["chosen"] == outcome.chosen
        truth = SimulatedPlatform(scenario, 5, row["test_index"]).truth
        bearings, ranges = truth.walker_truth()
        assert [t["index"] for t in row["trajectories"]] == truth.walkers.tolist()
        for k, t in enumerate(row["trajectories"]):
            assert t["bearings_rad"] == bearings[:, k].tolist() and t["ranges_m"] == ranges[:, k].tolist()
        trace = trace_public(row, scenario.rf_period_s)
        moving = [tg for tg in trace.targets if tg.bearings_rad is not None]
        assert [tg.index for tg in moving] == truth.walkers.tolist()
        assert all(len(tg.bearings_rad) == len(tg.ranges_m) == scenario.steps for tg in moving)
        walked += len(moving)
    assert walked == 4 * len(algorithms) * 3  # half of the 8 targets walk in every test


def test_no_truth_reaches_the_controller_or_the_learner_in_the_dynamic_world(mesh):
    """Measurements and training streams carry RSSI values and sorted box bearings only: no
    identity, range, POD, occlusion flag or clutter label."""
    import threading

    from ra2vipas.services.protocol.messages import TrainingRequest, training_job_id

    bus, store, scheduler = mesh()
    run_to_end(store, scheduler, "dynamic", DYNAMIC_SMALL, 1, 3, ["ra2vipas"])
    seen = 0
    for key, payload in bus.published:
        if key == keys.measurement("rig-1"):
            m = json.loads(payload)
            assert set(m) == {"episode_id", "step", "pan_rad", "rf", "frames"}
            assert set(m["rf"]) == {"iso_rssi_dbm", "dir_rssi_dbm"}
            assert all(set(f) == {"box_bearings_rad"} and f["box_bearings_rad"] == sorted(f["box_bearings_rad"]) for f in m["frames"])
            seen += 1
    assert seen == DYNAMIC_SMALL["steps"]
    scenario = build_scenario("dynamic", DYNAMIC_SMALL)
    done, replies = threading.Event(), []
    request = TrainingRequest(job_id=training_job_id(scenario, 3), scenario=scenario, seed=3)
    bus.query(keys.training("rig-1"), dump(request), 30.0, lambda r: (replies.extend(r), done.set()))
    assert done.wait(30.0) and replies and replies[0].ok
    stream = json.loads(replies[0].payload)
    assert set(stream) == {"job_id", "samples"} and len(stream["samples"]) == DYNAMIC_SMALL["n_train"]
    for sample in stream["samples"]:
        assert set(sample) == {"index", "iso_rssi_dbm", "frames"}
        assert all(set(f) == {"box_bearings_rad"} for f in sample["frames"])


def test_early_decisions_over_the_bus_equal_the_in_process_simulation(mesh):
    """With stop_confidence, a controller ends an episode at its first confident step; the
    orchestrator scores the held answer, tells the rig to drop the episode, and the results
    (DR, calibration, decision) equal the in-process campaign's value for value."""
    bus, store, scheduler = mesh()
    algorithms = ["ra2vipas", "rapas"]
    c = run_to_end(store, scheduler, "paper", SMALL, 4, 11, algorithms, stop_confidence=0.9)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("paper", build_scenario("paper", SMALL), 4, 11, algorithms, stop_confidence=0.9)
    assert untimed(c["results"]) == untimed(expected)
    assert c["results"]["stop_confidence"] == 0.9 and all("decision" in b for b in c["results"]["algorithms"].values())
    rows = store.episode_rows(c["id"])
    decided = [r for r in rows if r["decided_step"] is not None]
    assert decided, "no episode decided early: the test would prove nothing"
    for r in decided:
        assert len(r["estimates"]) == r["decided_step"] + 1 < SMALL["steps"] and len(r["hits"]) == SMALL["steps"]
        assert r["confidences"][-1] >= 0.9 > max(r["confidences"][:-1], default=0.0)
    settle(bus, scheduler.loop)
    stops = {EpisodeStop.model_validate_json(p).episode_id for k, p in bus.published
             if k == keys.episode_control("rig-1") and b'"decided early"' in p}
    assert len(stops) == len(decided)


def test_the_step_costs_the_nodes_report_add_up(mesh):
    """Each node times its steps (issue 22: services/transport/costs.py) and reports them once
    per episode, the controller in its EpisodeResult, the sensors in an EpisodeTiming (fast mode
    too); every step is counted on both sides, and the parts of a step add up to the step the
    controller measures (within 2 %: its stages are contiguous), with the transport (here the
    in-memory bus's dispatcher thread) non-negative from either side."""
    from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeTiming
    from ra2vipas.services.transport.costs import step_breakdown

    bus, store, scheduler = mesh()
    c = run_to_end(store, scheduler, "paper", SMALL, 2, 3, ["ra2vipas", "rapas"])
    assert c["status"] == "done", c["error"]
    results = [EpisodeResult.model_validate_json(p) for k, p in bus.published if k == keys.episode_result("rig-1")]
    timings = {t.episode_id: t for k, p in bus.published if k == keys.episode_timing("rig-1")
               for t in [EpisodeTiming.model_validate_json(p)]}
    assert len(results) == 4 and set(timings) == {r.episode_id for r in results}
    assert all(t.latencies_ms == () and t.costs.steps == 25 for t in timings.values())  # fast mode: costs only
    b = step_breakdown([r.costs for r in results], [timings[r.episode_id].costs for r in results])
    assert b["controller"]["steps"] == b["sensors"]["steps"] == 4 * 25
    assert b["controller"]["compute_ms"] > 0 and b["sensors"]["compute_ms"] > 0
    assert b["transport_ms"] >= 0 and b["transport_ms_sensors_view"] >= 0
    assert b["parts_sum_ms"] == pytest.approx(b["step_ms"], rel=0.02)
    assert 0 < b["controller_compute_share"] <= 1
    assert c["results"].get("latency_ms") is None  # fast-mode timing reports carry no latencies into the results


def test_a_realtime_episode_samples_on_its_grid_and_its_timer_stops_after_it(mesh):
    """Realtime pacing (the sensors' timer thread schedules every tick after the first itself,
    on the grid t0 + k T_RF, so the worker never wakes it mid-step): one sample per step on the
    grid, one latency per command, an EpisodeTiming per episode, and no tick left once it is
    over."""
    from ra2vipas.services.protocol.messages import EpisodeTiming

    bus, store, scheduler = mesh(window=1)
    overrides = {"steps": 8, "rf_period_s": 0.04, "n_train": 200, "n_targets": 8}
    # a fast episode first: a process's first controller step loads its compiled kernels (a fresh-clone CI once held
    # the sensors' worker ~0.3 s there, and every sample of the first realtime episode came at once)
    assert run_to_end(store, scheduler, "paper", overrides, 1, 5, ["ra2vipas"])["status"] == "done"
    before = len(bus.published)
    seen: list[tuple[float, int]] = []
    bus.subscribe(keys.measurement("rig-1"), lambda _k, p: seen.append((time.monotonic(), Measurement.model_validate_json(p).step)))
    c = run_to_end(store, scheduler, "paper", overrides, 2, 5, ["ra2vipas"], mode="realtime")
    assert c["status"] == "done", c["error"]
    timings = [EpisodeTiming.model_validate_json(p) for k, p in bus.published[before:] if k == keys.episode_timing("rig-1")]
    # one latency per command (7 after 8 samples); a command that a loaded machine delivers after its episode's end
    # tick (a whole T_RF after the last sample) finds no episode to time: only the last one can miss it
    assert len(timings) == 2 and all(len(t.latencies_ms) in (6, 7) for t in timings), timings
    assert sum(len(t.latencies_ms) for t in timings) >= 13, timings
    steps = [s for _, s in seen]
    assert steps == list(range(8)) * 2
    for episode in (seen[:8], seen[8:]):
        # the grid t0 + k T_RF that no sample precedes (a sample is never early; a loaded machine delays some):
        # most samples on it, and the episode spread over its 7 T_RF (every sample at once spans ~0 s)
        t0 = min(t - k * 0.04 for k, (t, _) in enumerate(episode))
        offsets = sorted(t - t0 - k * 0.04 for k, (t, _) in enumerate(episode))
        assert offsets[len(offsets) // 2] < 0.015, offsets
        assert episode[-1][0] - episode[0][0] >= 6.5 * 0.04, offsets
    time.sleep(0.15)
    assert len(seen) == 16  # nothing after the end
