"""Shell completion of the installed ``ra2vipas`` command, ``ra2vipas presets``, and the
``--token`` flag of ``ra2vipas orchestrator`` (a real process)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from ra2vipas.cli.stack import free_port
from ra2vipas.services.orchestrator.presets import PRESETS
from tests import http
from tests.cli.conftest import ROOT, ra2vipas
from tests.conftest import restore_ctrl_c

SCRIPT = Path(sys.executable).parent / "ra2vipas"


def complete(words: str) -> list[str]:
    """Candidates through Click's completion protocol, as the bash hook asks for them."""
    env = {**os.environ, "_RA2VIPAS_COMPLETE": "complete_bash", "COMP_WORDS": words, "COMP_CWORD": str(len(words.split(" ")) - 1)}
    proc = subprocess.run([str(SCRIPT)], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.split()


def test_the_installed_command_shows_its_bash_completion_script():
    assert SCRIPT.exists(), "pip install -e . puts the ra2vipas command next to the interpreter"
    # run from bash, as a user does: typer reads the shell from the parent processes (shellingham),
    # which a test runner started without a shell above it does not have
    proc = subprocess.run(["bash", "-c", f"'{SCRIPT}' --show-completion bash"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "_RA2VIPAS_COMPLETE=complete_bash" in proc.stdout and "complete -o default -F _ra2vipas_completion ra2vipas" in proc.stdout


def test_completion_offers_commands_and_option_values():
    assert {"start", "list", "show", "status", "watch", "results", "trace", "cancel", "delete", "export", "plot"} <= set(complete("ra2vipas campaign "))
    assert {"campaign", "presets", "rigs", "simulate", "up"} <= set(complete("ra2vipas "))
    assert complete("ra2vipas campaign start --preset pa") == ["paper", "paper-uniform"]
    assert complete("ra2vipas campaign plot abc --kind e") == ["episode"]


def test_presets_list_and_show_need_no_server():
    listed = ra2vipas("presets", "list", "--json")
    assert listed.returncode == 0
    names = [p["name"] for p in json.loads(listed.stdout.strip().splitlines()[-1])]
    assert names[:3] == ["paper", "paper-uniform", "dynamic"] and names == list(PRESETS)  # the paper's first, then every preset
    table = ra2vipas("presets", "show", "paper-uniform")
    assert table.returncode == 0 and "placement" in table.stdout and "one of reference|uniform" in table.stdout


@pytest.fixture()
def orchestrator_process(tmp_path):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", "orchestrator", "--port", str(port), "--db", str(tmp_path / "o.db"),
                             "--token", "flag-token", "--expect-rigs", "0", "--log-level", "WARNING"],
                            cwd=ROOT, start_new_session=True, preexec_fn=restore_ctrl_c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={k: v for k, v in os.environ.items() if k != "RA2VIPAS_TOKEN"})
    try:
        yield proc, f"http://127.0.0.1:{port}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        if proc.stdout:
            proc.stdout.close()


def test_orchestrator_token_flag_guards_state_changes(orchestrator_process):
    proc, api = orchestrator_process
    deadline = time.monotonic() + 60
    while True:
        try:
            http.get(f"{api}/health", timeout=2)
            break
        except httpx.HTTPError:
            assert proc.poll() is None and time.monotonic() < deadline, "the orchestrator did not come up"
            time.sleep(0.2)
    body = {"tests": 1, "algorithms": ["rapas"]}
    assert http.post(f"{api}/campaigns", json=body, timeout=10).status_code == 401
    ok = http.post(f"{api}/campaigns", json=body, headers={"Authorization": "Bearer flag-token"}, timeout=10)
    assert ok.status_code == 201
    assert http.get(f"{api}/campaigns/{ok.json()['id']}", timeout=10).status_code == 200
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30) == 0
