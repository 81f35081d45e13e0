"""Defence in depth at the orchestrator (issue 14): results and truth are accepted only on the
key of the rig an episode was assigned to, for the attempt in flight, and episode ids carry
an unguessable nonce. A forger that sees every episode start (the worst case: Zenoh's access
control is what keeps it off the control plane) still cannot change a campaign's results
unless it speaks on the assigned rig's own keys."""

from __future__ import annotations

import re
import threading

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeStart, EpisodeTruth, dump
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.transport.bus import MemoryBus
from tests.conftest import untimed
from tests.nodes.conftest import run_to_end, settle
from tests.nodes.test_mesh_in_memory import SMALL


class Forger:
    """Watches rig-1's episode starts and answers each with forged results and truth: on the
    other rig's keys, on a rig that does not exist, and with guessed ids (no nonce) on rig-1's
    own keys. Every forged answer points at the wrong target."""

    def __init__(self, bus: MemoryBus) -> None:
        self.bus = bus
        self.sent = 0
        self._lock = threading.Lock()
        self._handle = bus.subscribe(keys.episode_control("rig-1"), self._on_control)

    def _on_control(self, _key: str, payload: bytes) -> None:
        if b'"start"' not in payload:
            return
        start = EpisodeStart.model_validate_json(payload)
        steps = start.scenario.steps
        guessed = start.episode_id.rsplit(".", 1)[0]  # campaign.test.algorithm.attempt: the old, guessable id
        for rig, eid in (("rig-2", start.episode_id), ("evil", start.episode_id), ("rig-1", guessed)):
            self.bus.publish(keys.episode_truth(rig), dump(EpisodeTruth(episode_id=eid, bearings_rad=(0.0, 3.0), ranges_m=(1.0, 1.0),
                                                                         tx_index=1)))
            self.bus.publish(keys.episode_result(rig), dump(EpisodeResult(episode_id=eid, rig=rig, estimates_rad=(0.0,) * steps,
                                                                           pans_rad=(0.0,) * steps, rewards=(0.0,) * steps)))
            # and one that names the right rig in its body but comes on another rig's key
            self.bus.publish(keys.episode_result(rig), dump(EpisodeResult(episode_id=eid, rig="rig-1", estimates_rad=(0.0,) * steps,
                                                                           pans_rad=(0.0,) * steps, rewards=(0.0,) * steps)))
            with self._lock:
                self.sent += 3

    def close(self) -> None:
        self._handle.undeclare()


def test_forged_results_and_truth_change_nothing_and_are_counted(mesh):
    bus, store, scheduler = mesh()
    forger = Forger(bus)
    try:
        algorithms = ["ra2vipas", "rapas"]
        c = run_to_end(store, scheduler, "paper", SMALL, 4, 5, algorithms)
        assert c["status"] == "done", c["error"]
        assert untimed(c["results"]) == untimed(run_campaign("paper", build_scenario("paper", SMALL), 4, 5, algorithms))
        settle(bus, scheduler.loop)
        assert forger.sent >= 3 * 3 * 8  # three forgeries of three messages for each of the 8 episodes
        rejected = scheduler.status()["rejected"]
        assert rejected["wrong_rig"] > 0 and rejected["not_in_flight"] > 0
        assert rejected["wrong_rig"] + rejected["not_in_flight"] == forger.sent  # every forged message, and nothing else
        starts = [EpisodeStart.model_validate_json(p) for k, p in bus.published if k == keys.episode_control("rig-1") and b'"start"' in p]
        assert starts and all(re.fullmatch(r"[0-9a-f]{12}\.\d+\.(ra2vipas|rapas)\.\d+\.[0-9a-f]{16}", s.episode_id) for s in starts)
        assert len({s.episode_id.rsplit(".", 1)[1] for s in starts}) == len(starts)  # a fresh nonce every time
    finally:
        forger.close()


def test_the_same_forgery_on_the_assigned_rigs_own_keys_would_succeed(mesh):
    """The check can fail: what the orchestrator refuses above is exactly what it would take
    from the assigned rig itself (so the defence, not luck, kept the results right)."""
    bus, store, scheduler = mesh()

    def forge(_key: str, payload: bytes) -> None:
        if b'"start"' in payload:
            start = EpisodeStart.model_validate_json(payload)
            steps = start.scenario.steps
            bus.publish(keys.episode_truth("rig-1"), dump(EpisodeTruth(episode_id=start.episode_id, bearings_rad=(0.0, 3.0),
                                                                        ranges_m=(1.0, 1.0), tx_index=1)))
            bus.publish(keys.episode_result("rig-1"), dump(EpisodeResult(episode_id=start.episode_id, rig="rig-1",
                                                                          estimates_rad=(0.0,) * steps, pans_rad=(0.0,) * steps,
                                                                          rewards=(0.0,) * steps)))

    handle = bus.subscribe(keys.episode_control("rig-1"), forge)
    try:
        c = run_to_end(store, scheduler, "paper", SMALL, 3, 5, ["rapas"])
        assert c["status"] == "done"
        assert c["results"]["algorithms"]["rapas"]["dr_final"] == 0.0  # every forged estimate points at the wrong target
    finally:
        handle.undeclare()
