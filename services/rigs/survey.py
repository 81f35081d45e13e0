"""Surveys: a static real scene swept densely over the full circle, served back as a rig, so every
algorithm can be benchmarked on the same real data.

Active sensing cannot be replayed from one log (the pans change), so a *survey* records, for a
scene that does not move, several passes over a fixed set of pans; each (pan, pass) holds the ν
frames and the RSSI pair a platform measured there; and the *layout* (each target's bearing,
its range if known, which one carries the Tx). The survey rig (``SurveyNode``) answers any
commanded pan with a sample taken at the nearest recorded pan, drawing the passes of that pan
without replacement (a fresh random order per pan and per episode, from (seed, test_index)), and
publishes the episode's truth from the layout. The format is ``Survey`` (schema
``docs/schemas/Survey.json``): JSON, one object.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.measurements import (
    ADDRESS_PATTERN,
    MAX_TAGS,
    OPTIONAL_SINCE_1_3,
    SINCE_1_3,
    SINCE_1_4,
    Advertisement,
    CameraFrame,
    RFSample,
    TrainingSample,
)
from ra2vipas.services.protocol.messages import (
    Command,
    EpisodeStart,
    EpisodeStop,
    EpisodeTruth,
    Measurement,
    TrainingRequest,
    TrainingStream,
    decode,
    dump,
    episode_control_adapter,
)
from ra2vipas.services.protocol.rig import RigDescriptor
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.transport.bus import Bus, QueryError, undeclare_all

FORMAT = "ra2vipas survey v1"
log = logging.getLogger(__name__)


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class SurveySample(_Model):
    """What the platform measured at one pan in one pass: the 1.0 RSSI pair ``rf``, or (protocol
    1.3) the ``adverts`` heard during the sample, possibly none; never both. With several tags
    (1.4) the adverts name their tag, and with the paper's radio ``rf`` is tag 0's pair and
    ``rf_tags`` the other tags' (``Measurement.rf_tags``)."""

    rf: RFSample | None = Field(None, json_schema_extra=OPTIONAL_SINCE_1_3)
    frames: tuple[CameraFrame, ...] = Field(min_length=1, max_length=1000)
    adverts: tuple[Advertisement, ...] = Field(default=(), max_length=10_000, json_schema_extra=SINCE_1_3)
    rf_tags: tuple[RFSample, ...] = Field(default=(), max_length=MAX_TAGS - 1, json_schema_extra=SINCE_1_4,
                                          description="the paper's radio with several tags: every tag's pair but tag 0's")

    @model_validator(mode="after")
    def _one_form(self) -> "SurveySample":
        if self.rf is not None and self.adverts:
            raise ValueError("a survey sample holds rf (1.0) or adverts (1.3), not both")
        if self.rf_tags and self.rf is None:
            raise ValueError("a survey sample's rf_tags need rf, tag 0's pair")
        return self


class Layout(_Model):
    """The scene: every target's bearing in the platform frame [rad], its range [m] if known;
    with several tags (1.4), the target that carries each (``EpisodeTruth.tx_indices``)."""

    bearings_rad: tuple[float, ...] = Field(min_length=1, max_length=1000)
    ranges_m: tuple[float, ...] | None = Field(None, description="null if the ranges were not measured")
    tx_index: int = Field(ge=0, description="i*, the target carrying the Tx")
    tx_indices: tuple[int, ...] = Field(default=(), max_length=MAX_TAGS, json_schema_extra=SINCE_1_4,
                                        description="K > 1 tags: the carrier of tag k (tx_indices[0] is tx_index)")
    tag_addresses: tuple[Annotated[str, Field(pattern=ADDRESS_PATTERN)], ...] = Field(default=(), max_length=MAX_TAGS, json_schema_extra=SINCE_1_4,
                                           description="the tags' addresses, in the order of tx_indices (may be empty)")

    @model_validator(mode="after")
    def _consistent(self) -> "Layout":
        if self.tx_index >= len(self.bearings_rad):
            raise ValueError("tx_index must name one of the targets")
        if self.ranges_m is not None and len(self.ranges_m) != len(self.bearings_rad):
            raise ValueError("ranges_m must have one range per bearing")
        if self.tx_indices and (self.tx_indices[0] != self.tx_index or not all(0 <= i < len(self.bearings_rad) for i in self.tx_indices)):
            raise ValueError("tx_indices must start with tx_index and name targets of the layout")
        if self.tag_addresses and len(self.tag_addresses) != len(self.tx_indices):
            raise ValueError("tag_addresses must have one address per tag of tx_indices")
        return self


class Survey(_Model):
    """A survey file: the platform, the pans, the passes, the layout, and a training stream."""

    format: Literal["ra2vipas survey v1"] = FORMAT
    rig: RigDescriptor = Field(description="the platform that recorded it (its descriptor; kind becomes survey when served)")
    pans_rad: tuple[float, ...] = Field(min_length=4, max_length=100_000, description="the surveyed pans, increasing, in [-pi, pi)")
    passes: tuple[tuple[SurveySample, ...], ...] = Field(min_length=1, max_length=1000,
                                                         description="passes[p][j]: the sample of pass p at pans_rad[j]")
    layout: Layout
    training: tuple[TrainingSample, ...] = Field(default=(), max_length=100_000,
                                                 description="a POD training stream recorded on the same platform (may be empty)")
    notes: str = Field("", max_length=2000)

    @model_validator(mode="after")
    def _shape(self) -> "Survey":
        p = np.asarray(self.pans_rad)
        if np.any(np.diff(p) <= 0) or p[0] < -math.pi or p[-1] >= math.pi:
            raise ValueError("pans_rad must increase within [-pi, pi)")
        if any(len(one) != len(self.pans_rad) for one in self.passes):
            raise ValueError("every pass has one sample per pan")
        return self

    def descriptor(self, rig: str) -> RigDescriptor:
        """The survey rig's descriptor: the recording platform's hardware, kind ``survey``, fast
        mode only (nothing moves), knows the layout (episode truth), no training truth."""
        d = self.rig.model_dump(mode="json")
        d.update(rig=rig, kind="survey", modes=["fast"], training=bool(self.training), episode_truth=True, training_truth=False,
                 model=(d.get("model") or "") + " (survey)")
        return RigDescriptor.model_validate(d)


def load(path: str | Path) -> Survey:
    """Read a survey file (JSON).

    Raises
    ------
    ValueError
        Unreadable or invalid, one line naming the first problem.
    """
    try:
        return Survey.model_validate_json(Path(path).read_bytes())
    except OSError as err:
        raise ValueError(f"cannot read {path}: {err.strerror or err}") from None
    except ValidationError as err:
        e = err.errors()[0]
        raise ValueError(f"{path} is not a survey: {'.'.join(str(p) for p in e.get('loc', ()))}: {e.get('msg')}") from None


def sweep_pans(count: int) -> list[float]:
    """``count`` evenly spaced pans over the circle, from -pi."""
    return [-math.pi + 2.0 * math.pi * j / count for j in range(count)]


# -- recording a survey from a live rig ----------------------------------------------------------

def record_survey(bus: Bus, rig: str, pans: int = 180, passes: int = 3, n_train: int = 300, seed: int = 1,
                  layout: Layout | None = None, timeout: float = 10.0, scenario: Scenario | None = None) -> Survey:
    """Drive a live rig through ``passes`` sweeps of ``pans`` evenly spaced pans, in one fast
    episode (the scene must not change), and record its training stream. The layout comes from
    ``layout`` (an operator's), else from the rig's own ``EpisodeTruth`` (a simulator's).

    Raises
    ------
    RuntimeError
        The rig does not answer, or there is no layout; one line.
    """
    got: queue.Queue = queue.Queue()
    bus.query(keys.rig_info(rig), b"", timeout, got.put)
    replies = got.get(timeout=timeout + 5)
    descriptor = None
    for r in replies:
        if r.ok:
            d, _ = decode(RigDescriptor, r.payload)
            descriptor = d or descriptor
    if descriptor is None:
        raise RuntimeError(f"rig {rig} serves no descriptor: a survey must say what recorded it")
    sc = scenario or Scenario()
    fixed = {k: v for k, v in {"frames_per_rf": descriptor.frames_per_rf, "rf_period_s": descriptor.rf_period_s,
                               "fov_half_angle_deg": descriptor.fov_half_angle_deg,
                               "box_bearing_noise_deg": descriptor.box_bearing_noise_deg}.items() if v is not None}
    if descriptor.rx_dir is not None and descriptor.rx_dir.model != "unknown":
        fixed["antenna_model"] = descriptor.rx_dir.model
    sc = Scenario.model_validate({**sc.model_dump(mode="json"), **fixed, "steps": pans * passes, "n_train": n_train})
    # the recording platform's hardware as it was used, for the survey's descriptor
    hardware = descriptor.model_dump(mode="json")
    hardware.update(frames_per_rf=sc.frames_per_rf, rf_period_s=sc.rf_period_s, fov_half_angle_deg=sc.fov_half_angle_deg,
                    box_bearing_noise_deg=sc.box_bearing_noise_deg,
                    rx_dir=descriptor.rx_dir.model_dump(mode="json") if descriptor.rx_dir is not None else {"model": sc.antenna_model.value})
    if hardware["kind"] == "simulated":
        hardware["kind"] = "hardware"  # a survey rig has one value for each: those used here
    eid = f"survey.{int(time.time() * 1000)}"
    measured: dict[int, Measurement] = {}
    truths: list[EpisodeTruth] = []
    cv = threading.Condition()

    def on_measurement(_k, payload):
        m, _ = decode(Measurement, payload)
        if m is not None and m.episode_id == eid:
            with cv:
                measured[m.step] = m
                cv.notify_all()

    def on_truth(_k, payload):
        t, _ = decode(EpisodeTruth, payload)
        if t is not None and t.episode_id == eid:
            truths.append(t)

    handles = [bus.subscribe(keys.measurement(rig), on_measurement), bus.subscribe(keys.episode_truth(rig), on_truth)]
    try:
        bus.publish(keys.episode_control(rig), dump(EpisodeStart(episode_id=eid, campaign_id="survey", test_index=0, algorithm="sweep",
                                                                  seed=seed, scenario=sc)))
        time.sleep(0.2)
        angles = sweep_pans(pans)
        for step in range(pans * passes):
            bus.publish(keys.command(rig), dump(Command(episode_id=eid, step=step, pan_rad=angles[step % pans])))
            with cv:
                if not cv.wait_for(lambda: step in measured, timeout):
                    raise RuntimeError(f"rig {rig} did not answer step {step} within {timeout:g} s")
        training: tuple[TrainingSample, ...] = ()
        if descriptor.training and n_train:
            bus.query(keys.training(rig), dump(TrainingRequest(job_id="survey-training", scenario=sc, seed=seed)), 300.0, got.put)
            for r in got.get(timeout=310.0):
                stream, _ = decode(TrainingStream, r.payload) if r.ok else (None, None)
                if stream is not None:
                    training = stream.samples
                    break
    finally:
        bus.publish(keys.episode_control(rig), dump(EpisodeStop(episode_id=eid, reason="survey recorded")))
        undeclare_all(handles)
    if layout is None:
        if not truths:
            raise RuntimeError(f"rig {rig} published no truth: give the scene's layout (--layout FILE)")
        t = truths[0]
        if t.trajectories:
            raise RuntimeError("the scene moved during the survey (walking targets): a survey needs a static scene")
        layout = Layout(bearings_rad=t.bearings_rad, ranges_m=t.ranges_m, tx_index=t.tx_index, tx_indices=t.tx_indices,
                        tag_addresses=t.tag_addresses)
    passes_out = tuple(tuple(SurveySample(rf=measured[p * pans + j].rf, frames=measured[p * pans + j].frames,
                                              adverts=measured[p * pans + j].adverts, rf_tags=measured[p * pans + j].rf_tags)
                             for j in range(pans))
                       for p in range(passes))
    return Survey(rig=RigDescriptor.model_validate(hardware), pans_rad=tuple(angles), passes=passes_out, layout=layout,
                  training=training, notes=f"recorded from rig {rig}: {passes} passes of {pans} pans")


# -- serving a survey ----------------------------------------------------------------------------

class SurveyNode:
    """A sensors node that serves a survey: any commanded pan is answered from the nearest
    surveyed pan, its passes drawn without replacement (a random order per pan, fixed by the
    episode's (seed, test_index)); the episode's truth comes from the layout. Fast mode only."""

    def __init__(self, bus: Bus, rig: str, survey: Survey) -> None:
        from ra2vipas.services.transport.runtime import EventLoop

        self.bus, self.rig, self.survey = bus, keys.check_chunk(rig), survey
        self.descriptor = survey.descriptor(rig)
        self.pans = np.asarray(survey.pans_rad)
        self.loop = EventLoop(f"survey-{rig}")
        self.episodes: dict[str, dict] = {}
        self._finished: dict[str, None] = {}
        self._early: dict[str, bytes] = {}
        info = dump(self.descriptor)
        self._handles = [
            bus.subscribe(keys.episode_control(rig), lambda _k, p: self.loop.post(self._on_control, p)),
            bus.subscribe(keys.command(rig), lambda _k, p: self.loop.post(self._on_command, p)),
            bus.serve(keys.training(rig), self._on_training),
            bus.serve(keys.rig_info(rig), lambda _k, _p: info),
        ]
        self._handles.append(bus.announce(keys.alive("sensors", rig)))

    def nearest(self, pan: float) -> int:
        """Index of the surveyed pan nearest to ``pan`` on the circle."""
        d = np.abs((self.pans - pan + math.pi) % (2.0 * math.pi) - math.pi)
        return int(np.argmin(d))

    def _on_control(self, payload: bytes) -> None:
        from ra2vipas.services.transport.runtime import decode_or_reject

        msg = decode_or_reject(episode_control_adapter, payload, "episode control message", log, self.bus, self.rig, "sensors")
        if msg is None:
            return
        if isinstance(msg, EpisodeStop):
            self._end(msg.episode_id)
            return
        if msg.episode_id in self.episodes:
            return
        rng = np.random.default_rng(np.random.SeedSequence(entropy=msg.seed, spawn_key=(msg.test_index, 7)))
        self.episodes[msg.episode_id] = {"start": msg, "rng": rng, "orders": {}, "last": None}
        lay = self.survey.layout
        ranges = lay.ranges_m if lay.ranges_m is not None else (1.0,) * len(lay.bearings_rad)
        self.bus.publish(keys.episode_truth(self.rig), dump(EpisodeTruth(episode_id=msg.episode_id, bearings_rad=lay.bearings_rad,
                                                                         ranges_m=ranges, tx_index=lay.tx_index, tx_indices=lay.tx_indices,
                                                                         tag_addresses=lay.tag_addresses)))
        early = self._early.pop(msg.episode_id, None)
        if early is not None:
            self._on_command(early)

    def _draw(self, ep: dict, j: int) -> SurveySample:
        """The next pass of pan j, without replacement (a new random order once all were used)."""
        order = ep["orders"].get(j)
        if not order:
            order = list(ep["rng"].permutation(len(self.survey.passes)))
            ep["orders"][j] = order
        return self.survey.passes[order.pop()][j]

    def _on_command(self, payload: bytes) -> None:
        from ra2vipas.services.transport.runtime import decode_or_reject

        cmd = decode_or_reject(Command, payload, "command", log, self.bus, self.rig, "sensors")
        if cmd is None:
            return
        ep = self.episodes.get(cmd.episode_id)
        if ep is None:
            if cmd.step == 0 and cmd.episode_id not in self._finished:
                self._early[cmd.episode_id] = payload
                while len(self._early) > 1000:
                    self._early.pop(next(iter(self._early)))
            return
        last = ep["last"]
        if last is not None and cmd.step == last.step:
            self.bus.publish(keys.measurement(self.rig), dump(last))
            return
        expected = 0 if last is None else last.step + 1
        if cmd.step != expected or cmd.step >= ep["start"].scenario.steps:
            return
        j = self.nearest(float(cmd.pan_rad))
        sample = self._draw(ep, j)
        m = Measurement(episode_id=cmd.episode_id, step=cmd.step, pan_rad=float(self.pans[j]), rf=sample.rf, frames=sample.frames,
                        adverts=sample.adverts, rf_tags=sample.rf_tags)
        ep["last"] = m
        self.bus.publish(keys.measurement(self.rig), dump(m))
        if cmd.step == ep["start"].scenario.steps - 1:
            self._end(cmd.episode_id)

    def _end(self, episode_id: str) -> None:
        self._early.pop(episode_id, None)
        if self.episodes.pop(episode_id, None) is not None:
            self._finished[episode_id] = None
            while len(self._finished) > 10000:
                self._finished.pop(next(iter(self._finished)))

    def _on_training(self, _key: str, payload: bytes) -> bytes:
        req, reason = decode(TrainingRequest, payload)
        if req is None:
            raise QueryError(f"malformed TrainingRequest: {reason}")
        n, held = req.scenario.n_train, len(self.survey.training)
        if n > held:
            raise QueryError(f"this survey holds {held} training samples, the campaign asks for n_train = {n}")
        return dump(TrainingStream(job_id=req.job_id, samples=self.survey.training[:n]))

    def close(self) -> None:
        undeclare_all(self._handles)
        self.loop.stop()


def save(survey: Survey, path: str | Path) -> None:
    """Write ``survey`` as the wire writes messages (``messages.dump``): fields added since 1.0
    only when used, so a survey of a 1.0 rig is what it always was."""
    from ra2vipas.services.protocol.messages import dump

    Path(path).write_bytes(dump(survey))


def schema() -> dict:
    return json.loads(json.dumps(Survey.model_json_schema()))
