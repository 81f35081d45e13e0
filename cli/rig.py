"""``ra2vipas rig``: one rig's sensors and controller in one process.

For deployments that scale rigs by replicas (``docker compose up --scale rig=N``): replicas
share one configuration, so they cannot be told their rig name one by one, and a sensors node
and its controller must agree on it. A ``rig`` process runs both nodes, so they do, and takes
its name from ``--rig`` / ``RA2VIPAS_RIG`` or, when neither is given, from the host name (a
container's host name is unique and survives a restart).

The two nodes share one Zenoh session and one worker thread (``EventLoop(inline=True)``): a
command the controller sends reaches the sensors, and a measurement the sensors send reaches the
controller, as the message object itself (``EventLoop.send``), handled on the same worker as
soon as the sending handler returns: no router, no socket, no thread hop, no JSON encoding or
validation between them. Every message goes to the network under its documented key, as JSON,
whenever anyone else subscribes (``ZenohBus.publish_remote``: a recorder, a test). Both liveliness tokens are
the session's, so they disappear together if the process dies. ``--listen`` and ``--connect``
are the session's (``--split`` runs the two nodes as before, each with its own session: the
controller's connects through ``--connect`` or, without it, to the sensors' listener).
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import re
import socket
import sys
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail
from ra2vipas.cli.services import (
    ConfigOpt,
    ConnectOpt,
    ListenOpt,
    LogOpt,
    ModeOpt,
    OldModeOpt,
    PolicyOpt,
    RealtimePriorityOpt,
    open_error,
    served_policies,
    warn_if_unreachable,
    warn_while_alone,
    zenoh_settings,
)
from ra2vipas.services.transport.realtime import DEFAULT_PRIORITY
from ra2vipas.services.transport.zenoh_config import ZenohSettings

log = logging.getLogger("ra2vipas")

_NOT_IN_CHUNK = re.compile(r"[^A-Za-z0-9_-]+")


def rig_name_from_host(hostname: str) -> str:
    """A valid rig name (1-64 of ``A-Z a-z 0-9 - _``) from a host name: its first label with
    any other character replaced by ``-``, e.g. ``robot-1.lab.example`` -> ``robot-1``."""
    label = hostname.split(".", 1)[0]
    name = _NOT_IN_CHUNK.sub("-", label).strip("-")[:64]
    return name or "rig"


def controller_settings(sensors: ZenohSettings) -> ZenohSettings:
    """``rig --split``: the controller session's settings: the sensors' settings without their listeners (one
    port, one listener), joining through the same ``connect`` endpoints or, if there are none,
    through the sensors' own listener (on loopback when it listens on every address)."""
    connect = sensors.connect or tuple(ep.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:") for ep in sensors.listen)
    return dataclasses.replace(sensors, listen=(), connect=connect)


def rig(
    rig: Annotated[Optional[str], typer.Option("--rig", envvar="RA2VIPAS_RIG",
                                               help="Rig name (default: this host's name, e.g. the container's).")] = None,
    beta: Annotated[float, typer.Option(min=0.0, help="UCB exploration weight beta.")] = 4.0,
    policy: PolicyOpt = None,
    mode: ModeOpt = None, old_mode: OldModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None,
    zenoh_config: ConfigOpt = None, log_level: LogOpt = "INFO",
    split: Annotated[bool, typer.Option("--split", help="A Zenoh session and a worker thread per node (their traffic through the router), as two processes would.")] = False,
    realtime_priority: RealtimePriorityOpt = DEFAULT_PRIORITY,
) -> None:
    """Run one rig, its simulated sensors and its Ra²ViPAS controller, in one process and one Zenoh session."""
    from ra2vipas.services.controller.node import ControllerNode
    from ra2vipas.services.controller.policy import ControllerSettings
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.sensors.node import SensorsNode
    from ra2vipas.services.transport.runtime import EventLoop, configure_logging, wait_for_shutdown_signal
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    configure_logging(log_level)
    name = rig or rig_name_from_host(socket.gethostname())
    try:
        check_chunk(name, "rig")
    except ValueError as err:
        fail(str(err), EXIT_USAGE)
    settings = zenoh_settings(mode, connect, listen, zenoh_config, old_mode)
    served = list(served_policies(policy).values())
    try:
        os.nice(-5)  # like `ra2vipas sensors|controller`: the control loop first, where allowed
    except OSError:
        pass

    buses: list = []
    nodes: list = []
    loop = None
    try:
        try:
            buses.append(ZenohBus(settings))
            if split:
                buses.append(ZenohBus(controller_settings(settings)))
        except Exception as err:  # zenoh raises ZError for bad endpoints, ports in use, unreachable routers, ...
            fail(open_error(err, settings))
        warn_while_alone(buses[0].session, settings)
        warn_if_unreachable(settings)
        if not split:
            loop = EventLoop(f"rig-{name}", inline=True, realtime_priority=realtime_priority)
        nodes.append(ControllerNode(buses[-1], name, ControllerSettings(beta=beta), policies=served, loop=loop,
                                    realtime_priority=realtime_priority))
        nodes.append(SensorsNode(buses[0], name, loop=loop, realtime_priority=realtime_priority))
        gc.collect()
        gc.freeze()
        sys.setswitchinterval(0.0005)
        log.info("rig[%s] up (zenoh %s, connect %s, listen %s)", name, settings.mode, list(settings.connect), list(settings.listen))
        signum = wait_for_shutdown_signal()
        log.info("rig[%s]: signal %d, shutting down", name, signum)
    finally:
        for node in reversed(nodes):
            node.close()
        if loop is not None:
            loop.stop()
        for bus in reversed(buses):
            bus.close()
