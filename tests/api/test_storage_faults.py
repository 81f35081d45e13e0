"""Storage faults surface and heal (issue 14): a full disk (a small tmpfs) and a read-only
database at start-up (a read-only bind mount) make ``/health`` 503 with the cause and show in
the campaign's ``error``; the API answers 503 in JSON; when the database takes writes again
the orchestrator resumes by itself, and the campaign ends with every test recorded once and
the same results as an undisturbed run. Needs root (mounts), like the deployment tests; it
fails rather than skips without it."""

from __future__ import annotations

import errno
import os
import subprocess
import time
from pathlib import Path

import pytest

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import SensorsNode
from tests import http
from tests.api.live import SMALL, LiveAPI
from tests.conftest import untimed

OVERRIDES = {**SMALL, "steps": 60}
ALGORITHMS = ["ra2vipas", "rapas"]
TESTS, SEED = 3, 12


def _mount(*args: str) -> None:
    if os.geteuid() != 0:
        pytest.fail("storage-fault tests mount a tmpfs and bind mounts: run them as root (CI does)")
    subprocess.run(["mount", *args], check=True, capture_output=True)


@pytest.fixture()
def mounts():
    points: list[Path] = []

    def mount(*args: str, at: Path) -> Path:
        at.mkdir(parents=True, exist_ok=True)
        _mount(*args, str(at))
        points.append(at)
        return at

    yield mount
    for point in reversed(points):
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def fill(directory: Path) -> Path:
    """Write a file until the file system is full; return it."""
    filler = directory / "filler"
    chunk = b"\0" * 4096
    with open(filler, "wb", buffering=0) as f:
        while True:
            try:
                f.write(chunk)
            except OSError as err:
                assert err.errno == errno.ENOSPC, err
                return filler


def wait_for(predicate, what: str, timeout: float = 60.0, every: float = 0.1):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(every)
    raise AssertionError(f"{what} within {timeout} s (last: {last!r})")


def expected_results() -> dict:
    return untimed(run_campaign("paper", build_scenario("paper", OVERRIDES), TESTS, SEED, ALGORITHMS))


def assert_recorded_once(db: Path, cid: str) -> None:
    store = Store(str(db))
    try:
        rows = store.episode_rows(cid, status=None)
    finally:
        store.close()
    assert sorted((r["test_index"], r["algorithm"]) for r in rows) == sorted((k, a) for k in range(TESTS) for a in ALGORITHMS)
    assert all(r["status"] == "done" for r in rows)


def test_a_full_disk_fails_loudly_and_heals_without_a_restart(tmp_path, mounts):
    disk = mounts("-t", "tmpfs", "-o", "size=1m", "tmpfs", at=tmp_path / "disk")
    live = LiveAPI(disk / "full.db", rigs=())
    live.nodes.append(SensorsNode(live.bus, "rig-1"))  # trains the POD model; no controller yet, so nothing runs
    live.start()
    try:
        with live.client() as http:
            r = http.post("/campaigns", json={"overrides": OVERRIDES, "algorithms": ALGORITHMS, "tests": TESTS, "seed": SEED})
            assert r.status_code == 201, r.text
            cid = r.json()["id"]
            live.wait(cid, statuses=("running",))
            filler = fill(disk)
            live.nodes.append(ControllerNode(live.bus, "rig-1"))  # the rig is live: episodes run, their results cannot be written

            health = wait_for(lambda: (lambda h: h if h.status_code == 503 and h.json()["database_error"] else None)(http.get("/health")),
                              "/health did not report the database")
            body = health.json()
            assert body["database"] is False and "full" in body["database_error"] and body["status"] == "degraded"
            c = http.get(f"/campaigns/{cid}").json()
            assert c["status"] == "running" and "full" in c["error"] and c["progress"]["done"] < c["progress"]["total"]
            listed = http.get("/campaigns").json()["items"][0]
            assert listed["id"] == cid and "full" in listed["error"]

            before = http.get("/campaigns").json()["total"]
            refused = http.post("/campaigns", json={"overrides": OVERRIDES, "tests": 1})
            assert refused.status_code == 503 and refused.headers["retry-after"]
            assert refused.headers["content-type"].startswith("application/json") and "full" in refused.json()["detail"]
            assert http.get("/campaigns").json()["total"] == before  # nothing half-written

            filler.unlink()  # space again: no restart, no operator action
            c = live.wait(cid, timeout=120)
            assert c["status"] == "done" and c["error"] is None, c
            assert untimed(http.get(f"/campaigns/{cid}/results").json()) == expected_results()
            wait_for(lambda: http.get("/health").status_code == 200, "/health did not recover")
            assert http.get("/health").json()["database_error"] is None
    finally:
        live.stop()
    assert_recorded_once(disk / "full.db", cid)


def test_a_read_only_database_at_start_up_surfaces_and_heals(tmp_path, mounts):
    source = tmp_path / "source"
    source.mkdir()
    store = Store(str(source / "ro.db"))
    scenario = build_scenario("paper", OVERRIDES)
    cid = store.create_campaign(preset="paper", overrides=OVERRIDES, scenario=scenario.model_dump(mode="json"), algorithms=ALGORITHMS,
                                tests=TESTS, seed=SEED, mode="fast")
    store.close()
    view = mounts("--bind", str(source), at=tmp_path / "view")
    _mount("-o", "remount,ro,bind", str(view))

    live = LiveAPI(view / "ro.db").start()  # an orchestrator (re)started on a read-only file system
    try:
        with live.client() as http:
            health = http.get("/health")
            assert health.status_code == 503 and health.json()["database"] is False
            assert "unable to open" in health.json()["database_error"]
            r = http.get("/campaigns")
            assert r.status_code == 503 and "database" in r.json()["detail"]

            _mount("-o", "remount,rw,bind", str(view))
            c = wait_for(lambda: (lambda r: r.json() if r.status_code == 200 else None)(http.get(f"/campaigns/{cid}")),
                         "the campaign did not become readable")
            c = live.wait(cid, timeout=120)
            assert c["status"] == "done", c
            assert untimed(http.get(f"/campaigns/{cid}/results").json()) == expected_results()
    finally:
        live.stop()
    assert_recorded_once(view / "ro.db", cid)


def test_up_on_a_read_only_folder_starts_degraded_and_heals(tmp_path, mounts):
    """Issue 18: `ra2vipas up` with its database in a read-only folder gave no API at all (the
    orchestrator could not create its lock file, exited, and `up` gave up). Now the stack
    starts degraded: /health and the API answer 503 naming the cause ("read-only", not "disk
    I/O error"), and everything works once the folder is writable again, without a restart."""

    from tests.integration.conftest import Procs, start_stack, stop_stack

    source = tmp_path / "source"
    source.mkdir()
    view = mounts("--bind", str(source), at=tmp_path / "view")
    _mount("-o", "remount,ro,bind", str(view))
    registry = Procs()
    try:
        state = start_stack(registry, tmp_path, "--db", str(view / "ro.db"), rigs=1)
        api, up = state["api"], state["up"]
        health = http.get(f"{api}/health", timeout=5)
        assert health.status_code == 503 and health.json()["database"] is False, health.text
        assert "read-only" in health.json()["database_error"] and "disk I/O" not in health.json()["database_error"], health.json()
        assert health.json()["zenoh"] and health.json()["rigs"] == ["rig-1"]
        r = http.get(f"{api}/campaigns", timeout=5)
        assert r.status_code == 503 and r.headers["content-type"].startswith("application/json") and "read-only" in r.json()["detail"]
        r = http.post(f"{api}/campaigns", json={"overrides": OVERRIDES, "tests": 1}, timeout=5)
        assert r.status_code == 503 and "read-only" in r.json()["detail"]

        _mount("-o", "remount,rw,bind", str(view))
        wait_for(lambda: http.get(f"{api}/health", timeout=5).status_code == 200, "/health did not recover", timeout=90)
        r = http.post(f"{api}/campaigns", json={"overrides": OVERRIDES, "algorithms": ALGORITHMS, "tests": TESTS, "seed": SEED},
                       timeout=10)
        assert r.status_code == 201, r.text
        cid = r.json()["id"]
        c = wait_for(lambda: (lambda c: c if c["status"] in ("done", "failed") else None)(http.get(f"{api}/campaigns/{cid}", timeout=5).json()),
                     "the campaign did not finish", timeout=120)
        assert c["status"] == "done", c
        stop_stack(registry, up)
        out = up.stdout.read()
        assert "degraded: the database folder" in out and "read-only file system" in out, out
        assert "crashed" not in out and "exited (code" not in out, out  # the orchestrator never died
    finally:
        registry.cleanup()
    assert (view / "ro.db.lock").exists()
