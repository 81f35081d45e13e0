"""Running one service process, without the command line: Zenoh options (flag > environment >
default), the session, the node, shutdown on SIGINT/SIGTERM.

``ra2vipas sensors|learner|controller`` (``cli/services.py``) and ``python -m
ra2vipas.services.NAME`` (each service's ``__main__``) both run through ``run_node``; errors
are ``ServiceError`` (one line, an exit code), which each edge prints its own way. The
``__main__`` entries parse their flags with ``parser`` (argparse: the same flag names and
environment variables as the CLI, a usage error one ``error:`` line and exit 2).
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from typing import Callable, NoReturn

from ra2vipas.services.transport.zenoh_config import ZenohSettings, ZenohSettingsError

log = logging.getLogger("ra2vipas")

EXIT_FAILED = 1
EXIT_USAGE = 2


class ServiceError(Exception):
    """A service cannot start: one line for stderr, and the exit code (2: a usage error)."""

    def __init__(self, message: str, exit_code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def zenoh_settings(mode: str | None, connect: list[str] | None, listen: list[str] | None, config: str | None) -> ZenohSettings:
    """The Zenoh options (flag > environment > default) as settings."""
    try:
        return ZenohSettings.from_sources(mode=mode, connect=connect, listen=listen, config_file=config)
    except ZenohSettingsError as err:
        raise ServiceError(str(err), EXIT_USAGE) from None


def check_name(name: str, check: Callable[[str, str], None], what: str = "rig") -> None:
    """A rig or instance name the key expressions accept (``check`` raises ValueError)."""
    try:
        check(name, what)
    except ValueError as err:
        raise ServiceError(str(err), EXIT_USAGE) from None


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
    """Open the Zenoh session, build the node on it, serve until SIGINT/SIGTERM, close both.

    Raises
    ------
    ServiceError
        The Zenoh session did not open.
    """
    from ra2vipas.services.transport.zenoh_bus import ZenohBus

    # the handlers first: a signal that comes while the node starts (or right after it says it is
    # up) is a clean shutdown too, once it has started
    got, received = threading.Event(), {"signal": 0}

    def on_signal(signum, _frame) -> None:
        received["signal"] = signum
        got.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    try:
        bus = ZenohBus(zenoh)
    except Exception as err:  # zenoh raises ZError for bad endpoints, ports in use, unreachable routers, ...
        raise ServiceError(open_error(err, zenoh)) from None
    warn_while_alone(bus.session, zenoh)
    warn_if_unreachable(zenoh)
    node = None
    try:
        node = build(bus)
        gc.collect()
        gc.freeze()  # start-up objects never need scanning again: shorter GC pauses on the hot path
        sys.setswitchinterval(0.0005)  # a Zenoh thread waiting for the GIL gets it within 0.5 ms
        log.info("%s up (zenoh %s, connect %s, listen %s)", name, zenoh.mode, list(zenoh.connect), list(zenoh.listen))
        while not got.wait(0.5):
            pass
        log.info("%s: signal %d, shutting down", name, received["signal"])
    finally:
        if node is not None:
            node.close()
        bus.close()


def claim_cpu() -> None:
    """Sensors and controllers close the control loop, and a router carries their messages when
    they are its clients: where allowed (root, CAP_SYS_NICE) they run at a higher priority so
    a busy machine delays their replies less."""
    try:
        os.nice(-5)
    except OSError:
        pass


def yield_cpu(increment: int = 5) -> None:
    """Bookkeeping services (learner, router) run at a lower priority so that on a
    small machine the sensors and controllers, whose latency matters, get the cores first."""
    try:
        os.nice(increment)
    except OSError:
        pass


# -- the ``python -m ra2vipas.services.NAME`` entries ---------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse with a usage error as one ``error:`` line (exit 2), like the CLI's."""

    def error(self, message: str) -> NoReturn:
        print(f"error: {' '.join(message.split())} (see `{self.prog} --help`)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def parser(prog: str, description: str) -> argparse.ArgumentParser:
    """A service entry's parser with the Zenoh options every service takes (flag > environment >
    default, as ``ra2vipas NAME``) and ``--log-level`` (RA2VIPAS_LOG_LEVEL)."""
    p = _Parser(prog=prog, description=description)
    p.add_argument("--zenoh-mode", "--mode", dest="mode", help="Zenoh mode: peer|client|router [env RA2VIPAS_ZENOH_MODE].")
    p.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to (repeatable) [env RA2VIPAS_ZENOH_CONNECT].")
    p.add_argument("--listen", "-l", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on (repeatable) [env RA2VIPAS_ZENOH_LISTEN].")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file [env RA2VIPAS_ZENOH_CONFIG].")
    p.add_argument("--log-level", default=os.environ.get("RA2VIPAS_LOG_LEVEL", "INFO"), help="Log level [env RA2VIPAS_LOG_LEVEL].")
    return p


def add_realtime_priority(p: argparse.ArgumentParser) -> None:
    """``--realtime-priority`` (RA2VIPAS_REALTIME_PRIORITY) for the control loop's entries, as the CLI's."""
    from ra2vipas.services.transport.realtime import ENV, MAX_PRIORITY, parse_priority, priority_from_env

    def priority(text: str) -> int:
        try:
            return parse_priority(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    try:
        default = priority_from_env()
    except ValueError as err:
        raise ServiceError(str(err), EXIT_USAGE) from None
    p.add_argument("--realtime-priority", type=priority, default=default, metavar="N",
                   help=f"SCHED_FIFO priority of the control loop's threads while this process runs realtime episodes only "
                        f"(1-{MAX_PRIORITY}; 0: off; needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO) [env {ENV}; default {default}].")


def parse(p: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """Parse ``argv``; an unknown option is ``error: No such option: NAME`` (exit 2)."""
    args, unknown = p.parse_known_args(argv)
    if unknown:
        p.error(f"No such option: {unknown[0]}" if unknown[0].startswith("-") else f"Got unexpected extra argument ({unknown[0]})")
    return args


def zenoh_of(args: argparse.Namespace) -> ZenohSettings:
    """The Zenoh settings of parsed entry flags."""
    return zenoh_settings(args.mode, args.connect, args.listen, args.zenoh_config)


def main(entry: Callable[[], None]) -> NoReturn:
    """Run a service entry: a ``ServiceError`` is one ``error:`` line on stderr and its exit code."""
    try:
        entry()
    except ServiceError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)
    sys.exit(0)
