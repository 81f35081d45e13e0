"""The simulated sensors node with several tags (protocol 1.4; docs/tags.md): its truth names
each tag's carrier and address, and each measurement carries every tag's RF pair."""

from __future__ import annotations

import json
import time

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, EpisodeStart, EpisodeTruth, Measurement, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.sensors.world import SimulatedPlatform
from ra2vipas.services.transport.bus import MemoryBus

STEPS = 15


def test_the_simulated_sensors_node_sends_every_tags_pair_and_the_carriers():
    bus = MemoryBus()
    node = SensorsNode(bus, "sim-ward")
    got: list[bytes] = []
    truths: list[bytes] = []
    scenario = build_scenario("ward", {"steps": STEPS})
    try:
        bus.subscribe(keys.measurement("sim-ward"), lambda _k, payload: got.append(payload))
        bus.subscribe(keys.episode_truth("sim-ward"), lambda _k, payload: truths.append(payload))
        start = EpisodeStart(episode_id="w.0.ra2vipas.1", campaign_id="w", test_index=0, algorithm="ra2vipas", seed=3, scenario=scenario)
        bus.publish(keys.episode_control("sim-ward"), dump(start))
        assert bus.wait_idle()
        for t in range(STEPS):
            bus.publish(keys.command("sim-ward"), dump(Command(episode_id=start.episode_id, step=t, pan_rad=0.2 * t)))
            deadline = time.monotonic() + 60.0  # the node answers on its own thread: wait for step t's measurement
            while len(got) <= t and time.monotonic() < deadline:
                time.sleep(0.01)
    finally:
        node.close()
        bus.close()
    world = SimulatedPlatform(scenario, 3, 0)
    truth = EpisodeTruth.model_validate_json(truths[0])
    assert truth.carriers == world.truth.carriers and len(set(truth.carriers)) == 3
    assert truth.tag_addresses == world.truth.tag_addresses
    measurements = [Measurement.model_validate_json(p) for p in got]
    assert [m.step for m in measurements] == list(range(STEPS))
    for m in measurements:
        expected = world.sense(m.step, m.pan_rad)
        assert m.tags() == (0, 1, 2) and m.pairs() == expected.pairs()
        assert [p["tag"] for p in json.loads(dump(m))["rf_tags"]] == [1, 2]
