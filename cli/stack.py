"""A whole local stack as child processes: a Zenoh router on loopback, the orchestrator
(REST API), the learner and N rigs. Used by ``ra2vipas up``,
``ra2vipas campaign start --embedded`` and ``ra2vipas bench mesh``.

A rig is one process by default (``ra2vipas rig``: its sensors and controller on one Zenoh
session and one worker thread, their step messages delivered within the session and still
published to the router), or, with ``rig_layout="split"``, a ``sensors`` and a ``controller``
process, as a third-party hardware node and its controller run.

Everything listens on 127.0.0.1 only: the router and the API. The services are Zenoh
*clients* of the router and listen on nothing (as in a deployment across machines). Peers
talking directly would save a hop, but a peer mesh whose links are authenticated sometimes
misses a link between two peers, and the router does not carry their traffic then (seen as
a learner the orchestrator never sees); a client has one link, to the router, which carries
everything.

Unless ``insecure``, the stack has its own Zenoh credentials, made up when it starts: a
random user name and password in files only their owner can read (0600, in a private 0700
directory), which every service of the stack presents and the router requires (Zenoh
user/password authentication), so a process without them (another local user's, or one in
another network namespace) cannot open a session with the stack. The credentials reach the
children as file paths in their environment, never on a command line or in a log; the
directory is removed by ``stop()``.

With ``rig_acl`` (``up --rig-acl``) every service has its own identity instead, and the
router's access control (``services/transport/acl.py``) confines each to its own keys, so a
process holding one rig's credentials can neither pass for another rig nor forge its results.
Either way the files are their owner's: any process running as that user can read them.

``supervise()`` (``up``'s loop) restarts a service that died after a delay doubling from 0.5 s;
one in a crash loop (``CRASH_LIMIT`` crashes within ``CRASH_WINDOW_S``) is restarted at the
capped delay until it stays up, and the others are never touched: the stack is stopped by its
user only. What it is restarting is written to ``status_file``, which the orchestrator shows
in ``GET /rigs``.

Children get ``PR_SET_PDEATHSIG`` so they die with their parent even if it is killed with
SIGKILL; ``stop()`` sends SIGTERM, waits, then SIGKILLs stragglers, and reaps every pid it
started.
"""

from __future__ import annotations

import ctypes
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Child:
    name: str
    argv: list[str]
    env: dict[str, str]
    log_path: Path
    role: str = ""  # router, learner, orchestrator, rig (a whole rig), sensors or controller (half of a split one)
    rig: str = ""  # the rig it serves, if any
    proc: subprocess.Popen | None = None
    restarts: int = 0
    crashes: list[float] = field(default_factory=list)  # monotonic times it was found dead
    started_at: float = 0.0  # monotonic time of the last start
    restart_at: float | None = None  # monotonic time of the restart due (None: running, or not seen dead yet)
    backing_off: bool = False  # crashed CRASH_LIMIT times within CRASH_WINDOW_S: restarted at the capped delay only
    exit_code: int | None = None  # its last exit code

    def start(self) -> None:
        self.started_at = time.monotonic()
        log = open(self.log_path, "ab", buffering=0)
        self.proc = subprocess.Popen(self.argv, env=self.env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     preexec_fn=_die_with_parent, close_fds=True)
        log.close()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


@dataclass
class StackConfig:
    rigs: int = 1
    host: str = "127.0.0.1"
    port: int = 8080
    db_path: str = "ra2vipas.db"
    router_port: int = 0  # 0: pick a free port
    window: int = 8
    log_dir: str | None = None
    log_level: str = "INFO"
    zenoh_mode: str = "client"  # the services' mode: clients of the router, or peers (direct links, listening on loopback)
    insecure: bool = False  # True: no Zenoh credentials (any local process may join the stack)
    # True: each service its own Zenoh identity, and the router's access control confines each to its
    # own keys (services/transport/acl.py), as in the secured deployment; extra_rigs: identities
    # made for rigs run outside the stack (their env files in the credentials directory)
    rig_acl: bool = False
    extra_rigs: tuple[str, ...] = ()
    max_restart_delay: float = 30.0  # a crashed service's restart delay doubles from 0.5 s up to this
    # how a rig runs: "one-process" (``ra2vipas rig``: its sensors and controller in one process, one
    # Zenoh session and one worker thread) or "split" (a ``sensors`` and a ``controller`` process,
    # each its own session: the layout of a third-party hardware node and its controller)
    rig_layout: str = "one-process"


RIG_LAYOUTS = ("one-process", "split")


def _write_private(path: Path, text: str) -> None:
    """Create ``path`` readable and writable by its owner only (0600), failing if it exists."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)


@dataclass(frozen=True)
class StackCredentials:
    """Where a stack's Zenoh credentials are: ``directory`` (0700) holds ``password`` (the
    password alone) and ``credentials`` (``user:password``, the dictionary every service
    checks), both 0600, and ``zenoh.env``, the environment another process needs to join
    the stack (``set -a; . DIR/zenoh.env``): paths and the user name, no secret."""

    directory: Path
    user: str

    @property
    def password_file(self) -> Path:
        return self.directory / "password"

    @property
    def dictionary_file(self) -> Path:
        return self.directory / "credentials"

    @property
    def env_file(self) -> Path:
        return self.directory / "zenoh.env"

    def env(self) -> dict[str, str]:
        return {"RA2VIPAS_ZENOH_USER": self.user, "RA2VIPAS_ZENOH_PASSWORD_FILE": str(self.password_file),
                "RA2VIPAS_ZENOH_CREDENTIALS": str(self.dictionary_file)}

    @classmethod
    def create(cls) -> "StackCredentials":
        directory = Path(tempfile.mkdtemp(prefix="ra2vipas-stack-"))  # 0700: mkdtemp's own mode
        os.chmod(directory, 0o700)
        creds = cls(directory, f"stack-{secrets.token_hex(4)}")
        password = secrets.token_urlsafe(32)
        _write_private(creds.password_file, password + "\n")
        _write_private(creds.dictionary_file, f"{creds.user}:{password}\n")
        return creds

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


@dataclass(frozen=True)
class StackIdentities:
    """``up --rig-acl``: one Zenoh identity per service of the stack (and per extra rig), each
    with its own password (``directory/USER.password``, 0600), the router's dictionary of them
    all (``credentials``), its configuration with the access control (``router.json``) and one
    environment file per identity (``USER.env``: how a process joins as that identity)."""

    directory: Path
    identities: tuple

    @property
    def dictionary_file(self) -> Path:
        return self.directory / "credentials"

    @property
    def router_config(self) -> Path:
        return self.directory / "router.json"

    def env_file(self, user: str) -> Path:
        return self.directory / f"{user}.env"

    def env(self, user: str) -> dict[str, str]:
        return {"RA2VIPAS_ZENOH_USER": user, "RA2VIPAS_ZENOH_PASSWORD_FILE": str(self.directory / f"{user}.password")}

    @classmethod
    def create(cls, rigs: list[str], extra_rigs: list[str], endpoint: str, split: bool = True) -> "StackIdentities":
        """``rigs``: the stack's own (a ``sensors`` and a ``controller`` identity each if ``split``,
        else one ``rig`` identity); ``extra_rigs``: a ``rig`` identity each."""
        from ra2vipas.services.transport.acl import access_control, standard_identities

        if split:
            identities = standard_identities(rigs=list(extra_rigs), split_rigs=rigs)
        else:
            identities = standard_identities(rigs=[*rigs, *extra_rigs])
        directory = Path(tempfile.mkdtemp(prefix="ra2vipas-stack-"))
        os.chmod(directory, 0o700)
        made = cls(directory, tuple(identities))
        lines = []
        for identity in identities:
            password = secrets.token_urlsafe(32)
            _write_private(directory / f"{identity.user}.password", password + "\n")
            lines.append(f"{identity.user}:{password}\n")
            _write_private(made.env_file(identity.user), "".join(f"{k}={v}\n" for k, v in {
                "RA2VIPAS_ZENOH_MODE": "client", "RA2VIPAS_ZENOH_CONNECT": endpoint, **made.env(identity.user)}.items()))
        _write_private(made.dictionary_file, "".join(lines))
        _write_private(made.router_config, json.dumps({"mode": "router", "scouting": {"multicast": {"enabled": False}},
                                                       "access_control": access_control(identities)}, indent=2))
        return made

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


# the RA2VIPAS_* variables of the user's environment that reach the stack's services (the stack sets the others)
USER_SETTINGS = ("RA2VIPAS_TOKEN", "RA2VIPAS_PLOT_WORKERS", "RA2VIPAS_MAX_CONNECTIONS", "RA2VIPAS_MAX_CONNECTIONS_PER_CLIENT",
                 "RA2VIPAS_HEADER_TIMEOUT")


class StackError(RuntimeError):
    pass


def port_holder(port: int) -> str | None:
    """Who listens on TCP ``port`` on this machine: "pid N (command line)" from /proc, "an
    unknown process" when the socket's owner cannot be read, None when nobody listens."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            parts = line.split()
            if len(parts) > 9 and parts[3] == "0A" and int(parts[1].rsplit(":", 1)[1], 16) == port:  # 0A: LISTEN
                inodes.add(parts[9])
    if not inodes:
        return None
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
                if target.startswith("socket:[") and target[8:-1] in inodes:
                    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
                    return f"pid {pid} ({cmd[:120]})"
        except OSError:
            continue
    return "an unknown process"


def check_port_free(host: str, port: int, what: str) -> None:
    """Raise ``StackError`` (one line naming the port and who holds it) if ``port`` is taken.

    The check binds as the services will (``SO_REUSEADDR``, as uvicorn and Zenoh's listeners
    do), so the TIME-WAIT connections a stack that just stopped leaves behind do not count as
    taken: only a socket that listens there does (issue 18)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as err:
            who = port_holder(port)
            why = f"taken by {who}" if who else (err.strerror or str(err)).lower()
            raise StackError(f"{what} port {port} on {host} is {why}: stop it or choose another port") from None


def prepare_database(db_path: str) -> str | None:
    """Create the database's folder (one-line ``StackError`` if it cannot be) and refuse a
    database another orchestrator holds. A folder that exists but cannot be written now (a
    read-only file system, no permission) is no reason to refuse: the stack starts degraded
    (the API answers 503 naming the cause, and heals when the folder becomes writable); the
    returned line says so (None when the folder is writable)."""
    from ra2vipas.services.orchestrator.dblock import DatabaseFolderError, holder, make_folder

    try:
        folder = make_folder(db_path)
    except DatabaseFolderError as err:
        raise StackError(str(err)) from None
    pid = holder(db_path)
    if pid is not None:
        raise StackError(f"the database {db_path} is in use by another orchestrator{f' (pid {pid})' if pid else ''}: "
                         "stop that stack, or give this one another --db")
    if not os.access(folder, os.W_OK):
        try:
            why = "a read-only file system" if os.statvfs(folder).f_flag & os.ST_RDONLY else "no write permission"
        except OSError:
            why = "not writable"
        return (f"the database folder {folder} cannot be written now ({why}): the API answers 503 naming the cause "
                "until it can, then resumes by itself")
    return None


# a service that crashes this many times within CRASH_WINDOW_S is in a crash loop: `up` says so and
# restarts it at the capped delay only (never stopping the others), until it stays up for
# CRASH_WINDOW_S or the user stops the stack
CRASH_LIMIT = 5
CRASH_WINDOW_S = 60.0
FIRST_RESTART_DELAY_S = 0.5


def _ready_but_the_database(health: dict) -> bool:
    """Whether a 503 /health body says everything is up but the database (a degraded start)."""
    return (health.get("database") is False and bool(health.get("zenoh")) and bool(health.get("learners"))
            and len(health.get("ready_rigs") or []) >= int(health.get("expected_rigs") or 0))


@dataclass
class Stack:
    config: StackConfig
    children: list[Child] = field(default_factory=list)
    log_dir: Path | None = None
    credentials: StackCredentials | None = None
    identities: StackIdentities | None = None
    router_endpoint: str | None = None
    instance_id: str = field(default_factory=lambda: secrets.token_hex(8))
    database_warning: str | None = None  # why the database cannot be written at start (the stack starts degraded)
    database_error: str | None = None  # /health's database_error when the stack became ready without its database

    @property
    def api_url(self) -> str:
        return f"http://{self.config.host}:{self.config.port}"

    def start(self, ready_timeout: float = 90.0) -> None:
        """Check the ports and the database, then start every service and wait until /health
        answers 200 from *this* stack's orchestrator. ``StackError`` (one line) otherwise."""
        cfg = self.config
        check_port_free(cfg.host, cfg.port, "the API")
        if cfg.router_port:
            check_port_free("127.0.0.1", cfg.router_port, "the Zenoh router's")
        self.database_warning = prepare_database(cfg.db_path)
        self.log_dir = Path(cfg.log_dir or tempfile.mkdtemp(prefix="ra2vipas-logs-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        router_port = cfg.router_port or free_port()
        endpoint = self.router_endpoint = f"tcp/127.0.0.1:{router_port}"
        # the stack sets its own RA2VIPAS_* variables; the API token, the orchestrator's figure
        # renderer count and its connection limits are the user's
        base_env = {k: v for k, v in os.environ.items() if not k.startswith("RA2VIPAS_") or k in USER_SETTINGS}
        base_env.update({
            "RA2VIPAS_ZENOH_MODE": cfg.zenoh_mode,
            "RA2VIPAS_ZENOH_CONNECT": endpoint,
            "RA2VIPAS_ZENOH_LISTEN": "tcp/127.0.0.1:0" if cfg.zenoh_mode == "peer" else "",
            "RA2VIPAS_LOG_LEVEL": cfg.log_level,
            "PYTHONUNBUFFERED": "1",
        })
        rig_names = [f"rig-{i}" for i in range(1, cfg.rigs + 1)]
        if cfg.rig_layout not in RIG_LAYOUTS:
            raise StackError(f"unknown rig layout {cfg.rig_layout!r}; choose from {', '.join(RIG_LAYOUTS)}")
        split = cfg.rig_layout == "split"
        if cfg.rig_acl and not cfg.insecure:
            from ra2vipas.services.transport.acl import AclError

            try:
                self.identities = StackIdentities.create(rig_names, list(cfg.extra_rigs), endpoint, split=split)
            except AclError as err:
                raise StackError(f"--extra-rig: {err}") from None
        elif not cfg.insecure:
            self.credentials = StackCredentials.create()
            base_env.update(self.credentials.env())
            _write_private(self.credentials.env_file, "".join(f"{k}={v}\n" for k, v in {
                "RA2VIPAS_ZENOH_MODE": "client", "RA2VIPAS_ZENOH_CONNECT": endpoint, **self.credentials.env()}.items()))
        py = [sys.executable, "-m", "ra2vipas.cli.main"]
        # (name, role, rig, argv, environment)
        specs = [("router", "router", "", [*py, "router", "--listen", endpoint], {"RA2VIPAS_ZENOH_CONNECT": "", "RA2VIPAS_ZENOH_LISTEN": ""})]
        specs.append(("learner", "learner", "", [*py, "learner"], {}))
        for rig in rig_names:
            if split:
                specs.append((f"sensors-{rig}", "sensors", rig, [*py, "sensors", "--rig", rig], {}))
                specs.append((f"controller-{rig}", "controller", rig, [*py, "controller", "--rig", rig], {}))
            else:
                specs.append((rig, "rig", rig, [*py, "rig", "--rig", rig], {}))
        specs.append(("orchestrator", "orchestrator", "", [*py, "orchestrator"], {
            "RA2VIPAS_HOST": cfg.host, "RA2VIPAS_PORT": str(cfg.port), "RA2VIPAS_DB": cfg.db_path,
            "RA2VIPAS_WINDOW": str(cfg.window), "RA2VIPAS_EXPECT_RIGS": str(cfg.rigs), "RA2VIPAS_INSTANCE_ID": self.instance_id,
            "RA2VIPAS_SUPERVISOR_STATUS": str(self.status_file),
        }))
        if self.identities is not None:  # each service its own identity; the router checks them and enforces the ACL
            ids = self.identities
            specs = [(name, role, rig, argv, {**extra, **self._identity_env(role, rig, ids)}) for name, role, rig, argv, extra in specs]
        for name, role, rig, argv, extra in specs:
            env = {**base_env, **extra}
            env = {k: v for k, v in env.items() if v != ""}
            child = Child(name, argv, env, self.log_dir / f"{name}.log", role=role, rig=rig)
            child.start()
            self.children.append(child)
            if name == "router":
                self._wait_port(router_port, child, 15.0)
        self._wait_ready(ready_timeout)

    @staticmethod
    def _identity_env(role: str, rig: str, ids: StackIdentities) -> dict[str, str]:
        """The Zenoh identity of one of the stack's services (``--rig-acl``): the router checks
        them; a whole rig is its rig's name, a split one's halves ``RIG.sensors`` and
        ``RIG.controller`` (``acl.standard_identities``)."""
        if role == "router":
            return {"RA2VIPAS_ZENOH_CREDENTIALS": str(ids.dictionary_file), "RA2VIPAS_ZENOH_CONFIG": str(ids.router_config),
                    "RA2VIPAS_ZENOH_USER": "", "RA2VIPAS_ZENOH_PASSWORD_FILE": ""}
        user = rig if role == "rig" else f"{rig}.{role}" if rig else role
        return ids.env(user)

    def _wait_port(self, port: int, child: Child, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not child.alive():
                raise StackError(f"{child.name} exited during start-up:\n{child.tail()}")
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    return
            except OSError:
                time.sleep(0.05)
        raise StackError(f"{child.name} did not open port {port} within {timeout:.0f} s")

    def _wait_ready(self, timeout: float) -> None:
        # one client for every poll: an ``httpx.get`` makes a client, whose TLS context loads the CA
        # bundle (~75 ms of CPU) even for an http:// address; 30 polls cost a start-up 2.3 s of CPU
        with httpx.Client(timeout=1.0) as client:
            self._poll_health(client, timeout)

    def _poll_health(self, client: httpx.Client, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        last = "no answer"
        while time.monotonic() < deadline:
            dead = [c for c in self.children if not c.alive()]
            if dead:
                raise StackError(f"{dead[0].name} exited during start-up (log {dead[0].log_path}):\n{dead[0].tail()}")
            try:
                r = client.get(f"{self.api_url}/health")
                try:
                    instance = r.json().get("instance")
                except ValueError:
                    instance = None
                if instance != self.instance_id:  # someone else answers on our address: never adopt it
                    last = f"HTTP {r.status_code} from another server (instance {instance!r})"
                elif r.status_code == 200:
                    return
                elif self.database_warning and _ready_but_the_database(r.json()):
                    self.database_error = r.json().get("database_error") or "unavailable"
                    return
                else:
                    last = r.text
            except httpx.HTTPError as err:
                last = str(err)
            time.sleep(0.1)
        raise StackError(f"the stack was not ready within {timeout:.0f} s (last /health: {last[:300]})")

    def crashed(self, child: Child, now: float | None = None) -> float:
        """Record that ``child`` died and return the delay before restarting it: 0.5 s doubling
        with each crash within ``CRASH_WINDOW_S``, at most ``config.max_restart_delay``; once it
        crashed ``CRASH_LIMIT`` times within the window it is in a crash loop (``backing_off``)
        and waits the capped delay each time, until it stays up for ``CRASH_WINDOW_S``. Never
        gives up: a crash loop costs its own service only."""
        now = time.monotonic() if now is None else now
        child.crashes = [t for t in child.crashes if now - t < CRASH_WINDOW_S] + [now]
        cap = self.config.max_restart_delay
        if len(child.crashes) >= CRASH_LIMIT:
            child.backing_off = True
        if child.backing_off:
            return cap
        return min(cap, FIRST_RESTART_DELAY_S * 2 ** (len(child.crashes) - 1))

    def supervise(self, now: float | None = None) -> list[tuple[str, bool]]:
        """One pass of ``up``'s supervisor: notice dead services (each gets its restart time),
        restart those whose time has come, and end a back-off once a service has stayed up for
        ``CRASH_WINDOW_S``. Returns the lines to print, each with whether it goes to stderr;
        rewrites ``status_file`` when something changed. Services are handled independently: a
        service waiting out its back-off delays no other."""
        now = time.monotonic() if now is None else now
        lines: list[tuple[str, bool]] = []
        changed = False
        for child in self.children:
            if child.restart_at is None and not child.alive():
                child.exit_code = child.proc.returncode if child.proc is not None else None
                was_backing_off = child.backing_off
                delay = self.crashed(child, now)
                child.restart_at = now + delay
                changed = True
                if child.backing_off and not was_backing_off:
                    lines.append((f"ra2vipas up: {child.name} crashed {len(child.crashes)} times within {CRASH_WINDOW_S:.0f} s; "
                                  f"backing off: restarting it every {delay:g} s until it stays up (the other services keep "
                                  f"running; Ctrl-C stops the stack). Its last log lines ({child.log_path}):\n{child.tail()}", True))
                elif child.backing_off:
                    lines.append((f"ra2vipas up: {child.name} exited again (code {child.exit_code}); still backing off: "
                                  f"restarting it in {delay:g} s", True))
                else:
                    lines.append((f"ra2vipas up: {child.name} exited (code {child.exit_code}); restarting it in {delay:g} s", False))
            elif child.restart_at is not None and now >= child.restart_at:
                child.restart_at = None
                self.restart(child)
                changed = True
            elif child.backing_off and child.restart_at is None and now - child.started_at >= CRASH_WINDOW_S:
                child.backing_off = False
                changed = True
                lines.append((f"ra2vipas up: {child.name} has stayed up for {CRASH_WINDOW_S:.0f} s: back-off over", True))
        if changed:
            self.write_status()
        return lines

    @property
    def status_file(self) -> Path | None:
        """Where the supervisor writes which services it is restarting (``RA2VIPAS_SUPERVISOR_STATUS``
        of the orchestrator, shown in ``GET /rigs`` and the dashboard's rigs page)."""
        return None if self.log_dir is None else self.log_dir / "supervisor.json"

    def status(self) -> list[dict]:
        """The services that are down or backing off: name, state (``restarting`` or
        ``backing off``), crashes within ``CRASH_WINDOW_S``, last exit code and when the next
        restart is due (epoch seconds, None if it runs)."""
        mono, wall = time.monotonic(), time.time()
        out = []
        for c in self.children:
            if c.restart_at is None and not c.backing_off:
                continue
            recent = [t for t in c.crashes if mono - t < CRASH_WINDOW_S]
            out.append({"name": c.name, "state": "backing off" if c.backing_off else "restarting", "crashes": len(recent),
                        "window_s": CRASH_WINDOW_S, "exit_code": c.exit_code,
                        "next_restart_at": None if c.restart_at is None else wall + (c.restart_at - mono)})
        return out

    def write_status(self) -> None:
        path = self.status_file
        if path is None:
            return
        tmp = path.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps({"services": self.status(), "written_at": time.time()}))
            os.replace(tmp, path)
        except OSError:
            pass

    def restart(self, child: Child) -> None:
        child.restarts += 1
        child.start()

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM every child (orchestrator first, router last), wait, SIGKILL what is left;
        then delete the stack's credentials."""
        order = sorted(self.children, key=lambda c: (c.name != "orchestrator", c.name == "router"))
        for c in order:
            if c.alive():
                try:
                    c.proc.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + timeout
        for c in order:
            if c.proc is None:
                continue
            try:
                c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                c.proc.kill()
                c.proc.wait(5.0)
        if self.credentials is not None:
            self.credentials.remove()
        if self.identities is not None:
            self.identities.remove()

    def pids(self) -> list[int]:
        return [c.proc.pid for c in self.children if c.proc is not None]
