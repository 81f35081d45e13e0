"""``ra2vipas sensors|learner|controller|orchestrator|router``: start one service process.

Every service takes the same Zenoh options (flag > environment > default):
``--zenoh-mode`` (RA2VIPAS_ZENOH_MODE; ``--mode`` is its deprecated spelling), ``--connect`` (repeatable; RA2VIPAS_ZENOH_CONNECT,
comma-separated), ``--listen`` (repeatable; RA2VIPAS_ZENOH_LISTEN), ``--zenoh-config``
(RA2VIPAS_ZENOH_CONFIG, a Zenoh JSON5 file). ``--connect`` without a mode joins that router as a
client; a peer that no other host can reach says so at start-up. SIGINT/SIGTERM close the
session and exit 0.
"""

from __future__ import annotations

import gc
import logging
import os
import re
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Annotated, Callable, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.services.transport.zenoh_config import ZenohSettings, ZenohSettingsError

log = logging.getLogger("ra2vipas")

ModeOpt = Annotated[Optional[str], typer.Option("--zenoh-mode", help="Zenoh mode: peer|client|router [env RA2VIPAS_ZENOH_MODE; default client with --connect and no --listen (join that router), else peer].")]
OldModeOpt = Annotated[Optional[str], deprecated("--mode", "--zenoh-mode")]  # renamed: campaign start --mode is fast|realtime
ConnectOpt = Annotated[Optional[list[str]], typer.Option("--connect", "-e", metavar="ENDPOINT", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable) [env RA2VIPAS_ZENOH_CONNECT].")]
ListenOpt = Annotated[Optional[list[str]], typer.Option("--listen", "-l", metavar="ENDPOINT", help="Zenoh endpoint to listen on (repeatable) [env RA2VIPAS_ZENOH_LISTEN].")]
ConfigOpt = Annotated[Optional[str], typer.Option("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file, applied first [env RA2VIPAS_ZENOH_CONFIG].")]
LogOpt = Annotated[str, typer.Option("--log-level", envvar="RA2VIPAS_LOG_LEVEL", help="Log level.")]
RigOpt = Annotated[str, typer.Option("--rig", envvar="RA2VIPAS_RIG", help="Rig name (one sensing platform and its controller).")]
PolicyOpt = Annotated[Optional[list[str]], typer.Option("--policy", "-p", metavar="NAME", envvar="RA2VIPAS_POLICY", help="A pointing policy this controller serves: an installed name (ra2vipas policies) or module:Class (repeatable or comma-separated) [env RA2VIPAS_POLICY; default: every installed policy]. The orchestrator hands this rig only episodes of these.")]


def served_policies(policies: list[str] | None) -> dict[str, str]:
    """The controller's served policies from ``--policy`` values (each may be comma-separated;
    none: every installed one), checked here: one that does not load is one stderr line and
    exit 2."""
    from ra2vipas.services.controller import registry
    from ra2vipas.services.controller.node import served_policies as served

    names = [n.strip() for value in policies or [] for n in value.replace(" ", ",").split(",") if n.strip()]
    try:
        return served(names or None)
    except registry.UnknownPolicy as err:
        fail(str(err), EXIT_USAGE)


def zenoh_settings(mode, connect, listen, config, old_mode: str | None = None) -> ZenohSettings:
    """The Zenoh options (flag > environment > default) as settings; ``old_mode`` is the value of
    the deprecated ``--mode`` spelling of ``--zenoh-mode``."""
    mode = prefer(mode, old_mode, "--mode", "--zenoh-mode")
    try:
        return ZenohSettings.from_sources(mode=mode, connect=connect, listen=listen, config_file=config)
    except ZenohSettingsError as err:
        fail(str(err), EXIT_USAGE)


_RUST_WHERE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def endpoint_answers(endpoint: str, timeout_s: float = 2.0) -> bool | None:
    """Whether something accepts TCP connections at a ``tcp/`` or ``tls/`` Zenoh endpoint
    (None for other protocols)."""
    proto, _, address = endpoint.partition("/")
    if proto not in ("tcp", "tls"):
        return None
    host, _, port = address.split("#", 1)[0].split("?", 1)[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except (OSError, ValueError):
        return False


def not_joined(zenoh: ZenohSettings) -> str:
    """One line: why this node is not connected to any of its ``--connect`` endpoints."""
    eps = list(zenoh.connect)
    answering = [ep for ep in eps if endpoint_answers(ep)]
    if answering:
        creds = ("its user/password (RA2VIPAS_ZENOH_USER, RA2VIPAS_ZENOH_PASSWORD or _PASSWORD_FILE)" if zenoh.user
                 else "whether it requires a user/password (RA2VIPAS_ZENOH_USER, RA2VIPAS_ZENOH_PASSWORD), which this node did not give")
        return (f"{answering[0]} accepts connections but did not let this node's Zenoh session in: check {creds} "
                "and its TLS settings")
    return (f"nothing answers at {', '.join(eps)}: check --connect (RA2VIPAS_ZENOH_CONNECT) and that the router there is "
            "running")


def open_error(err: Exception, zenoh: ZenohSettings) -> str:
    """The one-line error for a Zenoh session that did not open (no Rust source path)."""
    text = _RUST_WHERE.sub("", " ".join(str(err).split())).strip()
    if zenoh.connect and ("Unable to connect" in text or "Timeout" in text):
        return f"cannot join the Zenoh network: {not_joined(zenoh)}"
    return f"cannot open the Zenoh session: {text}"


def warn_while_alone(session, zenoh: ZenohSettings, after_s: float = 10.0) -> None:
    """A peer whose ``--connect`` endpoints are unreachable still opens (Zenoh keeps trying in
    the background): log one error line if it has joined nobody after ``after_s``."""
    if zenoh.mode != "peer" or not zenoh.connect:
        return

    def check() -> None:
        deadline = time.monotonic() + after_s
        while time.monotonic() < deadline:
            try:
                info = session.info
                if info.routers_zid() or info.peers_zid():
                    return
            except Exception:  # the session closed meanwhile
                return
            time.sleep(0.5)
        log.error("not connected to any Zenoh node after %.0f s (still trying): %s", after_s, not_joined(zenoh))

    threading.Thread(target=check, name="zenoh-join-check", daemon=True).start()


def warn_if_unreachable(zenoh: ZenohSettings) -> None:
    """Log at start-up why a peer will hear nobody on other hosts (``ZenohSettings.reach_warning``)."""
    try:
        warning = zenoh.reach_warning()
    except Exception:  # the session opened with this configuration: nothing to add if it cannot be rebuilt
        return
    if warning:
        log.warning("%s", warning)


def run_node(name: str, zenoh: ZenohSettings, build: Callable) -> None:
    """Open the Zenoh session, build the node on it, serve until SIGINT/SIGTERM, close both."""
    from ra2vipas.services.transport.runtime import wait_for_shutdown_signal
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    try:
        bus = ZenohBus(zenoh)
    except Exception as err:  # zenoh raises ZError for bad endpoints, ports in use, unreachable routers, ...
        fail(open_error(err, zenoh))
    warn_while_alone(bus.session, zenoh)
    warn_if_unreachable(zenoh)
    node = None
    try:
        node = build(bus)
        gc.collect()
        gc.freeze()  # start-up objects never need scanning again: shorter GC pauses on the hot path
        sys.setswitchinterval(0.0005)  # a Zenoh thread waiting for the GIL gets it within 0.5 ms
        log.info("%s up (zenoh %s, connect %s, listen %s)", name, zenoh.mode, list(zenoh.connect), list(zenoh.listen))
        signum = wait_for_shutdown_signal()
        log.info("%s: signal %d, shutting down", name, signum)
    finally:
        if node is not None:
            node.close()
        bus.close()


def sensors(rig: RigOpt = "rig-1",
            hardware: Annotated[Optional[list[str]], typer.Option("--hardware", metavar="NAME=VALUE", help="Pin a hardware parameter of this simulated rig (repeatable): frames_per_rf, rf_period_s, fov_half_angle_deg, box_bearing_noise_deg, antenna_model (paper|db-gain|unknown), antenna_curvature, antenna_floor_db. Its descriptor says so, and it simulates that hardware whatever a campaign's scenario says.")] = None,
            undescribed: Annotated[bool, typer.Option("--undescribed", help="Serve no rig descriptor (behave as a v1 node).")] = False,
            mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
            zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO") -> None:
    """Run a rig's simulated sensors: the world, the camera detector, Rx(iso) and Rx(dir)."""
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.protocol.scenario import ScenarioError, parse_value
    from ra2vipas.services.sensors.node import SensorsNode, pinned_descriptor
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    _check_rig(rig, check_chunk)
    values = {}
    try:
        for item in hardware or []:
            name, sep, text = item.partition("=")
            if not sep or not name.strip():
                raise ValueError(f"--hardware expects NAME=VALUE, got {item!r}")
            name = name.strip()
            values[name] = text.strip() if name == "antenna_model" else parse_value(name, text)
        descriptor = pinned_descriptor(rig, values)
    except (ValueError, ScenarioError) as err:
        fail(str(err), EXIT_USAGE)
    _claim_cpu()
    run_node(f"sensors[{rig}]", zenoh_settings(mode, connect, listen, zenoh_config, old_mode),
             lambda bus: SensorsNode(bus, rig, descriptor=descriptor, describe=not undescribed))


def controller(rig: RigOpt = "rig-1", beta: Annotated[float, typer.Option(min=0.0, help="UCB exploration weight beta.")] = 4.0,
               policy: PolicyOpt = None, mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
               zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO") -> None:
    """Run a rig's controller: measurements in, pan commands out, for the pointing policies it
    serves (--policy; default every installed one), which it announces on rig/{rig}/policies."""
    from ra2vipas.services.controller.node import ControllerNode
    from ra2vipas.services.controller.policy import ControllerSettings
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    _check_rig(rig, check_chunk)
    served = list(served_policies(policy).values())
    _claim_cpu()
    run_node(f"controller[{rig}]", zenoh_settings(mode, connect, listen, zenoh_config, old_mode),
             lambda bus: ControllerNode(bus, rig, ControllerSettings(beta=beta), policies=served))


def learner(name: Annotated[str, typer.Option("--name", envvar="RA2VIPAS_LEARNER_NAME", help="Instance name.")] = "learner",
            cache_dir: Annotated[Optional[str], typer.Option("--cache-dir", envvar="RA2VIPAS_MODEL_CACHE", help="Keep trained POD models here across restarts.")] = None,
            mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
            zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO") -> None:
    """Run the POD learner: trains p_hat_D(r) once per scenario and seed, serves it."""
    from ra2vipas.services.learner.node import LearnerNode
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    _check_rig(name, check_chunk, "learner name")
    _yield_cpu()
    run_node(f"learner[{name}]", zenoh_settings(mode, connect, listen, zenoh_config, old_mode), lambda bus: LearnerNode(bus, name, cache_dir))


def orchestrator(
    host: Annotated[Optional[str], typer.Option(help="API bind address [env RA2VIPAS_HOST; default 127.0.0.1].")] = None,
    port: Annotated[Optional[int], typer.Option(min=1, max=65535, help="API port [env RA2VIPAS_PORT; default 8080].")] = None,
    db: Annotated[Optional[str], typer.Option("--db", help="SQLite file [env RA2VIPAS_DB; default ra2vipas.db].")] = None,
    window: Annotated[Optional[int], typer.Option(min=1, max=1024, help="Episodes in flight per rig [env RA2VIPAS_WINDOW; default 8].")] = None,
    expect_rigs: Annotated[Optional[int], typer.Option(min=0, max=1000, help="Rigs that must be live for /health to be 200 [env RA2VIPAS_EXPECT_RIGS; default 1].")] = None,
    token: Annotated[Optional[str], typer.Option("--token", help="Require `Authorization: Bearer TOKEN` on every request that changes state [env RA2VIPAS_TOKEN; default: none].")] = None,
    mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
    zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO",
) -> None:
    """Run the orchestrator: schedules campaigns over the rigs, stores results, serves the REST API."""
    import uvicorn

    from ra2vipas.services.orchestrator.api.app import create_app
    from ra2vipas.services.orchestrator.settings import OrchestratorSettings
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    # not niced like the learner and router: the API's latency matters (issue 14: at nice 5, any
    # nice-0 process on a busy 2-core machine pushed the read p99 past 1 s); figures are drawn by
    # its renderer processes at nice 19 instead
    from ra2vipas.services.orchestrator.settings import SettingsError

    try:
        settings = OrchestratorSettings.from_sources(host=host, port=port, db_path=db, window=window, expect_rigs=expect_rigs,
                                                     token=token, zenoh=zenoh_settings(mode, connect, listen, zenoh_config, old_mode))
    except SettingsError as err:
        fail(str(err), EXIT_USAGE)
    from ra2vipas.services.orchestrator.dblock import DatabaseInUse, DatabaseLock

    folder = Path(settings.db_path).expanduser().resolve().parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if not folder.is_dir():
            fail(f"cannot create the database folder {folder}: {(err.strerror or str(err)).lower()}; "
                 "create it, or give --db a path you can write")
    db_lock = DatabaseLock(settings.db_path)
    try:
        db_lock.acquire()  # held until this process exits
    except DatabaseInUse as err:
        fail(str(err))
    except OSError as err:  # e.g. a read-only folder: start degraded (503 naming the cause) and take it when it can be
        log.error("cannot lock the database %s: %s; the API answers 503 until it can (retrying)", settings.db_path,
                  (err.strerror or str(err)).lower())
    warn_if_unreachable(settings.zenoh)
    from ra2vipas.services.orchestrator.api.guard import ConnectionGuard, GuardLimits, raise_fd_limit, rate_limit_logs

    # what one client can hold (issue 18: slow clients once exhausted the descriptors): a deadline
    # for each request's head, a cap on connections overall and per client, under the fd limit
    limits = GuardLimits(settings.max_connections, settings.max_connections_per_client, settings.header_timeout_s)
    limits = limits.within_fd_limit(raise_fd_limit())
    guard = ConnectionGuard(limits)
    server = uvicorn.Server(uvicorn.Config(create_app(settings, db_lock=db_lock), host=settings.host, port=settings.port, log_level=log_level.lower(),
                                           access_log=log_level.upper() == "DEBUG", timeout_graceful_shutdown=5,
                                           http=guard.protocol_class(), backlog=limits.backlog))
    rate_limit_logs()  # after uvicorn set up its loggers: a flood of one line is logged 5 times per 10 s, then counted
    import signal

    # uvicorn shuts down gracefully on SIGINT/SIGTERM, then re-raises the signal to the handler
    # that was there before it; with this no-op one the process exits 0 like the other services.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: None)
    try:
        server.run()
    finally:
        db_lock.release()


def router(listen: ListenOpt = None, connect: ConnectOpt = None, zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO") -> None:
    """Run a standalone Zenoh router (Python) for hosts without the official zenohd binary.

    Without --listen it listens on tcp/127.0.0.1:7447 only: give e.g. --listen tcp/0.0.0.0:7447
    to accept other machines.

    Example:

        ra2vipas router --listen tcp/0.0.0.0:7447
    """
    from ra2vipas.services.transport.runtime import configure_logging, wait_for_shutdown_signal

    configure_logging(log_level)
    _claim_cpu()  # every message between clients passes through the router: it is on the control loop's path
    settings = zenoh_settings("router", connect, listen, zenoh_config)  # no listen endpoint anywhere: 127.0.0.1:7447
    import json

    import zenoh

    try:
        conf = settings.to_zenoh()
        session = zenoh.open(conf)
    except Exception as err:
        fail(f"cannot start the Zenoh router: {err}")
    endpoints = json.loads(conf.get_json("listen/endpoints"))
    log.info("zenoh router up, listening on %s", endpoints.get("router", endpoints) if isinstance(endpoints, dict) else endpoints)
    try:
        wait_for_shutdown_signal()
    finally:
        session.close()


def _claim_cpu() -> None:
    """Sensors and controllers close the control loop, and a router carries their messages when
    they are its clients: where allowed (root, CAP_SYS_NICE) they run at a higher priority so
    a busy machine delays their replies less."""
    try:
        os.nice(-5)
    except OSError:
        pass


def _yield_cpu(increment: int = 5) -> None:
    """Bookkeeping services (learner, router) run at a lower priority so that on a
    small machine the sensors and controllers, whose latency matters, get the cores first."""
    try:
        os.nice(increment)
    except OSError:
        pass


def _check_rig(name: str, check, what: str = "rig") -> None:
    try:
        check(name, what)
    except ValueError as err:
        fail(str(err), EXIT_USAGE)
