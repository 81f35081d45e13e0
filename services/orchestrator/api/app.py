"""``create_app(settings)``: the orchestrator's FastAPI application.

The lifespan opens the store and the bus (a Zenoh session unless a bus factory is given, as
tests do), starts the scheduler, and closes all three on shutdown.
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from typing import Callable

from fastapi import FastAPI

from services.orchestrator.api.routes import campaigns, health
from services.orchestrator.scheduler import Scheduler
from services.orchestrator.settings import OrchestratorSettings
from services.orchestrator.storage import Store
from services.transport.bus import Bus


def create_app(settings: OrchestratorSettings, bus_factory: Callable[[], Bus] | None = None) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        store = Store(settings.db_path)
        if bus_factory is None:
            from services.transport.zenoh_bus import ZenohBus

            bus = ZenohBus(settings.zenoh)
        else:
            bus = bus_factory()
        scheduler = Scheduler(bus, store, window=settings.window, name=settings.name)
        app.state.settings = settings
        app.state.store = store
        app.state.bus = bus
        app.state.bus_open = True
        app.state.scheduler = scheduler
        try:
            yield
        finally:
            app.state.bus_open = False
            scheduler.close()
            bus.close()
            store.close()

    app = FastAPI(
        title="ra2vipas orchestrator",
        summary="Transmitter discovery campaigns (Ra²ViPAS) over a Zenoh mesh",
        version="1",
        lifespan=lifespan,
    )
    app.include_router(health.router)
    app.include_router(campaigns.router)
    return app
