"""The secured deployment, as docs/deployment.md sets it up: `ra2vipas security init` writes the
files; `ra2vipas router` runs with router.env (mutual TLS, the credentials, the access
control of router.json5); the orchestrator, the learner and rig-2 run with their own env
files, as clients. An identity authenticated as rig-1 then cannot put on rig-2's keys, the
truth plane or control, nor announce a fake rig, and a campaign run while a process with
rig-1's credentials keeps trying all of that equals `ra2vipas simulate`. The same attempts,
with the same router restarted without its access control, succeed: a fake rig joins and
the campaign's results are forged.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest
import zenoh

from ra2vipas.services.protocol import keys
from ra2vipas.services.transport.zenoh_config import ZenohSettings
from tests import http
from tests.conftest import untimed
from tests.deploy.conftest import ROOT, Service, Services, clean_env, free_port, wait_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]

TOKEN = "secured-test-token"
SMALL = {"steps": 30, "n_train": 250, "n_targets": 10}


def read_env(path: Path) -> dict[str, str]:
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line and not line.startswith("#"))


@dataclass
class Deployment:
    tmp: Path
    secrets: Path
    procs: Services
    endpoint: str
    api: str
    router: Service | None = None
    services: dict[str, Service] = field(default_factory=dict)

    def env(self, user: str, **extra: str) -> dict[str, str]:
        """The environment ``security init`` wrote for ``user``, joining this test's router."""
        return clean_env({**read_env(self.secrets / f"{user}.env"), "RA2VIPAS_ZENOH_CONNECT": self.endpoint,
                          "RA2VIPAS_ZENOH_CONNECT_TIMEOUT": "5", **extra})

    def session(self, user: str) -> zenoh.Session:
        return zenoh.open(ZenohSettings.from_sources(env=self.env(user)).to_zenoh())

    def start_router(self, access_control: bool = True) -> None:
        env = {**read_env(self.secrets / "router.env"), "RA2VIPAS_ZENOH_LISTEN": self.endpoint}
        if not access_control:  # the same configuration without its access control
            text = (self.secrets / "router.json5").read_text()
            config = json.loads("\n".join(line for line in text.splitlines() if not line.startswith("//")))
            del config["access_control"]
            (self.tmp / "router-without-acl.json5").write_text(json.dumps(config))
            env["RA2VIPAS_ZENOH_CONFIG"] = str(self.tmp / "router-without-acl.json5")
        self.router = self.procs.start_cli("router" if access_control else "router-without-acl", "router", env=clean_env(env))
        wait_port("127.0.0.1", int(self.endpoint.rsplit(":", 1)[1]), self.router)

    def stop_router(self) -> None:
        os.killpg(self.router.proc.pid, signal.SIGTERM)
        self.router.proc.wait(15)

    def health(self, timeout: float = 120.0) -> dict:
        deadline = time.monotonic() + timeout
        last = "no answer"
        while time.monotonic() < deadline:
            dead = [s for s in self.services.values() if s.proc.poll() is not None]
            assert not dead, dead[0].tail()
            try:
                r = http.get(f"{self.api}/health", timeout=2)
                if r.status_code == 200:
                    return r.json()
                last = r.text
            except httpx.HTTPError as err:
                last = repr(err)
            time.sleep(0.2)
        raise AssertionError(f"/health not 200 within {timeout} s: {last[:300]}\n{self.procs.tails()}")

    def rigs(self) -> dict[str, dict]:
        return {r["name"]: r for r in http.get(f"{self.api}/rigs", timeout=5).json()["rigs"]}


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("secured")
    init = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "security", "init", "--rigs", "rig-1,rig-2", "--split-rigs", "robot-1",
                           "--out", str(tmp / "secrets"), "--router-host", "127.0.0.1", "--json"],
                          capture_output=True, text=True, timeout=120, cwd=ROOT, env=clean_env())
    assert init.returncode == 0, init.stderr
    procs = Services(tmp)
    port = free_port()
    d = Deployment(tmp=tmp, secrets=tmp / "secrets", procs=procs, endpoint=f"tls/127.0.0.1:{free_port()}", api=f"http://127.0.0.1:{port}")
    try:
        d.start_router()
        d.services["orchestrator"] = procs.start_cli("orchestrator", "orchestrator", env=d.env(
            "orchestrator", RA2VIPAS_HOST="127.0.0.1", RA2VIPAS_PORT=str(port), RA2VIPAS_DB=str(tmp / "ra2vipas.db"),
            RA2VIPAS_TOKEN=TOKEN, RA2VIPAS_EXPECT_RIGS="1"))
        d.services["learner"] = procs.start_cli("learner", "learner", env=d.env("learner", RA2VIPAS_MODEL_CACHE=str(tmp / "models")))
        d.services["rig-2"] = procs.start_cli("rig-2", "rig", env=d.env("rig-2"))
        health = d.health()
        assert health["rigs"] == ["rig-2"] and health["learners"] == ["learner"]
        yield d
    finally:
        procs.stop_all()


class Inbox:
    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self) -> list[bytes]:
        with self.lock:
            return [p for _, p in self.items]


def probe(d: Deployment) -> dict[str, bool]:
    """What an identity authenticated as rig-1 (and the split robot-1's controller) manages to
    do, as seen by sessions of the orchestrator's and rig-2's identities and by the running
    orchestrator: True where the attempt got through."""
    outcome: dict[str, bool] = {}
    with d.session("orchestrator") as orch, d.session("rig-2") as rig2, d.session("rig-1") as rig1, \
            d.session("robot-1.controller") as controller:
        results, truth, alive = Inbox(), Inbox(), Inbox()
        rig2_data, rig2_control = Inbox(), Inbox()
        handles = [orch.declare_subscriber(keys.episode_result_all(), results), orch.declare_subscriber(keys.episode_truth_all(), truth),
                   orch.liveliness().declare_subscriber(keys.alive_all(), alive, history=True),
                   rig2.declare_subscriber(f"{keys.PREFIX}/data/rig-2/*", rig2_data),
                   rig2.declare_subscriber(keys.episode_control("rig-2"), rig2_control)]
        spy = Inbox()
        handles += [rig1.declare_subscriber(keys.episode_control("rig-2"), spy), rig1.declare_subscriber(keys.measurement("rig-2"), spy)]
        handles += [rig1.liveliness().declare_token(keys.alive(role, name))
                    for role, name in (("sensors", "evil"), ("controller", "evil"), ("learner", "evil"), ("sensors", "rig-1"),
                                       ("controller", "rig-1"))]
        handles.append(rig1.declare_queryable(keys.pod_model(), lambda q: q.reply(keys.pod_model(), b"forged model")))
        time.sleep(1.0)
        for _ in range(10):
            rig1.put(keys.measurement("rig-2"), b"forged measurement")
            rig1.put(keys.command("rig-2"), b"forged command")
            rig1.put(keys.episode_control("rig-2"), b"forged control")
            rig1.put(keys.episode_result("rig-2"), b"forged result rig-2")
            rig1.put(keys.episode_result("evil"), b"forged result evil")
            rig1.put(keys.episode_truth("rig-2"), b"forged truth rig-2")
            rig1.put(keys.episode_result("rig-1"), b"own result rig-1")  # its own key: allowed
            controller.put(keys.episode_truth("robot-1"), b"forged truth robot-1")
            orch.put(keys.episode_control("rig-2"), b"from the orchestrator")  # allowed: the spy must not hear it
            rig2.put(keys.measurement("rig-2"), b"rig-2's own measurement")
            time.sleep(0.05)
        time.sleep(1.0)
        models = [r.ok.payload.to_bytes() for r in orch.get(keys.pod_model(), payload=b"{}", timeout=5.0) if r.ok is not None]
        rigs = d.rigs()
        outcome["put on rig-2's data"] = any(p.startswith(b"forged") for p in rig2_data.payloads())
        outcome["put on rig-2's control"] = b"forged control" in rig2_control.payloads()
        outcome["put a result for rig-2"] = b"forged result rig-2" in results.payloads()
        outcome["put a result for a rig that does not exist"] = b"forged result evil" in results.payloads()
        outcome["put truth for rig-2"] = b"forged truth rig-2" in truth.payloads()
        outcome["a controller put truth"] = b"forged truth robot-1" in truth.payloads()
        outcome["eavesdrop on rig-2"] = bool({b"from the orchestrator", b"rig-2's own measurement"} & set(spy.payloads()))
        outcome["serve the POD model"] = b"forged model" in models
        outcome["announce a fake rig"] = "evil" in rigs
        outcome["announce a learner"] = keys.alive("learner", "evil") in {k for k, _ in alive.items}
        # what rig-1 may do, and what the observers must see for the checks above to mean anything
        outcome["own result"] = b"own result rig-1" in results.payloads()
        outcome["own tokens"] = rigs.get("rig-1", {}).get("live", False)
        outcome["orchestrator controls rig-2"] = b"from the orchestrator" in rig2_control.payloads()
        outcome["rig-2 measures"] = b"rig-2's own measurement" in rig2_data.payloads()
        for h in reversed(handles):
            h.undeclare()
    return outcome


ATTACKS = ("put on rig-2's data", "put on rig-2's control", "put a result for rig-2", "put a result for a rig that does not exist",
           "put truth for rig-2", "a controller put truth", "eavesdrop on rig-2", "serve the POD model", "announce a fake rig",
           "announce a learner")
ALLOWED = ("own result", "own tokens", "orchestrator controls rig-2", "rig-2 measures")


def test_an_authenticated_rig_may_use_its_own_keys_and_nothing_else(deployment):
    outcome = probe(deployment)
    assert {a: outcome[a] for a in ALLOWED} == dict.fromkeys(ALLOWED, True), outcome
    assert {a: outcome[a] for a in ATTACKS} == dict.fromkeys(ATTACKS, False), outcome
    deadline = time.monotonic() + 30
    while "rig-1" in deployment.rigs() and time.monotonic() < deadline:  # its tokens went with its session
        time.sleep(0.2)
    assert "rig-1" not in deployment.rigs()  # both its nodes left: no longer listed (issue 18)


def campaign_args(tests: int, seed: int, algorithms: str) -> list[str]:
    return ["--preset", "paper", "--tests", str(tests), "--seed", str(seed), "--algorithms", algorithms,
            *[a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]]


def run(*args: str) -> dict:
    r = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", *args, "--json"], capture_output=True, text=True, timeout=300, cwd=ROOT,
                       env=clean_env({"RA2VIPAS_TOKEN": TOKEN}))
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def start_attacker(d: Deployment, name: str) -> tuple[Service, Path]:
    report = d.tmp / f"{name}.json"
    attacker = d.procs.start(name, [sys.executable, "-m", "tests.deploy.attacker", str(report)], d.env("rig-1"))
    attacker.wait_for_output("attacker up", 60)
    return attacker, report


def stop_attacker(attacker: Service, report: Path) -> dict:
    os.killpg(attacker.proc.pid, signal.SIGTERM)
    assert attacker.proc.wait(30) == 0, attacker.tail()
    return json.loads(report.read_text())


def test_a_campaign_under_attack_by_an_authenticated_rig_equals_simulate(deployment):
    attacker, report = start_attacker(deployment, "attacker")
    try:
        args = campaign_args(tests=2, seed=7, algorithms="ra2vipas,rapas")
        results = run("campaign", "start", "--api", deployment.api, *args, "--wait")
        rigs = deployment.rigs()
        assert "evil" not in rigs and [name for name, r in rigs.items() if r["live"]] == ["rig-2"], rigs
        assert rigs["rig-2"]["described"] == "described", rigs  # the orchestrator may query rig/*/info
    finally:
        seen = stop_attacker(attacker, report)
    assert seen["attempts"] > 0 and seen["forged"] > 0, seen  # it kept trying ...
    assert seen["heard"] == 0 and seen["heard_starts"] == 0, seen  # ... blind: no episode id, no data
    assert untimed(results) == untimed(run("simulate", *args))  # no "assumptions": the controller had its rig's descriptor


def test_without_the_access_control_the_same_attacker_wins(deployment):
    """Runs last: it replaces the router by one without access control (the services reconnect)."""
    deployment.stop_router()
    deployment.start_router(access_control=False)
    deployment.health()
    outcome = probe(deployment)
    assert {a: outcome[a] for a in ATTACKS} == dict.fromkeys(ATTACKS, True), outcome
    attacker, report = start_attacker(deployment, "attacker-without-acl")
    try:
        deadline = time.monotonic() + 30
        while not deployment.rigs().get("evil", {}).get("live") and time.monotonic() < deadline:
            time.sleep(0.2)
        assert deployment.rigs()["evil"]["live"], "the fake rig is taken for a real one"
        args = campaign_args(tests=4, seed=8, algorithms="rapas")
        results = run("campaign", "start", "--api", deployment.api, *args, "--wait")
    finally:
        seen = stop_attacker(attacker, report)
    assert seen["heard_starts"] > 0 and seen["heard"] > 0, seen
    assert untimed(results) != untimed(run("simulate", *args)), "the forged results went unnoticed"
