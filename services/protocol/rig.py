"""What a rig says about itself: the ``RigDescriptor`` served on ``rig/{rig}/info``, and how a
campaign's scenario is checked against it.

A descriptor describes the *platform*, never the world around it: the camera (nu frames per
RF sample, half field of view, the detector's bearing noise), the RF timing T_RF, how Rx(dir)
responds to the misalignment Delta = wrap(s - gamma), which pacing modes it supports and
whether it can give the ground truth a simulator knows, and (1.5) how many BLE tags its
receivers tell apart. The controller builds its sensor
model from it (``services/controller/policy.py`` ``sensor_config_from_descriptor``), and the
orchestrator refuses a campaign whose scenario contradicts a targeted rig's descriptor
(``conflicts``), unless the campaign asks to use the rig's values (``apply_rig_values``).

A field left ``null`` means *configurable*: the rig takes the campaign's value (a simulated
rig simulates whatever hardware the scenario describes). A ``hardware`` or ``survey`` rig has
one value for each: it must give them all (its Rx(dir) response may be ``unknown``, and the
controller then learns the lobe's orientation from the data).

Pure pydantic, like the rest of the protocol package.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from ra2vipas.services.protocol.measurements import MAX_TAGS
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.protocol.versions import V1_0, VERSION_PATTERN

RigKind = Literal["simulated", "hardware", "survey"]
RIG_KINDS: tuple[str, ...] = RigKind.__args__
RxDirModel = Literal["paper", "db-gain", "unknown"]


class _Message(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class RxDirResponse(_Message):
    """How Rx(dir)'s RSSI responds to the misalignment Delta between the camera axis and the Tx.

    ``paper``: z_dir = g(d) rho(Delta) (paper eq. 6; a dBm value scaled by rho, so the reading
    is *lowest* (most negative) when aligned: a dip). ``db-gain``: z_dir = g(d) + 10 log10
    max(rho, floor) (an antenna gain in dB: the reading *peaks* when aligned). Both with
    rho = 1 - a Delta^2 clipped to [0, 1]. ``unknown``: the rig does not know; the controller
    learns from the data whether the lobe is a peak or a dip.
    """

    model: RxDirModel = Field(description="paper | db-gain | unknown")
    curvature: float | None = Field(None, ge=0.0, le=100.0, description="a in rho = 1 - a Delta^2 (null: not known / configurable)")
    floor_db: float | None = Field(None, ge=-100.0, le=0.0, description="db-gain: the lowest gain [dB] (null: not known / configurable)")

    @property
    def lobe(self) -> str | None:
        """``peak`` (the reading grows with alignment), ``dip`` (the paper's model), None if unknown."""
        return {"paper": "dip", "db-gain": "peak"}.get(self.model)


class RigDescriptor(_Message):
    """A rig's description of itself (sensors -> anyone who queries ``rig/{rig}/info``)."""

    rig: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$", description="the rig's name (its key chunk)")
    kind: RigKind = Field(description="simulated (a simulator: knows the truth) | hardware (a real platform) | survey (serves a "
                                      "recorded survey of a real scene)")
    vendor: str = Field("", max_length=200, description="who made the platform (free text)")
    model: str = Field("", max_length=200, description="which platform (free text)")
    frames_per_rf: int | None = Field(None, ge=1, le=1000, description="nu, camera frames per RF sample (null: configurable)")
    rf_period_s: float | None = Field(None, gt=0.0, le=10.0, description="T_RF, RF sampling period [s] (null: configurable)")
    fov_half_angle_deg: float | None = Field(None, gt=0.0, le=180.0, description="camera half field of view [deg] (null: configurable)")
    box_bearing_noise_deg: float | None = Field(None, ge=0.0, le=10.0,
                                                description="std of a detector box's bearing [deg] (null: configurable)")
    rx_dir: RxDirResponse | None = Field(None, description="Rx(dir)'s response to the misalignment (null: configurable)")
    modes: tuple[Literal["fast", "realtime"], ...] = Field(("fast", "realtime"), min_length=1, max_length=2,
                                                           description="pacing modes the rig runs (fast: lockstep; realtime: every T_RF)")
    training: bool = Field(True, description="serves data/{rig}/training (a POD training episode on request)")
    episode_truth: bool = Field(False, description="publishes EpisodeTruth itself (a simulator or a survey knows the layout)")
    training_truth: bool = Field(False, description="serves truth/{rig}/training (the true POD of its training episodes, for R^2)")
    radio: Literal["pair", "adverts"] | None = Field(None, json_schema_extra={"since": "1.3"}, description=(
        "what the node's Measurements carry: pair (the 1.0 rf pair every step) | adverts (1.3: the BLE advertisements each "
        "receiver heard since the previous step, possibly none); null: follows the campaign's scenario (a simulator), or "
        "the pair (a node of 1.2 or older)"))
    box_heights: bool | None = Field(None, json_schema_extra={"since": "1.3"}, description=(
        "whether every box carries its angular height (CameraFrame.box_heights_rad, 1.3: a range cue); null: follows the "
        "campaign's scenario (a simulator), or no heights (a node of 1.2 or older)"))
    tags: int | None = Field(None, ge=1, le=MAX_TAGS, json_schema_extra={"since": "1.5"}, description=(
        "how many tags (transmitters) the node's receivers tell apart: tags 0 .. tags - 1 (1.5; a campaign whose n_tags "
        "exceeds it contradicts the rig); null: whatever the campaign searches for (a simulator), or not said (a node of "
        "1.4 or older)"))
    protocol: str = Field("1.1", pattern=VERSION_PATTERN, description=(
        "the protocol version the node speaks: the newest whose fields it accepts in what it receives (absent: 1.1, "
        "the version that introduced the descriptor; a node that serves no descriptor speaks 1.0)"))

    @model_validator(mode="after")
    def _fixed_hardware(self) -> "RigDescriptor":
        if self.kind != "simulated":
            missing = [name for name in HARDWARE_FIELDS if getattr(self, name) is None]
            if missing:
                raise ValueError(f"a {self.kind} rig has one value for each of its hardware fields; missing: {', '.join(missing)}")
        return self

    @property
    def configurable(self) -> list[str]:
        """The hardware fields the rig takes from the campaign."""
        return [name for name in HARDWARE_FIELDS if getattr(self, name) is None]


def speaks(descriptor: "RigDescriptor | None") -> str:
    """The protocol version a rig's nodes speak: its descriptor's, 1.0 when it serves none."""
    return V1_0 if descriptor is None else descriptor.protocol


DESCRIPTOR_TIMEOUT_S = 3.0
"""How long a query of ``rig/{rig}/info`` (or a controller's ``policies``) waits for replies: a v1
sensors node serves no descriptor, and the query then ends with none."""

DESCRIPTOR_REASK_S = (1.0, 2.0)
"""A descriptor or policies query that no node answered at all is asked again after these waits
before the rig is taken for a v1 node, by the orchestrator and by a rig's controller alike: right
after a liveliness token arrives or a link comes back (a restart, the end of a cut) the router may
not route the query to the rig's queryable yet, and one empty answer would have the campaign
modelled and scored under its scenario's assumptions (docs/protocol.md)."""

SENSORS_SETTLED_S = 10.0
"""A rig's controller takes a silent sensors node for another node than the one that described the
rig before (e.g. a v1 node under the same rig name) only once that node's liveliness token has
stood this long (Zenoh's default lease) before a descriptor query, and its re-asks, went
unanswered: a token that just came back (a restart, or a link back after a cut past the lease)
may not have its queryable routed yet. The orchestrator, which takes a silent rig for undescribed
(or its controller for silent) after its re-asks, asks again when a token that was younger than
this has stood this long, and then with a backoff while the node stays silent (docs/protocol.md)."""

HARDWARE_FIELDS = ("frames_per_rf", "rf_period_s", "fov_half_angle_deg", "box_bearing_noise_deg", "rx_dir")
"""The descriptor fields that describe the platform's hardware (null = configurable)."""


@dataclass(frozen=True)
class Conflict:
    """One scenario parameter that contradicts a rig's descriptor."""

    field: str  # the scenario parameter (or ``mode``)
    campaign: Any
    rig: Any
    relation: str = "is"  # how the rig's value binds: ``is`` (equal), or ``hears at most`` (``n_tags``)

    def describe(self, rig: str) -> str:
        return f"rig {rig}: {self.field}: the campaign says {self.campaign!r}, the rig {self.relation} {self.rig!r}"


def rig_values(descriptor: RigDescriptor) -> dict[str, Any]:
    """The scenario parameters the rig fixes, with its values (what ``use_rig_values`` applies).
    An ``unknown`` Rx(dir) response fixes no antenna parameter (the controller learns the lobe)."""
    out: dict[str, Any] = {}
    for name in ("frames_per_rf", "rf_period_s", "fov_half_angle_deg", "box_bearing_noise_deg"):
        value = getattr(descriptor, name)
        if value is not None:
            out[name] = value
    rx = descriptor.rx_dir
    if rx is not None and rx.model != "unknown":
        out["antenna_model"] = rx.model
        if rx.curvature is not None:
            out["antenna_curvature"] = rx.curvature
        if rx.floor_db is not None and rx.model == "db-gain":
            out["antenna_floor_db"] = rx.floor_db
    if descriptor.radio is not None:
        out["radio"] = descriptor.radio
    if descriptor.box_heights is not None:
        out["box_heights"] = descriptor.box_heights
    return out


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return a == b


def conflicts(descriptor: RigDescriptor, scenario: Scenario, mode: str = "fast") -> list[Conflict]:
    """Every scenario parameter (and the pacing ``mode``) that contradicts the descriptor, in a
    fixed order; empty when the campaign can run on the rig as it is."""
    out: list[Conflict] = []
    for name, value in rig_values(descriptor).items():
        current = getattr(scenario, name)
        current = current.value if isinstance(current, Enum) else current
        if not _same(current, value):
            out.append(Conflict(name, current, value))
    if fewer_tags(scenario, descriptor.tags):
        out.append(Conflict("n_tags", scenario.n_tags, descriptor.tags, "hears at most"))
    if mode not in descriptor.modes:
        out.append(Conflict("mode", mode, "|".join(descriptor.modes)))
    return out


def fewer_tags(scenario: Scenario, tags: int | None) -> dict[str, Any]:
    """What taking a rig's values does to ``n_tags``: lowered to the tags its receivers hear when the
    campaign searches for more (``{"n_tags": tags}``), else nothing (a campaign may search for fewer)."""
    return {"n_tags": tags} if tags is not None and scenario.n_tags > tags else {}


def apply_rig_values(descriptor: RigDescriptor, scenario: Scenario) -> Scenario:
    """The scenario with the rig's fixed hardware values in place of the campaign's, and no more
    tags than the rig hears (``fewer_tags``)."""
    values = {**rig_values(descriptor), **fewer_tags(scenario, descriptor.tags)}
    if not values:
        return scenario
    return Scenario.model_validate({**scenario.model_dump(mode="json"), **values})
