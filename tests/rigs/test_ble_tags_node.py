"""The example node with real BLE receivers listening for several tags (protocol 1.4; the bleak
driver on its fake scanner backend, tests/rigs/ble_node.py): its descriptor says 1.4, its training
stream carries, per 0.1 s sample, what Rx(iso) heard of tag 0 (mostly nothing, never a made-up pair), a two-tag
campaign runs on it through real processes (router, orchestrator, learner, the rig's controller;
the fake layout's truth, each tag's carrier included, published by the node), every advertisement
it sends names its tag and that tag's address, and each tag is scored against its own carrier. Bad tag addresses and receivers that cannot start stop the node in one line."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections import Counter

import httpx

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Measurement, TrainingRequest, TrainingStream, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.transport.zenoh_bus import ZenohBus
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests.integration.conftest import ROOT, wait_for_line
from tests.rigs.conftest import Scripts

BLE_NODE = ROOT / "tests" / "rigs" / "ble_node.py"
EXAMPLE = ROOT / "examples" / "hardware_node" / "hardware_node.py"
TAGS = ["E7:8F:13:56:24:CE", "C3:5A:01:9E:44:B2"]


def test_a_two_tag_campaign_runs_on_the_example_node_with_ble_receivers(local_stack):
    api, env = local_stack["api"], local_stack["env"]
    registry: Scripts = local_stack["registry"]
    node = registry.script(BLE_NODE, "--rig", "ble-2", "--connect", local_stack["router"], "--publish-truth",
                          *[a for tag in TAGS for a in ("--ble-tag", tag.lower())])
    controller = registry.start("controller", "--rig", "ble-2", env=env)
    wait_for_line(node, "hardware node ble-2 up", 60)
    bus = ZenohBus(ZenohSettings(mode="client", connect=(local_stack["router"],)))
    heard: Counter = Counter()
    addresses: dict[int, set] = {}
    steps_without = []
    lock = threading.Lock()

    def on_measurement(_key: str, payload: bytes) -> None:
        m = Measurement.model_validate_json(payload)  # every message the node sends is a valid one
        with lock:
            steps_without.append(not m.adverts)
            for a in m.adverts:
                heard[a.tag] += 1
                addresses.setdefault(a.tag, set()).add(a.address)

    handle = bus.subscribe(keys.measurement("ble-2"), on_measurement)
    try:
        # the training stream: each 0.1 s sample carries what Rx(iso) heard of tag 0 (maybe nothing), never a made-up pair
        got: queue.Queue = queue.Queue()
        request = TrainingRequest(job_id="ble-2-training", scenario=build_scenario("paper", {"n_train": 30}), seed=1)
        bus.query(keys.training("ble-2"), dump(request), 60.0, got.put)
        (reply,) = [r for r in got.get(timeout=70) if r.ok]
        stream = TrainingStream.model_validate_json(reply.payload)
        assert len(stream.samples) == 30 and all(s.iso_rssi_dbm is None for s in stream.samples)
        adverts = [a for s in stream.samples for a in s.adverts]
        # ~2 a second over the 3 s (more if a loaded machine stretches the recording)
        assert 3 <= len(adverts) <= 12 and {(a.receiver, a.tag) for a in adverts} == {("iso", 0)}, adverts
        assert sum(1 for s in stream.samples if not s.adverts) >= 15
        with httpx.Client(base_url=api, timeout=30) as http:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                rig = {r["name"]: r for r in http.get("/rigs").json()["rigs"]}.get("ble-2")
                if rig and rig["live"] and rig["descriptor"] and rig.get("policies"):
                    break
                time.sleep(0.2)
            assert rig and rig["descriptor"]["protocol"] == "1.5" and rig["descriptor"]["radio"] == "adverts", rig
            assert rig["descriptor"]["tags"] == 2  # protocol 1.5: it says how many tags it hears
            more = http.post("/campaigns", json={"overrides": {"steps": 20, "n_train": 80, "n_tags": 3}, "tests": 2, "seed": 3,
                                                 "algorithms": ["ra2vipas"], "rigs": ["ble-2"], "use_rig_values": False,
                                                 "mode": "realtime"})
            assert more.status_code == 422 and "scenario.n_tags: rig ble-2 hears at most 2, the campaign says 3" in more.text, more.text
            r = http.post("/campaigns", json={"overrides": {"steps": 20, "n_train": 80, "n_tags": 2}, "tests": 2, "seed": 3,
                                              "algorithms": ["ra2vipas"], "rigs": ["ble-2"], "use_rig_values": True,
                                              "mode": "realtime"})
            assert r.status_code == 201, r.text
            cid = r.json()["id"]
            deadline = time.monotonic() + 180
            while (c := http.get(f"/campaigns/{cid}").json())["status"] not in ("done", "failed", "cancelled") \
                    and time.monotonic() < deadline:
                time.sleep(0.3)
            assert c["status"] == "done", c
            results = http.get(f"/campaigns/{cid}/results").json()
            trace = http.get(f"/campaigns/{cid}/tests/0/ra2vipas").json()
    finally:
        handle.undeclare()
        bus.close()
    # 2 tests x 2 s of realtime steps, each tag advertising every ~0.45 s to both receivers (90 % heard)
    assert heard[0] >= 8 and heard[1] >= 8, heard
    assert addresses == {0: {TAGS[0]}, 1: {TAGS[1]}}  # each tag named with its own address, upper case
    assert any(steps_without) and not all(steps_without)  # most 0.1 s steps hear nothing: no made-up RSSI
    # one entry per tag, each scored (a truth without each tag's carrier would have the episodes rerun, never done)
    per_tag = results["algorithms"]["ra2vipas"]["tags"]["per_tag"]
    assert len(per_tag) == 2 and all(0.0 <= t["dr_final"] <= 1.0 and len(t["dr"]) == 20 for t in per_tag), per_tag
    assert trace["rig"] == "ble-2" and len(trace["steps"]) == 20
    for proc in (node, controller):
        os.killpg(proc.pid, signal.SIGTERM)
        assert proc.wait(30) == 0


def test_the_node_refuses_a_bad_tag_address_and_receivers_that_cannot_start_in_one_line():
    bad = subprocess.run([sys.executable, str(EXAMPLE), "--ble-tag", "E7:8F:13"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines()[-1].endswith("error: --ble-tag: 'E7:8F:13' is not a BLE address (six hex bytes, "
                                                       "e.g. E7:8F:13:56:24:CE) or a beacon identity (ibeacon:UUID[:MAJOR[:MINOR]], "
                                                       "eddystone:NAMESPACE[:INSTANCE])")
    beacon = subprocess.run([sys.executable, str(EXAMPLE), "--ble-tag", "ibeacon:f7826da6:1:42"], capture_output=True, text=True, timeout=60)
    assert beacon.returncode == 2 and "Traceback" not in beacon.stderr
    assert beacon.stderr.strip().splitlines()[-1].startswith("hardware_node.py: error: --ble-tag: 'ibeacon:f7826da6:1:42' is not an "
                                                          "iBeacon identity (ibeacon:UUID[:MAJOR[:MINOR]]"), beacon.stderr
    twice = subprocess.run([sys.executable, str(EXAMPLE), "--ble-tag", TAGS[0], "--ble-tag", TAGS[0].lower()], capture_output=True,
                           text=True, timeout=60)
    assert twice.returncode == 2 and twice.stderr.strip().splitlines()[-1].endswith(f"--ble-tag: tag address {TAGS[0]} given twice")
    # adapters that do not exist: without bleak, "needs bleak"; with it, BlueZ's refusal; either way one line, exit 1
    absent = subprocess.run([sys.executable, str(EXAMPLE), "--ble-tag", TAGS[0], "--iso-adapter", "hci97", "--dir-adapter", "hci98"],
                            capture_output=True, text=True, timeout=60)
    assert absent.returncode == 1 and "Traceback" not in absent.stderr, absent.stderr
    (line,) = [ln for ln in absent.stderr.splitlines() if " ERROR " in ln]
    assert "pip install bleak" in line or "Rx(iso) cannot scan on adapter hci97" in line, line
    assert json.dumps(absent.stdout) == '""'  # nothing else said
