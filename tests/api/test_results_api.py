"""Reading a finished campaign: results as JSON and CSV (reproducible from the file alone),
the per-test outcome table and trace, and the figures as PNG and SVG."""

from __future__ import annotations

import math

import pytest

from ra2vipas.services.orchestrator.api.export import read_results_csv
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol.scenario import Scenario

PNG = b"\x89PNG\r\n\x1a\n"


def test_results_carry_dr_curves_with_wilson_bands(http, done_campaign):
    r = http.get(f"/campaigns/{done_campaign['id']}/results")
    assert r.status_code == 200 and r.headers["content-type"] == "application/json"
    res = r.json()
    assert res["preset"] == "paper" and res["seed"] == 3 and res["tests"] == 3
    assert res["scenario"] == done_campaign["scenario"]
    assert list(res["algorithms"]) == ["ra2vipas", "rapas"]
    assert "latency_ms" not in res  # fast mode: absent, not null (the same object as `simulate --json`)
    steps = res["scenario"]["steps"]
    for block in res["algorithms"].values():
        assert len(block["dr"]) == len(block["dr_ci95"]) == steps
        assert all(lo <= dr <= hi for dr, (lo, hi) in zip(block["dr"], block["dr_ci95"]))
        assert block["dr_final"] == block["dr"][-1] and block["ci95"] == block["dr_ci95"][-1]
        assert set(block) == {"dr", "dr_final", "ci95", "dr_ci95", "time_to_dr90_s", "in_fov_final", "calibration"}
        assert set(block["calibration"]) == {"ece_final", "ece_final_floor", "ece_all", "confidence_final", "reliability"}
        assert 0.0 <= block["calibration"]["ece_final_floor"] <= 1.0
        assert 0.0 <= block["calibration"]["ece_final"] <= 1.0


def test_csv_export_by_query_or_accept_reproduces_the_campaign_from_the_file_alone(http, done_campaign):
    cid = done_campaign["id"]
    by_query = http.get(f"/campaigns/{cid}/results", params={"format": "csv"})
    by_accept = http.get(f"/campaigns/{cid}/results", headers={"Accept": "text/csv"})
    assert by_query.status_code == by_accept.status_code == 200
    assert by_query.headers["content-type"].startswith("text/csv")
    assert by_query.text == by_accept.text
    lines = by_query.text.splitlines()
    overridden = list(done_campaign["overrides"])
    # tidy: one header row, no comment lines; what was run leads every row, the overrides as columns
    assert lines[0] == ",".join(["campaign_id", "name", "preset", "seed", "tests", *overridden,
                                 "algorithm", "step", "time_s", "dr", "ci_lo", "ci_hi"])
    assert not any(line.startswith("#") for line in lines)
    steps = done_campaign["scenario"]["steps"]
    assert len(lines) == 1 + 2 * steps
    assert all(line.startswith(f"{cid},fixture,paper,3,3,") for line in lines[1:])

    meta = read_results_csv(by_query.text)
    assert meta["campaign_id"] == cid and meta["name"] == "fixture" and meta["seed"] == 3 and meta["tests"] == 3
    assert meta["overrides"] == done_campaign["overrides"] and meta["scenario"] == done_campaign["scenario"]
    results = http.get(f"/campaigns/{cid}/results").json()
    assert results["overrides"] == done_campaign["overrides"]
    for name, block in results["algorithms"].items():
        assert meta["curves"][name]["dr"] == block["dr"]
        assert meta["curves"][name]["dr_ci95"] == block["dr_ci95"]
    rerun = run_campaign(meta["preset"], Scenario.model_validate(meta["scenario"]), meta["tests"], meta["seed"], meta["algorithms"])
    for name in meta["algorithms"]:
        assert rerun["algorithms"][name]["dr"] == meta["curves"][name]["dr"]


def test_the_summary_is_its_own_csv_table_one_row_per_algorithm(http, done_campaign):
    import csv
    import io

    cid = done_campaign["id"]
    r = http.get(f"/campaigns/{cid}/results", params={"format": "csv", "table": "summary"})
    assert r.status_code == 200 and 'filename="campaign-' + cid + '-summary.csv"' in r.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(r.text)))
    results = http.get(f"/campaigns/{cid}/results").json()
    assert [row["algorithm"] for row in rows] == list(results["algorithms"])
    for row in rows:
        block = results["algorithms"][row["algorithm"]]
        assert row["campaign_id"] == cid and row["name"] == "fixture" and row["preset"] == "paper"
        assert all(row[k] == str(v) for k, v in done_campaign["overrides"].items())
        assert float(row["dr_final"]) == block["dr_final"] and [float(row["ci_lo"]), float(row["ci_hi"])] == block["ci95"]
        assert float(row["ece_final"]) == block["calibration"]["ece_final"]
        assert row["partial"] == "False" and row["tests_recorded"] == "3"
    assert http.get(f"/campaigns/{cid}/results", params={"format": "csv", "table": "totals"}).status_code == 422


def test_outcome_table_has_one_row_per_test_and_algorithm(http, done_campaign):
    cid = done_campaign["id"]
    page = http.get(f"/campaigns/{cid}/tests").json()
    assert page["total"] == 6 and len(page["items"]) == 6
    assert [(o["test_index"], o["algorithm"]) for o in page["items"]] == [(k, a) for k in range(3) for a in ("ra2vipas", "rapas")]
    results = http.get(f"/campaigns/{cid}/results").json()
    for name in ("ra2vipas", "rapas"):
        rows = [o for o in page["items"] if o["algorithm"] == name]
        assert sum(o["final_hit"] for o in rows) / 3 == pytest.approx(results["algorithms"][name]["dr_final"])
    for o in page["items"]:
        assert o["status"] == "done" and o["rig"] == "rig-1" and o["attempt"] == 1
        assert o["final_hit"] == (o["final_choice"] == o["tx_index"])
        if o["settled_s"] is not None:
            assert o["final_hit"] and o["first_hit_s"] <= o["settled_s"]
    one = http.get(f"/campaigns/{cid}/tests", params={"algorithm": "rapas", "limit": 1, "offset": 1}).json()
    assert one["total"] == 3 and [(o["test_index"], o["algorithm"]) for o in one["items"]] == [(1, "rapas")]
    assert http.get(f"/campaigns/{cid}/tests", params={"limit": 500}).status_code == 422
    assert http.get(f"/campaigns/{cid}/tests", params={"algorithm": "magic"}).status_code == 422


def test_trace_gives_pan_reward_estimate_and_association_per_step(http, done_campaign):
    cid = done_campaign["id"]
    trace = http.get(f"/campaigns/{cid}/tests/2/ra2vipas").json()
    steps, targets = trace["steps"], trace["targets"]
    assert len(steps) == done_campaign["scenario"]["steps"] and len(targets) == done_campaign["scenario"]["n_targets"]
    assert [t["is_tx"] for t in targets].count(True) == 1 and targets[trace["tx_index"]]["is_tx"]
    for s in steps:
        nearest = min(targets, key=lambda t: abs(math.remainder(s["gamma_hat_rad"] - t["bearing_rad"], 2 * math.pi)))
        assert s["i_hat"] == nearest["index"]  # the association rule, eq. 11
        assert s["hit"] == (s["i_hat"] == trace["tx_index"])
        assert -math.pi <= s["pan_rad"] < math.pi and math.isfinite(s["reward"])
    assert steps[0]["pan_rad"] == 0.0  # initial pan s_0
    outcome = http.get(f"/campaigns/{cid}/tests", params={"algorithm": "ra2vipas", "offset": 2, "limit": 1}).json()["items"][0]
    assert outcome["final_hit"] == steps[-1]["hit"] and outcome["final_estimate_rad"] == steps[-1]["gamma_hat_rad"]


@pytest.mark.parametrize("path, code", [("/tests/3/ra2vipas", 404), ("/tests/0/sweep", 404), ("/tests/0/magic", 404), ("/tests/0/Not%20a%20name", 422),
                                        ("/tests/-1/rapas", 422), ("/tests/0/rapas/plot?format=gif", 422)])
def test_trace_of_a_test_the_campaign_does_not_have(http, done_campaign, path, code):
    r = http.get(f"/campaigns/{done_campaign['id']}{path}")
    assert r.status_code == code, r.text


@pytest.mark.parametrize("path", ["/plots/dr", "/plots/pod", "/plots/reliability", "/tests/1/rapas/plot"])
def test_figures_render_as_png_and_svg(http, done_campaign, path):
    url = f"/campaigns/{done_campaign['id']}{path}"
    png = http.get(url)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png" and png.content.startswith(PNG)
    svg = http.get(url, params={"format": "svg"})
    assert svg.headers["content-type"] == "image/svg+xml" and b"<svg" in svg.content[:500]
    by_accept = http.get(url, headers={"Accept": "image/svg+xml"})
    assert by_accept.headers["content-type"] == "image/svg+xml"


def test_the_pod_model_and_its_training_truth_are_kept_for_the_figure(live, done_campaign):
    artifacts = live.app.state.store.pod_artifacts(done_campaign["id"])
    model, truth = artifacts["model"], artifacts["truth"]
    assert len(model["rssi_grid_dbm"]) == len(model["mean"]) == len(model["std"]) >= 2
    assert len(truth["rssi_dbm"]) == len(truth["pod"]) == done_campaign["scenario"]["n_train"]
    assert all(0.0 <= p <= 1.0 for p in truth["pod"])


def test_presets_list_every_parameter_with_its_range(http):
    assert [p["name"] for p in http.get("/presets").json()] == ["paper", "paper-uniform", "dynamic", "ble", "ble-dynamic", "ble-recorded", "ward"]
    paper = http.get("/presets/paper").json()
    assert set(paper["parameters"]) == set(Scenario.model_fields)
    assert paper["parameters"]["n_targets"] == {"value": 20, "allowed": "an integer in [1, 500]",
                                                 "description": Scenario.model_fields["n_targets"].description}
    assert paper["parameters"]["placement"]["allowed"] == "one of reference|uniform"
    assert http.get("/presets/paper-uniform").json()["parameters"]["placement"]["value"] == "uniform"
    dynamic = http.get("/presets/dynamic").json()["parameters"]
    assert dynamic["clutter_rate"] == {"value": 0.3, "allowed": "a number in [0.0, 100.0]",
                                       "description": Scenario.model_fields["clutter_rate"].description}
    r = http.get("/presets/moon")
    assert r.status_code == 404 and "paper" in r.json()["detail"]


def test_rigs_come_from_liveliness(http):
    body = http.get("/rigs").json()
    assert [(r["name"], r["live"], r["sensors"], r["controller"]) for r in body["rigs"]] == [("rig-1", True, True, True)]
    assert body["rigs"][0]["in_flight"] >= 0 and body["learners"] == ["learner"]


def test_tests_can_be_filtered_by_hit_and_campaigns_by_name(http, done_campaign):
    cid = done_campaign["id"]
    every = http.get(f"/campaigns/{cid}/tests", params={"limit": 200}).json()["items"]
    hits = http.get(f"/campaigns/{cid}/tests", params={"hit": "true", "limit": 200}).json()
    misses = http.get(f"/campaigns/{cid}/tests", params={"hit": "false", "limit": 200}).json()
    assert hits["total"] + misses["total"] == len(every)
    assert all(row["final_hit"] is True for row in hits["items"]) and all(row["final_hit"] is False for row in misses["items"])
    assert http.get(f"/campaigns/{cid}/tests", params={"hit": "maybe"}).status_code == 422
    named = http.get("/campaigns", params={"name": "fixture"}).json()
    assert named["total"] >= 1 and all(c["name"] == "fixture" for c in named["items"])
    assert http.get("/campaigns", params={"name": "no such name"}).json()["total"] == 0


@pytest.mark.parametrize("state", ["queued", "training", "running"])
def test_a_campaign_that_has_not_finished_has_no_results_yet(state):
    """409 for a campaign on its way (training its POD model included: a loaded machine caught
    `campaign results` saying a training campaign had "no results", as of one that ended)."""
    from fastapi import HTTPException

    from ra2vipas.services.orchestrator.api.routes.results import finished_results

    campaign = {"id": "c0ffee", "status": state, "results": None, "progress": {"done": 0, "total": 50}}
    with pytest.raises(HTTPException) as refused:
        finished_results(campaign)
    assert refused.value.status_code == 409
    assert refused.value.detail == f"campaign c0ffee is {state} (0/50 episodes done): no results yet"
