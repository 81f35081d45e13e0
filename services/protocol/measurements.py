"""What the sensors measure: the only inputs the controller and the learner ever receive.

These models carry measurements exactly as real hardware produces them: per control step the
BLE advertisements each receiver heard (protocol 1.3; a 1.0 node sends one RSSI pair instead)
and, per camera frame, the detector's boxes relative to the optical axis (their bearings and,
since 1.3, optionally their angular heights and scores). No target identity, range, POD or Tx
flag exists in any of them; the simulator's ground truth travels separately
(``ra2vipas.services.sensors.world.GroundTruth``).

Angles are radians, positive counter-clockwise (the paper's frame F_0); RSSI is dBm.

RF evidence of one step, two forms (``StepMeasurement.advertisements``):

* protocol 1.0: ``rf`` = one ``(iso_rssi_dbm, dir_rssi_dbm)`` pair every T_RF, read as one
  advertisement per receiver at the step's start (the paper's radio, eq. 8);
* protocol 1.3: ``adverts`` = every advertisement Rx(iso) and Rx(dir) heard since the previous
  step, 0..n per receiver, each with its own RSSI (integers allowed: real receivers report
  whole dBm), advertising channel (37/38/39, when the receiver says) and time offset within the
  step. An empty list is a step with *no RF evidence*: no consumer may replace it by a value.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

SINCE_1_3 = {"since": "1.3"}
"""Schema mark of a field added in protocol 1.3 (``versions.since``): senders omit it at its default."""
OPTIONAL_SINCE_1_3 = {"optional_since": "1.3"}
"""Schema mark of a 1.0 field that became optional in 1.3: senders omit it while it is absent
(``versions.wire_exclude``); a 1.0 receiver needs it, so a 1.3 sender leaves it out only for a
receiver that speaks 1.3."""

SINCE_1_4 = {"since": "1.4"}
"""Schema mark of a field added in protocol 1.4 (many tags, issue 21; docs/tags.md)."""

Receiver = Literal["iso", "dir"]
MAX_TAGS = 64
ADDRESS_PATTERN = r"^[0-9A-F]{2}(:[0-9A-F]{2}){5}$"
"""A tag's address as a BLE receiver reports it: six bytes, upper-case hex, colon-separated."""
TagIndex = Field(0, ge=0, lt=MAX_TAGS, json_schema_extra=SINCE_1_4,
                 description="k, which of the scene's tags sent it (0..K-1; absent: tag 0, the only tag before 1.4)")
ADVERTISING_CHANNELS = (37, 38, 39)
MAX_ADVERTS_PER_STEP = 10_000


class _Measurement(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class RFSample(_Measurement):
    """One RF sample (paper eq. 8): z_RF^(iso) and z_RF^(dir), taken together every T_RF."""

    iso_rssi_dbm: float = Field(description="z^(iso), RSSI at the omnidirectional receiver [dBm]")
    dir_rssi_dbm: float = Field(description="z^(dir), RSSI at the directional receiver [dBm]")
    tag: int = TagIndex


class Advertisement(_Measurement):
    """One BLE advertisement of the Tx heard by one receiver (protocol 1.3).

    ``rssi_dbm`` is what the receiver reported (real ones report whole dBm; nothing assumes
    a rounding); ``channel`` the advertising channel it came on (37, 38 or 39; null when the
    receiver does not say); ``offset_s`` when it arrived, in seconds after the start of the
    step whose measurement carries it (>= 0; it may exceed T_RF for a late packet).
    """

    receiver: Receiver = Field(description="which receiver heard it: iso (omnidirectional) | dir (directional, on the camera axis)")
    rssi_dbm: float = Field(ge=-200.0, le=50.0, strict=True, description="RSSI as the receiver reported it [dBm] (integers allowed)")
    channel: Literal[37, 38, 39] | None = Field(None, description="BLE advertising channel (null: not reported)")
    offset_s: float = Field(0.0, ge=0.0, le=1000.0, description="arrival time after the start of the step [s]")
    tag: int = TagIndex
    address: str | None = Field(None, pattern=ADDRESS_PATTERN, json_schema_extra=SINCE_1_4,
                                description="the advertiser's address as the receiver reported it, e.g. C3:5A:01:9E:44:B2 "
                                            "(null: not reported)")


class CameraFrame(_Measurement):
    """The detector's output for one camera frame: one bearing per box, no identities.

    Bearings are relative to the optical axis (inside the field of view) and sorted, so the
    order of boxes says nothing about which target produced them. Since 1.3 a frame may also
    carry, box by box in the same order, each box's angular height (the angle the box spans
    vertically: a range cue for a person of known height) and the detector's score; either list
    is empty (omitted) or has one value per box.
    """

    box_bearings_rad: tuple[float, ...] = Field(default=(), max_length=1000, description="box bearings w.r.t. the optical axis [rad]")
    box_heights_rad: tuple[float, ...] = Field(default=(), max_length=1000, json_schema_extra=SINCE_1_3,
                                               description="each box's angular height [rad], in the order of box_bearings_rad "
                                                           "(empty: the detector gives none)")
    box_scores: tuple[float, ...] = Field(default=(), max_length=1000, json_schema_extra=SINCE_1_3,
                                          description="each box's detector score in [0, 1], in the order of box_bearings_rad "
                                                      "(empty: the detector gives none)")

    @model_validator(mode="after")
    def _one_per_box(self) -> "CameraFrame":
        n = len(self.box_bearings_rad)
        for name in ("box_heights_rad", "box_scores"):
            values = getattr(self, name)
            if values and len(values) != n:
                raise ValueError(f"{name} has {len(values)} values for {n} boxes (give one per box, or none)")
        if any(not 0.0 < h < 3.2 for h in self.box_heights_rad):
            raise ValueError("box_heights_rad: every angular height must lie in (0, 3.2) rad")
        if any(not 0.0 <= s <= 1.0 for s in self.box_scores):
            raise ValueError("box_scores: every score must lie in [0, 1]")
        return self


def _pair(rf: RFSample) -> tuple[Advertisement, ...]:
    return (Advertisement.model_construct(receiver="iso", rssi_dbm=rf.iso_rssi_dbm, channel=None, offset_s=0.0, tag=rf.tag, address=None),
            Advertisement.model_construct(receiver="dir", rssi_dbm=rf.dir_rssi_dbm, channel=None, offset_s=0.0, tag=rf.tag, address=None))


class StepMeasurement(_Measurement):
    """What the platform senses at one control step t: the pan angle it was at, the RF
    evidence and the nu camera frames taken before it (paper eq. 21).

    The RF evidence is either ``rf`` (a 1.0 node's pair) or ``adverts`` (1.3: 0..n per
    receiver), never both; ``advertisements`` reads either as a list of advertisements.
    With several tags (1.4): every advertisement names its tag; with the paper's radio ``rf`` is
    tag 0's pair and ``rf_tags`` the pairs of the other tags, one per tag. A reader that asks for
    no tag reads tag 0, the only tag before 1.4 (``tag=None``: every tag).
    """

    step: int = Field(ge=0, description="t, index of the RF sample within the test")
    pan_rad: float = Field(description="s_t, pan angle at which the sample was taken [rad]")
    rf: RFSample | None = Field(None, json_schema_extra=OPTIONAL_SINCE_1_3,
                                description="the 1.0 RF sample, one (iso, dir) RSSI pair (required up to 1.2; since 1.3 absent "
                                            "when the node sends adverts instead)")
    frames: tuple[CameraFrame, ...] = Field(max_length=10000)
    adverts: tuple[Advertisement, ...] = Field(default=(), max_length=MAX_ADVERTS_PER_STEP, json_schema_extra=SINCE_1_3,
                                               description="every advertisement each receiver heard since the previous step, "
                                                           "possibly none (then the step carries no RF evidence)")
    rf_tags: tuple[RFSample, ...] = Field(default=(), max_length=MAX_TAGS - 1, json_schema_extra=SINCE_1_4,
                                          description="the paper's radio with several tags: the (iso, dir) pair of every tag "
                                                      "but tag 0 (whose pair is rf), each naming its tag")

    @model_validator(mode="after")
    def _one_form(self) -> "StepMeasurement":
        if self.rf is not None and self.adverts:
            raise ValueError("give rf (the 1.0 pair) or adverts (1.3), not both")
        if self.rf_tags:
            if self.rf is None:
                raise ValueError("rf_tags needs rf, tag 0's pair")
            tags = [self.rf.tag] + [p.tag for p in self.rf_tags]
            if len(set(tags)) != len(tags):
                raise ValueError(f"rf and rf_tags name a tag twice: {tags}")
        return self

    def pairs(self) -> tuple[RFSample, ...]:
        """The paper radio's pairs of this step, one per tag (``rf`` then ``rf_tags``); none with adverts."""
        return () if self.rf is None else (self.rf, *self.rf_tags)

    def advertisements(self, receiver: Receiver | None = None, tag: int | None = 0) -> tuple[Advertisement, ...]:
        """The step's advertisements of tag ``tag`` (None: of every tag), of ``receiver`` only if
        given; a 1.0 pair reads as one per receiver at offset 0. Empty: no RF evidence this step."""
        if self.rf is not None:
            ads = tuple(a for p in self.pairs() if tag is None or p.tag == tag for a in _pair(p))
        else:
            ads = self.adverts if tag is None else tuple(a for a in self.adverts if a.tag == tag)
        return ads if receiver is None else tuple(a for a in ads if a.receiver == receiver)

    def rssi_dbm(self, receiver: Receiver, tag: int | None = 0) -> tuple[float, ...]:
        """The RSSI values ``receiver`` reported this step from tag ``tag`` (None: every tag), in
        arrival order (maybe none)."""
        if self.rf is not None:
            return tuple(p.iso_rssi_dbm if receiver == "iso" else p.dir_rssi_dbm for p in self.pairs() if tag is None or p.tag == tag)
        return tuple(a.rssi_dbm for a in self.adverts if a.receiver == receiver and (tag is None or a.tag == tag))

    def tags(self) -> tuple[int, ...]:
        """The tags this step carries RF evidence of, sorted."""
        return tuple(sorted({p.tag for p in self.pairs()} | {a.tag for a in self.adverts}))


class TrainingSample(_Measurement):
    """One sample of the self-supervised POD training episode: the Tx's RF evidence and the nu
    frames the camera took while the Tx walked in view (paper eqs. 20-21).

    A 1.0 node sends one iso RSSI value (``iso_rssi_dbm``); a 1.3 node may send the
    advertisements heard during the sample instead (``adverts``, possibly none), never both.
    """

    index: int = Field(ge=0, description="j, index in the training episode")
    iso_rssi_dbm: float | None = Field(None, json_schema_extra=OPTIONAL_SINCE_1_3,
                                       description="z^(iso)_j [dBm] (required up to 1.2; since 1.3 absent when adverts are sent)")
    frames: tuple[CameraFrame, ...] = Field(max_length=10000)
    adverts: tuple[Advertisement, ...] = Field(default=(), max_length=MAX_ADVERTS_PER_STEP, json_schema_extra=SINCE_1_3,
                                               description="the advertisements heard during sample j, possibly none")

    @model_validator(mode="after")
    def _one_form(self) -> "TrainingSample":
        if self.iso_rssi_dbm is not None and self.adverts:
            raise ValueError("give iso_rssi_dbm (1.0) or adverts (1.3), not both")
        return self

    def advertisements_of(self, receiver: Receiver = "iso") -> tuple[Advertisement, ...]:
        """The advertisements ``receiver`` heard during this sample; a 1.0 value reads as one."""
        if self.iso_rssi_dbm is not None:
            return (Advertisement.model_construct(receiver="iso", rssi_dbm=self.iso_rssi_dbm, channel=None, offset_s=0.0),) \
                if receiver == "iso" else ()
        return tuple(a for a in self.adverts if a.receiver == receiver)

    def rssi_dbm(self, receiver: Receiver = "iso") -> tuple[float, ...]:
        """The RSSI values ``receiver`` reported during this sample (maybe none)."""
        if self.iso_rssi_dbm is not None:
            return (self.iso_rssi_dbm,) if receiver == "iso" else ()
        return tuple(a.rssi_dbm for a in self.adverts if a.receiver == receiver)
