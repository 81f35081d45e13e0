"""A campaign's life through the API: 409 while it runs, the progress stream, cancel (which
stops the episodes in flight on the rig), delete only when finished."""

from __future__ import annotations

import json
import threading
import time

import httpx
import pytest

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeStop
from tests.api.live import SMALL, LiveAPI

SLOW = {**SMALL, "steps": 100}  # realtime: 10 s per test on the wall clock


@pytest.fixture(scope="module")
def mesh(tmp_path_factory):
    server = LiveAPI(tmp_path_factory.mktemp("lifecycle") / "life.db").start()
    yield server
    server.stop()


@pytest.fixture()
def http(mesh):
    with mesh.client() as client:
        yield client


def start_running(mesh: LiveAPI, http: httpx.Client) -> str:
    """A realtime campaign with a test in flight."""
    r = http.post("/campaigns", json={"overrides": SLOW, "algorithms": ["ra2vipas"], "tests": 3, "seed": 4, "mode": "realtime"})
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        c = http.get(f"/campaigns/{cid}").json()
        if c["status"] == "running" and c["progress"]["running"] == 1:
            return cid
        time.sleep(0.05)
    raise AssertionError(f"campaign did not start running: {c}")


def read_events(response: httpx.Response, out: list) -> None:
    name = None
    for line in response.iter_lines():
        if line.startswith("event:"):
            name = line.split(":", 1)[1].strip()
        elif line.startswith("data:"):
            out.append((name, json.loads(line.split(":", 1)[1])))


def measurements_of(mesh: LiveAPI, cid: str) -> int:
    return sum(1 for key, payload in list(mesh.bus.published) if key.endswith("/measurement") and cid.encode() in payload)


def test_a_running_campaign_has_no_results_and_cannot_be_deleted_but_can_be_cancelled(mesh, http):
    cid = start_running(mesh, http)
    for path in ("/results", "/plots/dr", "/results?format=csv"):
        r = http.get(f"/campaigns/{cid}{path}")
        assert r.status_code == 409 and "running" in r.json()["detail"]
    running = http.get(f"/campaigns/{cid}/tests", params={"status": "running"}).json()["items"]
    assert len(running) == 1 and running[0]["final_hit"] is None
    assert http.get(f"/campaigns/{cid}/tests/{running[0]['test_index']}/ra2vipas").status_code == 409
    r = http.delete(f"/campaigns/{cid}")
    assert r.status_code == 409 and "cancel it first" in r.json()["detail"]
    assert http.get(f"/campaigns/{cid}").status_code == 200

    events: list = []
    with httpx.Client(base_url=mesh.url, timeout=30) as stream_client:
        with stream_client.stream("GET", f"/campaigns/{cid}/events", params={"interval": 0.05}) as stream:
            assert stream.headers["content-type"].startswith("text/event-stream")
            reader = threading.Thread(target=read_events, args=(stream, events))
            reader.start()
            time.sleep(0.3)
            rig = next(r for r in http.get("/rigs").json()["rigs"] if r["in_flight"])
            cancelled = http.post(f"/campaigns/{cid}/cancel")
            reader.join(10)
            assert not reader.is_alive(), "the stream did not end when the campaign was cancelled"

    assert cancelled.status_code == 200, cancelled.text
    c = cancelled.json()
    assert c["status"] == "cancelled" and c["finished_at"] is not None and c["progress"]["running"] == 0
    assert [name for name, _ in events] == ["progress"] * len(events)
    assert events[0][1]["status"] == "running" and events[-1][1]["status"] == "cancelled"

    # the episode in flight was stopped on its rig, and the rig's sensors stopped sampling it
    mesh.settle()
    stops = [EpisodeStop.model_validate_json(p) for k, p in list(mesh.bus.published)
             if k == keys.episode_control(rig["name"]) and b'"stop"' in p]
    assert any(s.episode_id.startswith(cid) and s.reason == "campaign cancelled" for s in stops)
    assert all(r["in_flight"] == 0 for r in http.get("/rigs").json()["rigs"])
    before = measurements_of(mesh, cid)
    time.sleep(0.5)
    assert measurements_of(mesh, cid) == before

    again = http.post(f"/campaigns/{cid}/cancel")
    assert again.status_code == 409 and "already finished (cancelled)" in again.json()["detail"]
    assert http.get(f"/campaigns/{cid}").json()["status"] == "cancelled"
    assert http.delete(f"/campaigns/{cid}").status_code == 204
    assert http.get(f"/campaigns/{cid}").status_code == 404
    assert http.delete(f"/campaigns/{cid}").status_code == 404


def test_cancelling_through_the_scheduler_marks_the_campaign_cancelled(mesh, http):
    cid = start_running(mesh, http)
    mesh.scheduler.cancel(cid)
    c = mesh.wait(cid, statuses=("cancelled",), timeout=10)
    assert c["progress"]["running"] == 0


def test_the_progress_stream_follows_a_campaign_to_the_end(mesh, http):
    r = http.post("/campaigns", json={"overrides": SMALL, "algorithms": ["ra2vipas", "rapas"], "tests": 4, "seed": 6})
    cid = r.json()["id"]
    events: list = []
    with http.stream("GET", f"/campaigns/{cid}/events", params={"interval": 0.05}) as stream:
        read_events(stream, events)
    assert events and all(name == "progress" for name, _ in events)
    done = [e["progress"]["done"] for _, e in events]
    assert done == sorted(done) and done[-1] == 8
    assert events[-1][1]["status"] == "done" and events[-1][1]["pod"]["r2"] is not None
    # a finished campaign: one event, then the stream ends
    with http.stream("GET", f"/campaigns/{cid}/events") as stream:
        again: list = []
        read_events(stream, again)
    assert [e["status"] for _, e in again] == ["done"]
    assert http.get(f"/campaigns/{cid}/events", params={"interval": 0}).status_code == 422


def test_a_finished_campaign_can_be_deleted_with_its_tests(mesh, http):
    r = http.post("/campaigns", json={"overrides": SMALL, "algorithms": ["rapas"], "tests": 2, "seed": 9})
    cid = r.json()["id"]
    assert mesh.wait(cid)["status"] == "done"
    assert http.post(f"/campaigns/{cid}/cancel").status_code == 409
    assert http.delete(f"/campaigns/{cid}").status_code == 204
    assert mesh.app.state.store.episode_rows(cid, status=None) == []
    assert http.get(f"/campaigns/{cid}/tests").status_code == 404


def test_the_cap_on_progress_streams_is_exact_under_a_burst(mesh, http):
    """66 streams were admitted under the old count-in-the-generator cap of 64; the cap holds
    when every request arrives at once, and a place frees when a stream closes."""
    from ra2vipas.services.orchestrator.api.routes.events import MAX_STREAMS

    cid = start_running(mesh, http)
    extra = 6
    barrier = threading.Barrier(MAX_STREAMS + extra)
    statuses: list[int] = []
    lock = threading.Lock()
    release = threading.Event()

    def open_stream() -> None:
        with httpx.Client(base_url=mesh.url, timeout=30) as client:
            barrier.wait()
            with client.stream("GET", f"/campaigns/{cid}/events", params={"interval": 1}) as stream:
                with lock:
                    statuses.append(stream.status_code)
                if stream.status_code == 200:
                    release.wait(30)  # hold the stream open until every request has been answered

    threads = [threading.Thread(target=open_stream) for _ in range(MAX_STREAMS + extra)]
    for t in threads:
        t.start()
    try:
        deadline = time.monotonic() + 30
        while len(statuses) < len(threads) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sorted(statuses) == [200] * MAX_STREAMS + [503] * extra
    finally:
        release.set()
        for t in threads:
            t.join(30)
    deadline = time.monotonic() + 10  # closed streams give their places back
    while time.monotonic() < deadline:
        # a new connection: ``http``'s pooled one sat idle past the server's keep-alive (2 s) during
        # the burst, and reusing it as the server closes it was once a connection reset
        with httpx.Client(base_url=mesh.url, timeout=30) as fresh:
            with fresh.stream("GET", f"/campaigns/{cid}/events", params={"interval": 1}) as stream:
                if stream.status_code == 200:
                    break
        time.sleep(0.1)
    else:
        raise AssertionError("no stream place came back after the streams closed")
    http.post(f"/campaigns/{cid}/cancel")
