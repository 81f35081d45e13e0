"""A rig faked at the wire level that answers every episode at once: what measures how many
episodes one orchestrator can score and store (``ra2vipas bench orchestrator``).

``InstantRig`` speaks the rig's side of docs/protocol.md on a ``Bus``: it serves its
descriptor and the training queryables (the learner trains on it like on a simulated rig),
announces its sensors and controller, and answers each ``EpisodeStart`` on
``control/{rig}/episode`` with an ``EpisodeTruth`` and a complete ``EpisodeResult`` (every
step's estimate: the Tx's bearing), both encoded once per campaign and stamped with the
episode's id, so answering costs the rig a JSON parse and two publications. Nothing is
simulated per episode: the orchestrator is the only part of the mesh doing real work.
"""

from __future__ import annotations

import json
import logging

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeResult, TrainingStream, TrainingTruth, dump
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.sensors.node import _training_request, simulated_descriptor
from ra2vipas.services.sensors.world import SimulatedPlatform, TrainingEpisode, episode_truth
from ra2vipas.services.transport.bus import Bus, undeclare_all
from ra2vipas.services.transport.runtime import EventLoop

log = logging.getLogger(__name__)

PLACEHOLDER = "instant-rig-episode-placeholder"


class InstantRig:
    """One fake rig on ``bus``; ``answered`` counts the episodes it answered."""

    def __init__(self, bus: Bus, rig: str) -> None:
        self.bus = bus
        self.rig = keys.check_chunk(rig)
        self.loop = EventLoop(f"instant-{rig}")
        self.answered = 0
        self._templates: dict[str, tuple[bytes, bytes]] = {}  # campaign id -> (truth, result) with PLACEHOLDER
        self._truth_key, self._result_key = keys.episode_truth(rig), keys.episode_result(rig)
        info = dump(simulated_descriptor(rig))
        self._handles = [
            bus.serve(keys.rig_info(rig), lambda _k, _p: info),
            bus.serve(keys.training(rig), self._on_training),
            bus.serve(keys.training_truth(rig), self._on_training_truth),
            bus.subscribe(keys.episode_control(rig), lambda _k, p: self.loop.post(self._on_control, p)),
        ]
        self._handles += [bus.announce(keys.alive("sensors", rig)), bus.announce(keys.alive("controller", rig))]

    def _on_control(self, payload: bytes) -> None:
        try:
            msg = json.loads(payload)
            eid, campaign = msg["episode_id"], msg["campaign_id"]
        except (ValueError, KeyError, TypeError):
            return  # an EpisodeStop, or not ours
        templates = self._templates.get(campaign)
        if templates is None:
            templates = self._templates[campaign] = self._encode(Scenario.model_validate(msg["scenario"]), int(msg["seed"]))
        stamp = eid.encode()
        self.bus.publish(self._truth_key, templates[0].replace(PLACEHOLDER.encode(), stamp))
        self.bus.publish(self._result_key, templates[1].replace(PLACEHOLDER.encode(), stamp))
        self.answered += 1

    def _encode(self, scenario: Scenario, seed: int) -> tuple[bytes, bytes]:
        truth = SimulatedPlatform(scenario, seed, 0).truth
        tx = float(truth.bearings_rad[truth.tx_index])
        steps = scenario.steps
        result = EpisodeResult(episode_id=PLACEHOLDER, rig=self.rig, estimates_rad=(tx,) * steps, pans_rad=(tx,) * steps,
                               rewards=(0.0,) * steps)
        return dump(episode_truth(truth, PLACEHOLDER)), dump(result)

    def _on_training(self, _key: str, payload: bytes) -> bytes:
        req = _training_request(payload)
        return dump(TrainingStream.model_construct(job_id=req.job_id, samples=tuple(TrainingEpisode(req.scenario, req.seed).samples())))

    def _on_training_truth(self, _key: str, payload: bytes) -> bytes:
        req = _training_request(payload)
        truth = TrainingEpisode(req.scenario, req.seed).truth
        return dump(TrainingTruth(job_id=req.job_id, rssi_dbm=tuple(float(v) for v in truth.rssi_dbm), pod=tuple(float(v) for v in truth.pod)))

    def close(self) -> None:
        undeclare_all(self._handles)
        self.loop.stop()
