"""``ra2vipas rig`` (a rig's sensors and controller in one process, the compose file's
scalable ``rig`` service): it names itself after its host, waits for a router that starts
after it, runs a campaign with the compose file's orchestrator and learner, and leaves the
mesh cleanly on SIGTERM."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time

import httpx
import pytest
import zenoh

from ra2vipas.cli.rig import controller_settings, rig_name_from_host
from ra2vipas.services.protocol import keys
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests import http
from tests.conftest import differences, untimed
from tests.deploy.compose import environment, interpolate, load, ra2vipas_argv
from tests.deploy.conftest import ROOT, clean_env, free_port, wait_port

TOKEN = "rig-test-token"


@pytest.mark.parametrize("hostname, rig", [
    ("3f2a9c1b0d4e", "3f2a9c1b0d4e"),  # a container's
    ("robot-1.lab.example", "robot-1"),
    ("lab pc#2", "lab-pc-2"),
    ("x" * 80, "x" * 64),
    ("...", "rig"),
])
def test_the_rig_name_comes_from_the_host_name(hostname, rig):
    assert rig_name_from_host(hostname) == rig
    keys.check_chunk(rig)


def test_the_controller_session_joins_where_the_sensors_session_does():
    s = ZenohSettings(mode="client", connect=("tcp/router:7447",))
    assert controller_settings(s) == s
    p = ZenohSettings(mode="peer", listen=("tcp/0.0.0.0:7447", "tcp/[::]:7448", "tcp/10.0.0.5:7449"))
    c = controller_settings(p)
    assert c.listen == () and c.connect == ("tcp/127.0.0.1:7447", "tcp/[::1]:7448", "tcp/10.0.0.5:7449")


def alive_tokens(endpoint: str) -> list[str]:
    with zenoh.open(ZenohSettings(mode="client", connect=(endpoint,), connect_timeout_s=5).to_zenoh()) as s:
        return sorted(str(r.ok.key_expr) for r in s.liveliness().get(keys.alive_all(), timeout=2.0) if r.ok)


def test_the_compose_deployment_on_one_host_runs_a_campaign_through_a_rig(procs, tmp_path):
    compose = interpolate(load(), {"RA2VIPAS_TOKEN": TOKEN, "RA2VIPAS_RIGS": "1"})
    zport, api_port = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    loopback = {"RA2VIPAS_ZENOH_CONNECT": endpoint}

    def start(name: str, **overrides: str):
        svc = compose["services"][name]
        return procs.start(name, ra2vipas_argv(svc), clean_env({**environment(svc), **loopback, **overrides}))

    name = rig_name_from_host(socket.gethostname())
    rig = start("rig")  # before its router: it keeps trying to connect
    time.sleep(2.0)
    assert rig.proc.poll() is None, rig.tail()
    router = procs.start_cli("router", "router", "--listen", endpoint, env=clean_env())
    wait_port("127.0.0.1", zport, router)
    rig.wait_for_output(f"rig[{name}] up", 60)
    start("learner", RA2VIPAS_MODEL_CACHE=str(tmp_path / "models"))
    start("orchestrator", RA2VIPAS_HOST="127.0.0.1", RA2VIPAS_PORT=str(api_port), RA2VIPAS_DB=str(tmp_path / "ra2vipas.db"))
    api = f"http://127.0.0.1:{api_port}"
    deadline = time.monotonic() + 90
    health = {}
    while time.monotonic() < deadline:
        try:
            r = http.get(f"{api}/health", timeout=2)
            health = r.json()
            if r.status_code == 200:
                break
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    assert health.get("ready") and health["rigs"] == [name], f"{health}\n{procs.tails()}"

    args = ["--preset", "paper", "--tests", "2", "--seed", "4", "--algorithms", "ra2vipas,sweep",
            "--set", "steps=20", "--set", "n_train=200", "--set", "n_targets=8"]
    mesh = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "start", "--api", api, *args, "--wait", "--json"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT, env=clean_env({"RA2VIPAS_TOKEN": TOKEN}))
    assert mesh.returncode == 0, f"{mesh.stderr}\n{procs.tails()}"
    sim = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "simulate", *args, "--json"], capture_output=True, text=True,
                         timeout=300, cwd=ROOT)
    assert sim.returncode == 0, sim.stderr
    got, want = (untimed(json.loads(p.stdout.strip().splitlines()[-1])) for p in (mesh, sim))
    assert got == want, differences(got, want)

    assert {keys.alive("sensors", name), keys.alive("controller", name)} <= set(alive_tokens(endpoint))
    rig.proc.send_signal(signal.SIGTERM)
    assert rig.proc.wait(15) == 0, rig.tail()
    left: list[str] = []
    for _ in range(30):
        left = [t for t in alive_tokens(endpoint) if t.endswith(f"/{name}")]
        if not left:
            break
        time.sleep(0.2)
    assert not left, f"tokens still declared after the rig stopped: {left}"
