"""Each service is a process that joins Zenoh, declares its liveliness token and exits
promptly and cleanly on SIGINT/SIGTERM."""

from __future__ import annotations

import signal
import time

import pytest
import zenoh

from ra2vipas.cli.stack import free_port
from ra2vipas.services.protocol import keys
from tests.integration.conftest import wait_for_line

SERVICES = {
    "sensors": (["sensors", "--rig", "rig-5"], keys.alive("sensors", "rig-5")),
    "controller": (["controller", "--rig", "rig-5"], keys.alive("controller", "rig-5")),
    "learner": (["learner", "--name", "lrn-5"], keys.alive("learner", "lrn-5")),
}


@pytest.mark.parametrize("name", sorted(SERVICES))
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_service_announces_itself_and_stops_on_signal(procs, name, sig):
    args, token = SERVICES[name]
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    p = procs.start(*args, "--listen", endpoint, env={"RA2VIPAS_ZENOH_MODE": "peer"})
    wait_for_line(p, " up (zenoh", 60)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        found = []
        for _ in range(50):
            found = [str(r.ok.key_expr) for r in session.liveliness().get(keys.alive_all(), timeout=2.0) if r.ok]
            if token in found:
                break
            time.sleep(0.1)
        assert token in found
    started = time.monotonic()
    p.send_signal(sig)
    assert p.wait(15) == 0
    assert time.monotonic() - started < 10


def test_bad_zenoh_settings_are_one_line_errors(procs):
    p = procs.start("learner", "--zenoh-mode", "satellite")
    assert p.wait(30) == 2
    out = p.stdout.read()
    assert out.strip().splitlines()[-1].startswith("error: zenoh mode must be one of")
    p = procs.start("sensors", "--connect", "nowhere")
    assert p.wait(30) == 2
    assert "invalid Zenoh endpoint 'nowhere'" in p.stdout.read()
