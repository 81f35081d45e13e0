"""A node that speaks protocol 1.0 keeps working (docs/protocol.md, "Compatibility").

A sensors node written from the 1.0 page alone serves no descriptor and validates strictly
against the 1.0 schemas (``tests/nodes/v1_bus.py``, from the frozen ``docs/schemas/v1``): a
campaign that uses no newer feature runs on it to the end, and every message on its rig's keys
is a 1.0 message. A 1.0 controller gets 1.0 messages only (its POD model too). A node that
rejects an episode's message and says so on ``result/{rig}/rejected`` fails that episode at
once, with its reason, instead of after five silent 60 s timeouts.
"""

from __future__ import annotations

import json
import time

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.scenario import build_scenario
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end
from tests.nodes.v1_bus import StrictV1Bus, v1_errors, v1_schema_of

SMALL = {"steps": 25, "n_train": 200, "n_targets": 8}
RIG = "rig-1"


def _run(store, scheduler, tests, seed, algorithms, timeout) -> dict:
    return run_to_end(store, scheduler, "paper", SMALL, tests, seed, algorithms, timeout=timeout)


def _wire_errors(published: list[tuple[str, bytes]]) -> list[str]:
    """Every publication on a 1.0 rig's control, data, truth and timing keys that the 1.0
    schemas reject (the controller's ``EpisodeResult`` goes to the orchestrator, which speaks
    the newest version: checked apart)."""
    out = []
    for key, payload in published:
        if keys.rig_of(key) != RIG or key == keys.episode_result(RIG):
            continue
        name = v1_schema_of(key)
        errors = [f"no such key in protocol 1.0: {key}"] if name is None else v1_errors(name, payload)
        out += [f"{key}: {e}" for e in errors[:1]]
    return out


def test_a_strict_1_0_sensors_node_runs_a_campaign_to_the_end(mesh):
    strict: list[StrictV1Bus] = []
    bus, store, scheduler = mesh({RIG: {"sensors_bus": lambda b: strict.append(StrictV1Bus(b)) or strict[0], "sensors": {"describe": False}}})
    algorithms = ["ra2vipas", "rapas", "ravipas", "sweep"]
    c = _run(store, scheduler, 3, 11, algorithms, timeout=50.0)  # the old failure: a 60 s timeout per attempt
    node = strict[0]
    assert node.rejected == [], node.rejected[:3]
    assert c["status"] == "done", c["error"]
    assert node.violations == [], node.violations[:3]
    expected = run_campaign("paper", build_scenario("paper", SMALL), 3, 11, algorithms)
    got = untimed(c["results"])
    assert got.pop("assumptions")["rigs"] == [RIG]  # undescribed: scored under the scenario's assumptions
    assert got == untimed(expected)
    assert _wire_errors(bus.published) == []
    starts = [p for k, p in bus.published if k == keys.episode_control(RIG)]
    assert starts and all(b"stop_confidence" not in p for p in starts)
    # what the controller sent the orchestrator: current, and 1.0 once its 1.1 fields are left out
    from ra2vipas.services.protocol.messages import EpisodeResult, dump

    results = [p for k, p in bus.published if k == keys.episode_result(RIG)]
    assert len(results) == 3 * len(algorithms)
    for p in results:
        assert v1_errors("EpisodeResult", dump(EpisodeResult.model_validate_json(p), version="1.0")) == []


def test_a_1_0_controller_gets_only_1_0_messages(mesh):
    """A 1.0 controller asks for its POD model without ``protocol``: the learner answers in 1.0
    (no ``rf_noise_correlation``: white noise, what 1.0 means), and the episode starts and
    measurements it receives are 1.0 messages."""
    from ra2vipas.services.protocol.messages import PODRequest, dump

    def as_v1(key: str, payload: bytes) -> bytes:
        return dump(PODRequest.model_validate_json(payload), version="1.0") if key == keys.pod_model() else payload

    strict: list[StrictV1Bus] = []
    bus, store, scheduler = mesh({RIG: {"controller_bus": lambda b: strict.append(StrictV1Bus(b, check_sent=False, as_v1_request=as_v1)) or strict[0],
                                           "sensors": {"describe": False}}})
    c = _run(store, scheduler, 2, 5, ["ra2vipas", "rapas"], timeout=50.0)
    assert strict[0].rejected == [], strict[0].rejected[:3]
    assert c["status"] == "done", c["error"]
    assert len(store.episode_rows(c["id"])) == 4


def test_an_episode_a_node_keeps_rejecting_fails_fast_with_the_reason(mesh):
    """A newer orchestrator's field the sensors node does not know: the node drops the start
    and says so on ``result/{rig}/rejected``; each attempt fails at once and the campaign fails
    within seconds naming the field, not after five 60 s timeouts."""

    class NewerOrchestrator:
        """The sensors node's bus, with a field from a protocol it does not speak in every start."""

        def __init__(self, bus) -> None:
            self.bus = bus

        def subscribe(self, key, callback):
            def add_field(k, p):
                doc = json.loads(p)
                if doc.get("kind") == "start":
                    p = json.dumps({**doc, "box_sizes": True}).encode()
                callback(k, p)
            return self.bus.subscribe(key, add_field if key == keys.episode_control(RIG) else callback)

        def __getattr__(self, name):
            return getattr(self.bus, name)

    bus, store, scheduler = mesh({RIG: {"sensors_bus": NewerOrchestrator}})
    started = time.monotonic()
    c = _run(store, scheduler, 1, 3, ["rapas"], timeout=30.0)
    assert time.monotonic() - started < 30.0
    assert c["status"] == "failed"
    assert "failed 5 times" in c["error"] and "rejected" in c["error"] and "box_sizes" in c["error"], c["error"]
    assert "sensors of rig rig-1" in c["error"], c["error"]
