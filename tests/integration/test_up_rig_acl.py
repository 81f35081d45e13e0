"""``ra2vipas up --rig-acl`` (issue 18): with the stack's shared credentials any process that has
them can join as a fake rig and forge results. With ``--rig-acl`` every service has its own
identity and the router's access control confines each to its own keys: the stack runs a
campaign as before, while a process holding one rig's identity (here an ``--extra-rig``, as
an untrusted rig driver would) cannot announce another rig, put results on another rig's
keys."""

from __future__ import annotations

import time
from pathlib import Path

from tests import http
from tests.api.live import SMALL
from tests.integration.conftest import start_stack, stop_stack


def _env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if "=" in line)


def test_up_with_rig_acl_runs_campaigns_and_confines_each_identity(procs, tmp_path):
    import re

    import zenoh

    from ra2vipas.services.protocol import keys
    from ra2vipas.services.transport.zenoh_config import ZenohSettings

    state = start_stack(procs, tmp_path, "--rig-acl", "--extra-rig", "robot-9", rigs=1)
    api = state["api"]
    env_file = Path(re.search(r"robot-9 joins with the environment in (\S+\.env)", state["line"]).group(1))
    assert oct(env_file.stat().st_mode & 0o777) == "0o600"
    r = http.post(f"{api}/campaigns", json={"overrides": SMALL, "algorithms": ["rapas"], "tests": 2, "seed": 3}, timeout=10)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    deadline = time.monotonic() + 120
    while http.get(f"{api}/campaigns/{cid}", timeout=5).json()["status"] not in ("done", "failed") and time.monotonic() < deadline:
        time.sleep(0.5)
    assert http.get(f"{api}/campaigns/{cid}", timeout=5).json()["status"] == "done"

    # a loaded machine may time an episode out and dispatch it again, its first result then arriving stale
    # (``not_in_flight``): what this test checks is that the forged result adds no rejection
    rejected_before = http.get(f"{api}/health", timeout=5).json()["rejected_messages"]
    with zenoh.open(ZenohSettings.from_sources(env=_env(env_file)).to_zenoh()) as session:
        own = session.liveliness().declare_token(keys.alive("sensors", "robot-9"))  # its own name: allowed
        fake = session.liveliness().declare_token(keys.alive("sensors", "rig-7"))  # another rig: refused by the router
        fake_ctl = session.liveliness().declare_token(keys.alive("controller", "rig-7"))
        session.put(keys.episode_result("rig-1"), b'{"forged": true}')
        deadline = time.monotonic() + 10
        rigs = {}
        while time.monotonic() < deadline:
            rigs = {x["name"]: x for x in http.get(f"{api}/rigs", timeout=5).json()["rigs"]}
            if "robot-9" in rigs:
                break
            time.sleep(0.2)
        assert "robot-9" in rigs and "rig-7" not in rigs, rigs
        assert rigs["rig-1"]["announced"] == "announced", rigs["rig-1"]  # its controller's own identity may serve its policies
        time.sleep(1.0)
        health = http.get(f"{api}/health", timeout=5).json()
        assert health["rejected_messages"] == rejected_before, health  # the forged result never reached the orchestrator
        for token in (own, fake, fake_ctl):
            token.undeclare()
    stop_stack(procs, state["up"])
