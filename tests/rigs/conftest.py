"""Fixtures of the real-rigs tests: an insecure local stack shared by the tests of this package
that run the commands a user runs (``record``, ``survey record``, ``survey serve``), and a bare
router for the conformance kits' tests (one per test module)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import restore_ctrl_c
from tests.integration.conftest import ROOT, Procs, wait_for_line


class Scripts(Procs):
    """Also runs plain scripts (the example node), each in its own process group, killed at teardown."""

    def script(self, path: Path, *args: str) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, str(path), *args], cwd=ROOT, start_new_session=True, preexec_fn=restore_ctrl_c, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONPATH": ""})
        self.procs.append(p)
        return p


@pytest.fixture(scope="module")
def router():
    """A Zenoh router on a free loopback port: (the process registry, its endpoint)."""
    from ra2vipas.cli.stack import free_port

    registry = Scripts()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = registry.start("router", "--listen", endpoint)
    wait_for_line(proc, "zenoh router up", 60)
    yield registry, endpoint
    registry.cleanup()


@pytest.fixture(scope="package")
def local_stack(tmp_path_factory):
    """An insecure local stack (``ra2vipas up --rig-count 1``, rig ``rig-1``): its API, its router's
    endpoint, the Zenoh environment that joins it, and the process registry (every process
    started through it is killed at the end)."""
    from ra2vipas.cli.stack import free_port

    tmp = tmp_path_factory.mktemp("local-stack")
    registry = Scripts()
    try:
        up = registry.start("up", "--rig-count", "1", "--port", str(free_port()), "--db", str(tmp / "s.db"), "--insecure",
                            "--log-dir", str(tmp / "logs"))
        line = wait_for_line(up, "API on http://", 120)
        api = re.search(r"(http://[0-9.:]+)", line).group(1)
        router = re.search(r"Zenoh router (tcp/127\.0\.0\.1:\d+)", line)
        assert router, line
        yield {"api": api, "router": router.group(1), "registry": registry,
               "env": {"RA2VIPAS_ZENOH_MODE": "client", "RA2VIPAS_ZENOH_CONNECT": router.group(1)}}
    finally:
        registry.cleanup()


def cli(*args: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    """``ra2vipas ARGS`` as a user runs it (a subprocess), with ``env`` added."""
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, **(env or {})})
