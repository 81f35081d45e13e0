"""Ctrl-C on `campaign watch` / `start --wait` stops following, not the campaign, and says how
to come back; a cancelled campaign's results are those of its recorded episodes, marked
partial, in the API and the CLI (issue 13)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import httpx

from tests.api.live import SMALL
from tests.cli.conftest import ROOT, ra2vipas

LONG = {**SMALL, "steps": 120}


def _start(live, tests: int = 400) -> str:
    body = {"preset": "paper", "overrides": LONG, "algorithms": ["ra2vipas"], "tests": tests, "seed": 9}
    r = httpx.post(f"{live.url}/campaigns", json=body, timeout=30)
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _progress(live, cid: str) -> dict:
    return httpx.get(f"{live.url}/campaigns/{cid}", timeout=30).json()


def test_ctrl_c_on_watch_prints_the_id_and_the_commands_and_leaves_the_campaign_running(live):
    cid = _start(live)
    env = {k: v for k, v in os.environ.items() if k not in ("RA2VIPAS_API", "RA2VIPAS_TOKEN")}
    proc = subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", "campaign", "watch", cid, "--api", live.url],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while _progress(live, cid)["progress"]["done"] < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)  # the watcher is following by now
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, (out, err)
    text = " ".join(err.split())
    assert f"interrupted: campaign {cid} keeps running" in text
    assert f"ra2vipas campaign watch {cid} --api {live.url}" in text and f"ra2vipas campaign cancel {cid} --api {live.url}" in text
    assert "Traceback" not in err
    assert _progress(live, cid)["status"] in ("queued", "running", "done")
    httpx.post(f"{live.url}/campaigns/{cid}/cancel", timeout=30)


def test_a_cancelled_campaign_has_partial_results(live):
    cid = _start(live)
    deadline = time.monotonic() + 60
    while _progress(live, cid)["progress"]["done"] < 3 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert httpx.post(f"{live.url}/campaigns/{cid}/cancel", timeout=30).status_code == 200
    c = _progress(live, cid)
    assert c["status"] == "cancelled"
    r = httpx.get(f"{live.url}/campaigns/{cid}/results", timeout=30)
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
    r = httpx.get(f"{live.url}/campaigns/{running}/results", timeout=30)
    assert r.status_code == 409 and "no results yet" in r.json()["detail"]
    httpx.post(f"{live.url}/campaigns/{running}/cancel", timeout=30)
