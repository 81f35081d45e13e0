"""Campaigns on BLE advertisements (issue 20, protocol 1.3) through the in-memory mesh: the
sensors node sends each step's packets (often none), the controller node reads them, and the
results equal ``simulate``'s value for value."""

from __future__ import annotations

import json

import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.scenario import build_scenario
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end

BLE_SMALL = {"steps": 120, "n_train": 200, "n_targets": 8}  # the paper's 12 s: ~24 packets a receiver


@pytest.mark.parametrize("preset", ["ble", "ble-recorded", "ble-dynamic"])
def test_a_campaign_on_advertisements_over_the_bus_equals_simulate(mesh, preset):
    bus, store, scheduler = mesh()
    algorithms = ["ra2vipas", "rapas", "ravipas"]
    c = run_to_end(store, scheduler, preset, BLE_SMALL, 2, 7, algorithms, timeout=240.0)
    assert c["status"] == "done", c["error"]
    expected = run_campaign(preset, build_scenario(preset, BLE_SMALL), 2, 7, algorithms)
    got = untimed(c["results"])
    # the rig check's notes are the mesh's own (simulate runs no rig); on packets its lobe evidence
    # can misfire (docs/radio.md, "What is not done yet"): everything else is equal value for value
    notes = got.pop("warnings", [])
    assert all("contradicts the assumed Rx(dir) response" in n for n in notes)
    assert got == untimed(expected)
    # what crossed the wire: packets, never a made-up pair, and steps without any
    counts = []
    for key, payload in bus.published:
        if key == keys.measurement("rig-1"):
            m = json.loads(payload)
            assert m.get("rf") is None
            counts.append(len(m.get("adverts", ())))
    assert counts and 0 in counts and max(counts) >= 1
