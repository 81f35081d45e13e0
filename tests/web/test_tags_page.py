"""A campaign with several tags through the REST API and the dashboard (issue 21): the results
carry every tag, the summary CSV its columns, the DR plot draws, and the campaign page shows the
per-tag table."""

from __future__ import annotations

import io

import pandas as pd

from ra2vipas.services.orchestrator.dashboard import data
from tests.api.live import SMALL, LiveAPI


def test_a_two_tag_campaign_is_reported_per_tag_by_the_api_and_the_page(tmp_path):
    server = LiveAPI(tmp_path / "tags.db").start()
    try:
        with server.client() as http:
            r = http.post("/campaigns", json={"overrides": {**SMALL, "n_tags": 2}, "algorithms": ["ra2vipas", "ra2vipas-seq"],
                                              "tests": 3, "seed": 2, "stop_confidence": 0.9})
            assert r.status_code == 201, r.text
            cid = r.json()["id"]
            assert server.wait(cid)["status"] == "done"
            results = http.get(f"/campaigns/{cid}/results").json()
            for name in ("ra2vipas", "ra2vipas-seq"):
                assert len(results["algorithms"][name]["tags"]["per_tag"]) == 2
            summary = pd.read_csv(io.StringIO(http.get(f"/campaigns/{cid}/results", params={"format": "csv", "table": "summary"}).text))
            assert list(summary.tag1_dr_final) == [results["algorithms"][n]["tags"]["per_tag"][1]["dr_final"] for n in summary.algorithm]
            png = http.get(f"/campaigns/{cid}/plots/dr", params={"format": "png"}, timeout=60)
            assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
            page = http.get(f"/ui/campaigns/{cid}").text
            assert 'id="tags-table"' in page and "all (mean per tag" in page
    finally:
        server.stop()


def test_the_per_tag_table_has_a_row_per_tag_and_one_for_all_found():
    tag = {"dr": [1.0], "dr_final": 0.75, "ci95": [0.5, 0.9], "dr_ci95": [[0.5, 0.9]], "time_to_dr90_s": None, "in_fov_final": 1.0,
           "calibration": {"ece_final": 0.04}, "decision": {"median_s": 1.25}}
    tags = {"per_tag": [tag, {**tag, "dr_final": 0.5}], "mean_tag_dr_final": 0.625, "all_found": tag, "all_decided": {"median_s": 2.5}}
    table = data.tags_table({"algorithms": {"ra2vipas": {"tags": tags}, "rapas": {"dr": [1.0]}}})
    assert [(r["tag"], r["cells"][0]) for r in table["rows"]] == [("0", "0.750"), ("1", "0.500"), ("all (mean per tag 0.625)", "0.750")]
    assert table["rows"][0]["cells"][3:] == ["0.040", "1.25"] and table["rows"][-1]["cells"][4] == "2.50"
    assert data.tags_table({"algorithms": {"rapas": {"dr": [1.0]}}}) is None
    summary = data.summary_table({"algorithms": {"ra2vipas": {"dr_final": 0.75, "tags": tags}}})
    assert not [k for k in summary["keys"] if k.startswith("tags.")]  # shown in the per-tag table, not as summary columns
