"""A campaign's POD model request on the in-memory bus when the learner cannot train yet
(issue 18, section 2): no sensors live, sensors live but out of the learner's reach, one
failed request. The model plane is ``model/pod`` (learner) over ``data/*/training`` (sensors);
liveliness tokens are what the orchestrator sees of the rigs."""

from __future__ import annotations

import time

import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.learner.node import LearnerNode
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import ErrorReply, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from ra2vipas.services.transport.bus import MemoryBus, QueryError
from tests.conftest import untimed

SMALL = {"steps": 20, "n_train": 200, "n_targets": 8}
FAST_RETRIES = {"tick_s": 0.05, "model_retry_s": (0.1, 0.4), "model_patience_s": 1.5}


@pytest.fixture()
def parts(tmp_path):
    bus = MemoryBus()
    store = Store(str(tmp_path / "retries.db"))
    closers: list = []
    yield bus, store, closers
    for c in reversed(closers):
        c.close()
    bus.close()
    store.close()


def create(store: Store, tests: int = 3, seed: int = 5) -> str:
    scenario = build_scenario("paper", SMALL)
    return store.create_campaign(preset="paper", overrides=SMALL, scenario=scenario.model_dump(mode="json"),
                                 algorithms=["ra2vipas"], tests=tests, seed=seed, mode="fast", stop_confidence=0.0)


def wait_finished(store: Store, cid: str, timeout: float = 60.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        c = store.campaign(cid)
        if c["status"] in ("done", "failed", "cancelled"):
            return c
        time.sleep(0.02)
    raise AssertionError(f"campaign did not finish: {store.campaign(cid)}")


class CountingLearner(LearnerNode):
    """The real learner, counting the model requests it is asked; the first ``fail_first``
    answer the error ``error`` instead."""

    def __init__(self, bus, fail_first: int = 0, error: str = "the learner's disk is full") -> None:
        self.requests = 0
        self._fail_first, self._error = fail_first, error
        super().__init__(bus)

    def _on_request(self, key: str, payload: bytes) -> bytes:
        self.requests += 1
        if self.requests <= self._fail_first:
            raise QueryError(dump(ErrorReply(error=self._error)).decode())
        return super()._on_request(key, payload)


def test_a_campaign_waits_for_sensors_that_come_up_seconds_later(parts):
    """Today the first request failed the campaign at once: ``no training stream: no sensors answered``."""
    bus, store, closers = parts
    closers.append(ControllerNode(bus, "rig-1"))
    learner = CountingLearner(bus)
    closers.append(learner)
    scheduler = Scheduler(bus, store, window=3, **FAST_RETRIES)
    closers.append(scheduler)
    cid = create(store, tests=4)
    scheduler.submit(cid)
    time.sleep(2.0)  # longer than the patience for sensors the orchestrator would see
    c = store.campaign(cid)
    assert c["status"] == "training", f"the campaign must wait for a rig's sensors: {c['status']} {c['error']}"
    assert learner.requests >= 1
    closers.append(SensorsNode(bus, "rig-1"))  # its token: the scheduler asks the learner again at once
    started = time.monotonic()
    c = wait_finished(store, cid)
    assert c["status"] == "done", c["error"]
    assert time.monotonic() - started < 30
    expected = run_campaign("paper", build_scenario("paper", SMALL), 4, 5, ["ra2vipas"])
    assert untimed(c["results"]) == untimed(expected)


def test_live_sensors_the_learner_cannot_reach_fail_the_campaign_naming_them_after_retries(parts):
    """The orchestrator sees rig-7's sensors and controller (their liveliness tokens), but no
    training queryable answers the learner: asked again with backoff, then failed with the rig's
    name and the likely cause, not ``no sensors answered``."""
    bus, store, closers = parts
    tokens = [bus.announce(keys.alive("sensors", "rig-7")), bus.announce(keys.alive("controller", "rig-7"))]
    learner = CountingLearner(bus)
    closers.append(learner)
    scheduler = Scheduler(bus, store, **FAST_RETRIES)
    closers.append(scheduler)
    deadline = time.monotonic() + 10
    while "rig-7" not in scheduler.live_rigs() and time.monotonic() < deadline:
        time.sleep(0.02)
    cid = create(store)
    started = time.monotonic()
    scheduler.submit(cid)
    c = wait_finished(store, cid)
    took = time.monotonic() - started
    for t in tokens:
        t.undeclare()
    assert c["status"] == "failed"
    error = c["error"]
    assert error != "POD model unavailable: no training stream: no sensors answered"
    assert error.startswith("POD model unavailable: the learner's training query reached no sensors"), error
    assert "sees the sensors of rig rig-7 live" in error and "peer mode" in error and "--zenoh-mode client" in error, error
    assert "--listen" in error
    assert learner.requests >= 3, "asked again with backoff before failing"
    assert FAST_RETRIES["model_patience_s"] <= took < 15


def test_one_failed_model_request_does_not_fail_the_campaign(parts):
    bus, store, closers = parts
    closers.extend([SensorsNode(bus, "rig-1"), ControllerNode(bus, "rig-1")])
    learner = CountingLearner(bus, fail_first=1)
    closers.append(learner)
    scheduler = Scheduler(bus, store, window=3, **FAST_RETRIES)
    closers.append(scheduler)
    cid = create(store, tests=3, seed=8)
    scheduler.submit(cid)
    c = wait_finished(store, cid)
    assert c["status"] == "done", c["error"]
    assert learner.requests >= 2  # the failed one, the one that trained (and the controller's, cached)
    assert untimed(c["results"]) == untimed(run_campaign("paper", build_scenario("paper", SMALL), 3, 8, ["ra2vipas"]))


def test_a_learner_that_keeps_failing_fails_the_campaign_with_its_error(parts):
    bus, store, closers = parts
    closers.extend([SensorsNode(bus, "rig-1"), ControllerNode(bus, "rig-1")])
    learner = CountingLearner(bus, fail_first=10**6)
    closers.append(learner)
    scheduler = Scheduler(bus, store, **FAST_RETRIES)
    closers.append(scheduler)
    cid = create(store)
    scheduler.submit(cid)
    c = wait_finished(store, cid)
    assert c["status"] == "failed"
    assert c["error"].startswith("POD model unavailable: the learner's disk is full ("), c["error"]
    assert learner.requests >= 3


def _described(scheduler: Scheduler, rig: str) -> None:
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        state = scheduler.rigs.get(rig)
        if state is not None and state.described == "described" and rig in scheduler.live_rigs():
            return
        time.sleep(0.02)
    raise AssertionError(f"rig {rig} was not described")


def test_a_training_episode_too_short_to_learn_from_fails_at_once_on_a_simulated_rig(parts):
    """BLE with n_train = 40 (8 advertisements): a simulated rig's training episode of this scenario and seed is the
    same each time, so the campaign fails after one request with the learner's words, not after the model patience."""
    bus, store, closers = parts
    closers.extend([SensorsNode(bus, "rig-1"), ControllerNode(bus, "rig-1")])
    learner = CountingLearner(bus)
    closers.append(learner)
    scheduler = Scheduler(bus, store, **{**FAST_RETRIES, "model_patience_s": 60.0})
    closers.append(scheduler)
    _described(scheduler, "rig-1")
    overrides = {"steps": 20, "n_train": 40}
    scenario = build_scenario("ble", overrides)
    cid = store.create_campaign(preset="ble", overrides=overrides, scenario=scenario.model_dump(mode="json"), algorithms=["rapas"],
                                tests=2, seed=1, mode="fast", stop_confidence=0.0)
    scheduler.submit(cid)
    c = wait_finished(store, cid, timeout=50)
    assert c["status"] == "failed" and learner.requests == 1, (c["status"], learner.requests)
    assert c["error"] == ("POD model unavailable: cannot learn the POD from the training episode: the training stream carries 8 "
                          "Rx(iso) advertisements in 40 samples; the POD learner needs at least 10 (n_train = 40: raise it) (every "
                          "live rig is simulated or a recorded survey: its training episode of this scenario and seed is the "
                          "same each time)"), c["error"]


def test_the_same_error_from_a_real_rigs_training_episode_is_asked_again(parts):
    """A hardware rig records a new training episode each time (a tag back in range): the learner's "too short"
    is asked again, as any failure is, and the second answer runs the campaign."""
    from ra2vipas.services.learner.trained import TRAINING_DATA_ERROR
    from ra2vipas.services.protocol.rig import RigDescriptor

    bus, store, closers = parts
    paper = build_scenario("paper", SMALL)
    hardware = RigDescriptor(rig="rig-1", kind="hardware", frames_per_rf=paper.frames_per_rf, rf_period_s=paper.rf_period_s,
                             fov_half_angle_deg=paper.fov_half_angle_deg, box_bearing_noise_deg=paper.box_bearing_noise_deg,
                             rx_dir={"model": "paper", "curvature": paper.antenna_curvature}, episode_truth=True,
                             training_truth=True, protocol="1.5")
    closers.extend([SensorsNode(bus, "rig-1", descriptor=hardware), ControllerNode(bus, "rig-1")])
    learner = CountingLearner(bus, fail_first=1, error=f"{TRAINING_DATA_ERROR}: the training stream carries 3 samples")
    closers.append(learner)
    scheduler = Scheduler(bus, store, window=3, **FAST_RETRIES)
    closers.append(scheduler)
    _described(scheduler, "rig-1")
    cid = create(store, tests=2, seed=8)
    scheduler.submit(cid)
    c = wait_finished(store, cid)
    assert c["status"] == "done", c["error"]
    assert learner.requests >= 2
