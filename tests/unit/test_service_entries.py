"""`python -m ra2vipas.services.NAME`: each service's own entry (no CLI import) joins Zenoh,
says it is up, and exits 0 on SIGTERM; a bad flag or setting is one `error:` line and exit 2."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from ra2vipas.cli.stack import free_port
from tests import http
from tests.conftest import kill_process_groups, restore_ctrl_c
from tests.integration.conftest import ROOT, wait_for_line

ENTRIES = {
    "learner": ["--name", "lrn-7"],
    "controller": ["--rig", "rig-7", "--policy", "ra2vipas,rapas"],
    "sensors": ["--rig", "rig-7", "--hardware", "frames_per_rf=5"],
}


@pytest.fixture()
def started():
    procs: list[subprocess.Popen] = []

    def start(name: str, *args: str, env: dict | None = None) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-m", f"ra2vipas.services.{name}", *args], cwd=ROOT, env={**os.environ, **(env or {})},
                             start_new_session=True, preexec_fn=restore_ctrl_c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True)
        procs.append(p)
        return p

    yield start
    kill_process_groups(procs)


@pytest.mark.parametrize("name", sorted(ENTRIES))
def test_a_service_entry_starts_and_stops_on_sigterm(started, name):
    p = started(name, *ENTRIES[name], "--listen", f"tcp/127.0.0.1:{free_port()}", env={"RA2VIPAS_ZENOH_MODE": "peer"})
    line = wait_for_line(p, " up (zenoh", 120)
    assert "zenoh peer" in line
    p.send_signal(signal.SIGTERM)
    assert p.wait(30) == 0


@pytest.mark.parametrize("name, args, words", [
    ("learner", ["--zenoh-mode", "satellite"], "error: zenoh mode must be one of"),
    ("sensors", ["--connect", "nowhere"], "invalid Zenoh endpoint 'nowhere'"),
    ("controller", ["--policy", "no-such-policy"], "no-such-policy"),
    ("controller", ["--beta", "-1"], "error: Invalid value for '--beta'"),
    ("sensors", ["--hardware", "frames_per_rf"], "error: --hardware expects NAME=VALUE"),
    ("sensors", ["--hardware", "n_tags=0"], "error: n_tags: Input should be greater than or equal to 1"),
    ("orchestrator", ["--frobnicate"], "error: No such option: --frobnicate"),
])
def test_a_bad_setting_is_one_error_line_and_exit_2(started, name, args, words):
    p = started(name, *args)
    assert p.wait(60) == 2
    out = p.stdout.read().strip().splitlines()
    assert out and words in out[-1] and out[-1].startswith("error: ") and "Traceback" not in "\n".join(out)


def test_the_orchestrator_entry_serves_the_api_and_stops_on_sigterm(started, tmp_path):
    import time

    import httpx

    port = free_port()
    p = started("orchestrator", "--port", str(port), "--db", str(tmp_path / "o.db"), "--expect-rigs", "0",
                "--listen", f"tcp/127.0.0.1:{free_port()}", env={"RA2VIPAS_ZENOH_MODE": "peer"})
    deadline, health = time.monotonic() + 120, None
    while health is None and time.monotonic() < deadline and p.poll() is None:
        try:
            health = http.get(f"http://127.0.0.1:{port}/health", timeout=2)
        except httpx.HTTPError:
            time.sleep(0.3)
    assert health is not None, p.stdout.read() if p.poll() is not None else "no answer"
    assert "status" in health.json()  # the API answers (503 while it has no learner: degraded, but serving)
    p.send_signal(signal.SIGTERM)
    assert p.wait(30) == 0
