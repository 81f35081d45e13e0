"""Linux network namespaces for deployment tests (root only): the ``ip`` command, and cleanup of
namespaces by name (``r2v-<pid of the test process>-<host>``), including ones left behind by
a killed earlier run."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
from pathlib import Path


class NetnsError(RuntimeError):
    pass


def ip(*args: str) -> str:
    try:
        r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    except FileNotFoundError:
        raise NetnsError("the `ip` command (iproute2) is not installed") from None
    if r.returncode != 0:
        raise NetnsError(f"`ip {' '.join(args)}` failed: {r.stderr.strip() or r.stdout.strip()}")
    return r.stdout


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def destroy_namespace(ns: str, errors: list[str]) -> None:
    """Kill what still runs in ``ns`` (the services were stopped before), delete it and its /etc/netns files."""
    try:
        pids = ip("netns", "pids", ns).split()
    except NetnsError:
        pids = []
    for pid in pids:
        try:
            os.kill(int(pid), signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        ip("netns", "del", ns)
    except NetnsError as err:
        if "No such file" not in str(err):
            errors.append(str(err))
    shutil.rmtree(Path("/etc/netns") / ns, ignore_errors=True)


def remove_stale_namespaces() -> None:
    """Namespaces left by an earlier run that was killed before its cleanup (its pid is gone)."""
    try:
        names = [line.split()[0] for line in ip("netns", "list").splitlines() if line.strip()]
    except NetnsError:
        return
    for name in names:
        m = re.fullmatch(r"r2v-(\d+)-\w+", name)
        if m and not _pid_alive(int(m.group(1))):
            destroy_namespace(name, [])
