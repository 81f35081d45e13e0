"""Every CSV the product writes loads in pandas as it is (issue 23, point 1): the campaign's
``dr`` and ``summary`` tables and the study's table (API and ``ra2vipas study results --csv``),
with their documented columns, no ``#`` comment lines; a study's rows say what was run (preset,
seed, overrides) and its DataFrame has the same columns, in the same order, in this process and
through ``Client``."""

from __future__ import annotations

import io

import pandas as pd

import ra2vipas
from tests.api.live import SMALL
from tests.cli.conftest import ra2vipas as cli

BASE = {k: v for k, v in SMALL.items() if k != "n_targets"}
STUDY_HEAD = ["study_id", "point", "n_targets", "preset", "seed", *BASE, "algorithm", "tests", "dr_final", "ci95_lo", "ci95_hi",
              "time_to_dr90_s", "in_fov_final", "pod_r2"]


def test_the_campaign_tables_load_in_pandas(done_campaign, http):
    cid = done_campaign["id"]
    dr = pd.read_csv(io.StringIO(http.get(f"/campaigns/{cid}/results", params={"format": "csv"}).text))
    assert list(dr.columns) == ["campaign_id", "name", "preset", "seed", "tests", *SMALL, "algorithm", "step", "time_s", "dr",
                                "ci_lo", "ci_hi"]
    assert len(dr) == 2 * SMALL["steps"] and set(dr.campaign_id) == {cid}
    summary = pd.read_csv(io.StringIO(http.get(f"/campaigns/{cid}/results", params={"format": "csv", "table": "summary"}).text))
    assert list(summary.columns[:9]) == ["campaign_id", "name", "preset", "seed", "tests", *SMALL, "algorithm"]
    assert {"dr_final", "ci_lo", "ci_hi", "time_to_dr90_s", "in_fov_final", "pod_r2", "partial", "tests_recorded"} <= set(summary.columns)


def test_the_study_table_loads_in_pandas_from_the_api_and_the_cli_alike(live, tmp_path):
    with ra2vipas.Client(live.url) as client:
        s = client.start_study({"n_targets": [4, 6]}, overrides=BASE, tests=2, seed=6, algorithms=["rapas", "sweep"])
        remote = client.wait_study(s["id"], timeout=120)
    with live.client() as http:
        text = http.get(f"/studies/{s['id']}/results", params={"format": "csv"}).text
    assert not any(line.startswith("#") for line in text.splitlines())
    table = pd.read_csv(io.StringIO(text))
    assert list(table.columns[:len(STUDY_HEAD)]) == STUDY_HEAD and table.columns[-1] == "campaign_id"
    assert set(table.study_id) == {s["id"]} and set(table.preset) == {"paper"} and set(table.seed) == {6}
    assert list(table.n_targets) == [4, 4, 6, 6] and list(table.algorithm) == ["rapas", "sweep"] * 2
    out = tmp_path / "study.csv"
    assert cli("study", "results", s["id"], "--api", live.url, "--csv", str(out)).returncode == 0
    assert pd.read_csv(out).equals(table)
    # the DataFrame: the CSV's columns, in this process and through the client
    here = ra2vipas.to_dataframe(ra2vipas.study({"n_targets": [4, 6]}, overrides=BASE, tests=2, seed=6, algorithms=["rapas", "sweep"]))
    there = ra2vipas.to_dataframe(remote)
    assert list(here.columns) == list(there.columns) == list(table.columns)
    assert list(here.dr_final) == list(there.dr_final) == list(table.dr_final)
