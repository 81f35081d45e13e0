"""Parameter studies through the API (real server, real SQLite, the real nodes on an in-memory bus):
create, read, list (pages), results (JSON, CSV), plots (a heat map for two parameters), campaign
options (stop_confidence, mode), cancel, delete, the error paths, interleaving, restart (queued
and in the middle of running)."""

from __future__ import annotations

import csv
import io
import json
import sqlite3
import time

import numpy as np
import pytest

import ra2vipas
from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeStart, episode_control_adapter
from tests.api.live import SMALL, LiveAPI
from tests.conftest import differences, untimed

BASE = {k: v for k, v in SMALL.items() if k != "n_targets"}
BODY = {"preset": "paper", "overrides": BASE, "vary": {"n_targets": [4, 8]}, "algorithms": ["ra2vipas", "rapas"], "tests": 3,
        "seed": 3, "name": "study fixture"}


def wait_study(server: LiveAPI, sid: str, statuses=("done", "failed", "cancelled"), timeout: float = 180.0) -> dict:
    deadline = time.monotonic() + timeout
    with server.client() as http:
        while time.monotonic() < deadline:
            s = http.get(f"/studies/{sid}").json()
            if s["status"] in statuses:
                return s
            time.sleep(0.05)
    raise AssertionError(f"study {sid} did not reach {statuses}: {s}")


@pytest.fixture(scope="module")
def done_study(live):
    with live.client() as http:
        r = http.post("/studies", json=BODY)
    assert r.status_code == 201, r.text
    assert r.headers["location"] == f"/studies/{r.json()['id']}"
    s = wait_study(live, r.json()["id"])
    assert s["status"] == "done", s
    return s


@pytest.fixture(scope="module")
def grid_study(live):
    """Two varied parameters (a 2 x 2 grid), early decisions and realtime pacing (T_RF 20 ms, so
    an episode takes at most 0.4 s): one test of Ra²ViPAS per point."""
    body = {**BODY, "overrides": {**BASE, "rf_period_s": 0.02}, "vary": {"n_targets": [4, 8], "rf_noise_db": [2.0, 4.0]},
            "algorithms": ["ra2vipas"], "tests": 1, "stop_confidence": 0.9, "mode": "realtime", "name": "grid"}
    with live.client() as http:
        r = http.post("/studies", json=body)
    assert r.status_code == 201, r.text
    s = wait_study(live, r.json()["id"])
    assert s["status"] == "done", s
    return s


@pytest.fixture(scope="module")
def idle(tmp_path_factory):
    """A server with no rig and no learner: a study stays queued or training."""
    server = LiveAPI(tmp_path_factory.mktemp("idle") / "idle.db", rigs=(), learner=False).start()
    yield server
    server.stop()


def test_a_study_has_one_campaign_per_point_and_its_progress(done_study, http):
    s = http.get(f"/studies/{done_study['id']}").json()
    assert s["parameters"] == ["n_targets"] and s["vary"] == {"n_targets": [4, 8]} and s["points_total"] == 2
    assert s["progress"] == {"done": 12, "running": 0, "pending": 0, "total": 12}
    assert [p["values"] for p in s["points"]] == [{"n_targets": 4}, {"n_targets": 8}]
    for p in s["points"]:
        c = http.get(f"/campaigns/{p['campaign_id']}").json()
        assert c["status"] == "done" and c["seed"] == 3 and c["tests"] == 3
        assert c["scenario"]["n_targets"] == p["values"]["n_targets"] and c["scenario"]["steps"] == SMALL["steps"]
        assert p["pod"]["r2"] == c["pod"]["r2"]
    page = http.get("/studies", params={"status": "done"}).json()
    assert done_study["id"] in [i["id"] for i in page["items"]] and all(i["points"] is None for i in page["items"])


def test_results_one_row_per_point_and_algorithm_equal_to_the_points_campaigns(done_study, http):
    res = http.get(f"/studies/{done_study['id']}/results").json()
    assert res["partial"] is False and res["status"] == "done" and len(res["rows"]) == 4
    assert [(r["n_targets"], r["algorithm"]) for r in res["rows"]] == [(4, "ra2vipas"), (4, "rapas"), (8, "ra2vipas"), (8, "rapas")]
    for row in res["rows"]:
        campaign = http.get(f"/campaigns/{row['campaign_id']}/results").json()
        block = campaign["algorithms"][row["algorithm"]]
        assert row["dr_final"] == block["dr_final"] and [row["ci95_lo"], row["ci95_hi"]] == block["ci95"]
        assert row["time_to_dr90_s"] == block["time_to_dr90_s"] and row["pod_r2"] == campaign["pod"]["r2"]
        assert row["calibration_ece_final"] == block["calibration"]["ece_final"]
        assert row["calibration_ece_final_floor"] == block["calibration"]["ece_final_floor"] is not None
        assert row["tests"] == 3
    text = http.get(f"/studies/{done_study['id']}/results", params={"format": "csv"}).text
    rows = list(csv.DictReader(io.StringIO(text)))
    assert len(rows) == 4 and rows[0]["n_targets"] == "4" and float(rows[0]["dr_final"]) == res["rows"][0]["dr_final"]
    assert {r["study_id"] for r in rows} == {done_study["id"]} and rows[0]["preset"] == "paper" and rows[0]["seed"] == "3"
    assert http.get(f"/studies/{done_study['id']}/results", headers={"Accept": "text/csv"}).headers["content-type"].startswith("text/csv")


def test_a_point_equals_the_campaign_with_the_same_parameters_and_seed(done_study, live, http):
    point = done_study["points"][1]
    r = http.post("/campaigns", json={"preset": "paper", "overrides": {**SMALL, "n_targets": 8}, "algorithms": ["ra2vipas", "rapas"],
                                      "tests": 3, "seed": 3})
    assert r.status_code == 201, r.text
    assert live.wait(r.json()["id"])["status"] == "done"
    alone = untimed(http.get(f"/campaigns/{r.json()['id']}/results").json())
    in_study = untimed(http.get(f"/campaigns/{point['campaign_id']}/results").json())
    assert in_study == alone, differences(in_study, alone)


def test_plots_png_svg_and_bad_metrics(done_study, http):
    sid = done_study["id"]
    png = http.get(f"/studies/{sid}/plots/dr_final")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    svg = http.get(f"/studies/{sid}/plots/time_to_dr90_s", params={"format": "svg"})
    assert svg.status_code == 200 and b"<svg" in svg.content[:400]
    bad = http.get(f"/studies/{sid}/plots/nonsense")
    assert bad.status_code == 422 and "nonsense" in bad.json()["detail"] and "dr_final" in bad.json()["detail"]
    assert http.get("/studies/nope/plots/dr_final").status_code == 404


def test_two_varied_parameters_plot_as_a_heat_map(grid_study, done_study, http):
    sid = grid_study["id"]
    assert grid_study["parameters"] == ["n_targets", "rf_noise_db"] and grid_study["points_total"] == 4
    png = http.get(f"/studies/{sid}/plots/dr_final")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    svg = http.get(f"/studies/{sid}/plots/decision_median_s", params={"format": "svg"})
    assert svg.status_code == 200 and svg.headers["content-type"].startswith("image/svg+xml")
    assert b"<image" in svg.content  # the heat map's raster (a line plot has none)
    line = http.get(f"/studies/{done_study['id']}/plots/dr_final", params={"format": "svg"})  # one parameter
    assert line.status_code == 200 and b"<image" not in line.content


def test_a_study_with_stop_confidence_reports_decisions_in_its_rows(grid_study, http):
    res = http.get(f"/studies/{grid_study['id']}/results").json()
    assert res["stop_confidence"] == 0.9 and len(res["rows"]) == 4
    for row in res["rows"]:
        campaign = http.get(f"/campaigns/{row['campaign_id']}").json()
        assert campaign["stop_confidence"] == 0.9
        decision = http.get(f"/campaigns/{row['campaign_id']}/results").json()["algorithms"]["ra2vipas"]["decision"]
        assert row["decision_accuracy"] == decision["accuracy"] and row["decision_undecided"] == decision["undecided"]
        assert [row["decision_accuracy_ci95_lo"], row["decision_accuracy_ci95_hi"]] == decision["accuracy_ci95"]
        assert row["decision_median_s"] == decision["median_s"]
    text = http.get(f"/studies/{grid_study['id']}/results", params={"format": "csv"}).text
    rows = list(csv.DictReader(io.StringIO(text)))
    assert {r["stop_confidence"] for r in rows} == {"0.9"}
    assert [float(r["decision_accuracy"]) for r in rows] == [r["decision_accuracy"] for r in res["rows"]]


def test_a_study_in_realtime_mode_runs_its_points_in_realtime(grid_study, live, http):
    """Each point is a realtime campaign; its latency percentiles (reduced as the episodes
    stream past: reduce.LatencyTally) are numpy's over every latency its episodes recorded."""
    res = http.get(f"/studies/{grid_study['id']}/results").json()
    assert grid_study["mode"] == res["mode"] == "realtime"
    for point in grid_study["points"]:
        cid = point["campaign_id"]
        assert http.get(f"/campaigns/{cid}").json()["mode"] == "realtime"
        latency = http.get(f"/campaigns/{cid}/results").json()["latency_ms"]  # only a realtime campaign has one
        with sqlite3.connect(live.db_path) as db:
            stored = db.execute("SELECT latencies FROM episodes WHERE campaign_id=?", (cid,)).fetchall()
        recorded = [v for (text,) in stored for v in json.loads(text)]
        assert recorded and latency == {"p50": round(float(np.percentile(recorded, 50)), 4),
                                        "p99": round(float(np.percentile(recorded, 99)), 4)}


def test_studies_come_in_pages_newest_first(done_study, grid_study, http):
    everything = http.get("/studies", params={"limit": 100}).json()
    ids = [s["id"] for s in everything["items"]]
    assert everything["total"] == len(ids) >= 2 and everything["limit"] == 100 and everything["offset"] == 0
    assert {grid_study["id"], done_study["id"]} <= set(ids)
    created = [s["created_at"] for s in everything["items"]]
    assert created == sorted(created, reverse=True)  # newest first
    pages = [http.get("/studies", params={"limit": 1, "offset": k}).json() for k in range(len(ids))]
    assert [p["items"][0]["id"] for p in pages] == ids
    assert all(p["total"] == len(ids) and p["offset"] == k for k, p in enumerate(pages))
    two = http.get("/studies", params={"limit": 2, "offset": 1}).json()
    assert [s["id"] for s in two["items"]] == ids[1:3] and two["limit"] == 2
    past = http.get("/studies", params={"offset": len(ids)}).json()
    assert past["items"] == [] and past["total"] == len(ids)
    for bad in ({"limit": 0}, {"offset": -1}, {"limit": "x"}):
        r = http.get("/studies", params=bad)
        assert r.status_code == 422 and list(bad)[0] in r.json()["detail"], r.text


@pytest.mark.parametrize("vary, allowed", [
    ({"rf_noise_db": [2.0, -3.0]}, "rf_noise_db: expected a number in [0.0, 30.0], got -3.0"),
    ({"n_targets": [4, 0]}, "n_targets: expected an integer in [1, 500], got 0"),
    ({"fov_half_angle_deg": [10.0, 200.0]}, "fov_half_angle_deg: expected a number in (0.0, 180.0], got 200.0"),
    ({"antenna_model": ["db-gain", "dbgain"]}, "antenna_model: expected one of paper|db-gain, got 'dbgain'"),
])
def test_a_value_out_of_range_is_a_422_naming_the_allowed_range(http, vary, allowed):
    r = http.post("/studies", json={**BODY, "vary": vary})
    assert r.status_code == 422, r.text
    assert allowed in r.json()["detail"], r.json()["detail"]
    assert len(r.json()["detail"].splitlines()) == 1


def test_a_point_goes_with_its_study_and_a_finished_study_cannot_be_cancelled(done_study, http):
    cid = done_study["points"][0]["campaign_id"]
    r = http.delete(f"/campaigns/{cid}")
    assert r.status_code == 409 and done_study["id"] in r.json()["detail"]
    r = http.post(f"/studies/{done_study['id']}/cancel")
    assert r.status_code == 409 and "finished" in r.json()["detail"]


def test_delete_removes_the_study_its_points_and_their_tests(live, http):
    r = http.post("/studies", json={**BODY, "vary": {"rf_noise_db": [2.0, 4.0]}, "tests": 1, "algorithms": ["rapas"]})
    sid = r.json()["id"]
    s = wait_study(live, sid)
    cids = [p["campaign_id"] for p in s["points"]]
    assert http.delete(f"/studies/{sid}").status_code == 204
    assert http.get(f"/studies/{sid}").status_code == 404
    assert http.get(f"/studies/{sid}/results").status_code == 404
    assert all(http.get(f"/campaigns/{cid}").status_code == 404 for cid in cids)
    assert http.delete(f"/studies/{sid}").status_code == 404


@pytest.mark.parametrize("body, where, words", [
    ({"vary": {"n_target": [1, 2]}}, ["body", "vary", "n_target"], ["n_target", "n_targets"]),
    ({"vary": {"rf_noise_db": [1.0, -3.0]}}, ["body", "vary", "rf_noise_db"], ["rf_noise_db", "-3"]),
    ({"vary": {"n_targets": [4, 8]}, "overrides": {**BASE, "n_targets": 5}}, ["body", "vary", "n_targets"], ["both"]),
    ({"vary": {"n_targets": list(range(2, 19)), "rf_noise_db": [float(v) for v in range(1, 17)]}}, ["body", "vary"], ["272", "256"]),
    ({"vary": {"n_targets": [4, 4]}}, ["body", "vary", "n_targets"], ["twice"]),
    ({"vary": {"n_targets": [4]}, "preset": "nope"}, ["body", "preset"], ["nope"]),
    ({"vary": {"n_targets": list(range(2, 202))}, "tests": 10000}, ["body", "tests"], ["episodes"]),
])
def test_a_bad_grid_is_a_422_naming_the_parameter_and_nothing_is_stored(http, body, where, words):
    before = http.get("/studies").json()["total"]
    r = http.post("/studies", json={**BODY, **body})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert r.json()["errors"][0]["loc"][:len(where)] == where, r.json()
    for word in words:
        assert word in detail, detail
    assert http.get("/studies").json()["total"] == before


@pytest.mark.parametrize("body", [{"vary": {}}, {"vary": {"n_targets": []}}, {"vary": {"n_targets": [4]}, "tests": 0}, {"vary": {"x": {"a": 1}}}])
def test_a_malformed_body_is_a_422(http, body):
    r = http.post("/studies", json={**BODY, **body})
    assert r.status_code == 422 and r.json()["detail"]


def test_unknown_studies_are_404(http):
    for method, path in (("GET", "/studies/nope"), ("GET", "/studies/nope/results"), ("POST", "/studies/nope/cancel"),
                         ("DELETE", "/studies/nope")):
        r = http.request(method, path)
        assert r.status_code == 404 and "nope" in r.json()["detail"], (method, path, r.text)


def test_a_queued_study_has_no_rows_cannot_be_deleted_and_cancels(idle):
    with idle.client() as http:
        r = http.post("/studies", json={**BODY, "vary": {"n_targets": [4, 8, 12]}})
        sid = r.json()["id"]
        s = http.get(f"/studies/{sid}").json()
        assert s["status"] in ("queued", "training") and s["progress"]["pending"] == 18
        res = http.get(f"/studies/{sid}/results").json()
        assert res["rows"] == [] and res["partial"] is True
        assert http.get(f"/studies/{sid}/plots/dr_final").status_code == 409
        r = http.delete(f"/studies/{sid}")
        assert r.status_code == 409 and "cancel" in r.json()["detail"]
        s = http.post(f"/studies/{sid}/cancel").json()
        assert s["status"] == "cancelled" and all(p["status"] == "cancelled" for p in s["points"])
        assert http.delete(f"/studies/{sid}").status_code == 204


def test_state_changes_need_the_token(guarded):
    with guarded.client() as http:
        assert http.post("/studies", json=BODY).status_code == 401
        assert http.post("/studies/x/cancel").status_code == 401
        assert http.delete("/studies/x").status_code == 401
        assert http.get("/studies").status_code == 200


def test_points_are_interleaved_test_by_test(live):
    """Every point gets its first tests before any point gets its last: the scheduler hands
    episodes out by test index across the points (seen on the rig's control key, in the order
    it sends them; they may finish in another order: a point whose POD model the controller
    is still fetching starts later)."""
    handed_out: list[tuple[str, int]] = []
    handle = live.bus.subscribe(keys.episode_control("rig-1"), lambda _k, p: handed_out.append(_started(p)))
    try:
        with live.client() as http:
            r = http.post("/studies", json={**BODY, "vary": {"n_targets": [4, 6, 8]}, "tests": 4, "algorithms": ["rapas"]})
        s = wait_study(live, r.json()["id"])
    finally:
        handle.undeclare()
    assert s["status"] == "done"
    point_of = {p["campaign_id"]: p["point"] for p in s["points"]}
    order = [(cid, k) for cid, k in handed_out if cid in point_of]
    assert sorted(order) == sorted((cid, k) for cid in point_of for k in range(4)), order  # each once: no rerun
    last_first = max(i for i, (_, k) in enumerate(order) if k == 0)
    first_last = min(i for i, (_, k) in enumerate(order) if k == 3)
    assert last_first < first_last, order  # first come, first served would hand out point 0's test 3 before point 2's test 0


def _started(payload: bytes) -> tuple[str, int] | tuple[None, None]:
    msg = episode_control_adapter.validate_json(payload)
    return (msg.campaign_id, msg.test_index) if isinstance(msg, EpisodeStart) else (None, None)


def test_a_study_survives_a_restart_of_the_orchestrator(tmp_path):
    db = tmp_path / "restart.db"
    first = LiveAPI(db, rigs=(), learner=False).start()
    try:
        with first.client() as http:
            sid = http.post("/studies", json={**BODY, "tests": 2, "algorithms": ["rapas"]}).json()["id"]
    finally:
        first.stop()
    second = LiveAPI(db).start()
    try:
        s = wait_study(second, sid)
        assert s["status"] == "done" and s["progress"]["done"] == 4
        with second.client() as http:
            assert len(http.get(f"/studies/{sid}/results").json()["rows"]) == 2
    finally:
        second.stop()


def test_a_study_survives_a_restart_of_the_orchestrator_in_the_middle_of_running(tmp_path):
    """The first orchestrator records tests 0-1 of both points, then stops with tests 2-3 in
    flight on its rig (held there: they never finish) and test 4 pending; the second one
    resumes the study: every test is recorded once, and the results are those of the same
    study run in one go (every draw of test k depends only on (seed, k))."""
    db = tmp_path / "restart-running.db"
    body = {**BODY, "tests": 5, "algorithms": ["rapas"]}
    first = LiveAPI(db)
    controller = next(n for n in first.nodes if isinstance(n, ControllerNode))
    begin = controller._begin

    def held_from_test_2(episode_id: str, model) -> None:
        ep = controller.episodes.get(episode_id)
        if ep is None or ep.start.test_index < 2:
            begin(episode_id, model)

    controller._begin = held_from_test_2
    first.start()
    try:
        with first.client() as http:
            sid = http.post("/studies", json=body).json()["id"]
            deadline = time.monotonic() + 60
            while (s := http.get(f"/studies/{sid}").json())["progress"]["done"] < 4 or s["progress"]["running"] < 4:
                assert time.monotonic() < deadline, s
                time.sleep(0.05)
        assert s["status"] == "running" and s["progress"] == {"done": 4, "running": 4, "pending": 2, "total": 10}, s
    finally:
        first.stop()
    second = LiveAPI(db).start()
    try:
        s = wait_study(second, sid, timeout=60)
        assert s["status"] == "done" and s["progress"]["done"] == 10, s
        with second.client() as http:
            res = http.get(f"/studies/{sid}/results").json()
    finally:
        second.stop()
    with sqlite3.connect(db) as conn:
        recorded = conn.execute("SELECT campaign_id, test_index, COUNT(*) FROM episodes WHERE status='done'"
                                " GROUP BY campaign_id, test_index").fetchall()
    assert len(recorded) == 10 and all(n == 1 for *_, n in recorded)
    in_one_go = ra2vipas.study(body["vary"], preset="paper", overrides=BASE, tests=5, seed=body["seed"], algorithms=["rapas"])
    resumed = [{k: v for k, v in row.items() if k != "campaign_id"} for row in res["rows"]]
    expected = [{k: v for k, v in row.items() if k != "campaign_id"} for row in in_one_go["rows"]]
    assert resumed == expected, differences(resumed, expected)
