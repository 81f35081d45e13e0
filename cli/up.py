"""``ra2vipas up``: the whole local stack in the foreground."""

from __future__ import annotations

import signal
import sys
import threading
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.cli.stack import RIG_LAYOUTS, Stack, StackConfig, StackError


def up(
    rigs: Annotated[int, typer.Option("--rig-count", min=1, max=64, help="Sensor+controller pairs (rigs) to start.")] = 1,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=1, max=64)] = None,
    port: Annotated[int, typer.Option(min=1, max=65535, envvar="RA2VIPAS_PORT", help="API port.")] = 8080,
    host: Annotated[str, typer.Option(envvar="RA2VIPAS_HOST", help="API bind address.")] = "127.0.0.1",
    db: Annotated[str, typer.Option("--db", envvar="RA2VIPAS_DB", help="SQLite file of campaigns and results.")] = "ra2vipas.db",
    router_port: Annotated[int, typer.Option(min=0, max=65535, help="Port of the loopback Zenoh router (0: any free port).")] = 0,
    window: Annotated[int, typer.Option(min=1, max=1024, help="Episodes in flight per rig.")] = 8,
    log_dir: Annotated[Optional[str], typer.Option(help="Directory for the services' logs (default: a new temporary directory).")] = None,
    max_restart_delay: Annotated[float, typer.Option(min=0.5, max=3600, help="A crashed service is restarted after 0.5 s, doubling up to this many seconds; one in a crash loop (5 crashes within a minute) waits this long each time.")] = 30.0,
    rig_acl: Annotated[bool, typer.Option("--rig-acl", help="Give every service its own Zenoh identity and let the router's access control confine each to its own keys (as the secured deployment does): a process holding one rig's credentials cannot pass for another rig, forge its results, or act as the orchestrator or the learner.")] = False,
    extra_rigs: Annotated[Optional[list[str]], typer.Option("--extra-rig", metavar="NAME", help="With --rig-acl: make an identity for a rig run outside the stack (repeatable); its environment file is printed, and it may act as that rig only.")] = None,
    rig_layout: Annotated[str, typer.Option("--rig-layout", envvar="RA2VIPAS_RIG_LAYOUT", help="one-process: each rig's sensors and controller in one process, one Zenoh session and one worker thread (ra2vipas rig; their step messages are delivered inside the session and still published to the router); split: a sensors and a controller process per rig, as a third-party hardware node and its controller run.")] = "one-process",
    insecure: Annotated[bool, typer.Option("--insecure", help="No Zenoh credentials: any local process may join the stack's Zenoh network (by default the stack makes up its own, readable by you only).")] = False,
) -> None:
    """Run a local stack in the foreground: Zenoh router, orchestrator (REST API), learner and rigs.

    Starts a Zenoh router on loopback, the orchestrator, the learner and RIG_COUNT
    rigs (each one process with its sensors and controller, or two with --rig-layout split), and prints the API address once GET /health answers 200; Ctrl-C
    or SIGTERM stops every process it started. A service that crashes is restarted after a
    delay that doubles with each crash (0.5 s to --max-restart-delay, 30 s); one that crashes
    5 times within a minute is in a crash loop: up says so on stderr with its last log lines
    (and GET /rigs shows it) and restarts it every --max-restart-delay seconds until it stays
    up, never stopping the other services. Before starting anything it checks that
    the API port is free (else one line naming who holds it), creates the database's folder,
    and refuses a database another orchestrator holds.

    Everything listens on 127.0.0.1 only, and the stack's Zenoh network is closed to any
    process without its credentials (made up at start, in a file only you can read, deleted
    at stop); another process joins it with the environment in the printed zenoh.env file.
    The boundary is your user: any process running as you can read those files and join
    with the stack's full rights (announce a rig, send its results). With --rig-acl every
    service has its own identity and the router confines each to its own keys (a process
    with one rig's credentials cannot pass for another rig or forge its results);
    --extra-rig NAME makes an identity for a rig run outside the stack. Run code you do not
    trust at all as another user, or use the secured deployment (ra2vipas security init).

    A database folder that cannot be written at start (a read-only file system) starts the
    stack degraded: the API answers 503 naming the cause until the folder is writable.

    Examples:

        ra2vipas up --rig-count 2 --port 8080 --db ra2vipas.db

        ra2vipas up --db /var/lib/ra2vipas/ra2vipas.db --log-dir logs

        ra2vipas up --rig-layout split
    """
    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count")
    if extra_rigs and not rig_acl:
        fail("--extra-rig needs --rig-acl", EXIT_USAGE)
    if rig_acl and insecure:
        fail("--rig-acl and --insecure contradict each other: choose one", EXIT_USAGE)
    if rig_layout not in RIG_LAYOUTS:
        fail(f"--rig-layout: unknown layout {rig_layout!r}; choose from {', '.join(RIG_LAYOUTS)}", EXIT_USAGE)
    stop = threading.Event()

    def on_signal(_signum, _frame) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    stack = Stack(StackConfig(rigs=rigs, host=host, port=port, db_path=db, router_port=router_port, window=window, log_dir=log_dir,
                              insecure=insecure, max_restart_delay=max_restart_delay, rig_acl=rig_acl,
                              extra_rigs=tuple(extra_rigs or ()), rig_layout=rig_layout))
    try:
        try:
            stack.start()
        except StackError as err:
            fail(str(err))
        if stack.identities is not None:
            extra = "".join(f"; {rig} joins with the environment in {stack.identities.env_file(rig)}" for rig in extra_rigs or ())
            zenoh_info = (f"Zenoh router {stack.router_endpoint}, one identity per service, each confined to its own keys "
                          f"(--rig-acl; files in {stack.identities.directory}){extra}")
        elif stack.credentials is not None:
            zenoh_info = (f"Zenoh router {stack.router_endpoint}, closed to processes without its credentials "
                          f"(join with the environment in {stack.credentials.env_file})")
        else:
            zenoh_info = f"Zenoh router {stack.router_endpoint} without credentials (--insecure): any local process may join"
        print(f"ra2vipas up: API on {stack.api_url} (rigs: {rigs}, database: {db}, logs: {stack.log_dir}); {zenoh_info}; "
              "Ctrl-C to stop", flush=True)  # one line: scripts wait for it
        print(f"ra2vipas up: dashboard on {stack.api_url}/", flush=True)
        if stack.database_error:
            print(f"ra2vipas up: degraded: {stack.database_warning} (database_error: {stack.database_error})", file=sys.stderr,
                  flush=True)
        while not stop.wait(0.5):
            for line, to_stderr in stack.supervise():
                print(line, file=sys.stderr if to_stderr else sys.stdout, flush=True)
    finally:
        stack.stop()
    print("ra2vipas up: stopped", flush=True)
