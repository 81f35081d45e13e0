"""Pointing policies found by name (issue 19), the way Optuna finds samplers: every policy,
the four built-ins included, is an entry point of the group ``ra2vipas.policies``::

    [project.entry-points."ra2vipas.policies"]
    ra2vipas = "ra2vipas.services.controller.builtins:Ra2ViPAS"

or is named as ``module:Class`` (in process: ``ra2vipas simulate -a my_module:MyPolicy``).
Every list of policy names in the product comes from ``names()``.
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata
from typing import Any

from ra2vipas.services.controller.contract import EpisodeContext, Policy

GROUP = "ra2vipas.policies"
NAME_PATTERN = r"^[a-z][a-z0-9_.-]{0,63}$"
"""A policy's name on the wire, in results, plots and URLs."""
BUILTINS: tuple[str, ...] = ("ra2vipas", "rapas", "ravipas", "sweep")
"""The policies ra2vipas ships, in the order tables and plots show them (paper Sec. IV-B, plus
the non-active sweep). They are registered through the same entry-point group as anyone's;
this table is their fallback in a source tree whose metadata is not installed."""
SHIPPED_BASELINES: tuple[str, ...] = ("ra2vipas-seq",)
"""Policies ra2vipas also ships, run only when named: ``ra2vipas-seq``, Ra²ViPAS one tag at a
time (the many-tags baseline of issue 21; ``joint.SequentialSearch``)."""
_BUILTIN_TARGETS = {name: f"ra2vipas.services.controller.builtins:{cls}"
                    for name, cls in zip(BUILTINS + SHIPPED_BASELINES, ("Ra2ViPAS", "RaPAS", "RaViPAS", "Sweep", "Ra2ViPASSequential"))}


class UnknownPolicy(ValueError):
    """A name that no installed policy has, or a ``module:Class`` that does not load."""


@dataclass(frozen=True)
class PolicyInfo:
    """Where a policy comes from."""

    name: str
    target: str  # "module:Class"
    package: str  # the distribution that registered it ("ra2vipas" for the built-ins)
    version: str

    @property
    def builtin(self) -> bool:
        return self.package == "ra2vipas" and self.name in BUILTINS


@lru_cache(maxsize=1)
def _registered() -> dict[str, PolicyInfo]:
    found: dict[str, PolicyInfo] = {}
    for ep in metadata.entry_points(group=GROUP):
        dist = getattr(ep, "dist", None)
        package = dist.metadata["Name"] if dist is not None else "?"
        version = dist.version if dist is not None else "?"
        if not re.match(NAME_PATTERN, ep.name) or ep.name in found:
            continue
        found[ep.name] = PolicyInfo(ep.name, ep.value, package, version)
    for name, target in _BUILTIN_TARGETS.items():
        if name not in found:
            found[name] = PolicyInfo(name, target, "ra2vipas", _own_version())
    return found


def _own_version() -> str:
    try:
        return metadata.version("ra2vipas")
    except metadata.PackageNotFoundError:
        return "source"


def refresh() -> None:
    """Forget what was found (after installing a package in this process)."""
    _registered.cache_clear()
    _load_target.cache_clear()


def names() -> tuple[str, ...]:
    """Every registered policy: the built-ins in their order, then the others by name."""
    found = _registered()
    return BUILTINS + tuple(sorted(n for n in found if n not in BUILTINS))


def info(name: str) -> PolicyInfo:
    """Where ``name`` (a registered name or ``module:Class``) comes from. Raises ``UnknownPolicy``."""
    found = _registered()
    if name in found:
        return found[name]
    cls = load(name)
    module = cls.__module__.split(".")[0]
    package, version = module, "?"
    try:
        dist = metadata.packages_distributions().get(module, [None])[0]
        if dist:
            package, version = dist, metadata.version(dist)
    except Exception:  # noqa: BLE001 - provenance is best effort for an unregistered class
        pass
    return PolicyInfo(name, name, package, version)


def is_valid_name(name: str) -> bool:
    return bool(re.match(NAME_PATTERN, name))


@lru_cache(maxsize=None)
def _load_target(target: str) -> type[Policy]:
    module_name, _, attr = target.partition(":")
    try:
        obj: Any = importlib.import_module(module_name)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as exc:
        raise UnknownPolicy(f"cannot load policy {target!r}: {exc}") from exc
    if not (isinstance(obj, type) and issubclass(obj, Policy)):
        raise UnknownPolicy(f"{target!r} is not a ra2vipas.Policy subclass")
    return obj


def load(name: str) -> type[Policy]:
    """The policy class of a registered name or of ``module:Class``. Raises ``UnknownPolicy``
    naming the policies that are installed."""
    found = _registered()
    if name in found:
        return _load_target(found[name].target)
    if ":" in name:
        return _load_target(name)
    raise UnknownPolicy(f"unknown policy {name!r}; installed: {', '.join(names())} (or give module:Class)")


def describe() -> list[dict[str, Any]]:
    """Every registered policy as {name, package, version, builtin, summary}: what ``ra2vipas
    policies`` prints and ``GET /policies`` answers (a policy that does not load says why)."""
    rows = []
    for name in names():
        found = info(name)
        try:
            summary = load(name).summary
        except UnknownPolicy as err:
            summary = f"does not load: {err}"
        rows.append({"name": name, "package": found.package, "version": found.version, "builtin": found.builtin,
                     "summary": summary})
    return rows


def provenance(names) -> dict[str, dict[str, str]]:
    """{name: {"package", "version"}} of every policy among ``names`` that ra2vipas does not
    ship (results carry it; the built-ins come with ra2vipas itself). A name that does not load
    here is reported with package "?"."""
    out = {}
    for name in names:
        if name in BUILTINS or name in SHIPPED_BASELINES:
            continue
        try:
            found = info(name)
            out[name] = {"package": found.package, "version": found.version}
        except UnknownPolicy:
            out[name] = {"package": "?", "version": "?"}
    return out


def check(names: list[str] | tuple[str, ...]) -> list[str]:
    """``names`` with duplicates dropped (order kept), each a registered policy or a
    ``module:Class`` that loads. Raises ``UnknownPolicy`` naming the first that is neither."""
    out = list(dict.fromkeys(names))
    if not out:
        raise UnknownPolicy("no policy given")
    for name in out:
        load(name)
    return out


def result_name(name: str) -> str:
    """What results call the policy ``name``: itself, or for ``module:Class`` the class's
    ``name`` when it sets one."""
    if ":" not in name:
        return name
    cls_name = load(name).name
    return cls_name if cls_name and is_valid_name(cls_name) else name


def create(name: str, context: EpisodeContext, settings: Any = None) -> Policy:
    """A new policy object for one episode; ``settings`` (a ``ControllerSettings``) tunes the
    built-ins and is not given to other policies. Raises ``UnknownPolicy``."""
    from ra2vipas.services.controller.builtins import BuiltinPolicy

    cls = load(name)
    return cls(context, settings) if issubclass(cls, BuiltinPolicy) else cls(context)
