"""`python -m ra2vipas.services.orchestrator`: run the orchestrator (as `ra2vipas orchestrator`)."""

from __future__ import annotations

from ra2vipas.services.transport import service


def main(argv: list[str] | None = None) -> None:
    p = service.parser("python -m ra2vipas.services.orchestrator",
                       "Run the orchestrator: schedules campaigns over the rigs, stores results, serves the REST API.")
    p.add_argument("--host", help="API bind address [env RA2VIPAS_HOST; default 127.0.0.1].")
    p.add_argument("--port", type=int, help="API port [env RA2VIPAS_PORT; default 8080].")
    p.add_argument("--db", help="SQLite file [env RA2VIPAS_DB; default ra2vipas.db].")
    p.add_argument("--window", type=int, help="Episodes in flight per rig [env RA2VIPAS_WINDOW; default 8].")
    p.add_argument("--expect-rigs", type=int, help="Rigs that must be live for /health to be 200 [env RA2VIPAS_EXPECT_RIGS; default 1].")
    p.add_argument("--token", help="Require `Authorization: Bearer TOKEN` on every request that changes state [env RA2VIPAS_TOKEN].")
    args = service.parse(p, argv)
    from ra2vipas.services.orchestrator.server import serve
    from ra2vipas.services.orchestrator.settings import OrchestratorSettings, SettingsError
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(args.log_level)
    try:
        settings = OrchestratorSettings.from_sources(host=args.host, port=args.port, db_path=args.db, window=args.window,
                                                     expect_rigs=args.expect_rigs, token=args.token, zenoh=service.zenoh_of(args))
    except SettingsError as err:
        raise service.ServiceError(str(err), service.EXIT_USAGE) from None
    serve(settings, args.log_level)


if __name__ == "__main__":
    service.main(main)
