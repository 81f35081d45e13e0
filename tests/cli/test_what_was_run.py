"""Results carry what was run (issue 13): the overrides in the results object, `campaign list`
and its --name filter, the DR table's title, the CSV tables, `results --algorithm` without
--per-test, and `campaign plot ID1 ID2 --label PARAM` overlaying campaigns."""

from __future__ import annotations

import csv
import io
import json

import pytest

from tests.api.live import SMALL
from tests.cli.conftest import one_error_line, ra2vipas


def last_json(stdout: str):
    return json.loads(stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def crowd(live):
    """Two small finished campaigns that differ in n_targets, named."""
    ids = []
    with live.client() as http:
        for n in (5, 9):
            body = {"preset": "paper", "overrides": {**SMALL, "n_targets": n}, "algorithms": ["rapas"], "tests": 2, "seed": 4,
                    "name": f"crowd-{n}"}
            r = http.post("/campaigns", json=body)
            assert r.status_code == 201, r.text
            ids.append(r.json()["id"])
    for cid in ids:
        assert live.wait(cid)["status"] == "done"
    return ids


def test_list_shows_the_overrides_and_filters_by_name(live, crowd):
    table = ra2vipas("campaign", "list", "--api", live.url, "--name", "crowd-9")
    assert table.returncode == 0, table.stderr
    assert crowd[1] in table.stdout and crowd[0] not in table.stdout
    assert "n_targets=9" in table.stdout and "overrides" in table.stdout
    page = last_json(ra2vipas("campaign", "list", "--api", live.url, "--name", "crowd-5", "--json").stdout)
    assert [c["id"] for c in page["items"]] == [crowd[0]] and page["items"][0]["overrides"]["n_targets"] == 5
    nothing = last_json(ra2vipas("campaign", "list", "--api", live.url, "--name", "crowd", "--json").stdout)
    assert nothing["total"] == 0  # exactly this name


def test_the_results_say_what_was_run(live, crowd):
    results = last_json(ra2vipas("campaign", "results", crowd[1], "--api", live.url, "--json").stdout)
    assert results["overrides"] == {**SMALL, "n_targets": 9}
    table = ra2vipas("campaign", "results", crowd[1], "--api", live.url)
    assert table.returncode == 0, table.stderr
    assert "n_targets=9" in table.stdout


def test_results_algorithm_filters_the_dr_table_without_per_test(live, done_campaign):
    cid = done_campaign["id"]
    only = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--algorithm", "rapas", "--json").stdout)
    assert list(only["algorithms"]) == ["rapas"]
    table = ra2vipas("campaign", "results", cid, "--api", live.url, "--algorithm", "rapas")
    assert table.returncode == 0 and "rapas" in table.stdout and "ra2vipas " not in table.stdout.replace("Ra²ViPAS", "")
    bad = ra2vipas("campaign", "results", cid, "--api", live.url, "--algorithm", "magic")
    assert bad.returncode == 2 and "--algorithm must be one of" in one_error_line(bad)


def test_per_test_hit_and_miss(live, done_campaign):
    cid = done_campaign["id"]
    every = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--per-test", "--json").stdout)
    hits = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--per-test", "--hit", "--json").stdout)
    misses = last_json(ra2vipas("campaign", "results", cid, "--api", live.url, "--per-test", "--miss", "--json").stdout)
    assert hits["total"] + misses["total"] == every["total"]
    assert all(o["final_hit"] for o in hits["items"]) and not any(o["final_hit"] for o in misses["items"])
    lost = ra2vipas("campaign", "results", cid, "--api", live.url, "--miss")
    assert lost.returncode == 2 and "add --per-test" in one_error_line(lost)


def test_export_the_tidy_dr_table_and_the_summary_table(live, crowd, tmp_path):
    dr = tmp_path / "dr.csv"
    summary = tmp_path / "summary.csv"
    assert ra2vipas("campaign", "export", crowd[0], "--api", live.url, "-o", str(dr)).returncode == 0
    assert ra2vipas("campaign", "export", crowd[0], "--api", live.url, "--table", "summary", "-o", str(summary)).returncode == 0
    rows = list(csv.DictReader(io.StringIO(dr.read_text())))
    assert len(rows) == SMALL["steps"] and {r["n_targets"] for r in rows} == {"5"} and {r["name"] for r in rows} == {"crowd-5"}
    assert [r["step"] for r in rows] == [str(k) for k in range(1, SMALL["steps"] + 1)]
    (row,) = csv.DictReader(io.StringIO(summary.read_text()))
    assert row["campaign_id"] == crowd[0] and row["algorithm"] == "rapas" and row["n_targets"] == "5"
    assert float(row["dr_final"]) == float(rows[-1]["dr"])
    bad = ra2vipas("campaign", "export", crowd[0], "--api", live.url, "--table", "summary")
    assert bad.returncode == 2 and "--format csv" in one_error_line(bad)


def test_plot_overlays_campaigns_labelled_by_a_parameter(live, crowd, tmp_path):
    out = tmp_path / "crowd.svg"
    proc = ra2vipas("campaign", "plot", *crowd, "--label", "n_targets", "--api", live.url, "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "dr plot of 2 campaigns written to" in proc.stdout and b"<svg" in out.read_bytes()[:500]
    near = ra2vipas("campaign", "plot", *crowd, "--label", "n_target", "--api", live.url, "-o", str(out))
    assert near.returncode == 2 and "did you mean 'n_targets'?" in one_error_line(near)
    kind = ra2vipas("campaign", "plot", *crowd, "--kind", "pod", "--api", live.url, "-o", str(out))
    assert kind.returncode == 2 and "overlay DR curves" in one_error_line(kind)


def test_overlay_labels_and_titles_name_what_was_run():
    from ra2vipas.cli.campaign import label_value
    from ra2vipas.services.orchestrator.plots import dr_figure, overlay_figure, run_title

    results = {"preset": "paper", "overrides": {"n_targets": 30, "antenna_model": "db-gain"}, "tests": 50, "seed": 1,
               "scenario": {"rf_period_s": 0.1, "n_targets": 30}, "pod": {"r2": 0.9},
               "algorithms": {"rapas": {"dr": [0.5, 0.75], "dr_final": 0.75, "dr_ci95": [[0.4, 0.6], [0.6, 0.8]]}}}
    assert run_title(results) == "paper, n_targets=30, antenna_model=db-gain: 50 tests, seed 1"
    assert run_title(results, "crowd") == "crowd — paper, n_targets=30, antenna_model=db-gain: 50 tests, seed 1"
    partial = {**results, "partial": True, "tests_recorded": {"rapas": 17}}
    assert run_title(partial) == "paper, n_targets=30, antenna_model=db-gain: partial: 17 of 50 tests, seed 1"
    assert dr_figure(results, "crowd").axes[0].get_title().startswith("crowd — paper, n_targets=30")
    campaign = {"id": "abc", "name": "crowd"}
    assert label_value("n_targets", campaign, results) == "n_targets=30"
    assert label_value("seed", campaign, results) == "seed 1" and label_value("name", campaign, results) == "crowd"
    fig = overlay_figure([("n_targets=30", results), ("n_targets=10", results)], "DR_t by n_targets")
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == [
        "n_targets=30, RaPAS (final 0.750)", "n_targets=10, RaPAS (final 0.750)"]
