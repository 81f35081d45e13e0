"""Record a campaign's messages to an MCAP file, and replay it: re-score, or re-run a new
controller on the recorded episodes where its pans match the recorded ones.

MCAP (https://mcap.dev) is the robotics log format; the file opens in Foxglove. Layout:

* one channel per Zenoh key (topic = the key expression, e.g.
  ``ra2vipas/v1/data/rig-1/measurement``), message encoding ``json``: the payload exactly as it
  travelled (commands, measurements, episode starts and stops, results, timing, truth);
* each channel's schema is the message's JSON Schema (schema encoding ``jsonschema``), the same
  documents as ``docs/schemas``;
* ``ra2vipas/v1/rig/{rig}/info`` carries each rig's ``RigDescriptor`` and ``ra2vipas/v1/model/pod``
  the campaign's ``PODResponse`` (what a new controller needs to run);
* a metadata record ``ra2vipas.campaign`` holds the campaign object and its results object
  (``campaign``, ``results``: JSON text), and ``ra2vipas.recording`` how it was made
  (``source``: ``live`` with every message, or ``store``: what the orchestrator kept, without
  measurements: enough to re-score, not to re-run).

Replaying re-scores every recorded episode with the same association rule and reduction as the
orchestrator (``replay_scores``): it gives the recorded results back value for value. Re-running
(``rerun``) feeds a controller the recorded measurements in order, for as long as the pan it asks
for next is the pan the next recorded sample was taken at (a measurement taken elsewhere would
not be the one it asked for): the current controller code on its own recording matches every pan.
"""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import (
    Command,
    EpisodeResult,
    EpisodeStart,
    EpisodeStop,
    EpisodeTiming,
    EpisodeTruth,
    Measurement,
    PODResponse,
    episode_control_adapter,
)
from ra2vipas.services.protocol.rig import RigDescriptor

PROFILE = "ra2vipas"
CAMPAIGN_METADATA = "ra2vipas.campaign"
RECORDING_METADATA = "ra2vipas.recording"

# (plane, last chunk) of each recorded key family -> the message's schema
_FAMILIES = {
    ("control", "episode"): "EpisodeControl",
    ("data", "command"): "Command",
    ("data", "measurement"): "Measurement",
    ("result", "episode"): "EpisodeResult",
    ("result", "timing"): "EpisodeTiming",
    ("truth", "episode"): "EpisodeTruth",
    ("rig", "info"): "RigDescriptor",
    ("model", "pod"): "PODResponse",
}
SUBSCRIPTIONS = (keys.episode_control_all(), f"{keys.PREFIX}/data/*/command", f"{keys.PREFIX}/data/*/measurement",
                 keys.episode_result_all(), keys.episode_timing_all(), keys.episode_truth_all())
"""What a live recorder subscribes to (an identity that records needs these grants)."""


class RecordingError(Exception):
    """A recording cannot be written or read; the message says why in one line."""


def _schemas() -> dict[str, dict]:
    from ra2vipas.services.protocol.schemas import schema_documents

    return {name.removesuffix(".json"): doc for name, doc in schema_documents().items()}


def family_of(key: str) -> str | None:
    """The schema name of a recorded key (``Measurement`` for ``ra2vipas/v1/data/x/measurement``)."""
    parts = key.split("/")
    if key == keys.pod_model():
        return "PODResponse"
    if len(parts) == 5 and "/".join(parts[:2]) == keys.PREFIX:
        return _FAMILIES.get((parts[2], parts[4]))
    return None


def _campaign_of(schema: str, payload: bytes) -> tuple[str | None, str | None]:
    """(campaign id, episode id) of a recorded message, from its JSON (episode ids are
    ``campaign.test.algorithm.attempt.nonce``, the orchestrator's)."""
    try:
        msg = json.loads(payload)
    except ValueError:
        return None, None
    if not isinstance(msg, dict):
        return None, None
    eid = msg.get("episode_id")
    cid = msg.get("campaign_id") or (eid.split(".", 1)[0] if isinstance(eid, str) and "." in eid else None)
    return cid, eid if isinstance(eid, str) else None


@dataclass
class _Entry:
    key: str
    payload: bytes
    log_time: int


class Recorder:
    """Records a campaign's traffic from a ``Bus`` (live) into memory; ``write`` saves the MCAP.

    Subscribe it *before* the campaign's first episode starts (``ra2vipas campaign start
    --record``): messages of any campaign are kept until ``write`` keeps only the one asked for.
    """

    def __init__(self, bus=None, clock=time.time_ns) -> None:
        self.entries: list[_Entry] = []
        self._lock = threading.Lock()
        self.clock = clock
        self._handles = [bus.subscribe(k, self.note) for k in SUBSCRIPTIONS] if bus is not None else []

    def note(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.entries.append(_Entry(key, bytes(payload), self.clock()))

    def stop(self) -> None:
        for h in self._handles:
            try:
                h.undeclare()
            except Exception:
                pass
        self._handles = []

    def campaign_entries(self, campaign_id: str) -> list[_Entry]:
        with self._lock:
            return [e for e in self.entries if _campaign_of(family_of(e.key) or "", e.payload)[0] == campaign_id]


def write_mcap(path: str | Path, entries: Iterable[_Entry], *, campaign: dict, results: dict | None, source: str,
               descriptors: dict[str, dict] | None = None, pod: dict | None = None) -> int:
    """Write ``entries`` (plus the rigs' descriptors and the POD model) to an MCAP file with the
    JSON Schemas embedded; return the number of messages written.

    Raises
    ------
    RecordingError
        The file cannot be written.
    """
    from mcap.writer import Writer

    schemas = _schemas()
    entries = sorted(entries, key=lambda e: e.log_time)
    start = entries[0].log_time if entries else time.time_ns()
    extra = [_Entry(keys.rig_info(rig), json.dumps(d).encode(), start) for rig, d in sorted((descriptors or {}).items()) if d]
    if pod is not None:
        extra.append(_Entry(keys.pod_model(), json.dumps(pod).encode(), start))
    try:
        with open(path, "wb") as stream:
            writer = Writer(stream)
            writer.start(profile=PROFILE, library="ra2vipas")
            schema_ids: dict[str, int] = {}
            channels: dict[str, int] = {}
            count = 0
            for seq, e in enumerate(extra + entries):
                name = family_of(e.key)
                if name is None:
                    continue
                if name not in schema_ids:
                    schema_ids[name] = writer.register_schema(name=name, encoding="jsonschema",
                                                              data=json.dumps(schemas[name]).encode())
                if e.key not in channels:
                    channels[e.key] = writer.register_channel(topic=e.key, message_encoding="json", schema_id=schema_ids[name])
                writer.add_message(channel_id=channels[e.key], log_time=e.log_time, publish_time=e.log_time, data=e.payload,
                                   sequence=seq)
                count += 1
            writer.add_metadata(CAMPAIGN_METADATA, {"campaign": json.dumps(campaign), "results": json.dumps(results)})
            writer.add_metadata(RECORDING_METADATA, {"source": source, "format": "ra2vipas recording v1"})
            writer.finish()
    except OSError as err:
        raise RecordingError(f"cannot write {path}: {err.strerror or err}") from None
    return count


# -- reading --------------------------------------------------------------------------------------

@dataclass
class RecordedEpisode:
    episode_id: str
    start: EpisodeStart | None = None
    commands: dict[int, Command] = field(default_factory=dict)
    measurements: dict[int, Measurement] = field(default_factory=dict)
    result: EpisodeResult | None = None
    truth: EpisodeTruth | None = None
    timing: EpisodeTiming | None = None
    stopped: bool = False


@dataclass
class Recording:
    campaign: dict
    results: dict | None
    source: str
    episodes: dict[str, RecordedEpisode]
    descriptors: dict[str, RigDescriptor]
    pod: PODResponse | None

    def recorded(self) -> list[RecordedEpisode]:
        """The episodes that were recorded by the orchestrator: a result and a truth, the last
        attempt of each (test, algorithm), in (test, algorithm) order."""
        best: dict[tuple[int, str], RecordedEpisode] = {}
        for ep in self.episodes.values():
            if ep.start is None or ep.result is None or ep.truth is None or ep.result.status != "done":
                continue
            k = (ep.start.test_index, ep.start.algorithm)
            if k not in best or _attempt(ep.episode_id) > _attempt(best[k].episode_id):
                best[k] = ep
        return [best[k] for k in sorted(best)]


def _attempt(eid: str) -> int:
    parts = eid.split(".")
    try:
        return int(parts[3])
    except (IndexError, ValueError):
        return 0


def read_mcap(path: str | Path) -> Recording:
    """Load a recording.

    Raises
    ------
    RecordingError
        Not a readable MCAP file, or not a ra2vipas recording.
    """
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    episodes: dict[str, RecordedEpisode] = {}
    descriptors: dict[str, RigDescriptor] = {}
    pod = None
    meta: dict[str, dict] = {}
    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            for record in reader.iter_metadata():
                meta[record.name] = dict(record.metadata)
            stream.seek(0)
            reader = make_reader(stream)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                name = schema.name if schema is not None else family_of(channel.topic)
                data = message.data
                if name == "RigDescriptor":
                    d = RigDescriptor.model_validate_json(data)
                    descriptors[d.rig] = d
                    continue
                if name == "PODResponse":
                    pod = PODResponse.model_validate_json(data)
                    continue
                if name == "EpisodeControl":
                    msg = episode_control_adapter.validate_json(data)
                    ep = episodes.setdefault(msg.episode_id, RecordedEpisode(msg.episode_id))
                    if isinstance(msg, EpisodeStop):
                        ep.stopped = True
                    elif ep.start is None:
                        ep.start = msg
                    continue
                model = {"Command": Command, "Measurement": Measurement, "EpisodeResult": EpisodeResult,
                         "EpisodeTiming": EpisodeTiming, "EpisodeTruth": EpisodeTruth}.get(name)
                if model is None:
                    continue
                msg = model.model_validate_json(data)
                ep = episodes.setdefault(msg.episode_id, RecordedEpisode(msg.episode_id))
                if isinstance(msg, Command):
                    ep.commands.setdefault(msg.step, msg)
                elif isinstance(msg, Measurement):
                    ep.measurements.setdefault(msg.step, msg)
                elif isinstance(msg, EpisodeResult):
                    ep.result = ep.result or msg
                elif isinstance(msg, EpisodeTiming):
                    ep.timing = ep.timing or msg
                else:
                    ep.truth = ep.truth or msg
    except FileNotFoundError:
        raise RecordingError(f"no file {path}") from None
    except (OSError, McapError, ValueError) as err:
        raise RecordingError(f"{path} is not a readable ra2vipas recording: {str(err).splitlines()[0][:200]}") from None
    if CAMPAIGN_METADATA not in meta:
        raise RecordingError(f"{path} is an MCAP file but not a ra2vipas recording (no {CAMPAIGN_METADATA} metadata)")
    return Recording(campaign=json.loads(meta[CAMPAIGN_METADATA]["campaign"]),
                     results=json.loads(meta[CAMPAIGN_METADATA].get("results") or "null"),
                     source=meta.get(RECORDING_METADATA, {}).get("source", "live"), episodes=episodes, descriptors=descriptors,
                     pod=pod)


# -- replay ---------------------------------------------------------------------------------------

def replay_scores(rec: Recording) -> dict[str, Any]:
    """Re-score the recorded episodes (association rule, eq. 11) and reduce them like the
    orchestrator: the results object, value for value what the campaign recorded (bar the
    wall-clock fields).

    Raises
    ------
    RecordingError
        A test of the campaign has no recorded episode.
    """
    from ra2vipas.services.learner.trained import TrainedPOD
    from ra2vipas.services.orchestrator.metrics import score_episode, truth_bearings
    from ra2vipas.services.orchestrator.reduce import AlgorithmTally, LatencyTally, held, results_object
    from ra2vipas.services.orchestrator.rigcheck import RigChecks
    from ra2vipas.services.orchestrator.scheduler import score_tags
    from ra2vipas.services.protocol.scenario import Scenario

    c = rec.campaign
    scenario = Scenario.model_validate(c["scenario"])
    steps = scenario.steps
    tallies = {a: AlgorithmTally(steps, scenario.rf_period_s) for a in c["algorithms"]}
    checks = RigChecks()
    latencies = LatencyTally()
    episodes = rec.recorded()
    have = {(ep.start.test_index, ep.start.algorithm) for ep in episodes}
    missing = [(k, a) for k in range(c["tests"]) for a in c["algorithms"] if (k, a) not in have]
    if missing:
        raise RecordingError(f"{len(missing)} test(s) have no recorded episode, e.g. test {missing[0][0]} of {missing[0][1]}")
    for ep in episodes:
        res, truth = ep.result, ep.truth
        hits, in_fov, _ = score_episode(np.asarray(res.estimates_rad), truth_bearings(truth, steps), truth.tx_index,
                                        scenario.fov_half_angle_rad, steps, res.decided_step)
        tallies[ep.start.algorithm].add(hits, in_fov, held(list(res.confidences), steps) or None, res.decided_step,
                                        len(res.estimates_rad), test_index=ep.start.test_index)
        tags = score_tags(res, truth, truth_bearings(truth, steps), scenario, res.decided_step)
        if tags:  # several tags (issue 21): each scored against its carrier, as the orchestrator does
            tallies[ep.start.algorithm].add_tags(np.asarray(tags["hits"], dtype=bool), np.asarray(tags["in_fov"], dtype=bool),
                                                 None if tags["confidences"] is None else np.asarray(tags["confidences"]),
                                                 tags["decided"])
        checks.add(res.rig, None if res.model_check is None else res.model_check.model_dump(mode="json"))
        if ep.timing is not None:
            latencies.add(ep.timing.latencies_ms)
    pod_block = (rec.results or {}).get("pod") or {}
    pod = TrainedPOD(model=None, r2=pod_block.get("r2"), train_seconds=pod_block.get("train_seconds") or 0.0)
    results = results_object(c["preset"], scenario, c["tests"], c["seed"], pod, tallies, None, c.get("stop_confidence") or 0.0)
    results["id"] = c.get("id")  # the recorded campaign's, as its API results carry it
    if latencies.count:
        results["latency_ms"] = latencies.summary()
    checks.notes(results)
    if pod_block.get("note"):
        results["pod"]["note"] = pod_block["note"]
    return results


@dataclass
class Rerun:
    """One recorded episode re-run by a controller: how many of its steps it could take (its
    pans matched the recorded ones) and its estimates there."""

    episode_id: str
    test_index: int
    algorithm: str
    steps: int  # the episode's recorded steps
    matched: int  # steps the new controller took on recorded measurements
    estimates: list[float]
    hits: list[bool]
    same_estimates: bool  # equal, step for step, to the recorded controller's (every tag's, with several)
    tag_estimates: list[list[float]] = field(default_factory=list)  # several tags (issue 21): per tag, per step taken
    tag_hits: list[list[bool]] = field(default_factory=list)  # per tag, eq. 11 against its carrier
    # why it stopped before the recorded end: "pan" (the controller asked for a pan other than the next recorded
    # sample's), "missing" (the recording lacks the measurement of a step the episode took: a message lost), None
    stopped: str | None = None


def rerun(rec: Recording, algorithm: str | None = None, settings=None, pan_tolerance_rad: float = 1e-9) -> list[Rerun]:
    """Feed every recorded episode's measurements to a new controller (the recorded episode's
    algorithm, or ``algorithm``; ``settings`` a ``ControllerSettings``), step by step, while the
    pan it asks for next is the pan the next sample was recorded at (within
    ``pan_tolerance_rad``).

    Raises
    ------
    RecordingError
        The recording has no measurements (made from the store) or no POD model.
    """
    from ra2vipas.services.controller import registry
    from ra2vipas.services.controller.contract import episode_context
    from ra2vipas.services.controller.policy import sensor_config_from_descriptor, sensor_config_from_scenario
    from ra2vipas.services.orchestrator.metrics import score_episode, truth_bearings
    from ra2vipas.services.protocol.angles import wrap

    episodes = rec.recorded()
    if not any(ep.measurements for ep in episodes):
        raise RecordingError(f"the recording holds no measurements (source: {rec.source}): it can be re-scored, not re-run")
    if rec.pod is None:
        raise RecordingError("the recording has no POD model (ra2vipas/v1/model/pod): a controller cannot run without it")
    out = []
    for ep in episodes:
        start = ep.start
        sc = start.scenario
        descriptor = rec.descriptors.get(ep.result.rig)
        uses_descriptor = ep.result.model_check is not None and ep.result.model_check.sensor_model == "descriptor"
        config = sensor_config_from_descriptor(descriptor, sc) if (descriptor is not None and uses_descriptor) else sensor_config_from_scenario(sc)
        # the policy as the controller node makes it (registry.create): with several tags, the joint search
        context = episode_context(config, rec.pod.model, sc, start.seed, start.test_index, start.stop_confidence)
        ctl = registry.create(algorithm or start.algorithm, context, settings)
        pan = ctl.first_pan()
        estimates: list[float] = []
        tag_estimates: list[list[float]] = []
        recorded = list(ep.result.estimates_rad)
        stopped = None
        for t in range(sc.steps):
            m = ep.measurements.get(t)
            if m is None:
                stopped = "missing" if t < len(recorded) else None
                break
            if abs(float(wrap(pan - m.pan_rad))) > pan_tolerance_rad:
                stopped = "pan"
                break
            d = ctl.step(m)
            estimates.append(d.estimate_rad)
            tags = getattr(d, "tags", None) if sc.n_tags > 1 else None
            if tags:
                tag_estimates.append([float(x.estimate_rad) for x in tags])
            pan = d.next_pan_rad
        hits: list[bool] = []
        bearings = truth_bearings(ep.truth, sc.steps)
        if estimates:
            h, _, _ = score_episode(np.asarray(estimates), bearings, ep.truth.tx_index, sc.fov_half_angle_rad, len(estimates), None)
            hits = [bool(x) for x in h]
        per_tag = [list(col) for col in zip(*tag_estimates)] if tag_estimates else []
        tag_hits = [[bool(x) for x in score_episode(np.asarray(e), bearings, ep.truth.carriers[k], sc.fov_half_angle_rad, len(e), None)[0]]
                    for k, e in enumerate(per_tag) if k < len(ep.truth.carriers)]
        recorded_tags = [list(r.estimates_rad) for r in sorted(ep.result.tags, key=lambda r: r.tag)]
        out.append(Rerun(ep.episode_id, start.test_index, algorithm or start.algorithm, len(recorded), len(estimates), estimates, hits,
                         estimates == recorded and per_tag == recorded_tags, per_tag, tag_hits, stopped))
    return out


def rerun_summary(reruns: list[Rerun]) -> dict[str, Any]:
    """Per algorithm: episodes, the share of steps matched, episodes matched to the end, and over
    those the final DR, whether the estimates equal the recorded ones, and how many episodes
    stopped early because the controller asked for another pan or because the recording lacks a
    measurement (``Rerun.stopped``)."""
    by: dict[str, list[Rerun]] = defaultdict(list)
    for r in reruns:
        by[r.algorithm].append(r)
    out = {}
    for name, rs in by.items():
        full = [r for r in rs if r.matched == r.steps and r.steps]
        out[name] = {
            "episodes": len(rs), "steps_matched": round(sum(r.matched for r in rs) / max(1, sum(r.steps for r in rs)), 6),
            "episodes_matched": len(full),
            "dr_final_matched": round(sum(r.hits[-1] for r in full) / len(full), 6) if full else None,
            "same_estimates": sum(r.same_estimates for r in rs),
            "stopped_other_pan": sum(r.stopped == "pan" for r in rs),
            "stopped_missing_measurement": sum(r.stopped == "missing" for r in rs),
        }
        if full and all(r.tag_hits for r in full):  # several tags: each tag's final DR over those episodes
            out[name]["tag_dr_final_matched"] = [round(sum(r.tag_hits[k][-1] for r in full) / len(full), 6)
                                                 for k in range(len(full[0].tag_hits))]
    return out


def entries_from_trace(campaign: dict, trace: dict) -> list[_Entry]:
    """The messages of one recorded test rebuilt from what the orchestrator kept (``GET
    /campaigns/{id}/tests/{k}/{algorithm}``): its start, the commands (the pans), its result and
    its truth. No measurements: the store does not keep them."""
    from ra2vipas.services.protocol.messages import TargetTrajectory, dump
    from ra2vipas.services.protocol.scenario import Scenario

    eid = f"{campaign['id']}.{trace['test_index']}.{trace['algorithm']}.{trace['attempt']}.store"
    rig = trace.get("rig") or "unknown"
    steps = trace["steps"]
    start = EpisodeStart(episode_id=eid, campaign_id=campaign["id"], test_index=trace["test_index"], algorithm=trace["algorithm"],
                         seed=campaign["seed"], scenario=Scenario.model_validate(campaign["scenario"]), mode=campaign["mode"],
                         stop_confidence=campaign.get("stop_confidence") or 0.0)
    out = [(keys.episode_control(rig), dump(start))]
    out += [(keys.command(rig), dump(Command(episode_id=eid, step=s["step"], pan_rad=s["pan_rad"]))) for s in steps]
    confidences = [s["confidence"] for s in steps] if steps and all(s.get("confidence") is not None for s in steps) else []
    result = EpisodeResult.model_validate({
        "episode_id": eid, "rig": rig, "estimates_rad": [s["gamma_hat_rad"] for s in steps], "pans_rad": [s["pan_rad"] for s in steps],
        "rewards": [s["reward"] for s in steps], "confidences": confidences, "decided_step": trace.get("decided_step"),
        "model_check": trace.get("model_check")})
    targets = trace["targets"]
    truth = EpisodeTruth(episode_id=eid, bearings_rad=[t["bearing_rad"] for t in targets], ranges_m=[t["range_m"] for t in targets],
                         tx_index=trace["tx_index"],
                         trajectories=[TargetTrajectory(index=t["index"], bearings_rad=t["bearings_rad"], ranges_m=t["ranges_m"])
                                       for t in targets if t.get("bearings_rad")])
    out += [(keys.episode_result(rig), dump(result)), (keys.episode_truth(rig), dump(truth))]
    base = time.time_ns()
    return [_Entry(k, p, base + i) for i, (k, p) in enumerate(out)]
