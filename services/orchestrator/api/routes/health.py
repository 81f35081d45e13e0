"""/health: the API, the database and the Zenoh mesh."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from ra2vipas.services.orchestrator.api.deps import SchedulerDep, SettingsDep, StoreDep
from ra2vipas.services.orchestrator.api.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health, responses={503: {"model": Health, "description": "not ready"}})
def health(request: Request, response: Response, store: StoreDep, scheduler: SchedulerDep, settings: SettingsDep) -> Health:
    """200 once the database answers and takes writes, the Zenoh session is open, a learner is
    alive and the expected rigs are alive and have said what they are (each one's descriptor and
    its controller's policies answered, or a v1 node's silence taken as such: ``ready_rigs``, the
    rigs episodes may go to); 503 (same body) until then, or while the database
    is failing (``database_error`` says why; the orchestrator retries by itself). Also counts
    the result-plane and truth-plane messages it dropped, by reason."""
    fault = store.fault
    db_ok = store.ping() and fault is None
    zenoh_ok = bool(getattr(request.app.state, "bus_open", False))
    rigs, ready_rigs = scheduler.live_rigs(), scheduler.ready_rigs()
    snapshot = scheduler.status()
    ready = db_ok and zenoh_ok and len(ready_rigs) >= settings.expect_rigs and bool(snapshot["learners"])
    if not ready:
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    state = "ok" if ready else ("degraded" if not db_ok or not zenoh_ok else "starting")
    database_error = None if db_ok else (fault.describe() if fault is not None else "unavailable")
    return Health(status=state, ready=ready, database=db_ok, database_error=database_error, zenoh=zenoh_ok, rigs=rigs, ready_rigs=ready_rigs,
                  expected_rigs=settings.expect_rigs, learners=snapshot["learners"], rejected_messages=snapshot["rejected"],
                  waiting_writes=snapshot["waiting_writes"], instance=settings.instance_id)
