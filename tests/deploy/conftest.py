"""Fixtures for deployment tests: service processes that are always cleaned up (each in its
own process group, SIGTERM then SIGKILL at teardown), with their output in log files."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def clean_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment without any RA2VIPAS_* variable, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RA2VIPAS_")}
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


class Service:
    def __init__(self, name: str, proc: subprocess.Popen, log: Path) -> None:
        self.name, self.proc, self.log = name, proc, log

    def output(self) -> str:
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 25) -> str:
        return f"--- {self.name} (pid {self.proc.pid}, exit {self.proc.poll()}) ---\n" + "\n".join(self.output().splitlines()[-lines:])

    def wait_for_output(self, needle: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if needle in self.output():
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError(f"{needle!r} not in {self.name}'s output within {timeout} s\n{self.tail()}")


class Services:
    """Processes started by a test; ``stop_all`` leaves none behind."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.started: list[Service] = []

    def start(self, name: str, argv: list[str], env: dict[str, str], prefix: list[str] | None = None) -> Service:
        """Run ``prefix + argv`` (e.g. ``ip netns exec NS`` + a ``python -m ra2vipas.cli.main`` line)."""
        log = self.log_dir / f"{name}.log"
        with open(log, "ab", buffering=0) as out:
            proc = subprocess.Popen([*(prefix or []), *argv], cwd=ROOT, env=env, stdin=subprocess.DEVNULL, stdout=out,
                                    stderr=subprocess.STDOUT, start_new_session=True)
        service = Service(name, proc, log)
        self.started.append(service)
        return service

    def start_cli(self, name: str, *args: str, env: dict[str, str], prefix: list[str] | None = None) -> Service:
        return self.start(name, [sys.executable, "-m", "ra2vipas.cli.main", *args], env, prefix)

    def tails(self) -> str:
        return "\n".join(s.tail() for s in self.started)

    def stop_all(self, timeout: float = 10.0) -> None:
        for s in self.started:
            if s.proc.poll() is None:
                _signal_group(s.proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for s in self.started:
            try:
                s.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            _signal_group(s.proc.pid, signal.SIGKILL)  # whatever is left of the group
            if s.proc.poll() is None:
                s.proc.wait(10)


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


@pytest.fixture()
def procs(tmp_path):
    registry = Services(tmp_path)
    yield registry
    registry.stop_all()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(host: str, port: int, service: Service, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if service.proc.poll() is not None:
            raise AssertionError(f"{service.name} exited during start-up\n{service.tail()}")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"{service.name} did not open {host}:{port} within {timeout} s\n{service.tail()}")
