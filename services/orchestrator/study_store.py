"""Storage of parameter studies, on the campaign database (``storage.Store``, schema version 5).

A study is a row of ``studies`` (its grid and campaign options) and one campaign per point,
whose ``study_id`` and ``study_point`` say where it belongs: the points are ordinary
campaigns, run, resumed after a restart and read like any other. A study's status and progress
are derived from its points' campaigns when it is read (``study.status_of``), never stored, so
they cannot disagree with them.

Creating a study writes the study, every point's campaign and every episode in one
transaction; cancelling cancels every unfinished point in one; deleting removes the points'
episodes, the points and the study in one.
"""

from __future__ import annotations

import json
import time
from typing import Any, Sequence

from ra2vipas.services.orchestrator.storage import ACTIVE, CampaignActiveError, Store, new_record_id
from ra2vipas.services.orchestrator.study import status_of

# the study's status in SQL (for filtering a page), the same rule as study.status_of
_AGGREGATE = """
SELECT s.id AS id, s.created_at AS created_at,
  CASE
    WHEN SUM(c.status IN ('queued', 'training', 'running')) > 0 THEN
      CASE WHEN SUM(c.status = 'queued') = COUNT(*) THEN 'queued'
           WHEN SUM(c.status = 'running') > 0 OR SUM(c.status IN ('done', 'failed', 'cancelled')) > 0 THEN 'running'
           ELSE 'training' END
    WHEN SUM(c.status = 'failed') > 0 THEN 'failed'
    WHEN SUM(c.status = 'cancelled') > 0 THEN 'cancelled'
    ELSE 'done'
  END AS status
FROM studies s JOIN campaigns c ON c.study_id = s.id GROUP BY s.id
"""


class StudyStore:
    """Studies on a ``Store`` (its connection, lock and transactions)."""

    def __init__(self, store: Store) -> None:
        self.store = store

    def create(self, *, preset: str, overrides: dict, vary: dict[str, list], points: Sequence[tuple[dict, dict]],
               algorithms: list[str], tests: int, seed: int, mode: str, name: str | None = None,
               stop_confidence: float = 0.0) -> tuple[str, list[str]]:
        """Insert a study, one campaign per point (``points``: (its overrides, its resolved
        scenario) in grid order) and all their pending episodes in one transaction; return the
        study id and the points' campaign ids in grid order.

        Raises
        ------
        StorageFault
            The database cannot be written (nothing was).
        """
        sid = new_record_id()
        now = time.time()
        cids = []
        with self.store.transaction() as db:
            db.execute("INSERT INTO studies(id, name, preset, overrides, vary, algorithms, tests, seed, mode, stop_confidence,"
                       " created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                       (sid, name, preset, json.dumps(overrides), json.dumps(vary), json.dumps(algorithms), tests, seed, mode,
                        stop_confidence, now))
            for i, (point_overrides, scenario) in enumerate(points):
                cid = new_record_id()
                label = f"{name or 'study ' + sid} #{i}"[:100]
                db.execute(
                    "INSERT INTO campaigns(id, name, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at,"
                    " stop_confidence, study_id, study_point) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, 'queued', ?, ?, ?, ?)",
                    (cid, label, preset, json.dumps(point_overrides), json.dumps(scenario), json.dumps(algorithms), tests, seed,
                     mode, now, stop_confidence, sid, i))
                db.executemany("INSERT INTO episodes(campaign_id, test_index, algorithm, status) VALUES (?, ?, ?, 'pending')",
                               [(cid, k, a) for k in range(tests) for a in algorithms])
                cids.append(cid)
        return sid, cids

    def study(self, sid: str) -> dict[str, Any] | None:
        """The study with its derived status, progress (episodes over every point), timings,
        first error and its points (campaign id, status, progress, POD fit) in grid order."""
        with self.store._reading() as db:
            row = db.execute("SELECT * FROM studies WHERE id=?", (sid,)).fetchone()
            if row is None:
                return None
            points = db.execute(
                "SELECT id, study_point, status, overrides, started_at, finished_at, pod_r2, pod_train_seconds, error"
                " FROM campaigns WHERE study_id=? ORDER BY study_point", (sid,)).fetchall()
            counts: dict[str, dict[str, int]] = {p["id"]: {} for p in points}
            for cid, st, n in db.execute(
                    "SELECT e.campaign_id, e.status, COUNT(*) FROM episodes e JOIN campaigns c ON c.id = e.campaign_id"
                    " WHERE c.study_id=? GROUP BY e.campaign_id, e.status", (sid,)):
                counts[cid][st] = n
        return _study_dict(row, [dict(p) for p in points], counts)

    def studies(self, *, status: str | None = None, limit: int = 50, offset: int = 0) -> tuple[list[dict[str, Any]], int]:
        """One page of studies, newest first (without their points), optionally only those in
        ``status``; and how many match in all."""
        where, args = (" WHERE status=?", [status]) if status else ("", [])
        with self.store._reading() as db:
            total = db.execute(f"SELECT COUNT(*) FROM ({_AGGREGATE}){where}", args).fetchone()[0]
            ids = [r[0] for r in db.execute(f"SELECT id FROM ({_AGGREGATE}){where} ORDER BY created_at DESC, id LIMIT ? OFFSET ?",
                                            [*args, limit, offset])]
        out = []
        for sid in ids:
            s = self.study(sid)
            if s is not None:
                s["points"] = None
                out.append(s)
        return out, total

    def points(self, sid: str) -> list[dict[str, Any]]:
        """The study's points' campaigns (every column, results included) in grid order."""
        with self.store._reading() as db:
            ids = [r[0] for r in db.execute("SELECT id FROM campaigns WHERE study_id=? ORDER BY study_point", (sid,))]
        return [c for c in (self.store.campaign(cid) for cid in ids) if c is not None]

    def membership(self, cid: str) -> tuple[str, int] | None:
        """(study id, point index) of a campaign that is a study's point, else None."""
        with self.store._reading() as db:
            row = db.execute("SELECT study_id, study_point FROM campaigns WHERE id=?", (cid,)).fetchone()
        return None if row is None or row[0] is None else (row[0], int(row[1]))

    def cancel(self, sid: str) -> list[str]:
        """Cancel every unfinished point of a study (and their unfinished episodes) in one
        transaction; return the campaigns cancelled (none if the study had finished)."""
        with self.store.transaction() as db:
            marks = ",".join("?" * len(ACTIVE))
            cids = [r[0] for r in db.execute(f"SELECT id FROM campaigns WHERE study_id=? AND status IN ({marks})", (sid, *ACTIVE))]
            if not cids:
                return []
            now = time.time()
            for cid in cids:
                db.execute(f"UPDATE campaigns SET status='cancelled', finished_at=? WHERE id=? AND status IN ({marks})",
                           (now, cid, *ACTIVE))
                db.execute("UPDATE episodes SET status='cancelled', rig=NULL WHERE campaign_id=? AND status IN ('pending', 'running')",
                           (cid,))
            return cids

    def delete(self, sid: str) -> list[str] | None:
        """Delete a finished study, its points and all their episodes in one transaction; return
        the deleted campaigns' ids, or None if there is no such study.

        Raises
        ------
        CampaignActiveError
            A point is still queued, training or running (cancel the study first).
        """
        with self.store.transaction() as db:
            if db.execute("SELECT 1 FROM studies WHERE id=?", (sid,)).fetchone() is None:
                return None
            rows = db.execute("SELECT id, status FROM campaigns WHERE study_id=?", (sid,)).fetchall()
            active = [r for r in rows if r[1] in ACTIVE]
            if active:
                raise CampaignActiveError(f"study {sid} is still running ({len(active)} of {len(rows)} points unfinished); "
                                          "cancel it first")
            cids = [r[0] for r in rows]
            for cid in cids:
                db.execute("DELETE FROM episodes WHERE campaign_id=?", (cid,))
            db.execute("DELETE FROM campaigns WHERE study_id=?", (sid,))
            db.execute("DELETE FROM studies WHERE id=?", (sid,))
            return cids


def _study_dict(row: Any, points: list[dict[str, Any]], counts: dict[str, dict[str, int]]) -> dict[str, Any]:
    d = dict(row)
    for k in ("overrides", "vary", "algorithms"):
        d[k] = json.loads(d[k])
    states: dict[str, int] = {}
    for p in points:
        states[p["status"]] = states.get(p["status"], 0) + 1
    d["status"] = status_of(states) if points else "done"
    progress = {"done": 0, "running": 0, "pending": 0, "total": 0}
    out_points = []
    for p in points:
        c = counts.get(p["id"], {})
        pp = {"done": c.get("done", 0), "running": c.get("running", 0), "pending": c.get("pending", 0), "total": sum(c.values())}
        for k in progress:
            progress[k] += pp[k]
        overrides = json.loads(p["overrides"])
        out_points.append({"point": p["study_point"], "values": {n: overrides.get(n) for n in d["vary"]}, "campaign_id": p["id"],
                           "status": p["status"], "progress": pp,
                           "pod": {"r2": p["pod_r2"], "train_seconds": p["pod_train_seconds"]}})
    d["progress"] = progress
    d["points"] = out_points
    d["points_total"] = len(points)
    started = [p["started_at"] for p in points if p["started_at"] is not None]
    d["started_at"] = min(started) if started else None
    finished = [p["finished_at"] for p in points if p["finished_at"] is not None]
    d["finished_at"] = max(finished) if finished and d["status"] not in ACTIVE else None
    d["error"] = next((f"point {p['study_point']}: {p['error']}" for p in points if p["status"] == "failed" and p["error"]), None)
    return d


def point_results(store: Store, campaign: dict[str, Any]) -> tuple[dict[str, Any] | None, dict[str, int], bool]:
    """A point's results object, the tests each algorithm's row rests on, and whether it is
    partial: the stored results of a done point; otherwise the episodes recorded so far,
    reduced the same way (``reduce.AlgorithmTally``, a page at a time), or None if there are none."""
    from ra2vipas.services.learner.trained import TrainedPOD
    from ra2vipas.services.orchestrator.reduce import AlgorithmTally, held, results_object
    from ra2vipas.services.protocol.scenario import Scenario

    algorithms = campaign["algorithms"]
    if campaign["status"] == "done" and campaign.get("results"):
        return campaign["results"], {a: campaign["tests"] for a in algorithms}, False
    if not campaign["progress"]["done"]:
        return None, {}, True
    scenario = Scenario.model_validate(campaign["scenario"])
    steps = scenario.steps
    tallies = {a: AlgorithmTally(steps, scenario.rf_period_s) for a in algorithms}
    for row in store.episode_outcomes(campaign["id"]):
        tallies[row["algorithm"]].add(row["hits"], row["in_fov"], held(row.get("confidences") or [], steps) or None,
                                      row.get("decided_step"), row["n_estimates"], test_index=row.get("test_index"))
    shown = {a: t for a, t in tallies.items() if t.tests}
    if not shown:
        return None, {}, True
    pod = TrainedPOD(model=None, r2=campaign["pod_r2"], train_seconds=campaign["pod_train_seconds"] or 0.0)  # type: ignore[arg-type]
    stop = campaign.get("stop_confidence") or 0.0
    results = results_object(campaign["preset"], scenario, campaign["tests"], campaign["seed"], pod, shown, None, stop)
    return results, {a: t.tests for a, t in shown.items()}, True
