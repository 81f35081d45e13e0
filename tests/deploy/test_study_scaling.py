"""How a study's throughput scales with rigs across hosts, and what the orchestrator costs per
episode (issue 10): Linux network namespaces as hosts in a star around the Zenoh router (as in
test_multihost.py), the orchestrator and the learner on one host, and 1, 2, then 4 rig hosts
each running ``ra2vipas rig`` with the compose file's command and environment. The same study
runs on each; the test prints, per rig count, the study's wall time, episodes and control steps
per second, the orchestrator's CPU time per episode and the rigs' CPU time per control step
(from /proc), and the rigs' per-core efficiency against in-process: the study's episodes run in
this process on one core cost some CPU per control step (``in_process_cpu_ms_per_step``), and
``rig_core_efficiency`` is that over the rigs' (issue 22: what a rig core does of what an
in-process core does). It writes them to ``$RA2VIPAS_SCALING_OUT`` if set.

It asserts what must hold whatever the machine: the study finishes on every rig count, every
rig took part, and the results are identical value for value whatever the number of rigs.
Speeds are reported, never asserted (a 2-core machine shared with other work cannot show 4
rigs' worth of speed; the README says how to read the numbers). Size it with
``RA2VIPAS_SCALING_TESTS`` (tests per point, default 24: enough episodes to keep 4 rigs busy past their windows).

Needs root (network namespaces): without it the test fails and says so; it never skips.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import httpx
import pytest

from tests import http
from tests.conftest import differences
from tests.deploy.compose import environment, interpolate, load, ra2vipas_argv
from tests.deploy.conftest import Services, clean_env
from tests.deploy.netns import NetnsError, destroy_namespace, ip, remove_stale_namespaces

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

TOKEN = "scaling-test-token"
RIG_COUNTS = (1, 2, 4)
TESTS = int(os.environ.get("RA2VIPAS_SCALING_TESTS", "24"))
STUDY = {"preset": "paper", "overrides": {"steps": 60, "n_train": 250}, "vary": {"n_targets": [10, 20]},
         "algorithms": ["ra2vipas", "rapas"], "tests": TESTS, "seed": 5}
HOSTS = ("router", "orch", *(f"rig{i}" for i in range(1, max(RIG_COUNTS) + 1)))


class Star:
    """Namespaces ``r2v-<pid>-<host>``, each linked to the router's by a veth pair, plus the
    operator's link (this namespace) to the orchestrator's host."""

    def __init__(self) -> None:
        self.tag = str(os.getpid())
        self.made: list[str] = []
        self.operator_if = ""
        self.api_host = ""

    def ns(self, host: str) -> str:
        return f"r2v-{self.tag}-{host}"

    def prefix(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns(host)]

    def build(self) -> None:
        for host in HOSTS:
            ip("netns", "add", self.ns(host))
            self.made.append(self.ns(host))
            ip("-n", self.ns(host), "link", "set", "lo", "up")
        router = self.ns("router")
        for i, host in enumerate(HOSTS[1:], start=1):
            ip("link", "add", f"to-{host}", "netns", router, "type", "veth", "peer", "name", "eth0", "netns", self.ns(host))
            ip("-n", router, "addr", "add", f"10.78.{i}.1/30", "dev", f"to-{host}")
            ip("-n", self.ns(host), "addr", "add", f"10.78.{i}.2/30", "dev", "eth0")
            ip("-n", router, "link", "set", f"to-{host}", "up")
            ip("-n", self.ns(host), "link", "set", "eth0", "up")
            etc = Path("/etc/netns") / self.ns(host)
            etc.mkdir(parents=True, exist_ok=True)
            (etc / "hosts").write_text(f"127.0.0.1 localhost\n10.78.{i}.1 router\n")
        octet = (int(self.tag) + 7) % 250
        self.operator_if = f"r2s{self.tag}op"[:15]
        self.api_host = f"10.214.{octet}.2"
        ip("link", "add", self.operator_if, "type", "veth", "peer", "name", "op0", "netns", self.ns("orch"))
        ip("addr", "add", f"10.214.{octet}.1/30", "dev", self.operator_if)
        ip("-n", self.ns("orch"), "addr", "add", f"{self.api_host}/30", "dev", "op0")
        ip("link", "set", self.operator_if, "up")
        ip("-n", self.ns("orch"), "link", "set", "op0", "up")

    def destroy(self) -> None:
        errors: list[str] = []
        if self.operator_if:
            try:
                ip("link", "del", self.operator_if)
            except NetnsError as err:
                if "Cannot find device" not in str(err):
                    errors.append(str(err))
        for ns in self.made:
            destroy_namespace(ns, errors)
        assert not errors, "cleaning up the namespaces failed: " + "; ".join(errors)


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process and its reaped children (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = sum(int(v) for v in fields[11:15])  # utime stime cutime cstime
    return ticks / os.sysconf("SC_CLK_TCK")


def orchestrator_pid(service) -> int:
    """The orchestrator's Python process: ``ip netns exec`` execs it, so it is the started pid."""
    return service.proc.pid


def wait_rigs(api: str, count: int, timeout: float = 90.0) -> list[str]:
    deadline = time.monotonic() + timeout
    rigs: list[str] = []
    while time.monotonic() < deadline:
        try:
            rigs = http.get(f"{api}/health", timeout=3).json().get("rigs", [])
        except (httpx.HTTPError, ValueError):
            rigs = []
        if len(rigs) == count:
            return rigs
        time.sleep(0.2)
    raise AssertionError(f"expected {count} live rigs, the orchestrator sees {rigs}")


def in_process_cpu_ms_per_step() -> float:
    """CPU [ms] per control step of ``STUDY``'s episodes run in this process on one core (every
    test of every algorithm of every point; the POD trained first, not counted: the rigs of a
    study after the first train nothing either, the learner has the model)."""
    from ra2vipas.services.orchestrator.simulate import run_test, train_pod
    from ra2vipas.services.protocol.scenario import build_scenario

    ((name, values),) = STUDY["vary"].items()
    steps, cpu = 0, 0.0
    for value in values:
        scenario = build_scenario(STUDY["preset"], {**STUDY["overrides"], name: value})
        pod = train_pod(scenario, STUDY["seed"], cache=False).model
        for algorithm in STUDY["algorithms"]:  # the kernels loaded and the imports done first, as in a running rig
            run_test(scenario, STUDY["seed"], 0, algorithm, pod)
        t0 = time.process_time()
        for test in range(STUDY["tests"]):
            for algorithm in STUDY["algorithms"]:
                run_test(scenario, STUDY["seed"], test, algorithm, pod)
        cpu += time.process_time() - t0
        steps += STUDY["tests"] * len(STUDY["algorithms"]) * scenario.steps
    return 1000.0 * cpu / steps


def test_study_throughput_with_1_2_and_4_rig_hosts(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scaling")
    in_process_ms = in_process_cpu_ms_per_step()
    remove_stale_namespaces()
    net = Star()
    procs = Services(tmp)
    report: list[dict] = []
    try:
        try:
            net.build()
        except (NetnsError, OSError) as err:
            pytest.fail(f"cannot build the test network of Linux network namespaces: {err}. This test needs root "
                        "(CAP_SYS_ADMIN and CAP_NET_ADMIN) and iproute2; it does not skip.", pytrace=False)
        compose = interpolate(load(), {"RA2VIPAS_TOKEN": TOKEN, "RA2VIPAS_RIGS": "1"})
        router_cmd = compose["services"]["router"]["command"]
        listen = [router_cmd[i + 1] for i, arg in enumerate(router_cmd) if arg in ("--listen", "-l")]
        procs.start_cli("router", "router", *[a for ep in listen for a in ("--listen", ep)], env=clean_env(),
                        prefix=net.prefix("router"))

        def service(name: str, **env: str) -> tuple[list[str], dict[str, str]]:
            svc = compose["services"][name]
            return ra2vipas_argv(svc), clean_env({**environment(svc), **env})

        argv, env = service("orchestrator", RA2VIPAS_DB=str(tmp / "ra2vipas.db"), RA2VIPAS_LOG_LEVEL="WARNING")
        orch = procs.start("orchestrator", argv, env, prefix=net.prefix("orch"))
        argv, env = service("learner", RA2VIPAS_MODEL_CACHE=str(tmp / "models"), RA2VIPAS_LOG_LEVEL="WARNING")
        procs.start("learner", argv, env, prefix=net.prefix("orch"))
        rig_pids: list[int] = []
        api = f"http://{net.api_host}:{environment(compose['services']['orchestrator'])['RA2VIPAS_PORT']}"
        started_rigs = 0
        rows_by_count: dict[int, list[dict]] = {}
        with httpx.Client(base_url=api, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10) as http:
            for count in RIG_COUNTS:
                while started_rigs < count:
                    started_rigs += 1
                    argv, env = service("rig", RA2VIPAS_RIG=f"rig-{started_rigs}", RA2VIPAS_LOG_LEVEL="WARNING")
                    rig_pids.append(procs.start(f"rig-{started_rigs}", argv, env, prefix=net.prefix(f"rig{started_rigs}")).proc.pid)
                wait_rigs(api, count)
                cpu_before = cpu_seconds(orchestrator_pid(orch))
                rigs_before = sum(map(cpu_seconds, rig_pids))
                t0 = time.monotonic()
                r = http.post("/studies", json={**STUDY, "name": f"{count} rigs"})
                assert r.status_code == 201, r.text
                sid = r.json()["id"]
                deadline = time.monotonic() + 600
                while time.monotonic() < deadline:
                    s = http.get(f"/studies/{sid}").json()
                    if s["status"] in ("done", "failed", "cancelled"):
                        break
                    time.sleep(0.1)
                wall = time.monotonic() - t0
                assert s["status"] == "done", f"{s['status']} {s['progress']} {s.get('error')}\n{procs.tails()}"
                orch_cpu = cpu_seconds(orchestrator_pid(orch)) - cpu_before
                rigs_cpu = sum(map(cpu_seconds, rig_pids)) - rigs_before
                episodes = s["progress"]["done"]
                steps = episodes * STUDY["overrides"]["steps"]
                # the episodes' wall time, without the POD training before them: first to last episode recorded
                import sqlite3

                with sqlite3.connect(f"file:{tmp / 'ra2vipas.db'}?mode=ro", uri=True, timeout=10) as db:
                    cids = [p["campaign_id"] for p in s["points"]]
                    marks = ",".join("?" * len(cids))
                    rigs_used = {r[0] for r in db.execute(f"SELECT DISTINCT rig FROM episodes WHERE campaign_id IN ({marks})", cids)}
                    started_at = min(p for p in (http.get(f"/campaigns/{c}").json()["started_at"] for c in cids) if p)
                    last = db.execute(f"SELECT MAX(finished_at) FROM episodes WHERE campaign_id IN ({marks})", cids).fetchone()[0]
                assert rigs_used == {f"rig-{i}" for i in range(1, count + 1)}, f"with {count} rigs, episodes ran on {rigs_used}"
                rows_by_count[count] = http.get(f"/studies/{sid}/results").json()["rows"]
                report.append({"rigs": count, "episodes": episodes, "control_steps": steps, "wall_s": round(wall, 2),
                               "episodes_per_s": round(episodes / wall, 2), "steps_per_s": round(steps / wall, 1),
                               "steps_per_s_after_training": round(steps / max(1e-9, last - started_at), 1),
                               "orchestrator_cpu_s": round(orch_cpu, 3),
                               "orchestrator_cpu_ms_per_episode": round(1000 * orch_cpu / episodes, 2),
                               # the rigs' CPU per control step (with 1 rig it includes the training episode's
                               # samples the rig's sensors make for the learner), and what a rig core does of an
                               # in-process one
                               "rig_cpu_ms_per_step": round(1000 * rigs_cpu / steps, 4),
                               "in_process_cpu_ms_per_step": round(in_process_ms, 4),
                               "rig_core_efficiency": round(in_process_ms / (1000 * rigs_cpu / steps), 3) if rigs_cpu > 0 else None,
                               "load_average": [round(v, 2) for v in os.getloadavg()]})
    finally:
        procs.stop_all()
        net.destroy()
    print("\nstudy scaling (" + json.dumps(STUDY) + "):")
    for row in report:
        print(json.dumps(row))
    if os.environ.get("RA2VIPAS_SCALING_OUT"):
        Path(os.environ["RA2VIPAS_SCALING_OUT"]).write_text(json.dumps({"study": STUDY, "runs": report}, indent=1))

    def strip(rows: list[dict]) -> list[dict]:
        return [{k: v for k, v in r.items() if k != "campaign_id"} for r in rows]

    base = strip(rows_by_count[RIG_COUNTS[0]])
    for count in RIG_COUNTS[1:]:
        assert strip(rows_by_count[count]) == base, differences(strip(rows_by_count[count]), base)
