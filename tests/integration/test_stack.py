"""The real thing: `ra2vipas up` (Zenoh router + orchestrator + learner + 2 rigs as separate
processes), driven through the CLI and the REST API, then stopped."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys

import pytest

from ra2vipas.cli.stack import free_port
from ra2vipas.services.protocol.versions import PROTOCOL_VERSION
from tests import http
from tests.conftest import untimed
from tests.integration.conftest import ROOT, Procs, alive, children_of, wait_for_line

SMALL = ["--set", "steps=30", "--set", "n_train=250", "--set", "n_targets=10"]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stack")
    registry = Procs()
    port = free_port()
    up = registry.start("up", "--rig-count", "2", "--port", str(port), "--db", str(tmp / "stack.db"), "--log-dir", str(tmp / "logs"))
    line = wait_for_line(up, "API on http://", 120)
    api = re.search(r"(http://[0-9.:]+)", line).group(1)
    state = {"api": api, "up": up, "children": children_of(up.pid), "db": tmp / "stack.db", "logs": tmp / "logs"}
    yield state
    registry.cleanup()


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT)




def test_up_starts_router_orchestrator_learner_and_two_rigs(stack):
    assert len(stack["children"]) == 1 + 1 + 1 + 2  # each rig one process (its sensors and controller on one Zenoh session)
    health = http.get(f"{stack['api']}/health", timeout=10)
    assert health.status_code == 200
    body = health.json()
    assert body["ready"] and body["database"] and body["zenoh"]
    assert body["rigs"] == ["rig-1", "rig-2"] and body["learners"] == ["learner"]
    # each rig's descriptor reached the orchestrator through the stack's access control
    rigs = http.get(f"{stack['api']}/rigs", timeout=10).json()["rigs"]
    assert [(r["name"], r["described"], r["descriptor"]["kind"]) for r in rigs] == [("rig-1", "described", "simulated"),
                                                                                   ("rig-2", "described", "simulated")]
    # and each controller's policies (rig/{rig}/policies), through the same access control
    assert [(r["name"], r["announced"], r["controller_protocol"]) for r in rigs] == [("rig-1", "announced", PROTOCOL_VERSION),
                                                                                    ("rig-2", "announced", PROTOCOL_VERSION)]
    assert all([p["name"] for p in r["policies"]][:4] == ["ra2vipas", "rapas", "ravipas", "sweep"] for r in rigs)


def mesh_and_simulate(stack, args: list[str]) -> tuple[dict, dict]:
    """The results object of the campaign ``args`` run through the stack, and of ``simulate``."""
    mesh = cli("campaign", "start", "--api", stack["api"], *args, "--wait", "--json")
    assert mesh.returncode == 0, mesh.stderr
    sim = cli("simulate", *args, "--json")
    assert sim.returncode == 0, sim.stderr
    return json.loads(mesh.stdout.strip().splitlines()[-1]), json.loads(sim.stdout.strip().splitlines()[-1])


def test_campaign_through_the_cli_equals_simulate_value_for_value(stack):
    args = ["--preset", "paper", "--tests", "4", "--seed", "5", "--algorithms", "ra2vipas,rapas,ravipas,sweep", *SMALL]
    mesh_results, sim_results = mesh_and_simulate(stack, args)
    assert untimed(mesh_results) == untimed(sim_results)
    assert mesh_results["steps_per_second"] > 0


def test_a_three_tag_campaign_through_real_processes_equals_simulate(stack):
    """Issue 21 through the stack: every tag's RF pair over Zenoh, the joint search and the
    one-tag-at-a-time baseline in the rigs' controller processes, each tag scored against its
    carrier by the orchestrator; value for value what ``simulate`` gives, per tag too."""
    args = ["--preset", "paper", "--tests", "3", "--seed", "5", "--algorithms", "ra2vipas,ra2vipas-seq", *SMALL, "--set", "n_tags=3",
            "--stop-confidence", "0.9"]
    mesh_results, sim_results = mesh_and_simulate(stack, args)
    assert untimed(mesh_results) == untimed(sim_results)
    for name in ("ra2vipas", "ra2vipas-seq"):
        assert len(mesh_results["algorithms"][name]["tags"]["per_tag"]) == 3


def test_campaign_start_status_and_results_commands(stack):
    started = cli("campaign", "start", "--api", stack["api"], "--tests", "2", "--seed", "9", "-a", "rapas", *SMALL)
    assert started.returncode == 0, started.stderr
    cid = started.stdout.strip().splitlines()[-1]
    assert re.fullmatch(r"[0-9a-f]{12}", cid)
    status = cli("campaign", "status", cid, "--api", stack["api"], "--json")
    assert status.returncode == 0
    assert json.loads(status.stdout.strip().splitlines()[-1])["id"] == cid
    import time

    for _ in range(600):
        c = http.get(f"{stack['api']}/campaigns/{cid}", timeout=10).json()
        if c["status"] == "done":
            break
        time.sleep(0.1)
    results = cli("campaign", "results", cid, "--api", stack["api"])
    assert results.returncode == 0 and "rapas" in results.stdout and "POD regression" in results.stdout


def test_api_rejects_bad_campaigns_and_unknown_ids(stack):
    api = stack["api"]
    r = http.post(f"{api}/campaigns", json={"preset": "paper", "overrides": {"n_targets": 0}}, timeout=10)
    assert r.status_code == 422 and "n_targets" in r.json()["detail"]
    r = http.post(f"{api}/campaigns", json={"preset": "paper", "tests": 0}, timeout=10)
    assert r.status_code == 422
    assert http.get(f"{api}/campaigns/nope", timeout=10).status_code == 404
    bad = cli("campaign", "start", "--api", api, "--set", "rf_noise_db=99")
    assert bad.returncode == 2 and bad.stderr.startswith("error: ")


def test_cli_reports_an_unreachable_api_in_one_line():
    r = cli("campaign", "status", "abc", "--api", f"http://127.0.0.1:{free_port()}")
    assert r.returncode == 1
    assert r.stderr.strip().startswith("error: cannot reach the API") and "Traceback" not in r.stderr


def test_stopping_the_stack_leaves_no_process(stack):
    up = stack["up"]
    children = stack["children"]
    assert children and all(alive(p) for p in children)
    up.send_signal(signal.SIGTERM)
    assert up.wait(30) == 0
    assert not [p for p in children if alive(p)]
    assert not alive(up.pid)
