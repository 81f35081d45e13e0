"""/presets, /policies and /rigs: what a campaign can be made of."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, status
from fastapi.exceptions import RequestValidationError

from ra2vipas.services.controller import registry
from ra2vipas.services.orchestrator.api.deps import SchedulerDep, SettingsDep
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.schemas import PolicyPublic, PresetPublic, PresetSummary, RigsPublic
from ra2vipas.services.orchestrator.api.views import rigs_public, supervised_services
from ra2vipas.services.orchestrator.presets import preset_object, preset_summaries
from ra2vipas.services.protocol.scenario import PRESETS

router = APIRouter(tags=["presets and rigs"])


@router.get("/presets", response_model=list[PresetSummary])
def list_presets() -> list[PresetSummary]:
    """The named scenarios."""
    return [PresetSummary(**p) for p in preset_summaries()]


@router.get("/presets/{name}", response_model=PresetPublic, responses=responses(404))
def show_preset(name: str) -> PresetPublic:
    """Every scenario parameter of a preset with its value, allowed range and meaning (any of
    them can be overridden in ``POST /campaigns``)."""
    if name not in PRESETS:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no preset {name!r}; presets: {', '.join(PRESETS)}")
    return PresetPublic.model_validate(preset_object(name))


@router.get("/policies", response_model=list[PolicyPublic])
def list_policies() -> list[PolicyPublic]:
    """The pointing policies a campaign can name: the built-ins and every installed policy
    (entry points ``ra2vipas.policies``), with the package and version each comes from."""
    return [PolicyPublic(**row) for row in registry.describe()]


def check_policies(names: list[str], served: dict[str, tuple[str, ...] | None] | None = None) -> None:
    """422 naming a policy the campaign cannot run, with the ones it can.

    ``served``: the policies each live rig the campaign may run on serves (``Scheduler.served``;
    None: not known yet). Once one of them is known, a policy must be served by a live
    controller (the list is their union); a rig whose controller has not answered yet may
    still serve any installed one. With no such rig live (campaigns may be queued before the
    rigs come up), a policy must be installed here (the registry)."""
    known = [p for p in (served or {}).values() if p is not None]
    if known:
        union = {name for policies in known for name in policies}
        available = [n for n in registry.BUILTINS if n in union] + sorted(union - set(registry.BUILTINS))
        pending = any(p is None for p in served.values())
        unknown = [n for n in names if n not in available and not (pending and n in registry.names())]
        if unknown:
            raise RequestValidationError([{"loc": ("body", "algorithms"), "type": "value_error",
                                           "msg": f"no live controller serves policy {unknown[0]!r}; available: "
                                                  f"{', '.join(available)}"}])
        return
    installed = registry.names()
    unknown = [n for n in names if n not in installed]
    if unknown:
        raise RequestValidationError([{"loc": ("body", "algorithms"), "type": "value_error",
                                       "msg": f"unknown policy {unknown[0]!r}; available: {', '.join(installed)}"}])


@router.get("/rigs", response_model=RigsPublic)
def list_rigs(scheduler: SchedulerDep, settings: SettingsDep) -> RigsPublic:
    """Rigs (sensors + controller) and learners seen through Zenoh liveliness; a rig is live
    while both its nodes hold their tokens, and one whose nodes have both left is no longer
    listed. Each rig shows the policies its controller serves (``policies``: only episodes of
    those go there; a 1.0 or 1.1 controller serves the four built-ins). Under ``ra2vipas up``, ``services`` lists the stack's services that crashed and
    wait to be restarted (backing off when in a crash loop)."""
    return rigs_public(scheduler.status(), supervised_services(settings.supervisor_status))
