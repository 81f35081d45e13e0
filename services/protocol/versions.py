"""Protocol versions, and what a sender may put on the wire for a receiver of a given version.

The keys stay ``ra2vipas/v1/...``; within v1 the messages grow by *minor* versions, each
adding only optional fields (docs/protocol.md, "Compatibility"):

* ``1.0``: the messages as first published, frozen in ``docs/schemas/v1/``.
* ``1.1``: ``EpisodeStart.stop_confidence``; ``EpisodeResult.confidences``, ``decided_step``
  and ``model_check``; ``PODModel.rf_noise_correlation``; the ``RigDescriptor`` (queryable
  ``rig/{rig}/info``) and its ``protocol``; ``PODRequest.protocol``; ``ErrorReply.episode_id``
  and the key ``result/{rig}/rejected``.
* ``1.2``: ``EpisodeStart.algorithm`` (and every ``algorithm`` field) may name any pointing
  policy (``messages.POLICY_NAME_PATTERN``), not only the four built-ins: a node of 1.0 or 1.1
  validates it against the closed list and rejects another name. A controller says which
  policies it serves (``ControllerInfo``, queryable ``rig/{rig}/policies``); one that serves no
  such queryable (1.0, 1.1) serves the four built-ins, and the orchestrator hands a rig only
  episodes of the policies its controller serves.
* ``1.3``: real radios (issue 20). ``Measurement.adverts``: every BLE advertisement each
  receiver heard since the previous step (receiver, RSSI, channel, time offset), possibly none,
  in place of the 1.0 ``rf`` pair, which becomes optional (``optional_since``); the same for
  ``TrainingSample.adverts`` and ``iso_rssi_dbm``. ``CameraFrame.box_heights_rad`` and
  ``box_scores``. The scenario's radio and box-height parameters (``Scenario``: all off by
  default). A campaign whose scenario turns them on needs rigs that speak 1.3
  (``campaign_features``).
* ``1.4``: many tags (issue 21; docs/tags.md). ``Advertisement.tag`` and ``address``,
  ``RFSample.tag`` and ``Measurement.rf_tags`` (the paper radio's pair of every tag after tag 0):
  each piece of RF evidence names the tag it came from (absent: tag 0, so 1.3 messages mean what
  they meant). ``EpisodeTruth.tx_indices`` and ``tag_addresses`` (who carries which tag);
  ``EpisodeResult.tags`` (per tag: estimates, confidences, decided step; a single-tag controller
  sends none). The scenario's ``n_tags`` and ``one_tag_per_person``: a campaign with K > 1 needs
  rigs that speak 1.4.
* ``1.5``: ``RigDescriptor.tags``: how many tags a node's receivers tell apart. The orchestrator
  refuses a campaign that searches for more on that rig (``rig.conflicts``); absent, the node
  takes every campaign's ``n_tags`` (a simulator, or a node of 1.4 or older). Nothing a node
  receives changes: no campaign needs a rig that speaks 1.5.

Every field added after 1.0 carries the version that added it in its schema (``"since"``).
A sender omits such a field while it holds its default (``messages.dump``), so a message that
uses no newer feature is byte for byte what a 1.0 sender sent; and it sends a newer feature
only to a receiver that speaks its version. A sensors node says which version it speaks in its
descriptor (``RigDescriptor.protocol``; a node that serves no descriptor speaks 1.0); a client
of the learner says it in its ``PODRequest.protocol``. The orchestrator refuses a campaign
whose features a targeted rig does not speak (``missing_features``).

Adding a field to a message a node receives (the next version, say 1.2): give it a default and
``json_schema_extra={"since": "1.2"}``, add ``"1.2"`` to ``VERSIONS`` and make it
``PROTOCOL_VERSION``, list it in ``campaign_features`` when a campaign setting turns it on,
freeze the 1.1 schemas beside ``docs/schemas/v1`` and say what 1.2 adds on the protocol page.
``tests/protocol/test_compatibility.py`` fails on a field added without its ``since``.

Pure Python and pydantic, like the rest of the protocol package.
"""

from __future__ import annotations

from functools import cache
from typing import Any, get_args

from pydantic import BaseModel

V1_0 = "1.0"
V1_1 = "1.1"
V1_2 = "1.2"
V1_3 = "1.3"
V1_4 = "1.4"
V1_5 = "1.5"
PROTOCOL_VERSION = V1_5
"""The newest version: what this code speaks."""
VERSIONS: tuple[str, ...] = (V1_0, V1_1, V1_2, V1_3, V1_4, PROTOCOL_VERSION)
BUILTIN_POLICIES: tuple[str, ...] = ("ra2vipas", "rapas", "ravipas", "sweep")
"""The policy names every version knows (1.0 and 1.1: the only ones)."""
VERSION_PATTERN = r"^1\.[0-9]{1,3}$"


def version_key(version: str) -> tuple[int, int]:
    """``"1.10"`` -> ``(1, 10)``: versions compare as numbers, not as text."""
    major, minor = version.split(".")
    return int(major), int(minor)


def newer(version: str, than: str) -> bool:
    return version_key(version) > version_key(than)


def since(model: type[BaseModel], name: str) -> str:
    """The version that added field ``name`` of ``model`` (``1.0`` for the original fields)."""
    extra = model.model_fields[name].json_schema_extra
    return extra.get("since", V1_0) if isinstance(extra, dict) else V1_0


def optional_since(model: type[BaseModel], name: str) -> str | None:
    """The version that made 1.0 field ``name`` of ``model`` optional (None: it never was)."""
    extra = model.model_fields[name].json_schema_extra
    return extra.get("optional_since") if isinstance(extra, dict) else None


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in get_args(annotation) for m in _models_in(arg)]


@cache
def has_newer_fields(model: type[BaseModel]) -> bool:
    """Whether ``model`` or a message nested in it has a field added after 1.0."""
    return any(since(model, name) != V1_0 or optional_since(model, name) is not None or any(has_newer_fields(m) for m in _models_in(info.annotation))
               for name, info in model.model_fields.items())


def wire_exclude(message: BaseModel, version: str | None = None) -> dict[str, Any]:
    """What ``dump`` leaves out of ``message`` (pydantic's ``exclude`` form, nested): every field
    newer than 1.0 that holds its default, and, for a receiver that speaks ``version``, every
    field newer than that whatever it holds (the receiver reads the field's default: the caller
    accepts that loss, e.g. an AR(1) fading model read as white noise by a 1.0 controller)."""
    out: dict[str, Any] = {}
    cls = type(message)
    if not has_newer_fields(cls):
        return out
    for name, added, default, optional, nested in _exclusion_plan(cls):
        value = getattr(message, name)
        if added != V1_0:
            if (version is not None and newer(added, version)) or value == default:
                out[name] = True
                continue
        elif value is None and optional:
            out[name] = True  # a 1.0 field absent since it became optional: absent on the wire too
            continue
        if nested:
            inner = _exclude_value(value, version)
            if inner:
                out[name] = inner
    return out


@cache
def _exclusion_plan(cls: type[BaseModel]) -> tuple[tuple[str, str, Any, bool, bool], ...]:
    """Per field of ``cls``, what ``wire_exclude`` needs, worked out once (it runs for every
    message sent, e.g. a measurement per control step): its name, the version that added it,
    its default (fields added after 1.0), whether it became optional after 1.0, and whether a
    message it may hold has anything to leave out (else its value is not walked)."""
    plan = []
    for name, info in cls.model_fields.items():
        added = since(cls, name)
        default = info.get_default(call_default_factory=True) if added != V1_0 else None
        nested = any(has_newer_fields(m) for m in _models_in(info.annotation))
        plan.append((name, added, default, optional_since(cls, name) is not None, nested))
    return tuple(plan)


def _exclude_value(value: Any, version: str | None) -> dict[Any, Any]:
    """``wire_exclude`` of a field's value: a message, or a sequence (of sequences) of messages."""
    if isinstance(value, BaseModel):
        return wire_exclude(value, version)
    if isinstance(value, (tuple, list)) and value and isinstance(value[0], (BaseModel, tuple, list)):
        return {i: e for i, item in enumerate(value) if (e := _exclude_value(item, version))}
    return {}


# -- what a campaign needs ------------------------------------------------------------------

def campaign_features(stop_confidence: float = 0.0, algorithms: tuple[str, ...] | list[str] = (),
                      scenario: BaseModel | None = None) -> list[tuple[str, str]]:
    """The newer-than-1.0 features a campaign uses, as ``(feature, version)``: what a rig must
    speak to run it (its sensors and controller both receive its ``EpisodeStart``). A
    ``scenario`` that sets a parameter added after 1.0 away from its default (e.g. the 1.3
    radio) needs the version that added it."""
    out = []
    if stop_confidence:
        out.append(("stop_confidence", V1_1))
    out += [(f"policy {name!r}", V1_2) for name in algorithms if name not in BUILTIN_POLICIES]
    if scenario is not None:
        cls = type(scenario)
        for name, info in cls.model_fields.items():
            added = since(cls, name)
            if added != V1_0 and getattr(scenario, name) != info.get_default(call_default_factory=True):
                out.append((f"scenario parameter {name!r}", added))
    return out


def missing_features(speaks: str, features: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The features of ``features`` that a node speaking ``speaks`` does not know."""
    return [(feature, version) for feature, version in features if newer(version, speaks)]


def describe_missing(rig: str, speaks: str, feature: str, version: str) -> str:
    how = "serves no descriptor: it speaks protocol 1.0" if speaks == V1_0 else f"speaks protocol {speaks}"
    return (f"rig {rig} {how}; {feature} needs protocol {version} (a node that does not know the field rejects every "
            f"EpisodeStart that carries it)")
