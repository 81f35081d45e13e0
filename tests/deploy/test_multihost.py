"""The deployment across machines, on one machine: four Linux network namespaces ("hosts") for
the Zenoh router, a rig's sensors, its controller, and the orchestrator with the learner,
joined to the router's host by veth pairs (a star: the other hosts reach only the router, as
behind a firewall that lets 7447 through), plus one link from the orchestrator's host to
this process (the operator's machine, which calls the REST API).

Every service runs with the command and environment docker-compose.yml gives it (the split
``sensors`` and ``controller`` services, which share the rig name ``robot-1``); ``router``
in each host's /etc/hosts resolves to the router host's address on that host's link, as the
compose network's DNS would. Three differences, because there is no container here: the
router is ``ra2vipas router`` (the Python stand-in for the official image) listening where
the compose router listens; the SQLite file and the model cache live in a temporary
directory instead of the /data and /models volumes; one rig instead of two
(RA2VIPAS_RIGS=1).

Needs root (network namespaces): without it the test fails and says so; it never skips.
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from tests import http
from tests.conftest import untimed
from tests.deploy.compose import environment, interpolate, load, ra2vipas_argv
from tests.deploy.conftest import ROOT, Services, clean_env
from tests.deploy.netns import NetnsError, destroy_namespace, ip, remove_stale_namespaces

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]

RIG = "robot-1"  # the compose file's default RA2VIPAS_SPLIT_RIG
HOSTS = ("router", "sensors", "controller", "orch")
TOKEN = "multihost-test-token"
VARS = {"RA2VIPAS_TOKEN": TOKEN, "RA2VIPAS_RIGS": "1"}
SMALL = ["--set", "steps=30", "--set", "n_train=250", "--set", "n_targets=10"]


@dataclass
class Network:
    """The namespaces ``r2v-<pid>-<host>`` and their links; ``destroy`` removes all of it."""

    tag: str = field(default_factory=lambda: str(os.getpid()))
    namespaces: dict[str, str] = field(default_factory=dict)
    operator_if: str = ""
    api_host: str = ""

    def ns(self, host: str) -> str:
        return f"r2v-{self.tag}-{host}"

    def exec_prefix(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns(host)]

    def build(self) -> None:
        for host in HOSTS:
            ip("netns", "add", self.ns(host))
            self.namespaces[host] = self.ns(host)
            ip("-n", self.ns(host), "link", "set", "lo", "up")
        router = self.ns("router")
        for i, host in enumerate(HOSTS[1:], start=1):  # router 10.77.i.1 <-> host 10.77.i.2, one /30 per link
            ip("link", "add", f"to-{host}", "netns", router, "type", "veth", "peer", "name", "eth0", "netns", self.ns(host))
            ip("-n", router, "addr", "add", f"10.77.{i}.1/30", "dev", f"to-{host}")
            ip("-n", self.ns(host), "addr", "add", f"10.77.{i}.2/30", "dev", "eth0")
            ip("-n", router, "link", "set", f"to-{host}", "up")
            ip("-n", self.ns(host), "link", "set", "eth0", "up")
            etc = Path("/etc/netns") / self.ns(host)  # `ip netns exec` mounts these over /etc
            try:
                etc.mkdir(parents=True, exist_ok=True)
                (etc / "hosts").write_text(f"127.0.0.1 localhost\n10.77.{i}.1 router\n")
            except OSError as err:
                raise NetnsError(f"cannot write {etc}/hosts: {err}") from None
        # the operator's link: this (root) namespace <-> the orchestrator's host
        octet = int(self.tag) % 250
        self.operator_if = f"r2v{self.tag}op"[:15]
        self.api_host = f"10.213.{octet}.2"
        ip("link", "add", self.operator_if, "type", "veth", "peer", "name", "op0", "netns", self.ns("orch"))
        ip("addr", "add", f"10.213.{octet}.1/30", "dev", self.operator_if)
        ip("-n", self.ns("orch"), "addr", "add", f"{self.api_host}/30", "dev", "op0")
        ip("link", "set", self.operator_if, "up")
        ip("-n", self.ns("orch"), "link", "set", "op0", "up")

    def cut(self, host: str) -> None:
        """Unplug ``host``'s cable at the router's end."""
        ip("-n", self.ns("router"), "link", "set", f"to-{host}", "down")

    def restore(self, host: str) -> None:
        ip("-n", self.ns("router"), "link", "set", f"to-{host}", "up")

    def destroy(self) -> None:
        errors: list[str] = []
        if self.operator_if:  # the one link in this namespace (its peer goes with it)
            try:
                ip("link", "del", self.operator_if)
            except NetnsError as err:
                if "Cannot find device" not in str(err):
                    errors.append(str(err))
        for ns in self.namespaces.values():
            destroy_namespace(ns, errors)
        assert not errors, "cleaning up the namespaces failed: " + "; ".join(errors)


@dataclass
class Mesh:
    net: Network
    procs: Services
    api: str
    db: Path

    def diagnostics(self) -> str:
        return self.procs.tails()


def compose_service(compose: dict, name: str, **env_overrides: str) -> tuple[list[str], dict[str, str]]:
    svc = compose["services"][name]
    return ra2vipas_argv(svc), clean_env({**environment(svc), **env_overrides})


@pytest.fixture(scope="module")
def mesh(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("multihost")
    remove_stale_namespaces()
    net = Network()
    procs = Services(tmp)
    try:
        problem = None
        try:
            net.build()
        except NetnsError as err:
            problem = str(err)
        if problem:
            pytest.fail(f"cannot build the test network of Linux network namespaces: {problem}. The multi-host deployment "
                        "test needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN) and iproute2; it does not skip.", pytrace=False)
        compose = interpolate(load(), VARS)
        router_cmd = compose["services"]["router"]["command"]
        listen = [router_cmd[i + 1] for i, arg in enumerate(router_cmd) if arg in ("--listen", "-l")]
        procs.start_cli("router", "router", *[a for ep in listen for a in ("--listen", ep)], env=clean_env(),
                        prefix=net.exec_prefix("router"))
        db = tmp / "ra2vipas.db"
        for name, host, overrides in (("orchestrator", "orch", {"RA2VIPAS_DB": str(db)}),
                                      ("learner", "orch", {"RA2VIPAS_MODEL_CACHE": str(tmp / "models")}),
                                      ("sensors", "sensors", {}), ("controller", "controller", {})):
            argv, env = compose_service(compose, name, **overrides)
            procs.start(name, argv, env, prefix=net.exec_prefix(host))
        port = int(environment(compose["services"]["orchestrator"])["RA2VIPAS_PORT"])
        api = f"http://{net.api_host}:{port}"
        mesh = Mesh(net=net, procs=procs, api=api, db=db)
        wait_healthy(mesh, timeout=120)
        yield mesh
    finally:
        procs.stop_all()
        net.destroy()


def wait_healthy(mesh: Mesh, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    last = "no answer"
    while time.monotonic() < deadline:
        dead = [s for s in mesh.procs.started if s.proc.poll() is not None]
        assert not dead, f"{dead[0].name} exited\n{mesh.diagnostics()}"
        try:
            r = http.get(f"{mesh.api}/health", timeout=2)
            if r.status_code == 200:
                return r.json()
            last = r.text
        except httpx.HTTPError as err:
            last = repr(err)
        time.sleep(0.2)
    raise AssertionError(f"/health not 200 within {timeout} s (last: {last[:300]})\n{mesh.diagnostics()}")




def simulate(args: list[str]) -> dict:
    r = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "simulate", *args, "--json"], capture_output=True, text=True,
                       timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def start_campaign(mesh: Mesh, body: dict) -> str:
    r = http.post(f"{mesh.api}/campaigns", json=body, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
    assert r.status_code in (200, 201, 202), r.text
    return r.json()["id"]


def campaign(mesh: Mesh, cid: str) -> dict:
    return http.get(f"{mesh.api}/campaigns/{cid}", timeout=10).json()


def wait_done(mesh: Mesh, cid: str, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    c = {}
    while time.monotonic() < deadline:
        c = campaign(mesh, cid)
        if c["status"] in ("done", "failed", "cancelled"):
            break
        time.sleep(0.2)
    assert c.get("status") == "done", f"campaign {cid}: {c.get('status')} {c.get('progress')} {c.get('error')}\n{mesh.diagnostics()}"
    return http.get(f"{mesh.api}/campaigns/{cid}/results", timeout=10).json()


def episodes(mesh: Mesh, cid: str) -> list[tuple]:
    with sqlite3.connect(f"file:{mesh.db}?mode=ro", uri=True, timeout=10) as db:
        return db.execute("SELECT test_index, algorithm, status, attempt, rig FROM episodes WHERE campaign_id = ? "
                          "ORDER BY test_index, algorithm", (cid,)).fetchall()


def body_and_args(tests: int, seed: int, algorithms: list[str], steps: int) -> tuple[dict, list[str]]:
    overrides = {"steps": steps, "n_train": 250, "n_targets": 10}
    body = {"preset": "paper", "tests": tests, "seed": seed, "algorithms": algorithms, "overrides": overrides}
    args = ["--preset", "paper", "--tests", str(tests), "--seed", str(seed), "--algorithms", ",".join(algorithms),
            *[a for k, v in overrides.items() for a in ("--set", f"{k}={v}")]]
    return body, args


def test_the_hosts_reach_each_other_only_through_the_router(mesh):
    health = wait_healthy(mesh, 30)
    assert health["rigs"] == [RIG] and health["learners"]
    # a star: the sensors' host has a route to the router's address only, none to the controller's
    route = subprocess.run([*mesh.net.exec_prefix("sensors"), "ip", "route", "get", "10.77.2.2"], capture_output=True, text=True)
    assert route.returncode != 0 and "unreachable" in route.stderr
    assert subprocess.run([*mesh.net.exec_prefix("sensors"), "ip", "route", "get", "10.77.1.1"], capture_output=True).returncode == 0
    # the compose file's API token applies
    r = http.post(f"{mesh.api}/campaigns", json={"preset": "paper", "tests": 1}, timeout=10)
    assert r.status_code == 401


def test_a_campaign_across_four_hosts_equals_simulate(mesh):
    _, args = body_and_args(tests=2, seed=3, algorithms=["ra2vipas", "rapas", "ravipas", "sweep"], steps=30)
    run = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "start", "--api", mesh.api, *args, "--wait", "--json"],
                         capture_output=True, text=True, timeout=300, cwd=ROOT, env=clean_env({"RA2VIPAS_TOKEN": TOKEN}))
    assert run.returncode == 0, f"{run.stderr}\n{mesh.diagnostics()}"
    results = json.loads(run.stdout.strip().splitlines()[-1])
    assert untimed(results) == untimed(simulate(args))


def cut_mid_campaign(mesh: Mesh, host: str, body: dict) -> str:
    """Start a campaign, unplug ``host`` while episodes are on the rig; return its id with
    the link down."""
    cid = start_campaign(mesh, body)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        c = campaign(mesh, cid)
        if (c["status"] == "running" and c["progress"]["running"] > 0) or c["status"] not in ("queued", "training", "running"):
            break
        time.sleep(0.02)
    mesh.net.cut(host)
    c = campaign(mesh, cid)
    if c["status"] != "running" or c["progress"]["done"] >= c["progress"]["total"]:
        mesh.net.restore(host)
        raise AssertionError(f"the campaign must still be running when the link goes down, got {c['status']} {c['progress']}")
    return cid


def test_a_short_link_cut_to_the_controller_is_ridden_out(mesh):
    body, args = body_and_args(tests=8, seed=11, algorithms=["ra2vipas", "rapas"], steps=120)
    cid = cut_mid_campaign(mesh, "controller", body)
    try:
        time.sleep(3.0)  # shorter than Zenoh's 10 s lease: the session survives, TCP retransmits
        assert campaign(mesh, cid)["status"] == "running"
    finally:
        mesh.net.restore("controller")
    results = wait_done(mesh, cid, timeout=120)
    assert untimed(results) == untimed(simulate(args))
    rows = episodes(mesh, cid)
    assert len(rows) == 16 and all(r[2] == "done" for r in rows)
    assert all(r[3] == 1 for r in rows), "the Zenoh sessions survived the outage: no episode was rerun"


def test_a_rig_lost_by_a_long_link_cut_is_used_again_once_it_is_back(mesh):
    body, args = body_and_args(tests=8, seed=12, algorithms=["ra2vipas", "rapas"], steps=120)
    cid = cut_mid_campaign(mesh, "sensors", body)
    try:
        # past Zenoh's lease the router drops the sensors' session: the orchestrator sees the
        # rig's liveliness token go and requeues its episodes
        deadline = time.monotonic() + 40
        rigs = [RIG]
        while time.monotonic() < deadline and RIG in rigs:
            rigs = http.get(f"{mesh.api}/health", timeout=5).json()["rigs"]
            time.sleep(0.2)
        assert RIG not in rigs, f"the orchestrator still sees {RIG} 40 s after its link went down\n{mesh.diagnostics()}"
        stalled = campaign(mesh, cid)
        assert stalled["status"] == "running" and stalled["progress"]["done"] < stalled["progress"]["total"]
    finally:
        mesh.net.restore("sensors")
    results = wait_done(mesh, cid, timeout=120)  # the sensors reconnect, the rig is live again and finishes the campaign
    assert wait_healthy(mesh, 30)["rigs"] == [RIG]
    assert untimed(results) == untimed(simulate(args))
    rows = episodes(mesh, cid)
    assert len(rows) == 16 and len({(r[0], r[1]) for r in rows}) == 16, "every test once"
    assert all(r[2] == "done" and r[4] == RIG for r in rows)
    assert max(r[3] for r in rows) >= 2, "the episodes in flight when the rig was lost were run again"
