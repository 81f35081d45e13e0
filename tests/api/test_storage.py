"""The SQLite store: WAL, schema version and migrations, one transaction per write, and the
campaign state rules the API relies on (a finished campaign never changes status; only a
finished campaign can be deleted)."""

from __future__ import annotations

import sqlite3

import pytest

from ra2vipas.services.orchestrator import storage
from ra2vipas.services.orchestrator.storage import CampaignActiveError, EpisodeKey, Store, StoreError


@pytest.fixture()
def store(tmp_path):
    s = Store(str(tmp_path / "s.db"))
    yield s
    s.close()


def new_campaign(store: Store, tests: int = 2, algorithms=("rapas",)) -> str:
    return store.create_campaign(preset="paper", overrides={}, scenario={"steps": 2, "rf_period_s": 0.1}, algorithms=list(algorithms),
                                 tests=tests, seed=1, mode="fast")


def finish(store: Store, key: EpisodeKey) -> bool:
    return store.finish_episode(key, hits=[False, True], in_fov=[True, True], estimates=[0.1, 0.2], pans=[0.0, 0.5], rewards=[1.0, 2.0],
                                chosen=[1, 0], tx_index=0, bearings=[0.2, 1.0], ranges=[2.0, 3.0], latencies=None)


def test_the_database_is_in_wal_mode_at_the_current_schema_version(tmp_path, store):
    db = sqlite3.connect(tmp_path / "s.db")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()[0] == str(storage.SCHEMA_VERSION) == "7"
    db.close()


def test_a_version_1_database_is_migrated_and_keeps_its_campaigns(tmp_path):
    path = tmp_path / "v1.db"
    db = sqlite3.connect(path)
    db.executescript(storage._MIGRATIONS[1] + ";CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
                     "INSERT INTO meta VALUES ('schema_version', '1');"
                     "INSERT INTO campaigns(id, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at)"
                     " VALUES ('old', 'paper', '{}', '{}', '[\"rapas\"]', 1, 1, 'fast', 'done', 1.0);")
    db.close()
    s = Store(str(path))
    try:
        assert s.campaign("old")["status"] == "done" and s.campaign("old")["stop_confidence"] == 0
        assert s.pod_artifacts("old") == {"model": None, "truth": None}
        s.set_pod_artifacts("old", model={"mean": [0.5]}, truth={"rssi_dbm": [-40.0], "pod": [0.5]})
        assert s.pod_artifacts("old")["truth"]["pod"] == [0.5]
    finally:
        s.close()
    db = sqlite3.connect(path)
    assert db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()[0] == "7"
    db.close()


def test_a_version_2_database_gains_trajectories_and_keeps_its_episodes(tmp_path):
    path = tmp_path / "v2.db"
    db = sqlite3.connect(path)
    db.executescript(storage._MIGRATIONS[1] + ";" + storage._MIGRATIONS[2] + ";CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);"
                     "INSERT INTO meta VALUES ('schema_version', '2');"
                     "INSERT INTO campaigns(id, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at)"
                     " VALUES ('old', 'paper', '{}', '{}', '[\"rapas\"]', 1, 1, 'fast', 'done', 1.0);"
                     "INSERT INTO episodes(campaign_id, test_index, algorithm, status, hits, bearings)"
                     " VALUES ('old', 0, 'rapas', 'done', '[1]', '[0.5]');")
    db.close()
    s = Store(str(path))
    try:
        row = s.episode("old", 0, "rapas")
        assert row["hits"] == [1] and row["bearings"] == [0.5] and row["trajectories"] is None
    finally:
        s.close()


def test_walking_targets_per_step_truth_is_kept_with_the_episode(store):
    cid = new_campaign(store, tests=2)
    walk = [{"index": 1, "bearings_rad": [1.0, 1.1], "ranges_m": [3.0, 3.05]}]
    assert store.finish_episode(EpisodeKey(cid, 0, "rapas"), hits=[False, True], in_fov=[True, True], estimates=[0.1, 1.1],
                                pans=[0.0, 0.5], rewards=[1.0, 2.0], chosen=[0, 1], tx_index=1, bearings=[0.2, 1.0],
                                ranges=[2.0, 3.0], latencies=None, trajectories=walk)
    assert finish(store, EpisodeKey(cid, 1, "rapas"))  # a static world: no trajectories
    assert store.episode(cid, 0, "rapas")["trajectories"] == walk
    assert store.episode(cid, 1, "rapas")["trajectories"] is None


def test_a_database_from_a_newer_version_is_refused(tmp_path):
    path = tmp_path / "new.db"
    Store(str(path)).close()
    db = sqlite3.connect(path)
    db.execute("UPDATE meta SET value='99' WHERE key='schema_version'")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="schema version 99"):
        Store(str(path))


def test_a_failed_transaction_leaves_nothing_behind(store):
    cid = new_campaign(store)
    with pytest.raises(RuntimeError):
        with store.transaction() as db:
            db.execute("UPDATE episodes SET status='done', hits='[1]' WHERE campaign_id=?", (cid,))
            raise RuntimeError("crash mid-write")
    assert {r["status"] for r in store.episode_rows(cid, status=None)} == {"pending"}


def test_a_test_is_recorded_once(store):
    cid = new_campaign(store)
    key = EpisodeKey(cid, 0, "rapas")
    store.mark_running(key, "rig-1", 1)
    assert finish(store, key) is True
    assert finish(store, key) is False
    row = store.episode(cid, 0, "rapas")
    assert row["status"] == "done" and row["hits"] == [0, 1] and row["chosen"] == [1, 0]


def test_a_burst_of_tests_is_recorded_in_one_transaction_each_once_with_its_floats_exact(store, monkeypatch):
    """``finish_episodes`` (the orchestrator's batched save): every test of the burst recorded,
    one already recorded refused, the stored floats read back exactly as given (the lists are
    encoded by pydantic_core, not json.dumps), and a failure records none of them."""
    import json
    import random

    cid = new_campaign(store, tests=3)
    keys = [EpisodeKey(cid, i, "rapas") for i in range(3)]
    assert store.mark_running_many(keys[:2], "rig-1") == [1, 1]
    assert store.mark_running_many(keys[:1], "rig-2") == [2]  # handed out again: the next attempt
    assert store.attempt_of(keys[0]) == 2 and store.episode(cid, 0, "rapas")["rig"] == "rig-2"
    assert finish(store, keys[0]) is True
    rng = random.Random(5)
    estimates = [rng.uniform(-3.2, 3.2) * 10 ** rng.randint(-9, 3) for _ in range(120)] + [1e-7, 1 / 3, -0.0]
    fields = dict(hits=[True], in_fov=[False], estimates=estimates, pans=[0.25], rewards=[float("nan")], chosen=[3], tx_index=1,
                  bearings=[0.5], ranges=[1.5], latencies=[0.75], confidences=[0.5], decided_step=None,
                  model_check={"sensor_model": "scenario"})
    writes: list[str] = []
    real = store.transaction

    def counted():
        writes.append("transaction")
        return real()

    monkeypatch.setattr(store, "transaction", counted)
    assert store.finish_episodes([(keys[0], fields), (keys[1], fields), (keys[2], fields)]) == [False, True, True]
    assert writes == ["transaction"]
    row = store.episode(cid, 2, "rapas")
    assert row["estimates"] == estimates and row["estimates"] == json.loads(json.dumps(estimates))
    assert row["hits"] == [1] and row["in_fov"] == [0] and row["rewards"][0] != row["rewards"][0]  # NaN kept
    assert row["model_check"] == {"sensor_model": "scenario"} and row["confidences"] == [0.5]
    assert store.episode(cid, 0, "rapas")["estimates"] == [0.1, 0.2]  # recorded once: the burst did not overwrite it

    cid2 = new_campaign(store, tests=2)
    keys2 = [EpisodeKey(cid2, i, "rapas") for i in range(2)]
    bad = dict(fields, tx_index=object())  # not storable: the transaction fails after the first row
    with pytest.raises(Exception):
        store.finish_episodes([(keys2[0], fields), (keys2[1], bad)])
    assert {r["status"] for r in store.episode_rows(cid2, status=None)} == {"pending"}


def test_a_finished_campaign_never_changes_status(store):
    cid = new_campaign(store)
    assert store.set_campaign(cid, status="running") is True
    assert store.set_campaign(cid, status="done", finished_at=2.0) is True
    assert store.set_campaign(cid, status="running") is False
    assert store.cancel_campaign(cid) is False
    assert store.campaign(cid)["status"] == "done"
    assert store.set_campaign(cid, pod_r2=0.9) is True  # other columns may still be written


def test_cancel_marks_the_campaign_and_its_unfinished_tests(store):
    cid = new_campaign(store, tests=3)
    store.set_campaign(cid, status="running")
    store.mark_running(EpisodeKey(cid, 0, "rapas"), "rig-1", 1)
    finish(store, EpisodeKey(cid, 0, "rapas"))
    store.mark_running(EpisodeKey(cid, 1, "rapas"), "rig-1", 1)
    assert store.cancel_campaign(cid) is True
    c = store.campaign(cid)
    assert c["status"] == "cancelled" and c["finished_at"] is not None
    assert c["progress"] == {"done": 1, "running": 0, "pending": 0, "total": 3}
    assert finish(store, EpisodeKey(cid, 1, "rapas")) is False  # a late result of a cancelled campaign is not recorded
    assert store.set_campaign(cid, status="done") is False
    assert store.cancel_campaign(cid) is False


def test_only_a_finished_campaign_can_be_deleted(store):
    cid = new_campaign(store)
    with pytest.raises(CampaignActiveError, match="cancel it first"):
        store.delete_campaign(cid)
    assert store.campaign(cid) is not None
    store.cancel_campaign(cid)
    assert store.delete_campaign(cid) is True
    assert store.campaign(cid) is None and store.episode_rows(cid, status=None) == []
    assert store.delete_campaign(cid) is False


def test_pages_of_campaigns_and_of_tests(store):
    ids = [new_campaign(store, tests=3, algorithms=("rapas", "sweep")) for _ in range(5)]
    page, total = store.campaigns(limit=2, offset=1)
    assert total == 5 and [c["id"] for c in page] == [ids[3], ids[2]]
    assert all(c["progress"]["total"] == 6 and "pod_model" not in c for c in page)
    rows, total = store.episode_page(ids[0], algorithm="sweep", limit=2, offset=1)
    assert total == 3 and [(r["test_index"], r["algorithm"]) for r in rows] == [(1, "sweep"), (2, "sweep")]
