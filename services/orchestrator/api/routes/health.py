"""/health: the API, the database and the Zenoh mesh."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from ra2vipas.services.orchestrator.api.deps import SchedulerDep, SettingsDep, StoreDep
from ra2vipas.services.orchestrator.api.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, responses={503: {"model": Health, "description": "not ready"}})
def health(request: Request, response: Response, store: StoreDep, scheduler: SchedulerDep, settings: SettingsDep) -> Health:
    """200 once the database answers, the Zenoh session is open and the expected rigs and a
    learner are alive; 503 (same body) until then."""
    db_ok = store.ping()
    zenoh_ok = bool(getattr(request.app.state, "bus_open", False))
    rigs = scheduler.live_rigs()
    learners = scheduler.status()["learners"]
    ready = db_ok and zenoh_ok and len(rigs) >= settings.expect_rigs and bool(learners)
    if not ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    state = "ok" if ready else ("degraded" if not db_ok or not zenoh_ok else "starting")
    return Health(status=state, ready=ready, database=db_ok, zenoh=zenoh_ok, rigs=rigs, expected_rigs=settings.expect_rigs, learners=learners)
