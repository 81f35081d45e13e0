"""The dashboard's server side without a browser: its data against the REST API's (same
store, same campaign), the growing DR curves against the final results, the generic summary,
the pages' status codes, the static files, and that no dashboard route enters the OpenAPI
schema (the API's contract and its Schemathesis run stay as they were)."""

from __future__ import annotations

import gzip

import httpx
import pytest

from ra2vipas.services.orchestrator.dashboard import data
from ra2vipas.services.orchestrator.dashboard.routes import ASSET_VERSION, STATIC
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.sensors.node import simulated_descriptor
from tests.api.live import SMALL, LiveAPI


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    server = LiveAPI(tmp_path_factory.mktemp("dash") / "dash.db").start()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def campaign(live):
    """12 tests of Ra²ViPAS and RaPAS on a small scenario, done."""
    with live.client() as http:
        r = http.post("/campaigns", json={"overrides": {**SMALL, "n_targets": 12}, "algorithms": ["ra2vipas", "rapas"], "tests": 12,
                                          "seed": 11, "name": "pages"})
    assert r.status_code == 201
    c = live.wait(r.json()["id"])
    assert c["status"] == "done"
    return c


@pytest.fixture()
def http(live):
    with live.client() as client:
        yield client


def test_no_dashboard_route_is_in_the_openapi_schema(http):
    paths = http.get("/openapi.json").json()["paths"]
    assert not [p for p in paths if p == "/" or p.startswith("/ui")]


def test_every_page_answers_and_unknown_campaigns_are_404(http, campaign):
    cid = campaign["id"]
    for path in ("/", "/?status=done&preset=paper", f"/ui/campaigns/{cid}", f"/ui/campaigns/{cid}/tests?missed=true",
                 f"/ui/campaigns/{cid}/tests/3/rapas", "/ui/rigs", "/ui/new", "/ui/new?preset=dynamic",
                 "/ui/new/parameters?preset=paper-uniform"):
        r = http.get(path)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html"), path
    missing = http.get("/ui/campaigns/nope")
    assert missing.status_code == 404 and "no campaign &#39;nope&#39;" in missing.text and missing.headers["content-type"].startswith("text/html")
    assert http.get(f"/ui/campaigns/{cid}/tests/99/rapas").status_code == 404
    assert http.get(f"/ui/campaigns/{cid}/tests/0/ravipas").status_code == 404  # not one of its algorithms
    assert http.get("/?status=bogus").status_code == 422


def test_pages_forbid_framing_inline_scripts_and_other_origins(http, campaign):
    """Issue 18: the pages sent no Content-Security-Policy or X-Frame-Options. Every page, its
    fragments, errors and the API's JSON carry both; the pages themselves have no inline script
    or style attribute for the policy to block (the browser tests fail on any CSP report)."""
    import re

    cid = campaign["id"]
    for path in ("/", f"/ui/campaigns/{cid}", f"/ui/campaigns/{cid}/tests/3/rapas", "/ui/rigs", "/ui/new", "/ui/studies",
                 "/ui/campaigns/nope", "/campaigns", "/health", "/static/app.js"):
        r = http.get(path)
        csp = r.headers.get("content-security-policy", "")
        assert "frame-ancestors 'none'" in csp and "script-src 'self';" in csp and "style-src 'self';" in csp, (path, csp)
        assert "unsafe-inline" not in csp and "unsafe-eval" not in csp, path
        assert r.headers.get("x-frame-options") == "DENY" and r.headers.get("x-content-type-options") == "nosniff", path
        if r.headers["content-type"].startswith("text/html"):
            assert not re.search(r"<script(?![^>]*\bsrc=)(?![^>]*application/json)[^>]*>", r.text), path  # inline code
            assert not re.search(r"\son[a-z]+=|\sstyle=", r.text), path  # inline handlers and style attributes
    assert "frame-ancestors 'none'" in http.get("/docs").headers["content-security-policy"]  # its own, looser policy


def test_the_test_table_pages_filters_and_sorts_like_the_api(live, campaign):
    cid = campaign["id"]
    store = live.app.state.store
    with live.client() as http:
        outcomes = http.get(f"/campaigns/{cid}/tests", params={"limit": 200}).json()["items"]
    by = {(o["test_index"], o["algorithm"]): o for o in outcomes}
    missed = sorted(k for (k, a), o in by.items() if a == "ra2vipas" and not o["final_hit"])
    rows, total = store.test_page(cid, missed_by="ra2vipas", limit=50)
    assert total == len(missed) and sorted({r["test_index"] for r in rows}) == missed
    grouped = data.test_rows(rows, ["ra2vipas", "rapas"], campaign["scenario"]["rf_period_s"])
    for t in grouped:  # both algorithms of each missed test, as the API reports them
        for cell in t["cells"]:
            api = by[(t["test_index"], cell.algorithm)]
            assert cell.final_hit == api["final_hit"] and cell.final_choice == api["final_choice"]
    # pages of 5 tests cover the 12 in order; sorting by confidence orders the final confidences
    seen = []
    for offset in (0, 5, 10):
        rows, total = store.test_page(cid, limit=5, offset=offset)
        assert total == 12
        seen += sorted({r["test_index"] for r in rows})
    assert seen == list(range(12))
    rows, _ = store.test_page(cid, sort="confidence", sort_algorithm="rapas", descending=True, limit=50)
    order = [t["test_index"] for t in data.test_rows(rows, ["ra2vipas", "rapas"], 0.1)]
    confidences = [by[(k, "rapas")]["final_confidence"] for k in order]
    assert confidences == sorted(confidences, reverse=True) and len(order) == 12


def test_the_growing_curves_end_equal_to_the_results(live, campaign):
    """Read incrementally in chunks of 5 episodes, the live DR and Wilson bands of a finished
    campaign are the results object's, step for step."""
    cid = campaign["id"]
    with live.client() as http:
        results = http.get(f"/campaigns/{cid}/results").json()
    live_dr = data.LiveDR(cid, ["ra2vipas", "rapas"], results["scenario"]["steps"], results["scenario"]["rf_period_s"])
    assert live_dr.update(live.app.state.store, chunk=5) == 24
    assert live_dr.update(live.app.state.store, chunk=5) == 0  # each episode is read once
    snap = live_dr.snapshot()
    for name, block in results["algorithms"].items():
        assert snap["algorithms"][name]["n"] == 12
        assert snap["algorithms"][name]["dr"] == pytest.approx(block["dr"], abs=1e-6)
        assert snap["algorithms"][name]["lo"] == pytest.approx([b[0] for b in block["dr_ci95"]], abs=1e-6)
        assert snap["algorithms"][name]["hi"] == pytest.approx([b[1] for b in block["dr_ci95"]], abs=1e-6)
    assert snap == {**data.dr_curves(results), "algorithms": {n: {**a, "n": 12} for n, a in snap["algorithms"].items()}}


def test_the_live_stream_sends_curves_and_progress_then_ends(http, campaign):
    with http.stream("GET", f"/ui/campaigns/{campaign['id']}/live") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        body = r.read().decode()
    events = [line.split(": ", 1)[1] for line in body.splitlines() if line.startswith("event: ")]
    assert events == ["curves", "progress"]


def test_curves_of_a_long_campaign_are_subsampled_with_the_last_step_kept():
    keep = data.subsample(10_000, 600)
    assert len(keep) <= 600 and keep[0] == 0 and keep[-1] == 9_999 and list(keep) == sorted(set(keep))
    assert list(data.subsample(120)) == list(range(120))


def test_the_summary_shows_known_fields_then_passes_unknown_ones_through():
    block = {"dr": [0.5, 1.0], "dr_final": 1.0, "ci95": [0.8, 1.0], "dr_ci95": [[0, 1], [0.8, 1.0]], "time_to_dr90_s": 0.2,
             "in_fov_final": 1.0, "calibration": {"ece_final": 0.05, "ece_all": 0.1, "reliability": [{"lo": 0}]},
             "brand_new": 0.123456, "nested": {"thing": 7}}
    table = data.summary_table({"algorithms": {"ra2vipas": block, "rapas": {**block, "brand_new": None}}})
    assert table["keys"][:4] == ["dr_final", "ci95", "time_to_dr90_s", "in_fov_final"]
    assert "calibration.ece_final" in table["keys"] and "decision.accuracy" not in table["keys"]
    assert table["keys"][-2:] == ["brand_new", "nested.thing"] and "calibration.reliability" not in table["keys"]
    ra2vipas = table["rows"][0]["cells"]
    assert ra2vipas[table["keys"].index("ci95")] == "0.800–1.000" and ra2vipas[table["keys"].index("brand_new")] == "0.123"
    assert table["rows"][1]["cells"][table["keys"].index("brand_new")] == "—"


def test_the_scenario_table_marks_what_differs_from_the_preset(campaign):
    rows = {r["name"]: r for r in data.scenario_rows(campaign["preset"], campaign["scenario"], campaign["overrides"])}
    assert {n for n, r in rows.items() if r["changed"]} == {"steps", "n_train", "n_targets"}
    assert rows["n_targets"]["value"] == 12 and rows["n_targets"]["preset_value"] == 20
    dynamic = data.scenario_rows("paper", {**campaign["scenario"], "steps": 120, "n_train": 900, "n_targets": 20}, {})
    assert not [r for r in dynamic if r["changed"]]


def test_the_form_inputs_carry_the_models_bounds():
    inputs = {p["name"]: p for p in data.parameter_inputs("paper")}
    assert inputs["n_targets"] | {} == {**inputs["n_targets"], "kind": "int", "min": 1, "max": 500, "min_open": False}
    assert inputs["rf_period_s"]["min"] == 0.0 and inputs["rf_period_s"]["min_open"] is True
    assert inputs["placement"]["kind"] == "enum" and set(inputs["placement"]["options"]) == {"reference", "uniform"}
    assert data.parameter_inputs("dynamic")[[p["name"] for p in data.parameter_inputs("dynamic")].index("clutter_rate")]["value"] == 0.3


def test_the_pod_data_follows_the_stored_model(http, live, campaign):
    body = http.get(f"/ui/campaigns/{campaign['id']}/pod.json").json()
    model = live.app.state.store.pod_artifacts(campaign["id"])["model"]
    assert body["ready"] and body["grid"] == pytest.approx(model["rssi_grid_dbm"], abs=1e-4)
    assert all(0 <= lo <= m <= hi <= 1 for lo, m, hi in zip(body["lo"], body["mean"], body["hi"]))
    assert body["samples"]["n"] == campaign["scenario"]["n_train"] and body["r2"] == campaign["pod"]["r2"]


def test_static_files_are_versioned_cached_and_compressed(http):
    page = http.get("/ui/new").text
    assert f"/ui/static/app.js?v={ASSET_VERSION}" in page and "cdn" not in page.lower()
    r = http.get(f"/ui/static/vendor/uPlot-1.6.32.iife.min.js?v={ASSET_VERSION}", headers={"Accept-Encoding": "gzip"})
    assert r.status_code == 200 and r.headers["content-encoding"] == "gzip" and "immutable" in r.headers["cache-control"]
    with httpx.stream("GET", f"{http.base_url}/ui/static/vendor/uPlot-1.6.32.iife.min.js", headers={"Accept-Encoding": "gzip"}) as s:
        raw = b"".join(s.iter_raw())  # the bytes on the wire
    assert len(raw) < (STATIC / "vendor/uPlot-1.6.32.iife.min.js").stat().st_size / 2
    assert gzip.decompress(raw) == (STATIC / "vendor/uPlot-1.6.32.iife.min.js").read_bytes()
    licenses = (STATIC / "vendor/LICENSES.txt").read_text()
    for name in ("htmx.org 2.0.11", "htmx-ext-sse 2.2.4", "uplot 1.6.32", "Leon Sorokin", "Zero-Clause BSD"):
        assert name in licenses


def test_warnings_and_the_scenarios_assumptions_are_shown_on_the_campaign_page_and_marked_on_home(tmp_path):
    """The issue's silent DR 0.00 case, small: a v1 rig (no descriptor) whose antenna is, unknown
    to everyone, a dB-gain one, run under the paper model. The results carry a warning and the
    scenario's assumptions; the campaign page shows both above the curves, and its row on the
    home page links to them. A campaign without either shows no such box."""
    from markupsafe import escape  # as the templates escape

    hidden = {"descriptor": simulated_descriptor("hidden-1", rx_dir={"model": "db-gain"}), "describe": False}
    server = LiveAPI(tmp_path / "w.db", rigs=("hidden-1",), sensors={"hidden-1": hidden}).start()
    try:
        server.settle()
        with server.client() as http:
            r = http.post("/campaigns", json={"overrides": {**SMALL, "steps": 30}, "algorithms": ["rapas"], "tests": 3, "seed": 4,
                                              "name": "warned"})
            assert r.status_code == 201, r.text
            cid = r.json()["id"]
            assert server.wait(cid)["status"] == "done"
            results = http.get(f"/campaigns/{cid}/results").json()
            assert results["warnings"] and results["assumptions"]["rigs"] == ["hidden-1"]
            page = http.get(f"/ui/campaigns/{cid}").text
            box = page[page.index('id="warnings"'):page.index('id="progress-title"')]  # above the progress and the curves
            for warning in results["warnings"]:
                assert str(escape(warning)) in box
            assert "3 of 3 episodes</strong>" in box and "(rig <code>hidden-1</code>): these episodes ran on undescribed rigs" in box
            row = http.get("/").text
            row = row[row.index(f'id="campaign-{cid}"'):]
            row = row[:row.index("</tr>")]
            assert f'href="/ui/campaigns/{cid}#warnings"' in row and "⚠ 1 warning<" in row
            clean = http.post("/campaigns", json={"overrides": SMALL, "algorithms": ["ravipas"], "tests": 1, "seed": 4}).json()["id"]
            assert server.wait(clean)["status"] == "done"
            assert "warnings" not in http.get(f"/campaigns/{clean}/results").json()
            # ... but still assumptions: the only rig is undescribed
            page = http.get(f"/ui/campaigns/{clean}").text
            assert 'id="warnings-list"' not in page and "Scored under the scenario's assumptions</h2>" in page
    finally:
        server.stop()


def test_the_home_page_pages_and_filters_by_preset_server_side(tmp_path):
    """57 campaigns (55 paper, then 2 dynamic; no rig, so they stay queued): pages of 50, newest
    first, with previous/next links; the live table's stream serves the same page; the preset
    filter keeps the dynamic ones only."""
    import re

    server = LiveAPI(tmp_path / "p.db", rigs=(), learner=False).start()
    try:
        with server.client() as http:
            names = [f"page-{k:02d}" for k in range(57)]
            for k, name in enumerate(names):
                r = http.post("/campaigns", json={"preset": "dynamic" if k >= 55 else "paper", "overrides": SMALL, "tests": 1,
                                                  "algorithms": ["rapas"], "name": name})
                assert r.status_code == 201, r.text

            def rows(text: str) -> list[str]:
                return re.findall(r'<tr id="campaign-[0-9a-f]+"[^>]*>\s*<td><a href="[^"]+">(page-\d\d)</a>', text)

            first = http.get("/").text
            assert rows(first) == names[::-1][:50] and "1–50 of 57" in first
            assert 'href="/?status=&amp;preset=&amp;offset=50" rel="next"' in first and 'rel="prev"' not in first
            second = http.get("/", params={"status": "", "preset": "", "offset": 50}).text
            assert rows(second) == names[::-1][50:] and "51–57 of 57" in second
            assert 'href="/?status=&amp;preset=&amp;offset=0" rel="prev"' in second and 'rel="next"' not in second
            assert 'sse-connect="/ui/streams/campaigns?status=&amp;preset=&amp;offset=50"' in second  # the live table keeps its page
            with http.stream("GET", "/ui/streams/campaigns", params={"offset": 50}) as stream:
                event = []
                for line in stream.iter_lines():
                    if not line and event:
                        break
                    event.append(line)
            assert event[0] == "event: rows" and rows("\n".join(line[6:] for line in event[1:])) == names[::-1][50:]
            dynamic = http.get("/", params={"preset": "dynamic"}).text
            assert rows(dynamic) == ["page-56", "page-55"] and "1–2 of 2" in dynamic
            assert '<option value="dynamic" selected>' in dynamic
    finally:
        server.stop()


def test_the_token_is_never_rendered_into_a_page(tmp_path):
    server = LiveAPI(tmp_path / "t.db", rigs=(), learner=False, token="page-secret-91").start()
    try:
        with server.client() as http:
            for path in ("/", "/ui/new", "/ui/rigs"):
                text = http.get(path).text
                assert "page-secret-91" not in text and '<meta name="ra2vipas-auth" content="required">' in text
            assert http.post("/campaigns", json={"tests": 1}).status_code == 401  # the page's actions go through the API's check
    finally:
        server.stop()


def test_a_store_without_the_campaign_has_no_tests(tmp_path):
    store = Store(str(tmp_path / "empty.db"))
    try:
        assert store.test_page("missing") == ([], 0) and store.done_hits("missing") == []
        with pytest.raises(ValueError):
            store.test_page("missing", sort="name; DROP TABLE campaigns")
    finally:
        store.close()
