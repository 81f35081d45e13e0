"""Helpers for tests that start real processes: every pid they start is cleaned up."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import kill_process_groups, restore_ctrl_c

ROOT = Path(__file__).resolve().parents[2]


def children_of(pid: int) -> list[int]:
    """Direct children of ``pid`` (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(entry.name))
    return out


def alive(pid: int) -> bool:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return False
    return fields[0] != "Z"


class Procs:
    """Started processes, killed (whole process group) at teardown whatever happened."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, *args: str, env: dict | None = None, **kw) -> subprocess.Popen:
        full_env = {**os.environ, **(env or {})}
        more = kw.pop("preexec_fn", None)

        def before_exec() -> None:
            restore_ctrl_c()
            if more is not None:
                more()

        p = subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", *args], cwd=ROOT, env=full_env, start_new_session=True, preexec_fn=before_exec,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)
        self.procs.append(p)
        return p

    def cleanup(self) -> None:
        kill_process_groups(self.procs)


@pytest.fixture()
def procs():
    registry = Procs()
    yield registry
    registry.cleanup()


def wait_for_line(proc: subprocess.Popen, needle: str, timeout: float) -> str:
    """Read the process's output until a line contains ``needle``; fail with the output so far."""
    import selectors

    seen = []
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not sel.select(timeout=0.2):
            if proc.poll() is not None:
                break
            continue
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        if needle in line:
            return line
    raise AssertionError(f"{needle!r} not seen within {timeout} s; output:\n{''.join(seen)}")


def start_stack(registry: Procs, tmp: Path, *extra: str, rigs: int = 2, **popen) -> dict:
    """``ra2vipas up`` with its database and logs under ``tmp``; returns api, the up process,
    the database path, the log directory and the line ``up`` printed once the API is ready.
    ``popen``: more keyword arguments of ``subprocess.Popen`` (e.g. ``preexec_fn``)."""
    import re

    from ra2vipas.cli.stack import free_port

    up = registry.start("up", "--rig-count", str(rigs), "--port", str(free_port()), "--db", str(tmp / "stack.db"),
                        "--log-dir", str(tmp / "logs"), *extra, **popen)
    line = wait_for_line(up, "API on http://", 120)
    return {"api": re.search(r"(http://[0-9.:]+)", line).group(1), "up": up, "db": tmp / "stack.db", "logs": tmp / "logs", "line": line}


def stack_zenoh_env(up_pid: int) -> dict[str, str]:
    """The environment a process of the stack's own user joins its Zenoh network with: the
    ``zenoh.env`` file ``ra2vipas up`` writes (found, like a user would, in its output or,
    here, through the router child's environment)."""
    for pid in children_of(up_pid):
        environ = dict(item.split("=", 1) for item in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in item)
        if "RA2VIPAS_ZENOH_PASSWORD_FILE" in environ:
            env_file = Path(environ["RA2VIPAS_ZENOH_PASSWORD_FILE"]).parent / "zenoh.env"
            return dict(line.split("=", 1) for line in env_file.read_text().splitlines() if "=" in line)
    raise AssertionError("no child of the stack has Zenoh credentials")


def stack_zenoh_session(up_pid: int):
    """A Zenoh client session on the stack, with its credentials (close it)."""
    import zenoh

    from ra2vipas.services.transport.zenoh_config import ZenohSettings

    return zenoh.open(ZenohSettings.from_sources(env=stack_zenoh_env(up_pid)).to_zenoh())


def stop_stack(registry: Procs, up: subprocess.Popen) -> None:
    up.send_signal(signal.SIGTERM)
    try:
        up.wait(30)
    finally:
        registry.cleanup()
