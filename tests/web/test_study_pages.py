"""The dashboard's studies pages without a browser: the list and the study page against the
REST API's study (same store), the plot's data against ``/studies/{id}/results``, links to the
points' campaigns and back, the exports, the live streams, the reliability diagram's data on a
campaign page, and the pure helpers (``data.study_table``, ``data.reliability_series``)."""

from __future__ import annotations

import html
import json
import re
import time

import pytest

from ra2vipas.services.orchestrator.dashboard import data
from tests.api.live import LiveAPI

BASE = {"steps": 20, "n_train": 200}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    server = LiveAPI(tmp_path_factory.mktemp("dash-studies") / "studies.db").start()
    yield server
    server.stop()


@pytest.fixture()
def http(live):
    with live.client() as client:
        yield client


def wait_study(http, sid: str, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        s = http.get(f"/studies/{sid}").json()
        if s["status"] in ("done", "failed", "cancelled"):
            return s
        time.sleep(0.1)
    raise AssertionError(f"study {sid} did not finish within {timeout} s")


@pytest.fixture(scope="module")
def study(live):
    """n_targets in (6, 10), 3 tests of Ra²ViPAS and RaPAS per point, done."""
    with live.client() as http:
        r = http.post("/studies", json={"overrides": BASE, "vary": {"n_targets": [6, 10]}, "algorithms": ["ra2vipas", "rapas"],
                                        "tests": 3, "seed": 5, "name": "pages study"})
        assert r.status_code == 201, r.text
        s = wait_study(http, r.json()["id"])
    assert s["status"] == "done"
    return s


def page_json(text: str, element_id: str):
    m = re.search(rf'<script type="application/json" id="{element_id}">(.*?)</script>', text, re.S)
    assert m, element_id
    return json.loads(m.group(1))


def test_studies_pages_answer_and_unknown_studies_are_404(http, study):
    sid = study["id"]
    listing = http.get("/ui/studies")
    assert listing.status_code == 200 and f'href="/ui/studies/{sid}"' in listing.text and "pages study" in listing.text
    assert f'id="study-{sid}" data-status="done"' in listing.text and "12/12" in listing.text  # episodes over both points
    assert f'href="/ui/studies/{sid}"' in http.get("/ui/studies?status=done").text
    assert f'href="/ui/studies/{sid}"' not in http.get("/ui/studies?status=running").text
    assert http.get("/ui/studies?status=bogus").status_code == 422
    missing = http.get("/ui/studies/nope")
    assert missing.status_code == 404 and "no study &#39;nope&#39;" in missing.text and missing.headers["content-type"].startswith("text/html")
    # every page's navigation links the studies list
    for path in ("/", "/ui/rigs", f"/ui/studies/{sid}"):
        assert '<a href="/ui/studies"' in http.get(path).text, path


def test_the_study_page_plots_the_rows_of_the_api_and_links_every_point(http, study):
    sid = study["id"]
    results = http.get(f"/studies/{sid}/results").json()
    text = http.get(f"/ui/studies/{sid}").text
    chart = page_json(text, "study-data")
    assert chart["parameters"] == ["n_targets"] and chart["vary"] == {"n_targets": [6, 10]}
    assert chart["algorithms"] == {"ra2vipas": "Ra²ViPAS", "rapas": "RaPAS"}
    api_rows = {(r["point"], r["algorithm"]): r for r in results["rows"]}
    assert {(r["point"], r["algorithm"]) for r in chart["rows"]} == set(api_rows) and len(api_rows) == 4
    for row in chart["rows"]:
        mine = api_rows[(row["point"], row["algorithm"])]
        for key in ("n_targets", "dr_final", "ci95_lo", "ci95_hi", "time_to_dr90_s", "tests"):
            assert row[key] == mine[key], key
    metrics = [m["key"] for m in chart["metrics"]]
    assert metrics[:2] == ["dr_final", "time_to_dr90_s"] and not [m for m in metrics if "ci95" in m]
    calibration = sorted(k for k in results["rows"][0] if k.startswith("calibration_"))
    assert calibration and set(calibration) <= set(metrics)  # the calibration fields the rows carry are offered
    # the metric selector offers the same list, the first selected by default
    options = re.findall(r'<option value="([^"]+)">', text.split('id="metric"')[1].split("</select>")[0])
    assert options == metrics
    # every point links its campaign; the table shows each row's final DR and interval
    for p in study["points"]:
        assert f'href="/ui/campaigns/{p["campaign_id"]}"' in text
    r0 = api_rows[(0, "rapas")]
    assert f"{r0['dr_final']:.3f} ({r0['ci95_lo']:.3f}–{r0['ci95_hi']:.3f})" in html.unescape(text)
    # exports: JSON, CSV and the plot as PNG and SVG
    exports = re.findall(r'href="(/studies/[^"]+)"', text)
    assert {f"/studies/{sid}/results", f"/studies/{sid}/results?format=csv", f"/studies/{sid}/plots/dr_final?format=png",
            f"/studies/{sid}/plots/dr_final?format=svg"} <= set(exports)
    for url in exports:
        assert http.get(url).status_code == 200, url
    assert 'id="delete-button"' in text and 'id="cancel-button"' not in text  # finished: delete, not cancel


def test_a_points_campaign_page_links_its_study_and_draws_the_reliability_bins(http, study):
    point = study["points"][1]
    results = http.get(f"/campaigns/{point['campaign_id']}/results").json()
    text = http.get(f"/ui/campaigns/{point['campaign_id']}").text
    assert f'<a href="/ui/studies/{study["id"]}" id="study-link">' in text and "point #1 of" in text
    bins = results["algorithms"]["ra2vipas"]["calibration"]["reliability"]
    shown = page_json(text, "reliability-data")["algorithms"]
    assert set(shown) == {"ra2vipas", "rapas"}
    assert shown["ra2vipas"]["n"] == [b["n"] for b in bins if b["n"]]
    assert shown["ra2vipas"]["confidence"] == [b["confidence"] for b in bins if b["n"]]
    assert shown["ra2vipas"]["accuracy"] == [b["accuracy"] for b in bins if b["n"]]
    assert shown["ra2vipas"]["ece"] == results["algorithms"]["ra2vipas"]["calibration"]["ece_final"]
    # a campaign that is no study's point has no such link
    other = http.post("/campaigns", json={"overrides": BASE, "tests": 1, "algorithms": ["rapas"]}).json()["id"]
    assert 'id="study-link"' not in http.get(f"/ui/campaigns/{other}").text


def test_the_live_stream_of_a_finished_study_sends_progress_and_results_then_ends(http, study):
    with http.stream("GET", f"/ui/studies/{study['id']}/live") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        body = r.read().decode()
    events = re.findall(r"^event: (\w+)$", body, re.M)
    assert events == ["progress", "results"]
    payloads = [json.loads(d) for d in re.findall(r"^data: (.*)$", body, re.M)]
    assert payloads[0]["status"] == "done" and payloads[0]["progress"]["done"] == 12 and len(payloads[0]["points"]) == 2
    assert {(r["point"], r["algorithm"]) for r in payloads[1]["chart"]["rows"]} == {(p, a) for p in (0, 1) for a in ("ra2vipas", "rapas")}
    assert 'id="points-table"' in payloads[1]["table"]


def test_the_studies_stream_sends_the_table_body(http, study):
    with http.stream("GET", "/ui/streams/studies") as r:
        lines = []
        for line in r.iter_lines():
            lines.append(line)
            if line == "" and any(x.startswith("data:") for x in lines):
                break
    assert lines[0] == "event: rows" and f'id="study-{study["id"]}"' in "\n".join(lines)


def test_a_running_study_is_cancelled_and_deleted_only_through_the_api_with_its_token(tmp_path):
    server = LiveAPI(tmp_path / "t.db", rigs=(), learner=False, token="study-secret-7").start()  # no rigs: it stays queued
    try:
        with server.client("study-secret-7") as http:
            sid = http.post("/studies", json={"overrides": BASE, "vary": {"n_targets": [6, 10]}, "tests": 2}).json()["id"]
        with server.client() as http:
            text = http.get(f"/ui/studies/{sid}").text
            assert "study-secret-7" not in text and '<meta name="ra2vipas-auth" content="required">' in text
            assert 'id="cancel-button"' in text and 'id="delete-button"' not in text and 'data-active="true"' in text
            assert "no test recorded yet" in text and "plot-exports\" hidden" in text  # no figure to export yet
            assert http.post(f"/studies/{sid}/cancel").status_code == 401  # the page's cancel goes through the API's check
    finally:
        server.stop()


def test_the_study_table_groups_rows_by_point_and_keeps_points_without_rows():
    points = [{"point": 0, "values": {"n_targets": 6}, "campaign_id": "a", "status": "done", "progress": {"done": 2, "total": 2}},
              {"point": 1, "values": {"n_targets": 10}, "campaign_id": "b", "status": "queued", "progress": {"done": 0, "total": 2}}]
    rows = [{"point": 0, "n_targets": 6, "algorithm": a, "tests": 2, "dr_final": v, "ci95_lo": 0.1, "ci95_hi": 0.9, "time_to_dr90_s": None,
             "in_fov_final": 1.0, "pod_r2": 0.8, "calibration_ece_final": 0.05} for a, v in (("ra2vipas", 0.5), ("rapas", 1.0))]
    table = data.study_table(points, {"rows": rows, "parameters": ["n_targets"], "algorithms": ["ra2vipas", "rapas"]})
    assert table["columns"][:2] == ["final DR (95 % CI)", "t(DR ≥ 0.9) [s]"] and "ECE (final)" in table["columns"]
    assert "decision accuracy" not in table["columns"]  # no row has it
    first, second = table["groups"]
    assert [r["label"] for r in first["rows"]] == ["Ra²ViPAS", "RaPAS"] and first["rows"][0]["cells"][:2] == ["0.500 (0.100–0.900)", "—"]
    assert second["rows"] == [] and second["campaign_id"] == "b"


def test_reliability_series_keeps_non_empty_bins_and_is_none_without_calibration():
    bins = [{"lo": 0.0, "hi": 0.5, "n": 0, "confidence": None, "accuracy": None},
            {"lo": 0.5, "hi": 1.0, "n": 4, "confidence": 0.8, "accuracy": 0.75}]
    series = data.reliability_series({"algorithms": {"ra2vipas": {"calibration": {"ece_final": 0.05, "reliability": bins}},
                                                     "sweep": {"dr_final": 1.0}}})
    assert series == {"algorithms": {"ra2vipas": {"label": "Ra²ViPAS", "color": "#1f6fb4", "ece": 0.05, "confidence": [0.8],
                                                  "accuracy": [0.75], "n": [4]}}}
    assert data.reliability_series({"algorithms": {"rapas": {"dr_final": 1.0}}}) is None
