"""Hostile traffic: thousands of malformed messages on every key of the mesh (garbage bytes,
wrong schemas, NaN, wrong types, huge and deeply nested payloads) are logged and dropped; no
service crashes and the mesh still computes the right answer afterwards."""

from __future__ import annotations

import json
import random
import time

import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import Command, EpisodeResult, EpisodeStart, EpisodeTruth, Measurement
from ra2vipas.services.protocol.scenario import build_scenario
from tests import http
from tests.conftest import differences, untimed
from tests.integration.conftest import Procs, alive, children_of, stack_zenoh_session, start_stack, stop_stack

VALID = {
    "command": Command(episode_id="x.0.ra2vipas.1", step=0, pan_rad=0.1).model_dump(mode="json"),
    "measurement": Measurement.model_validate({"episode_id": "x.0.ra2vipas.1", "step": 0, "pan_rad": 0.0,
                                               "rf": {"iso_rssi_dbm": -40.0, "dir_rssi_dbm": -30.0},
                                               "frames": [{"box_bearings_rad": [0.1]}] * 10}).model_dump(mode="json"),
    "start": EpisodeStart(episode_id="x.0.ra2vipas.1", campaign_id="x", test_index=0, algorithm="ra2vipas", seed=1,
                          scenario=build_scenario("paper", {"steps": 5})).model_dump(mode="json"),
    "result": EpisodeResult(episode_id="x.0.ra2vipas.1", rig="rig-1", estimates_rad=(0.1,)).model_dump(mode="json"),
    "truth": EpisodeTruth(episode_id="x.0.ra2vipas.1", bearings_rad=(0.1,), ranges_m=(1.0,), tx_index=0).model_dump(mode="json"),
}
BAD_VALUES = [float("nan"), float("inf"), -1, 10**30, "x", None, [], {}, True, "A" * 5000, -1e308, [[[[]]]]]


def _random_json(rng: random.Random, depth: int = 0):
    kind = rng.randrange(6 if depth < 4 else 3)
    if kind == 0:
        return rng.choice([0, -1, 1.5, 1e300, "", "text", True, None])
    if kind == 1:
        return rng.random() * 10**rng.randrange(-5, 20)
    if kind == 2:
        return "".join(rng.choice("abc{}[]\\\"") for _ in range(rng.randrange(20)))
    if kind == 3:
        return [_random_json(rng, depth + 1) for _ in range(rng.randrange(5))]
    return {rng.choice(["episode_id", "step", "pan_rad", "rf", "frames", "kind", "x"]): _random_json(rng, depth + 1) for _ in range(rng.randrange(5))}


def _mutate(rng: random.Random, message: dict) -> dict:
    m = json.loads(json.dumps(message))
    target = m
    while True:
        key = rng.choice(list(target))
        if isinstance(target[key], dict) and rng.random() < 0.5:
            target = target[key]
            continue
        target[key] = rng.choice(BAD_VALUES)
        return m


def payloads(n: int, seed: int = 0):
    rng = random.Random(seed)
    for i in range(n):
        r = rng.random()
        if r < 0.2:
            yield bytes(rng.randrange(256) for _ in range(rng.randrange(300)))
        elif r < 0.45:
            yield json.dumps(_random_json(rng)).encode()
        elif r < 0.9:
            yield json.dumps(_mutate(rng, VALID[rng.choice(list(VALID))]), allow_nan=True).encode()
        elif r < 0.95:
            yield b"[" * rng.randrange(1000, 100000)
        else:
            yield json.dumps(rng.choice(list(VALID.values())))[:-1].encode()  # truncated
    yield b"x" * (3 << 20)  # larger than any service accepts
    yield json.dumps({"episode_id": "x", "step": 0, "pan_rad": 0.0, "frames": [{"box_bearings_rad": [0.0] * 100000}]}).encode()


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    registry = Procs()
    state = start_stack(registry, tmp_path_factory.mktemp("fuzz"), rigs=1)
    yield state
    stop_stack(registry, state["up"])


def test_thousands_of_hostile_messages_crash_nothing(stack):
    children = children_of(stack["up"].pid)
    pub_keys = [keys.command("rig-1"), keys.measurement("rig-1"), keys.episode_control("rig-1"), keys.episode_result("rig-1"),
                keys.episode_timing("rig-1"), keys.episode_truth("rig-1")]
    query_keys = [keys.pod_model(), keys.training("rig-1"), keys.training_truth("rig-1")]
    sent = 0
    with stack_zenoh_session(stack["up"].pid) as session:  # a hostile process that has the stack's credentials
        time.sleep(1.0)
        publishers = [session.declare_publisher(k) for k in pub_keys]
        for i, payload in enumerate(payloads(3000)):
            publishers[i % len(publishers)].put(payload)
            sent += 1
            if i % 25 == 0:
                for reply in session.get(query_keys[(i // 25) % len(query_keys)], payload=payload[:100000], timeout=5.0):
                    assert reply.ok is None or reply.err is None
                sent += 1
        time.sleep(2.0)
    assert sent > 3000
    assert [p for p in children if not alive(p)] == [], "a service died"
    assert children_of(stack["up"].pid) == children, "a service was restarted"
    logs = "".join(p.read_text(errors="replace") for p in stack["logs"].glob("*.log"))
    assert "dropping" in logs  # the drops were logged

    overrides = {"steps": 40, "n_train": 250}
    body = {"preset": "paper", "tests": 3, "seed": 17, "algorithms": ["ra2vipas", "ravipas"], "overrides": overrides}
    cid = http.post(f"{stack['api']}/campaigns", json=body, timeout=30).json()["id"]
    deadline = time.monotonic() + 120
    while (c := http.get(f"{stack['api']}/campaigns/{cid}", timeout=10).json())["status"] not in ("done", "failed"):
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert c["status"] == "done", c["error"]
    got = http.get(f"{stack['api']}/campaigns/{cid}/results", timeout=10).json()
    expected = untimed(run_campaign("paper", build_scenario("paper", overrides), 3, 17, ["ra2vipas", "ravipas"]))
    assert untimed(got) == expected, differences(untimed(got), expected)
