"""FastAPI dependencies: the app's shared objects, reached through ``request.app.state``."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, status

from services.orchestrator.scheduler import Scheduler
from services.orchestrator.settings import OrchestratorSettings
from services.orchestrator.storage import Store


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_scheduler(request: Request) -> Scheduler:
    return request.app.state.scheduler


def get_settings(request: Request) -> OrchestratorSettings:
    return request.app.state.settings


def require_token(request: Request) -> None:
    """State-changing routes: when a token is configured, demand ``Authorization: Bearer <token>``."""
    token = request.app.state.settings.token
    if not token:
        return
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer" or value.strip() != token:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


StoreDep = Annotated[Store, Depends(get_store)]
SchedulerDep = Annotated[Scheduler, Depends(get_scheduler)]
SettingsDep = Annotated[OrchestratorSettings, Depends(get_settings)]
Authorized = Depends(require_token)
