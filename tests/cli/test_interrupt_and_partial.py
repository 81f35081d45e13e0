"""Ctrl-C on `campaign watch` / `start --wait` stops following, not the campaign, and says how
to come back; a cancelled or failed campaign's results are those of its recorded episodes,
marked partial, in the API and the CLI (issue 13)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.orchestrator.scheduler import MAX_ATTEMPTS
from tests import http
from tests.api.live import SMALL
from tests.cli.conftest import ROOT, ra2vipas
from tests.conftest import restore_ctrl_c

LONG = {**SMALL, "steps": 120}


def _start(live, tests: int = 400) -> str:
    body = {"preset": "paper", "overrides": LONG, "algorithms": ["ra2vipas"], "tests": tests, "seed": 9}
    r = http.post(f"{live.url}/campaigns", json=body, timeout=30)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _progress(live, cid: str) -> dict:
    return http.get(f"{live.url}/campaigns/{cid}", timeout=30).json()


def _open_streams(live) -> int:
    """Event streams the server is serving now: a CLI that follows a campaign holds one."""
    streams = getattr(live.app.state, "event_streams", None)
    return 0 if streams is None else streams.open


def _until(condition, timeout: float = 60.0, what: str = "a condition") -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _no_stream_open(live) -> None:
    """Wait until the streams of earlier followers are closed, so that the next one open is
    the CLI's under test."""
    _until(lambda: _open_streams(live) == 0, what="the earlier event streams to close")


def _interrupt(proc: subprocess.Popen) -> tuple[str, str]:
    """SIGINT (Ctrl-C) to a following CLI; its stdout and stderr once it exits."""
    try:
        proc.send_signal(signal.SIGINT)
        # the API it follows runs in this process beside the rigs' controllers: on a fresh clone
        # their numerical kernels compile there (numba holds the GIL), which can stall the API's
        # answers for tens of seconds
        return proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _cli(*args: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("RA2VIPAS_API", "RA2VIPAS_TOKEN")}
    return subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT, env=env, start_new_session=True, preexec_fn=restore_ctrl_c)


def _says_how_to_come_back(err: str, cid: str, api: str) -> None:
    text = " ".join(err.split())
    assert f"interrupted: campaign {cid} keeps running" in text, err
    assert f"ra2vipas campaign watch {cid} --api {api}" in text and f"ra2vipas campaign cancel {cid} --api {api}" in text, err
    assert "Traceback" not in err


def test_ctrl_c_on_watch_prints_the_id_and_the_commands_and_leaves_the_campaign_running(live):
    cid = _start(live)
    _no_stream_open(live)
    proc = _cli("campaign", "watch", cid, "--api", live.url)
    _until(lambda: _open_streams(live) == 1 and _progress(live, cid)["progress"]["done"] >= 1, what="the CLI to follow")
    out, err = _interrupt(proc)
    assert proc.returncode == 130, (out, err)
    _says_how_to_come_back(err, cid, live.url)
    assert _progress(live, cid)["status"] in ("queued", "running", "done")
    http.post(f"{live.url}/campaigns/{cid}/cancel", timeout=30)


def test_ctrl_c_on_start_wait_prints_the_id_and_the_commands_and_leaves_the_campaign_running(live):
    """`campaign start --wait` follows through the same code as `watch`; the id it printed first,
    on its own line, is in the message too."""
    name = "ctrl-c-on-start-wait"
    _no_stream_open(live)
    proc = _cli("campaign", "start", "--wait", "--name", name, "--algorithms", "ra2vipas", "--tests", "400", "--seed", "9",
                *(f"--set={k}={v}" for k, v in LONG.items()), "--api", live.url)

    def started() -> list[dict]:
        return http.get(f"{live.url}/campaigns", params={"name": name}, timeout=30).json()["items"]

    _until(lambda: _open_streams(live) == 1 and started() and started()[0]["progress"]["done"] >= 1, what="the CLI to follow")
    out, err = _interrupt(proc)
    [c] = started()
    cid = c["id"]
    assert proc.returncode == 130, (out, err)
    _says_how_to_come_back(err, cid, live.url)
    assert out == f"campaign {cid}\n"  # its id, and no results table: it never finished
    assert _progress(live, cid)["status"] in ("running", "done")
    http.post(f"{live.url}/campaigns/{cid}/cancel", timeout=30)


def test_a_cancelled_campaign_has_partial_results(live):
    cid = _start(live)
    deadline = time.monotonic() + 60
    while _progress(live, cid)["progress"]["done"] < 3 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert http.post(f"{live.url}/campaigns/{cid}/cancel", timeout=30).status_code == 200
    c = _progress(live, cid)
    assert c["status"] == "cancelled"
    r = http.get(f"{live.url}/campaigns/{cid}/results", timeout=30)
    assert r.status_code == 200, r.text
    results = r.json()
    assert results["partial"] is True
    recorded = results["tests_recorded"]["ra2vipas"]
    assert 3 <= recorded == c["progress"]["done"] < 400
    assert 0.0 <= results["algorithms"]["ra2vipas"]["dr_final"] <= 1.0
    shown = ra2vipas("campaign", "results", cid, "--api", live.url)
    assert shown.returncode == 0, shown.stderr
    assert f"partial results: the campaign stopped before its end; tests recorded: ra2vipas {recorded} (of 400)" in " ".join(shown.stdout.split())
    # a campaign still running has none yet
    running = _start(live, tests=50)
    r = http.get(f"{live.url}/campaigns/{running}/results", timeout=30)
    assert r.status_code == 409 and "no results yet" in r.json()["detail"]
    http.post(f"{live.url}/campaigns/{running}/cancel", timeout=30)


def test_a_failed_campaign_has_partial_results_of_its_recorded_episodes(live, monkeypatch):
    """The rig's controller fails every episode from test 3 on (its camera was unplugged) once
    tests 0-2 are recorded: test 3 fails MAX_ATTEMPTS times, the campaign ends ``failed`` with
    that error, and its results are the reduction of tests 0-2, marked partial (API, CSV, CLI)."""
    seed, tests = 31337, 12
    controller = next(n for n in live.nodes if isinstance(n, ControllerNode))
    begin = controller._begin
    held: list[str] = []  # touched on the controller's loop thread only
    unplugged = False

    def failing_begin(episode_id: str, model) -> None:
        ep = controller.episodes.get(episode_id)
        if ep is None or ep.start.seed != seed or ep.start.test_index < 3:
            begin(episode_id, model)
        elif unplugged:
            controller._fail(episode_id, "camera unplugged")
        else:
            held.append(episode_id)  # hangs until the camera is unplugged

    def unplug() -> None:
        nonlocal unplugged
        unplugged = True
        for episode_id in held:
            controller._fail(episode_id, "camera unplugged")

    monkeypatch.setattr(controller, "_begin", failing_begin)
    body = {"preset": "paper", "overrides": SMALL, "algorithms": ["ra2vipas"], "tests": tests, "seed": seed, "name": "fails"}
    r = http.post(f"{live.url}/campaigns", json=body, timeout=30)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    _until(lambda: _progress(live, cid)["progress"]["done"] >= 3, what="tests 0-2 to be recorded")
    controller.loop.post(unplug)
    c = live.wait(cid)
    assert c["status"] == "failed", c
    assert f"test 3 (ra2vipas) failed {MAX_ATTEMPTS} times: camera unplugged" in c["error"]
    assert c["progress"]["done"] == 3

    r = http.get(f"{live.url}/campaigns/{cid}/results", timeout=30)
    assert r.status_code == 200, r.text
    results = r.json()
    assert results["partial"] is True and results["tests_recorded"] == {"ra2vipas": 3} and results["tests"] == tests
    outcomes = http.get(f"{live.url}/campaigns/{cid}/tests", params={"status": "done"}, timeout=30).json()["items"]
    assert sorted(o["test_index"] for o in outcomes) == [0, 1, 2]
    assert results["algorithms"]["ra2vipas"]["dr_final"] == sum(o["final_hit"] for o in outcomes) / 3
    summary = http.get(f"{live.url}/campaigns/{cid}/results", params={"format": "csv", "table": "summary"}, timeout=30).text
    row = dict(zip(*[line.split(",") for line in summary.splitlines()]))
    assert row["partial"] == "True" and row["tests_recorded"] == "3", summary

    shown = ra2vipas("campaign", "results", cid, "--api", live.url)
    assert shown.returncode == 0, shown.stderr
    said = " ".join(shown.stdout.split())
    assert f"partial results: the campaign stopped before its end; tests recorded: ra2vipas 3 (of {tests})" in said
