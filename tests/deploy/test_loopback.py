"""Loopback means loopback: the default stack (`ra2vipas up`) listens on 127.0.0.1 only and its
Zenoh network is closed to every process without the stack's own credentials, on this host
or in another network namespace; a service or router started alone listens on loopback
unless told otherwise.

Uses Linux network namespaces: needs root, and fails (never skips) without it.
"""

from __future__ import annotations

import os
import re
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from ra2vipas.services.protocol import keys
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests.deploy.conftest import ROOT, clean_env
from tests.deploy.netns import NetnsError, destroy_namespace, ip, remove_stale_namespaces
from tests.integration.conftest import Procs, children_of, stack_zenoh_env, start_stack, stop_stack

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def _address(hex_address: str) -> str:
    raw = bytes.fromhex(hex_address)
    if len(raw) == 4:
        return socket.inet_ntop(socket.AF_INET, raw[::-1])
    return socket.inet_ntop(socket.AF_INET6, b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))


def sockets_of(pids: list[int], tables: tuple[str, ...] = ("tcp", "tcp6", "udp", "udp6")) -> list[tuple[str, str, int, int]]:
    """(table, local address, port, pid) of every listening TCP socket and bound UDP socket the
    processes ``pids`` hold (their fds' socket inodes looked up in /proc/net)."""
    owner: dict[str, int] = {}
    for pid in pids:
        try:
            fds = list(Path(f"/proc/{pid}/fd").iterdir())
        except OSError:
            continue
        for fd in fds:
            try:
                m = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd))
            except OSError:
                continue
            if m:
                owner[m.group(1)] = pid
    out = []
    for table in tables:
        for line in Path(f"/proc/{pids[0]}/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            local, state, inode = fields[1], fields[3], fields[9]
            address, port = local.rsplit(":", 1)
            listening = state == "0A" if table.startswith("tcp") else int(port, 16) != 0
            if listening and inode in owner:
                out.append((table, _address(address), int(port, 16), owner[inode]))
    return out


def rogue(endpoint: str, mode: str = "client", **security) -> zenoh.Session:
    return zenoh.open(ZenohSettings(mode=mode, connect=(endpoint,), connect_timeout_s=2, **security).to_zenoh())


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    registry = Procs()
    state = start_stack(registry, tmp_path_factory.mktemp("loopback"), rigs=1)
    state["env"] = stack_zenoh_env(state["up"].pid)
    state["router"] = state["env"]["RA2VIPAS_ZENOH_CONNECT"]
    state["pids"] = [state["up"].pid, *children_of(state["up"].pid)]
    yield state
    stop_stack(registry, state["up"])
    assert not Path(state["env"]["RA2VIPAS_ZENOH_PASSWORD_FILE"]).parent.exists(), "the credentials outlive the stack"


def member(stack) -> zenoh.Session:
    return zenoh.open(ZenohSettings.from_sources(env=stack["env"]).to_zenoh())


def alive_keys(session: zenoh.Session, want: str | None = None, timeout: float = 10.0) -> list[str]:
    deadline = time.monotonic() + timeout
    seen: list[str] = []
    while time.monotonic() < deadline:
        seen = sorted(str(r.ok.key_expr) for r in session.liveliness().get(keys.alive_all(), timeout=1.0) if r.ok)
        if want is None or want in seen:
            break
        time.sleep(0.2)
    return seen


def test_the_stack_listens_on_loopback_only(stack):
    found = sockets_of(stack["pids"])
    api_port = int(stack["api"].rsplit(":", 1)[1])
    router_port = int(stack["router"].rsplit(":", 1)[1])
    ports = {port for table, _, port, _ in found if table.startswith("tcp")}
    assert {api_port, router_port} <= ports, found
    assert all(address == "127.0.0.1" for _, address, _, _ in found), found
    assert ports == {api_port, router_port}, f"only the API and the router listen (the services are clients): {found}"


def test_the_credentials_are_private_and_never_on_a_command_line_or_in_a_log(stack):
    password_file = Path(stack["env"]["RA2VIPAS_ZENOH_PASSWORD_FILE"])
    directory = password_file.parent
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700
    for f in directory.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
    assert f"Zenoh router {stack['router']}, closed to processes without its credentials" in stack["line"]
    assert str(directory / "zenoh.env") in stack["line"]
    password = password_file.read_text().strip()
    assert len(password) >= 32
    for pid in stack["pids"]:
        assert password not in Path(f"/proc/{pid}/cmdline").read_text(errors="replace")
    logs = "".join(p.read_text(errors="replace") for p in stack["logs"].glob("*.log"))
    assert logs and password not in logs


def test_a_session_without_the_stacks_credentials_cannot_join(stack):
    user = stack["env"]["RA2VIPAS_ZENOH_USER"]
    endpoints = [f"tcp/127.0.0.1:{port}" for table, _, port, _ in sockets_of(stack["pids"], ("tcp",))
                 if port != int(stack["api"].rsplit(":", 1)[1])]
    assert endpoints == [stack["router"]]
    # with the credentials (what the stack's own services have) a session joins and sees the rig
    with member(stack) as inside:
        assert inside.info.routers_zid()
        assert keys.alive("sensors", "rig-1") in alive_keys(inside, keys.alive("sensors", "rig-1"))
        attempts = {"no credentials": {}, "wrong password": dict(user=user, password="guess"),
                    "unknown user": dict(user="mallory", password="guess")}
        for endpoint in endpoints:
            for what, security in attempts.items():
                with pytest.raises(zenoh.ZError):
                    rogue(endpoint, **security).close()
                # a peer opens without a router, but is left alone: no link, its token unseen, its puts lost
                with rogue(endpoint, "peer", **security) as intruder:
                    token = intruder.liveliness().declare_token(keys.alive("sensors", "intruder"))
                    got: list[bytes] = []
                    sub = inside.declare_subscriber(keys.episode_result("rig-1"), lambda s: got.append(s.payload.to_bytes()))
                    for _ in range(5):
                        intruder.put(keys.episode_result("rig-1"), b"forged")
                        time.sleep(0.1)
                    assert not intruder.info.routers_zid() and not intruder.info.peers_zid(), what
                    assert keys.alive("sensors", "intruder") not in alive_keys(inside, timeout=1.0), what
                    assert got == [], what
                    sub.undeclare()
                    token.undeclare()


@pytest.fixture()
def other_namespace():
    """A network namespace ``r2v-<pid>-rogue`` linked to this one by a veth pair: this host is
    10.215.N.1, the namespace 10.215.N.2."""
    remove_stale_namespaces()
    tag = str(os.getpid())
    ns = f"r2v-{tag}-rogue"
    host_if = f"r2v{tag}rg"[:15]
    octet = int(tag) % 250
    try:
        ip("netns", "add", ns)
    except NetnsError as err:
        pytest.fail(f"cannot create a network namespace ({err}): this test needs root and iproute2; it does not skip", pytrace=False)
    try:
        ip("-n", ns, "link", "set", "lo", "up")
        ip("link", "add", host_if, "type", "veth", "peer", "name", "eth0", "netns", ns)
        ip("addr", "add", f"10.215.{octet}.1/30", "dev", host_if)
        ip("-n", ns, "addr", "add", f"10.215.{octet}.2/30", "dev", "eth0")
        ip("link", "set", host_if, "up")
        ip("-n", ns, "link", "set", "eth0", "up")
        yield {"ns": ns, "host": f"10.215.{octet}.1", "prefix": ["ip", "netns", "exec", ns]}
    finally:
        errors: list[str] = []
        try:
            ip("link", "del", host_if)
        except NetnsError as err:
            if "Cannot find device" not in str(err):
                errors.append(str(err))
        destroy_namespace(ns, errors)
        assert not errors, errors


PROBE = """
import socket, sys, zenoh
from ra2vipas.services.transport.zenoh_config import ZenohSettings
host, ports = sys.argv[1], [int(p) for p in sys.argv[2].split(",")]
for port in ports:
    try:
        socket.create_connection((host, port), timeout=2).close()
        print(f"tcp {port} open")
    except OSError as err:
        print(f"tcp {port} closed ({err.strerror})")
    try:
        zenoh.open(ZenohSettings(mode="client", connect=(f"tcp/{host}:{port}",), connect_timeout_s=2).to_zenoh()).close()
        print(f"zenoh {port} joined")
    except zenoh.ZError:
        print(f"zenoh {port} refused")
"""


def test_from_another_network_namespace_nothing_of_the_stack_is_reachable(stack, other_namespace):
    ports = sorted({port for _, _, port, _ in sockets_of(stack["pids"], ("tcp", "tcp6"))})
    # control: something of this host that does listen beyond loopback is reachable from there
    control = socket.create_server(("0.0.0.0", 0))
    control_port = control.getsockname()[1]
    accepted = threading.Thread(target=lambda: control.accept()[0].close(), daemon=True)
    accepted.start()
    try:
        r = subprocess.run([*other_namespace["prefix"], sys.executable, "-c", PROBE, other_namespace["host"],
                            ",".join(map(str, [*ports, control_port]))], capture_output=True, text=True, timeout=120, cwd=ROOT,
                           env=clean_env())
    finally:
        control.close()
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert f"tcp {control_port} open" in lines, r.stdout
    for port in ports:
        assert f"tcp {port} closed (Connection refused)" in lines, r.stdout
        assert f"zenoh {port} refused" in lines, r.stdout


def test_an_insecure_stack_is_open_to_any_local_process(tmp_path):
    """What --insecure gives up (and what every stack was before): a process without
    credentials joins and sees the rigs."""
    registry = Procs()
    state = start_stack(registry, tmp_path, "--insecure", rigs=1)
    try:
        assert "without credentials (--insecure)" in state["line"]
        endpoint = re.search(r"Zenoh router (tcp/127\.0\.0\.1:\d+)", state["line"]).group(1)
        with rogue(endpoint) as intruder:
            assert intruder.info.routers_zid()
            assert keys.alive("sensors", "rig-1") in alive_keys(intruder, keys.alive("sensors", "rig-1"))
    finally:
        stop_stack(registry, state["up"])


def test_a_lone_router_and_peer_listen_on_loopback_unless_told(procs, other_namespace):
    """In a namespace of their own (port 7447 is free there): `ra2vipas router` without --listen,
    a learner in peer mode without --listen, and a router told --listen tcp/0.0.0.0:7448."""
    prefix = other_namespace["prefix"]
    default = procs.start_cli("router", "router", env=clean_env(), prefix=prefix)
    default.wait_for_output("zenoh router up", 30)
    peer = procs.start_cli("learner", "learner", "--mode", "peer", "--connect", "tcp/127.0.0.1:7447", env=clean_env(), prefix=prefix)
    peer.wait_for_output("learner[learner] up", 60)
    told = procs.start_cli("router-all", "router", "--listen", "tcp/0.0.0.0:7448", env=clean_env(), prefix=prefix)
    told.wait_for_output("zenoh router up", 30)
    found = sockets_of([default.proc.pid, peer.proc.pid, told.proc.pid])
    by_pid = {pid: sorted((address, port) for table, address, port, p in found if p == pid and table.startswith("tcp"))
              for pid in (default.proc.pid, peer.proc.pid, told.proc.pid)}
    assert by_pid[default.proc.pid] == [("127.0.0.1", 7447)], found
    assert len(by_pid[peer.proc.pid]) == 1 and by_pid[peer.proc.pid][0][0] == "127.0.0.1", found
    assert by_pid[told.proc.pid] == [("0.0.0.0", 7448)], found  # the check sees a wide listener when there is one
    assert all(address in ("127.0.0.1", "0.0.0.0") for _, address, _, _ in found)
    assert not [s for s in found if s[1] == "0.0.0.0" and s[3] != told.proc.pid], found
