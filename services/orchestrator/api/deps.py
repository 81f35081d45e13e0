"""FastAPI dependencies: the app's shared objects (through ``request.app.state``), the
bearer token check, and the campaign named in the path (404 if unknown)."""

from __future__ import annotations

import hmac
from typing import Annotated, Any, Optional

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.orchestrator.storage import Store

_bearer = HTTPBearer(auto_error=False, description="Required by state-changing requests when the server has a token (RA2VIPAS_TOKEN).")


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_scheduler(request: Request) -> Scheduler:
    return request.app.state.scheduler


def get_settings(request: Request) -> OrchestratorSettings:
    return request.app.state.settings


def require_token(request: Request, credentials: Annotated[Optional[HTTPAuthorizationCredentials], Depends(_bearer)]) -> None:
    """State-changing routes: when a token is configured, demand ``Authorization: Bearer <token>``."""
    token = request.app.state.settings.token
    if not token:
        return
    given = credentials.credentials.strip() if credentials is not None else ""
    if not hmac.compare_digest(given.encode(), token.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing or wrong bearer token (Authorization: Bearer <token>)",
                            headers={"WWW-Authenticate": "Bearer"})


StoreDep = Annotated[Store, Depends(get_store)]
SchedulerDep = Annotated[Scheduler, Depends(get_scheduler)]
SettingsDep = Annotated[OrchestratorSettings, Depends(get_settings)]
Authorized = Depends(require_token)


def get_campaign(campaign_id: str, store: StoreDep) -> dict[str, Any]:
    """The campaign row named by the ``{campaign_id}`` path parameter; 404 if there is none."""
    row = store.campaign(campaign_id)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {campaign_id!r}")
    return row


CampaignDep = Annotated[dict[str, Any], Depends(get_campaign)]
