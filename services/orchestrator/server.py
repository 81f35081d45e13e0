"""Serving the orchestrator's API in this process (``ra2vipas orchestrator`` and ``python -m
ra2vipas.services.orchestrator``): the database lock, the connection guard, uvicorn, shutdown on
SIGINT/SIGTERM with exit 0."""

from __future__ import annotations

import logging
import signal

from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.transport.service import ServiceError, warn_if_unreachable

log = logging.getLogger("ra2vipas")


def serve(settings: OrchestratorSettings, log_level: str = "INFO") -> None:
    """Take the database lock, serve the API until SIGINT/SIGTERM, release the lock.

    Not niced like the learner and router: the API's latency matters (issue 14: at nice 5, any
    nice-0 process on a busy machine delays every read); figures are drawn by its renderer
    processes at nice 10 instead.

    Raises
    ------
    ServiceError
        The database folder cannot be created, or another process holds the database.
    """
    import uvicorn

    from ra2vipas.services.orchestrator.api.app import create_app
    from ra2vipas.services.orchestrator.api.guard import ConnectionGuard, GuardLimits, raise_fd_limit, rate_limit_logs
    from ra2vipas.services.orchestrator.dblock import DatabaseFolderError, DatabaseInUse, DatabaseLock, make_folder

    try:
        make_folder(settings.db_path)
    except DatabaseFolderError as err:
        raise ServiceError(str(err)) from None
    db_lock = DatabaseLock(settings.db_path)
    try:
        db_lock.acquire()  # held until this process exits
    except DatabaseInUse as err:
        raise ServiceError(str(err)) from None
    except OSError as err:  # e.g. a read-only folder: start degraded (503 naming the cause) and take it when it can be
        log.error("cannot lock the database %s: %s; the API answers 503 until it can (retrying)", settings.db_path,
                  (err.strerror or str(err)).lower())
    warn_if_unreachable(settings.zenoh)
    # what one client can hold (issue 18: slow clients once exhausted the descriptors): a deadline
    # for each request's head, a cap on connections overall and per client, under the fd limit
    limits = GuardLimits(settings.max_connections, settings.max_connections_per_client, settings.header_timeout_s)
    limits = limits.within_fd_limit(raise_fd_limit())
    guard = ConnectionGuard(limits)
    server = uvicorn.Server(uvicorn.Config(create_app(settings, db_lock=db_lock), host=settings.host, port=settings.port,
                                           log_level=log_level.lower(), access_log=log_level.upper() == "DEBUG",
                                           timeout_graceful_shutdown=5, http=guard.protocol_class(), backlog=limits.backlog))
    rate_limit_logs()  # after uvicorn set up its loggers: a flood of one line is logged 5 times per 10 s, then counted
    # uvicorn shuts down gracefully on SIGINT/SIGTERM, then re-raises the signal to the handler
    # that was there before it; with this no-op one the process exits 0 like the other services.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: None)
    try:
        server.run()
    finally:
        db_lock.release()
