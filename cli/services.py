"""``ra2vipas sensors|learner|controller|orchestrator|router``: start one service process.

Every service takes the same Zenoh options (flag > environment > default):
``--zenoh-mode`` (RA2VIPAS_ZENOH_MODE; ``--mode`` is its deprecated spelling), ``--connect`` (repeatable; RA2VIPAS_ZENOH_CONNECT,
comma-separated), ``--listen`` (repeatable; RA2VIPAS_ZENOH_LISTEN), ``--zenoh-config``
(RA2VIPAS_ZENOH_CONFIG, a Zenoh JSON5 file). ``--connect`` without a mode joins that router as a
client; a peer that no other host can reach says so at start-up. SIGINT/SIGTERM close the
session and exit 0.
"""

from __future__ import annotations

import logging
from typing import Annotated, Callable, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.services.transport import service
from ra2vipas.services.transport.realtime import DEFAULT_PRIORITY
from ra2vipas.services.transport.service import ServiceError, open_error, warn_if_unreachable, warn_while_alone  # noqa: F401  (cli.rig)
from ra2vipas.services.transport.zenoh_config import ZenohSettings

log = logging.getLogger("ra2vipas")

ModeOpt = Annotated[Optional[str], typer.Option("--zenoh-mode", help="Zenoh mode: peer|client|router [env RA2VIPAS_ZENOH_MODE; default client with --connect and no --listen (join that router), else peer].")]
OldModeOpt = Annotated[Optional[str], deprecated("--mode", "--zenoh-mode")]  # renamed: campaign start --mode is fast|realtime
ConnectOpt = Annotated[Optional[list[str]], typer.Option("--connect", "-e", metavar="ENDPOINT", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable) [env RA2VIPAS_ZENOH_CONNECT].")]
ListenOpt = Annotated[Optional[list[str]], typer.Option("--listen", "-l", metavar="ENDPOINT", help="Zenoh endpoint to listen on (repeatable) [env RA2VIPAS_ZENOH_LISTEN].")]
ConfigOpt = Annotated[Optional[str], typer.Option("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file, applied first [env RA2VIPAS_ZENOH_CONFIG].")]
LogOpt = Annotated[str, typer.Option("--log-level", envvar="RA2VIPAS_LOG_LEVEL", help="Log level.")]
RealtimePriorityOpt = Annotated[int, typer.Option(
    "--realtime-priority", envvar="RA2VIPAS_REALTIME_PRIORITY", min=0, max=49,
    help="SCHED_FIFO priority of the control loop's threads while this process runs realtime episodes only "
         "(1-49; 0: off). Needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO; without, it says so once and runs at the "
         "ordinary priority. A fast episode in flight turns it off (a lockstep never sleeps).")]
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
        return service.zenoh_settings(mode, connect, listen, config)
    except ServiceError as err:
        fail(str(err), err.exit_code)


def run_node(name: str, zenoh: ZenohSettings, build: Callable) -> None:
    """``service.run_node`` (open the session, build the node, serve until SIGINT/SIGTERM), its
    errors one stderr line."""
    try:
        service.run_node(name, zenoh, build)
    except ServiceError as err:
        fail(str(err), err.exit_code)


def sensors(rig: RigOpt = "rig-1",
            hardware: Annotated[Optional[list[str]], typer.Option("--hardware", metavar="NAME=VALUE", help="Pin a hardware parameter of this simulated rig (repeatable): frames_per_rf, rf_period_s, fov_half_angle_deg, box_bearing_noise_deg, antenna_model (paper|db-gain|unknown), antenna_curvature, antenna_floor_db, n_tags (how many tags its receivers hear: a campaign searching for more is refused). Its descriptor says so, and it simulates that hardware whatever a campaign's scenario says.")] = None,
            undescribed: Annotated[bool, typer.Option("--undescribed", help="Serve no rig descriptor (behave as a v1 node).")] = False,
            realtime_priority: RealtimePriorityOpt = DEFAULT_PRIORITY,
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
             lambda bus: SensorsNode(bus, rig, descriptor=descriptor, describe=not undescribed, realtime_priority=realtime_priority))


def controller(rig: RigOpt = "rig-1", beta: Annotated[float, typer.Option(min=0.0, help="UCB exploration weight beta.")] = 4.0,
               policy: PolicyOpt = None, mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
               zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO", realtime_priority: RealtimePriorityOpt = DEFAULT_PRIORITY) -> None:
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
             lambda bus: ControllerNode(bus, rig, ControllerSettings(beta=beta), policies=served, realtime_priority=realtime_priority))


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
    from ra2vipas.services.orchestrator.settings import OrchestratorSettings
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    from ra2vipas.services.orchestrator.settings import SettingsError

    try:
        settings = OrchestratorSettings.from_sources(host=host, port=port, db_path=db, window=window, expect_rigs=expect_rigs,
                                                     token=token, zenoh=zenoh_settings(mode, connect, listen, zenoh_config, old_mode))
    except SettingsError as err:
        fail(str(err), EXIT_USAGE)
    from ra2vipas.services.orchestrator.server import serve

    try:
        serve(settings, log_level)
    except ServiceError as err:
        fail(str(err), err.exit_code)


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


_claim_cpu = service.claim_cpu
_yield_cpu = service.yield_cpu


def _check_rig(name: str, check, what: str = "rig") -> None:
    try:
        service.check_name(name, check, what)
    except ServiceError as err:
        fail(str(err), err.exit_code)
