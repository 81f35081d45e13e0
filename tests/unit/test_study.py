"""Parameter studies, the pure domain (study.py) and their storage (study_store.py on a real SQLite
file): grids, ranges, rows, status, migration, create/cancel/delete in one transaction."""

from __future__ import annotations

import sqlite3

import pytest

from ra2vipas.services.orchestrator import storage
from ra2vipas.services.orchestrator.storage import CampaignActiveError, CampaignInStudyError, EpisodeKey, Store
from ra2vipas.services.orchestrator.study import (
    MAX_POINTS,
    StudyError,
    check_size,
    expand,
    flatten,
    parse_range,
    parse_vary,
    point_rows,
    status_of,
    study_results,
    write_study_csv,
)
from ra2vipas.services.orchestrator.study_store import StudyStore


def test_ranges_are_inclusive_exact_decimal_steps_typed_as_the_parameter():
    assert parse_range("rf_noise_db", "0.1:0.3:0.1") == [0.1, 0.2, 0.3]
    assert parse_range("n_targets", "10:40:10") == [10, 40 - 20, 30, 40] and all(type(v) is int for v in parse_range("n_targets", "1:3:1"))
    assert parse_range("rf_noise_db", "6:2:-2") == [6.0, 4.0, 2.0]
    for bad, words in (("6:2:1", "never reaches"), ("1:2", "a:b:step"), ("1:x:1", "'x'"), ("1:2:0", "never reaches")):
        with pytest.raises(StudyError, match=words):
            parse_range("rf_noise_db", bad)
    with pytest.raises(StudyError, match="fractions"):
        parse_range("n_targets", "1:2:0.5")
    with pytest.raises(StudyError, match=str(MAX_POINTS)):
        parse_range("rf_noise_db", "0:1000:1")


def test_parse_vary_lists_ranges_and_errors():
    assert parse_vary("n_targets=10,20,40") == ("n_targets", [10, 20, 40])
    assert parse_vary("rf_noise_db=2:6:1") == ("rf_noise_db", [2.0, 3.0, 4.0, 5.0, 6.0])
    with pytest.raises(StudyError, match="n_targets"):
        parse_vary("n_target=1,2")
    with pytest.raises(StudyError, match="NAME="):
        parse_vary("n_targets")


def test_expand_is_the_product_first_parameter_slowest_and_names_bad_points():
    grid = expand("paper", {"steps": 20}, {"n_targets": [5, 10], "rf_noise_db": [2, 4.5]})
    assert [v for v, _ in grid] == [{"n_targets": 5, "rf_noise_db": 2.0}, {"n_targets": 5, "rf_noise_db": 4.5},
                                    {"n_targets": 10, "rf_noise_db": 2.0}, {"n_targets": 10, "rf_noise_db": 4.5}]
    assert all(sc.steps == 20 and sc.n_targets == v["n_targets"] for v, sc in grid)
    with pytest.raises(StudyError) as err:
        expand("paper", {}, {"rf_noise_db": [1.0, -2.0]})
    assert err.value.name == "rf_noise_db" and "-2" in str(err.value)
    with pytest.raises(StudyError, match="both"):
        expand("paper", {"n_targets": 3}, {"n_targets": [1, 2]})
    with pytest.raises(StudyError, match="points"):
        expand("paper", {}, {"n_targets": list(range(1, 18)), "rf_noise_db": [float(v) for v in range(1, 17)]})
    with pytest.raises(StudyError) as err:
        expand("nope", {}, {"n_targets": [1]})
    assert err.value.where == "preset"
    with pytest.raises(StudyError, match="episodes") as err:
        check_size(256, 10000, 4)
    assert err.value.where == "tests"


def test_flatten_keeps_scalars_splits_intervals_and_drops_curves():
    block = {"dr": [0.1, 0.2], "dr_ci95": [[0, 1], [0, 1]], "dr_final": 0.2, "ci95": [0.1, 0.3], "time_to_dr90_s": None,
             "calibration": {"ece_final": 0.05, "reliability": [{"lo": 0}]}, "decision": {"accuracy": 0.9, "accuracy_ci95": [0.8, 0.95]},
             "future_field": {"nested": {"x": 1}}}
    assert flatten(block) == {"dr_final": 0.2, "ci95_lo": 0.1, "ci95_hi": 0.3, "time_to_dr90_s": None, "calibration_ece_final": 0.05,
                              "decision_accuracy": 0.9, "decision_accuracy_ci95_lo": 0.8, "decision_accuracy_ci95_hi": 0.95,
                              "future_field_nested_x": 1}


def results_of(dr: float) -> dict:
    block = {"dr": [dr], "dr_final": dr, "ci95": [dr - 0.1, dr], "dr_ci95": [[dr - 0.1, dr]], "time_to_dr90_s": 0.1, "in_fov_final": 1.0}
    return {"tests": 3, "pod": {"r2": 0.9, "train_seconds": 0.1}, "algorithms": {"rapas": block, "sweep": block},
            "steps_per_second": 100.0}


def test_rows_results_object_and_csv():
    rows = point_rows(1, {"n_targets": 10}, results_of(0.5), "c1", {"rapas": 2})
    assert [r["algorithm"] for r in rows] == ["rapas", "sweep"] and rows[0]["tests"] == 2 and rows[1]["tests"] == 3
    assert rows[0]["n_targets"] == 10 and rows[0]["dr_final"] == 0.5 and rows[0]["pod_r2"] == 0.9 and rows[0]["campaign_id"] == "c1"
    meta = {"id": "s", "name": None, "status": "running", "preset": "paper", "overrides": {}, "vary": {"n_targets": [5, 10]},
            "algorithms": ["rapas", "sweep"], "tests": 3, "seed": 1}
    res = study_results(meta, [{"point": 0, "values": {"n_targets": 5}, "status": "queued", "results": None},
                               {"point": 1, "values": {"n_targets": 10}, "status": "running", "results": results_of(0.5)}], partial=True)
    assert res["parameters"] == ["n_targets"] and len(res["rows"]) == 2 and res["points"][0]["pod"] is None and res["partial"]
    text = write_study_csv(res)
    header, first = text.splitlines()[:2]
    assert header.startswith("study_id,point,n_targets,preset,seed,algorithm,tests,dr_final,ci95_lo,ci95_hi")
    assert first.startswith("s,1,10,paper,1,rapas,3,0.5,") and "#" not in text


@pytest.mark.parametrize("counts, expected", [
    ({"queued": 3}, "queued"), ({"queued": 2, "training": 1}, "training"), ({"queued": 1, "running": 1}, "running"),
    ({"queued": 1, "done": 1}, "running"), ({"done": 3}, "done"), ({"done": 2, "failed": 1}, "failed"),
    ({"done": 2, "cancelled": 1}, "cancelled"), ({"failed": 1, "cancelled": 1}, "failed"),
])
def test_a_study_status_follows_its_points(counts, expected):
    assert status_of(counts) == expected


@pytest.fixture()
def store(tmp_path):
    s = Store(str(tmp_path / "s.db"))
    yield s
    s.close()


def new_study(store: Store, points: int = 2, tests: int = 2) -> tuple[str, list[str]]:
    return StudyStore(store).create(preset="paper", overrides={}, vary={"n_targets": list(range(1, points + 1))},
                                    points=[({"n_targets": i + 1}, {"steps": 2, "rf_period_s": 0.1, "n_targets": i + 1})
                                            for i in range(points)],
                                    algorithms=["rapas"], tests=tests, seed=1, mode="fast")


def test_create_read_cancel_delete(store):
    studies = StudyStore(store)
    sid, cids = new_study(store, points=3)
    s = studies.study(sid)
    assert s["status"] == "queued" and s["points_total"] == 3 and s["progress"]["total"] == 6
    assert [p["values"] for p in s["points"]] == [{"n_targets": 1}, {"n_targets": 2}, {"n_targets": 3}]
    assert studies.membership(cids[1]) == (sid, 1) and studies.membership("nope") is None
    assert store.cancel_campaign(cids[0])  # one point alone may be cancelled, not deleted: it goes with its study
    with pytest.raises(CampaignInStudyError):
        store.delete_campaign(cids[0])
    assert studies.study(sid)["status"] == "running"  # a point finished, others have not
    with pytest.raises(CampaignActiveError):
        studies.delete(sid)
    assert studies.cancel(sid) == cids[1:] and studies.study(sid)["status"] == "cancelled"
    assert studies.cancel(sid) == []
    page, total = studies.studies(status="cancelled")
    assert total == 1 and page[0]["id"] == sid and page[0]["points"] is None
    assert studies.delete(sid) == cids and studies.study(sid) is None and all(store.campaign(c) is None for c in cids)
    assert studies.delete(sid) is None


def test_a_study_runs_once_a_point_has_run(store):
    sid, cids = new_study(store)
    store.set_campaign(cids[0], status="running")
    assert StudyStore(store).study(sid)["status"] == "running"
    key = EpisodeKey(cids[0], 0, "rapas")
    store.mark_running(key, "rig-1", 1)
    store.finish_episode(key, hits=[False, True], in_fov=[True, True], estimates=[0.1, 0.2], pans=[0.0, 0.5], rewards=[1.0, 2.0],
                         chosen=[1, 0], tx_index=0, bearings=[0.2, 1.0], ranges=[2.0, 3.0], latencies=None)
    assert StudyStore(store).study(sid)["progress"]["done"] == 1


def test_a_version_4_database_gains_studies_and_keeps_its_campaigns(tmp_path):
    path = tmp_path / "v4.db"
    db = sqlite3.connect(path)
    db.executescript(";".join(storage._MIGRATIONS[v] for v in (1, 2, 3, 4))
                     + ";CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
                     "INSERT INTO meta VALUES ('schema_version', '4');"
                     "INSERT INTO campaigns(id, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at)"
                     " VALUES ('old', 'paper', '{}', '{}', '[\"rapas\"]', 1, 1, 'fast', 'done', 1.0);")
    db.close()
    s = Store(str(path))
    try:
        assert s.campaign("old")["status"] == "done" and StudyStore(s).membership("old") is None
        assert StudyStore(s).studies() == ([], 0)
        assert s.delete_campaign("old")
    finally:
        s.close()
