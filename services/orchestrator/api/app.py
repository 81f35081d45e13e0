"""``create_app(settings)``: the orchestrator's FastAPI application.

The lifespan opens the store and the bus (a Zenoh session unless a bus factory is given, as
tests do), starts the scheduler and the figure renderers (``api.render``), and closes all
four on shutdown. OpenAPI at ``/docs`` and ``/openapi.json``; the web dashboard at ``/``
(``ra2vipas.services.orchestrator.dashboard``).
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from typing import Callable

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError

from ra2vipas.services.orchestrator.api.errors import responses, storage_fault, validation_error
from ra2vipas.services.orchestrator.api.headers import SecurityHeaders
from ra2vipas.services.orchestrator.api.limits import MAX_BODY_BYTES, BodySizeLimit
from ra2vipas.services.orchestrator.api.render import PlotRenderer
from ra2vipas.services.orchestrator.api.routes import campaigns, catalog, events, health, results, studies, tests
from ra2vipas.services.orchestrator.dashboard import routes as dashboard
from ra2vipas.services.orchestrator.dblock import DatabaseLock
from ra2vipas.services.orchestrator.scheduler import Scheduler
from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.orchestrator.storage import StorageFault, Store
from ra2vipas.services.transport.bus import Bus

log = logging.getLogger("ra2vipas")

DESCRIPTION = """
Run Monte Carlo campaigns of transmitter discovery (Ra²ViPAS and its baselines) on the rigs of
a Zenoh mesh, and read their results: discovery-rate curves with Wilson bands (JSON or CSV),
per-test outcomes and traces, and figures (PNG or SVG). Parameter studies (`/studies`) run one
campaign per point of a grid of scenario parameters and tabulate and plot DR against them.

When the server has a token (`RA2VIPAS_TOKEN`), every request that changes state needs
`Authorization: Bearer <token>`. Errors are `{"detail": "one line"}`; a 422 names the field
and what it accepts.
"""


def create_app(settings: OrchestratorSettings, bus_factory: Callable[[], Bus] | None = None,
               db_lock: DatabaseLock | None = None) -> FastAPI:
    """``db_lock``: the database's lock when the process could not take it at start (a
    read-only folder): the store takes it before it opens the database, and answers 503 with
    the cause until then."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        guard = db_lock.acquire if db_lock is not None and not db_lock.held else None
        store = Store(settings.db_path, lazy=True, guard=guard)  # a database that cannot be opened yet: 503 until it can
        if bus_factory is None:
            from ra2vipas.services.transport.zenoh_bus import ZenohBus

            bus = ZenohBus(settings.zenoh)
        else:
            bus = bus_factory()
        scheduler = Scheduler(bus, store, window=settings.window, name=settings.name)
        renderer = PlotRenderer(settings.plot_workers, rate=settings.plot_rate).start()
        app.state.renderer = renderer
        app.state.settings = settings
        app.state.store = store
        app.state.bus = bus
        app.state.bus_open = True
        app.state.scheduler = scheduler
        if bus_factory is None:
            z = settings.zenoh
            log.info("orchestrator[%s] up (zenoh %s, connect %s, listen %s)", settings.name, z.mode, list(z.connect),
                     list(z.listen))
        try:
            yield
        finally:
            app.state.bus_open = False
            renderer.close()
            scheduler.close()
            bus.close()
            store.close()

    app = FastAPI(
        title="ra2vipas orchestrator",
        summary="Transmitter discovery campaigns (Ra²ViPAS) over a Zenoh mesh",
        description=DESCRIPTION,
        version="1",
        lifespan=lifespan,
        responses=responses(400, 413, 422, 503),  # every route: our error body, not FastAPI's default 422 schema
    )
    app.add_middleware(BodySizeLimit, max_bytes=MAX_BODY_BYTES)
    app.add_middleware(SecurityHeaders)  # outermost: on every response, errors included
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(StorageFault, storage_fault)
    for module in (health, campaigns, events, results, tests, studies, catalog):
        app.include_router(module.router)
    dashboard.mount(app)  # the web dashboard at / (pages under /ui/, not in the OpenAPI schema)
    return app
