"""Per-tag results outside the results object (issue 21): the summary CSV's per-tag columns and
a study that varies the number of tags K."""

from __future__ import annotations

import io

import pandas as pd

from ra2vipas.services.orchestrator.api.export import write_results_csv
from ra2vipas.services.orchestrator.engine import run_study
from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.orchestrator.study import write_study_csv
from ra2vipas.services.protocol.scenario import build_scenario

SMALL = {"n_targets": 6, "steps": 20, "n_train": 200}


def test_the_summary_csv_has_each_tags_columns_and_one_tag_has_none():
    results = run_campaign("paper", build_scenario("paper", {**SMALL, "n_tags": 2}), tests=2, seed=1, algorithms=["ra2vipas"],
                           stop_confidence=0.9)
    table = pd.read_csv(io.StringIO(write_results_csv(results, table="summary")))
    tags = results["algorithms"]["ra2vipas"]["tags"]
    row = table.iloc[0]
    assert row["mean_tag_dr_final"] == tags["mean_tag_dr_final"] and row["all_found_final"] == tags["all_found"]["dr_final"]
    assert row["tag1_dr_final"] == tags["per_tag"][1]["dr_final"] and "tag1_ece_final" in table and "all_decided_median_s" in table
    single = run_campaign("paper", build_scenario("paper", SMALL), tests=1, seed=1, algorithms=["rapas"])
    assert not [c for c in pd.read_csv(io.StringIO(write_results_csv(single, table="summary"))).columns if "tag" in c]


def test_a_study_varies_the_number_of_tags():
    study = run_study("paper", SMALL, {"n_tags": [1, 2]}, tests=2, seed=1, algorithms=["ra2vipas"], workers=1)
    rows = {r["n_tags"]: r for r in study["rows"]}
    assert rows[1].get("tags_mean_tag_dr_final") is None
    assert 0.0 <= rows[2]["tags_mean_tag_dr_final"] <= 1.0 and "tags_all_found_dr_final" in rows[2]
    table = pd.read_csv(io.StringIO(write_study_csv(study)))
    assert list(table.n_tags) == [1, 2] and "tags_all_found_dr_final" in table
