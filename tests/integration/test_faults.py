"""Nothing lost, same answer: kill -9 a worker in the middle of a campaign on a real stack
(`ra2vipas up`, which restarts what dies) and check that every test is recorded exactly once
and that the results equal an undisturbed run with the same seed."""

from __future__ import annotations

import os
import signal
import sqlite3
import time
from pathlib import Path

import httpx
import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol.scenario import build_scenario
from tests import http
from tests.conftest import differences, untimed
from tests.integration.conftest import Procs, alive, children_of, start_stack, stop_stack

ALGORITHMS = ["ra2vipas", "rapas"]
TESTS = 30
SEED = 21
OVERRIDES = {"n_train": 300}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    registry = Procs()
    state = start_stack(registry, tmp_path_factory.mktemp("faults"), "--window", "4", rigs=2)
    yield state
    stop_stack(registry, state["up"])


@pytest.fixture(scope="module")
def undisturbed():
    results = run_campaign("paper", build_scenario("paper", OVERRIDES), TESTS, SEED, ALGORITHMS)
    return untimed(results)




def _child(up_pid: int, *words: str) -> int:
    for pid in children_of(up_pid):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        text = " ".join(c.decode() for c in cmd)
        if all(w in text for w in words):
            return pid
    raise AssertionError(f"no child of {up_pid} runs {words}")


def _get(api: str, path: str, deadline: float) -> dict:
    """GET with retries: the API may be restarting."""
    while True:
        try:
            r = http.get(f"{api}{path}", timeout=5)
            if r.status_code == 200:
                return r.json()
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            raise AssertionError(f"GET {path} kept failing")
        time.sleep(0.1)


def _campaign_with_a_kill(stack, victim: tuple[str, ...], at_fraction: float) -> tuple[dict, dict]:
    api, up = stack["api"], stack["up"]
    body = {"preset": "paper", "tests": TESTS, "seed": SEED, "algorithms": ALGORITHMS, "overrides": OVERRIDES}
    cid = http.post(f"{api}/campaigns", json=body, timeout=30).json()["id"]
    deadline = time.monotonic() + 300
    killed = None
    while True:
        c = _get(api, f"/campaigns/{cid}", deadline)
        p = c["progress"]
        if killed is None and c["status"] == "running" and p["done"] >= at_fraction * p["total"]:
            killed = _child(up.pid, *victim)
            os.kill(killed, signal.SIGKILL)
            done_at_kill = p["done"]
        if c["status"] in ("done", "failed", "cancelled"):
            break
        assert time.monotonic() < deadline, c
        time.sleep(0.05)
    assert killed is not None, f"the campaign finished before the kill: {c}"
    assert done_at_kill < p["total"], "the kill came too late to matter"
    assert not alive(killed)
    return c, _get(api, f"/campaigns/{cid}/results", deadline)


def _recorded_once(db: Path, cid: str) -> None:
    with sqlite3.connect(db) as conn:
        rows = conn.execute("SELECT test_index, algorithm, status FROM episodes WHERE campaign_id=?", (cid,)).fetchall()
    assert len(rows) == TESTS * len(ALGORITHMS)
    assert {(k, a) for k, a, _ in rows} == {(k, a) for k in range(TESTS) for a in ALGORITHMS}
    assert {s for _, _, s in rows} == {"done"}


@pytest.mark.parametrize("victim", [("main rig --rig rig-1",)])  # a whole rig: its sensors and controller, one process
def test_killing_a_rig_process_loses_nothing_and_changes_nothing(stack, undisturbed, victim):
    c, results = _campaign_with_a_kill(stack, victim, 0.15)
    assert c["status"] == "done", c["error"]
    _recorded_once(stack["db"], c["id"])
    assert not differences(untimed(results), undisturbed), differences(untimed(results), undisturbed)


def test_killing_the_orchestrator_resumes_from_sqlite(stack, undisturbed):
    c, results = _campaign_with_a_kill(stack, ("orchestrator",), 0.4)
    assert c["status"] == "done", c["error"]
    _recorded_once(stack["db"], c["id"])
    assert not differences(untimed(results), undisturbed), differences(untimed(results), undisturbed)


def test_killing_the_learner_before_a_new_model_is_needed(stack):
    """The learner dies; a campaign that needs a model nobody has cached yet waits for the
    restarted learner, which retrains it identically."""
    api, up = stack["api"], stack["up"]
    os.kill(_child(up.pid, "learner"), signal.SIGKILL)
    overrides = {"n_train": 200, "steps": 40}
    body = {"preset": "paper", "tests": 3, "seed": 99, "algorithms": ["ra2vipas"], "overrides": overrides}
    cid = http.post(f"{api}/campaigns", json=body, timeout=30).json()["id"]
    deadline = time.monotonic() + 180
    while (c := _get(api, f"/campaigns/{cid}", deadline))["status"] not in ("done", "failed"):
        time.sleep(0.1)
    assert c["status"] == "done", c["error"]
    expected = run_campaign("paper", build_scenario("paper", overrides), 3, 99, ["ra2vipas"])
    assert untimed(_get(api, f"/campaigns/{cid}/results", deadline)) == untimed(expected)
