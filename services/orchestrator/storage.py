"""Campaign storage: one SQLite file in WAL mode.

Rows here are the orchestrator's own records, distinct from wire messages and API schemas.
Every write is one transaction (``Store.transaction``), so a crash never leaves a
half-written test: an episode row is either still pending/running or done with its whole
trace. The schema carries a version (``meta.schema_version``) and migrations run on open.

A campaign moves queued -> training -> running -> done | failed | cancelled; once it is
finished its status never changes again (``set_campaign`` refuses), so a late result cannot
turn a cancelled campaign into a done one.

Storage faults (a full disk, a read-only file system, an I/O error) raise ``StorageFault``
and are remembered in ``Store.fault`` until a write succeeds again, so the API can answer
503 and ``/health`` can say why; a store that cannot even be opened (``Store(path,
lazy=True)``) starts unavailable and ``reopen()`` tries again. Nothing is half-written: a
failed transaction is rolled back whole.
"""

from __future__ import annotations

import errno
import json
import os
import sqlite3
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

from pydantic_core import to_json

SCHEMA_VERSION = 7

_MIGRATIONS: dict[int, str] = {
    1: """
    CREATE TABLE campaigns (
        id TEXT PRIMARY KEY,
        name TEXT,
        preset TEXT NOT NULL,
        overrides TEXT NOT NULL,
        scenario TEXT NOT NULL,
        algorithms TEXT NOT NULL,
        tests INTEGER NOT NULL,
        seed INTEGER NOT NULL,
        mode TEXT NOT NULL,
        status TEXT NOT NULL,
        created_at REAL NOT NULL,
        started_at REAL,
        finished_at REAL,
        pod_job TEXT,
        pod_r2 REAL,
        pod_train_seconds REAL,
        error TEXT,
        results TEXT,
        steps_per_second REAL
    );
    CREATE INDEX campaigns_status ON campaigns(status);
    CREATE TABLE episodes (
        campaign_id TEXT NOT NULL REFERENCES campaigns(id) ON DELETE CASCADE,
        test_index INTEGER NOT NULL,
        algorithm TEXT NOT NULL,
        status TEXT NOT NULL,
        rig TEXT,
        attempt INTEGER NOT NULL DEFAULT 0,
        hits TEXT,
        in_fov TEXT,
        estimates TEXT,
        pans TEXT,
        rewards TEXT,
        chosen TEXT,
        tx_index INTEGER,
        bearings TEXT,
        ranges TEXT,
        latencies TEXT,
        finished_at REAL,
        PRIMARY KEY (campaign_id, test_index, algorithm)
    );
    CREATE INDEX episodes_status ON episodes(campaign_id, status);
    """,
    # 2: the learned POD model (PODModel JSON) and its training episode's truth
    #    ({"rssi_dbm": [...], "pod": [...]}), for the POD figure (paper Fig. 3).
    2: """
    ALTER TABLE campaigns ADD COLUMN pod_model TEXT;
    ALTER TABLE campaigns ADD COLUMN pod_truth TEXT
    """,
    # 3: the walking targets' per-step truth of an episode (EpisodeTruth.trajectories:
    #    [{"index", "bearings_rad": [...], "ranges_m": [...]}]); NULL for a static world.
    3: """
    ALTER TABLE episodes ADD COLUMN trajectories TEXT
    """,
    # 4: confidence and early decision (issue 9): the campaign's stop_confidence (0 = off), each
    #    episode's per-step confidences (as the controller sent them) and the step it decided at.
    4: """
    ALTER TABLE campaigns ADD COLUMN stop_confidence REAL NOT NULL DEFAULT 0;
    ALTER TABLE episodes ADD COLUMN confidences TEXT;
    ALTER TABLE episodes ADD COLUMN decided_step INTEGER
    """,
    # 5: parameter studies (issue 10): a study row (its grid and campaign options) and, on each of
    #    its points' campaigns, the study and the point's index in the grid (study_store.py).
    5: """
    CREATE TABLE studies (
        id TEXT PRIMARY KEY,
        name TEXT,
        preset TEXT NOT NULL,
        overrides TEXT NOT NULL,
        vary TEXT NOT NULL,
        algorithms TEXT NOT NULL,
        tests INTEGER NOT NULL,
        seed INTEGER NOT NULL,
        mode TEXT NOT NULL,
        stop_confidence REAL NOT NULL DEFAULT 0,
        created_at REAL NOT NULL
    );
    CREATE INDEX studies_created ON studies(created_at);
    ALTER TABLE campaigns ADD COLUMN study_id TEXT REFERENCES studies(id);
    ALTER TABLE campaigns ADD COLUMN study_point INTEGER;
    CREATE INDEX campaigns_study ON campaigns(study_id, study_point)
    """,
    # 6: real rigs (issue 12): a campaign's rig targeting ({"rigs": [...] | null, "rig_kind": ... | null,
    #    "use_rig_values": bool, "rig_values": {param: value}}; NULL = any rig), and each episode's
    #    model check as its controller sent it (EpisodeResult.model_check; NULL from a v1 controller).
    6: """
    ALTER TABLE campaigns ADD COLUMN targeting TEXT;
    ALTER TABLE episodes ADD COLUMN model_check TEXT
    """,
    # 7: many tags (issue 21): an episode that searched for K > 1 tags, scored per tag
    #    ({"hits": [[0|1] * T] * K, "in_fov": same, "confidences": [[float] * T] * K | null,
    #    "decided": [step | null] * K}, the series held to the horizon); NULL for one tag.
    7: """
    ALTER TABLE episodes ADD COLUMN tags TEXT
    """,
}

ACTIVE = ("queued", "training", "running")
FINISHED = ("done", "failed", "cancelled")
EPISODE_STATES = ("pending", "running", "done", "cancelled")

# Every campaign column but the large POD artifacts (read them with ``Store.pod_artifacts``);
# lists leave out the results object too.
_LIST_COLUMNS = (
    "id, name, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at, started_at, finished_at,"
    " pod_job, pod_r2, pod_train_seconds, error, steps_per_second, stop_confidence, targeting"
)
_CAMPAIGN_COLUMNS = _LIST_COLUMNS + ", results"


def new_record_id() -> str:
    """A campaign's or study's id: 12 lower-case hex digits whose first is a letter (a-f), so that
    no table reader takes it for a number (pandas reads an all-digit id as an integer, and one
    such as ``123e45678901`` as a float). 16**11 x 6 ids: a clash needs ~10^6 records."""
    digits = uuid.uuid4().hex[:12]
    return "abcdef"[int(digits[0], 16) % 6] + digits[1:]


class StoreError(Exception):
    """A storage operation failed (e.g. the file cannot be opened or is from a newer version)."""


class StorageFault(StoreError):
    """The database cannot be read or written right now (disk full, read-only file system,
    I/O error, file missing). Transient: retry later; nothing was half-written."""


@dataclass(frozen=True)
class Fault:
    """The last storage fault: what failed, why, and since when (epoch seconds)."""

    operation: str
    cause: str
    since: float

    def describe(self) -> str:
        """One line, e.g. ``not writable: database or disk is full (since 12:01:02)``."""
        what = {"write": "not writable", "read": "not readable"}.get(self.operation, "unavailable")
        return f"{what}: {self.cause} (since {time.strftime('%H:%M:%S', time.localtime(self.since))})"


def _explain(err: BaseException, path: str) -> str:
    """The cause of a storage fault in one line. SQLite says "disk I/O error", "unable to open
    database file" or "attempt to write a readonly database" for a read-only file system or
    folder; the folder is checked so the cause names what it is ("read-only file system: disk
    I/O error", "permission denied: ...")."""
    text = str(err) or type(err).__name__
    if isinstance(err, OSError) and err.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return (err.strerror or text).lower()
    if isinstance(err, OSError) and err.strerror:
        text = err.strerror.lower()
    if isinstance(err, sqlite3.Error) or isinstance(err, OSError):
        folder = os.path.dirname(os.path.abspath(path)) or "."
        try:
            if os.statvfs(folder).f_flag & os.ST_RDONLY:
                return text if "read-only file system" in text else f"read-only file system: {text}"
            if not os.access(folder, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
                return text if "permission denied" in text else f"permission denied: {text}"
        except OSError:
            pass
    return text


class CampaignActiveError(StoreError):
    """The operation needs a finished campaign and this one is still queued, training or running."""


class CampaignInStudyError(StoreError):
    """The campaign is a point of a study: it goes with its study (delete the study)."""


@dataclass(frozen=True)
class EpisodeKey:
    campaign_id: str
    test_index: int
    algorithm: str


class Store:
    """Thread-safe access to the campaign database (one connection, one lock)."""

    def __init__(self, path: str, *, lazy: bool = False, guard: Callable[[], object] | None = None) -> None:
        """Open (and migrate) the database at ``path``.

        With ``lazy``, a database that cannot be opened now (read-only file system, I/O error)
        leaves the store unavailable, with the reason in ``fault``, instead of raising; call
        ``reopen()`` later. A file from a newer program version always raises. ``guard`` is
        called before each attempt to open (the orchestrator's ``DatabaseLock.acquire``, when
        it could not take the lock at start: the database is opened only once it holds it); an
        ``OSError`` or ``RuntimeError`` from it is a fault like the database's own.

        Raises
        ------
        StoreError
            The file cannot be opened (without ``lazy``), or its schema is newer than this program's.
        """
        self.path = path
        self._guard = guard
        self._lock = threading.RLock()
        self._db: sqlite3.Connection | None = None
        self.fault: Fault | None = None
        try:
            self.reopen()
        except StorageFault:
            if not lazy:
                raise

    @property
    def available(self) -> bool:
        """Whether the database is open."""
        return self._db is not None

    def reopen(self) -> None:
        """Open the database if it is not open (after a fault at start-up).

        Raises
        ------
        StorageFault
            It still cannot be opened; ``fault`` says why.
        """
        with self._lock:
            if self._db is not None:
                return
            db = None
            if self._guard is not None:
                try:
                    self._guard()
                except (OSError, RuntimeError) as err:
                    cause = (f"cannot lock the database: {_explain(err, self.path)}" if isinstance(err, OSError) else str(err))
                    self._record("open", RuntimeError(cause))
                    raise StorageFault(f"cannot open database {self.path!r}: {cause}") from None
            try:
                db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=30.0)
                db.row_factory = sqlite3.Row
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=NORMAL")
                db.execute("PRAGMA foreign_keys=ON")
                self._db = db
                self._migrate()
            except sqlite3.Error as err:
                self._db = None
                if db is not None:
                    db.close()
                self._record("open", err)
                raise StorageFault(f"cannot open database {self.path!r}: {err}") from None
            except StoreError:
                self._db = None
                db.close()
                raise
            self.fault = None

    # -- plumbing ---------------------------------------------------------------------------
    def _record(self, operation: str, err: BaseException) -> None:
        cause = _explain(err, self.path)
        if self.fault is None or (self.fault.operation, self.fault.cause) != (operation, cause):
            self.fault = Fault(operation=operation, cause=cause, since=time.time())

    def _conn(self) -> sqlite3.Connection:
        if self._db is None:
            raise StorageFault(f"database {self.path!r} is not open: {self.fault.cause if self.fault else 'closed'}")
        return self._db

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """BEGIN IMMEDIATE ... COMMIT, rolled back whole on any exception.

        Raises
        ------
        StorageFault
            The database could not be written (``fault`` keeps why until a write succeeds).
        """
        with self._lock:
            db = self._conn()
            try:
                db.execute("BEGIN IMMEDIATE")
                try:
                    yield db
                except BaseException:
                    if db.in_transaction:  # SQLite may have rolled back by itself (e.g. disk full)
                        db.execute("ROLLBACK")
                    raise
                db.execute("COMMIT")
            except sqlite3.Error as err:
                if db.in_transaction:
                    try:
                        db.execute("ROLLBACK")
                    except sqlite3.Error:
                        pass
                self._record("write", err)
                raise StorageFault(f"database {self.path!r} not writable: {err}") from None
            self.fault = None

    @contextmanager
    def _reading(self) -> Iterator[sqlite3.Connection]:
        """The connection for a read, under the lock; sqlite errors become ``StorageFault``."""
        with self._lock:
            db = self._conn()
            try:
                yield db
            except sqlite3.Error as err:
                self._record("read", err)
                raise StorageFault(f"database {self.path!r} cannot be read: {err}") from None

    def probe_write(self) -> None:
        """A small write (a heartbeat row) that clears ``fault`` if the database is writable.

        Raises
        ------
        StorageFault
            It is not.
        """
        with self.transaction() as db:
            db.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('heartbeat', ?)", (repr(time.time()),))

    def _migrate(self) -> None:
        db = self._conn()
        if db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='meta'").fetchone() is None:
            db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        row = db.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        version = int(row[0]) if row else 0
        if version > SCHEMA_VERSION:
            raise StoreError(f"database {self.path!r} has schema version {version}, newer than this program's {SCHEMA_VERSION}")
        for target in range(version + 1, SCHEMA_VERSION + 1):
            with self.transaction() as db:
                for statement in filter(str.strip, _MIGRATIONS[target].split(";")):
                    db.execute(statement)
                db.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('schema_version', ?)", (str(target),))

    def ping(self) -> bool:
        """Whether the database is open and answers a read."""
        try:
            with self._reading() as db:
                db.execute("SELECT 1").fetchone()
            return True
        except StorageFault:
            return False

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None

    # -- campaigns --------------------------------------------------------------------------
    def create_campaign(self, *, preset: str, overrides: dict, scenario: dict, algorithms: list[str], tests: int,
                        seed: int, mode: str, name: str | None = None, stop_confidence: float = 0.0,
                        targeting: dict | None = None) -> str:
        """Insert a campaign and all its pending episodes in one transaction; return its id.
        ``targeting``: the rigs it may run on (``{"rigs", "rig_kind", "use_rig_values",
        "rig_values"}``), None for any rig."""
        cid = new_record_id()
        now = time.time()
        with self.transaction() as db:
            db.execute(
                "INSERT INTO campaigns(id, name, preset, overrides, scenario, algorithms, tests, seed, mode, status, created_at,"
                " stop_confidence, targeting) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, 'queued', ?, ?, ?)",
                (cid, name, preset, json.dumps(overrides), json.dumps(scenario), json.dumps(algorithms), tests, seed, mode, now,
                 stop_confidence, None if targeting is None else json.dumps(targeting)),
            )
            db.executemany(
                "INSERT INTO episodes(campaign_id, test_index, algorithm, status) VALUES (?, ?, ?, 'pending')",
                [(cid, k, a) for k in range(tests) for a in algorithms],
            )
        return cid

    def campaign(self, cid: str) -> dict[str, Any] | None:
        with self._reading() as db:
            row = db.execute(f"SELECT {_CAMPAIGN_COLUMNS} FROM campaigns WHERE id=?", (cid,)).fetchone()
            if row is None:
                return None
            counts = dict(db.execute(
                "SELECT status, COUNT(*) FROM episodes WHERE campaign_id=? GROUP BY status", (cid,)).fetchall())
        return _campaign_dict(row, counts)

    def campaigns(self, *, status: str | None = None, preset: str | None = None, name: str | None = None, limit: int = 50,
                  offset: int = 0, standalone: bool = False) -> tuple[list[dict], int]:
        """One page of campaigns (without their results objects), newest first, optionally
        filtered (``name``: exact; ``standalone``: not the points of a study); and how many
        match in all."""
        clause, args = _where(status=status, preset=preset, name=name)
        if standalone:
            clause += (" AND " if clause else " WHERE ") + "study_id IS NULL"
        with self._reading() as db:
            total = db.execute(f"SELECT COUNT(*) FROM campaigns{clause}", args).fetchone()[0]
            rows = db.execute(f"SELECT {_LIST_COLUMNS} FROM campaigns{clause} ORDER BY created_at DESC, id LIMIT ? OFFSET ?",
                                    [*args, limit, offset]).fetchall()
            ids = [row["id"] for row in rows]
            counts: dict[str, dict[str, int]] = {i: {} for i in ids}
            if ids:
                for cid, st, n in db.execute(
                        f"SELECT campaign_id, status, COUNT(*) FROM episodes WHERE campaign_id IN ({','.join('?' * len(ids))})"
                        " GROUP BY campaign_id, status", ids):
                    counts[cid][st] = n
        return [_campaign_dict(row, counts[row["id"]]) for row in rows], total

    def active_campaigns(self) -> list[dict[str, Any]]:
        with self._reading() as db:
            ids = [r[0] for r in db.execute(
                f"SELECT id FROM campaigns WHERE status IN ({','.join('?' * len(ACTIVE))}) ORDER BY created_at, id", ACTIVE)]
        return [c for c in (self.campaign(i) for i in ids) if c]

    def set_campaign(self, cid: str, **fields: Any) -> bool:
        """Update columns of a campaign; False if nothing changed.

        An update that sets ``status`` applies only while the campaign is active: a finished
        campaign (done, failed, cancelled) keeps its status and everything written with it.
        """
        if not fields:
            return False
        cols = ", ".join(f"{k}=?" for k in fields)
        guard = f" AND status IN ({','.join('?' * len(ACTIVE))})" if "status" in fields else ""
        with self.transaction() as db:
            cur = db.execute(f"UPDATE campaigns SET {cols} WHERE id=?{guard}", [*fields.values(), cid, *(ACTIVE if guard else ())])
            return cur.rowcount > 0

    def cancel_campaign(self, cid: str) -> bool:
        """Mark an active campaign cancelled and its unfinished episodes with it, in one
        transaction; False if there is no such campaign or it had already finished."""
        with self.transaction() as db:
            cur = db.execute(
                f"UPDATE campaigns SET status='cancelled', finished_at=? WHERE id=? AND status IN ({','.join('?' * len(ACTIVE))})",
                (time.time(), cid, *ACTIVE))
            if cur.rowcount == 0:
                return False
            db.execute("UPDATE episodes SET status='cancelled', rig=NULL WHERE campaign_id=? AND status IN ('pending', 'running')", (cid,))
            return True

    def delete_campaign(self, cid: str) -> bool:
        """Delete a finished campaign with all its episodes; False if there is no such campaign.

        Raises
        ------
        CampaignActiveError
            The campaign is still queued, training or running (cancel it first).
        CampaignInStudyError
            The campaign is a point of a study (delete the study).
        """
        with self.transaction() as db:
            row = db.execute("SELECT status, study_id FROM campaigns WHERE id=?", (cid,)).fetchone()
            if row is None:
                return False
            if row[0] in ACTIVE:
                raise CampaignActiveError(f"campaign {cid} is {row[0]}; cancel it first")
            if row[1] is not None:
                raise CampaignInStudyError(f"campaign {cid} is a point of study {row[1]}; delete the study instead")
            db.execute("DELETE FROM episodes WHERE campaign_id=?", (cid,))
            db.execute("DELETE FROM campaigns WHERE id=?", (cid,))
            return True

    def set_pod_artifacts(self, cid: str, *, model: dict | None, truth: dict | None) -> None:
        """Keep the learned POD model (PODModel as JSON data) and its training truth
        (``{"rssi_dbm": [...], "pod": [...]}``) for the POD figure."""
        self.set_campaign(cid, pod_model=None if model is None else json.dumps(model, separators=(",", ":")),
                          pod_truth=None if truth is None else json.dumps(truth, separators=(",", ":")))

    def pod_artifacts(self, cid: str) -> dict[str, Any] | None:
        """``{"model": dict | None, "truth": dict | None}``; None if there is no such campaign."""
        with self._reading() as db:
            row = db.execute("SELECT pod_model, pod_truth FROM campaigns WHERE id=?", (cid,)).fetchone()
        if row is None:
            return None
        return {"model": None if row[0] is None else json.loads(row[0]), "truth": None if row[1] is None else json.loads(row[1])}

    # -- episodes ---------------------------------------------------------------------------
    def pending_episodes(self, cid: str) -> list[EpisodeKey]:
        with self._reading() as db:
            rows = db.execute(
                "SELECT test_index, algorithm FROM episodes WHERE campaign_id=? AND status='pending' ORDER BY test_index, rowid",
                (cid,)).fetchall()
        return [EpisodeKey(cid, r[0], r[1]) for r in rows]

    def reset_running(self, cid: str) -> int:
        """Put every running episode of a campaign back to pending (after a restart)."""
        with self.transaction() as db:
            return db.execute("UPDATE episodes SET status='pending', rig=NULL WHERE campaign_id=? AND status='running'", (cid,)).rowcount

    def mark_running_many(self, keys: Sequence[EpisodeKey], rig: str) -> list[int]:
        """Mark episodes running on ``rig`` in one transaction, each with its next attempt
        number (``attempt_of`` + 1, what ``mark_running`` is given); their attempt numbers.

        Raises
        ------
        StorageFault
            The database could not be written (nothing is marked).
        """
        attempts: list[int] = []
        with self.transaction() as db:
            for key in keys:
                row = db.execute("SELECT attempt FROM episodes WHERE campaign_id=? AND test_index=? AND algorithm=?",
                                 (key.campaign_id, key.test_index, key.algorithm)).fetchone()
                attempt = (int(row[0]) if row and row[0] is not None else 0) + 1
                db.execute("UPDATE episodes SET status='running', rig=?, attempt=? WHERE campaign_id=? AND test_index=? AND algorithm=? AND status!='done'",
                           (rig, attempt, key.campaign_id, key.test_index, key.algorithm))
                attempts.append(attempt)
        return attempts

    def mark_running(self, key: EpisodeKey, rig: str, attempt: int) -> None:
        with self.transaction() as db:
            db.execute("UPDATE episodes SET status='running', rig=?, attempt=? WHERE campaign_id=? AND test_index=? AND algorithm=? AND status!='done'",
                       (rig, attempt, key.campaign_id, key.test_index, key.algorithm))

    def mark_pending(self, key: EpisodeKey) -> None:
        with self.transaction() as db:
            db.execute("UPDATE episodes SET status='pending', rig=NULL WHERE campaign_id=? AND test_index=? AND algorithm=? AND status='running'",
                       (key.campaign_id, key.test_index, key.algorithm))

    def attempt_of(self, key: EpisodeKey) -> int:
        with self._reading() as db:
            row = db.execute("SELECT attempt FROM episodes WHERE campaign_id=? AND test_index=? AND algorithm=?",
                                   (key.campaign_id, key.test_index, key.algorithm)).fetchone()
        return int(row[0]) if row else 0

    def finish_episode(self, key: EpisodeKey, *, hits: list[bool], in_fov: list[bool], estimates: list[float], pans: list[float],
                       rewards: list[float], chosen: list[int], tx_index: int, bearings: list[float], ranges: list[float],
                       latencies: list[float] | None, trajectories: list[dict] | None = None,
                       confidences: list[float] | None = None, decided_step: int | None = None,
                       model_check: dict | None = None, tags: dict | None = None) -> bool:
        """Record a finished test in one transaction; False if it was already recorded (no
        duplicate) or its campaign was cancelled. ``bearings``/``ranges`` are the targets at
        step 0; ``trajectories`` the walking ones' per-step truth, if any; ``confidences`` the
        controller's per step (None from a v1 controller); ``decided_step`` an early decision;
        ``model_check`` how the controller modelled the rig (None from a v1 controller); ``tags``
        a search for several tags scored per tag (schema 7's ``episodes.tags``; None for one tag)."""
        return self.finish_episodes([(key, dict(
            hits=hits, in_fov=in_fov, estimates=estimates, pans=pans, rewards=rewards, chosen=chosen, tx_index=tx_index,
            bearings=bearings, ranges=ranges, latencies=latencies, trajectories=trajectories, confidences=confidences,
            decided_step=decided_step, model_check=model_check, tags=tags))])[0]

    def finish_episodes(self, finished: Sequence[tuple[EpisodeKey, dict[str, Any]]]) -> list[bool]:
        """Record finished tests in one transaction (the orchestrator saves a burst of them at
        once: one commit instead of one each); each ``(key, fields)`` as ``finish_episode``'s
        keyword arguments. Per test, False if it was already recorded or its campaign cancelled.

        Raises
        ------
        StorageFault
            The database could not be written (none of them is recorded).
        """
        now = time.time()
        with self.transaction() as db:
            return [db.execute(_FINISH_SQL, _finished_row(key, now, **fields)).rowcount == 1 for key, fields in finished]

    def episode_rows(self, cid: str, status: str | None = "done") -> list[dict[str, Any]]:
        with self._reading() as db:
            if status is None:
                rows = db.execute("SELECT * FROM episodes WHERE campaign_id=? ORDER BY test_index, algorithm", (cid,)).fetchall()
            else:
                rows = db.execute("SELECT * FROM episodes WHERE campaign_id=? AND status=? ORDER BY test_index, algorithm", (cid, status)).fetchall()
        return [_episode_dict(r) for r in rows]

    def episode_outcomes(self, cid: str, page: int = 500) -> Iterator[dict[str, Any]]:
        """A campaign's done episodes in (test index, algorithm) order, a page at a time (the lock
        is released between pages), each with only what its reduction needs: ``hits``,
        ``in_fov``, ``confidences`` (None from a v1 controller), ``decided_step``, ``latencies``,
        ``rig``, ``model_check`` (None from a v1 controller), ``tags`` (per tag, None for one tag) and ``n_estimates`` (control steps run). Memory holds one page, whatever the campaign's size.

        Raises
        ------
        StorageFault
            The database cannot be read.
        """
        after: tuple[int, str] = (-1, "")
        while True:
            with self._reading() as db:
                rows = db.execute(
                    "SELECT test_index, algorithm, rig, hits, in_fov, confidences, decided_step, latencies, model_check, tags,"
                    " json_array_length(estimates) AS n_estimates FROM episodes"
                    " WHERE campaign_id=? AND status='done' AND (test_index, algorithm) > (?, ?)"
                    " ORDER BY test_index, algorithm LIMIT ?", (cid, *after, page)).fetchall()
            for row in rows:
                yield _episode_dict(row)
            if len(rows) < page:
                return
            after = (rows[-1]["test_index"], rows[-1]["algorithm"])

    def episode_page(self, cid: str, *, algorithm: str | None = None, status: str | None = None, hit: bool | None = None,
                     limit: int = 50, offset: int = 0) -> tuple[list[dict[str, Any]], int]:
        """One page of a campaign's episodes ordered by (test index, algorithm), optionally
        filtered (``hit``: finished on the Tx or not; implies done); and how many match in all.
        Rows are summaries: ``hits`` per step and the last step's ``final_choice`` (î),
        ``final_in_fov`` and ``final_estimate`` (gamma_hat), not the whole trace."""
        clause, args = _where(campaign_id=cid, algorithm=algorithm, status=status)
        if hit is not None:
            clause += " AND status='done' AND json_extract(hits, '$[#-1]')=?"
            args = [*args, 1 if hit else 0]
        with self._reading() as db:
            total = db.execute(f"SELECT COUNT(*) FROM episodes{clause}", args).fetchone()[0]
            rows = db.execute(
                "SELECT test_index, algorithm, status, rig, attempt, tx_index, hits, json_extract(chosen, '$[#-1]') AS final_choice,"
                " json_extract(in_fov, '$[#-1]') AS final_in_fov, json_extract(estimates, '$[#-1]') AS final_estimate,"
                " json_extract(confidences, '$[#-1]') AS final_confidence, decided_step"
                f" FROM episodes{clause} ORDER BY test_index, algorithm LIMIT ? OFFSET ?", [*args, limit, offset]).fetchall()
        return [_episode_dict(r) for r in rows], total

    # -- dashboard reads (ra2vipas.services.orchestrator.dashboard) ------------------------------
    def test_page(self, cid: str, *, missed_by: str | None = None, sort: str = "test", sort_algorithm: str | None = None,
                  descending: bool = False, limit: int = 50, offset: int = 0) -> tuple[list[dict[str, Any]], int]:
        """One page of a campaign's *tests* (every algorithm's summary row of each, shaped as
        ``episode_page``'s) and how many tests match in all.

        ``missed_by``: only the tests this algorithm finished on a miss (î at the last step is
        not the Tx). ``sort``: ``test`` (index) or ``confidence`` (``sort_algorithm``'s final
        confidence; tests without one last), then by index.
        """
        if sort not in ("test", "confidence"):
            raise ValueError(f"sort: expected test|confidence, got {sort!r}")
        where, args = ["campaign_id=?", "algorithm=?"], [cid, missed_by or sort_algorithm]
        if missed_by:
            where.append("status='done' AND json_extract(hits, '$[#-1]')=0")
        if args[1] is None:  # neither a filter nor a sort by algorithm: one row per test from any algorithm
            where, args = ["campaign_id=?", "algorithm=(SELECT MIN(algorithm) FROM episodes WHERE campaign_id=?)"], [cid, cid]
        direction = "DESC" if descending else "ASC"
        order = f"test_index {direction}"
        if sort == "confidence":
            order = f"json_extract(confidences, '$[#-1]') IS NULL, json_extract(confidences, '$[#-1]') {direction}, test_index"
        clause = " WHERE " + " AND ".join(where)
        with self._reading() as db:
            total = db.execute(f"SELECT COUNT(*) FROM episodes{clause}", args).fetchone()[0]
            tests = [r[0] for r in db.execute(f"SELECT test_index FROM episodes{clause} ORDER BY {order} LIMIT ? OFFSET ?",
                                              [*args, limit, offset])]
            if not tests:
                return [], total
            rows = db.execute(
                "SELECT test_index, algorithm, status, rig, attempt, tx_index, hits, json_extract(chosen, '$[#-1]') AS final_choice,"
                " json_extract(in_fov, '$[#-1]') AS final_in_fov, json_extract(estimates, '$[#-1]') AS final_estimate,"
                " json_extract(confidences, '$[#-1]') AS final_confidence, decided_step"
                f" FROM episodes WHERE campaign_id=? AND test_index IN ({','.join('?' * len(tests))})", [cid, *tests]).fetchall()
        rank = {k: i for i, k in enumerate(tests)}
        out = sorted((_episode_dict(r) for r in rows), key=lambda d: (rank[d["test_index"]], d["algorithm"]))
        return out, total

    def done_hits(self, cid: str, after: tuple[float, int, str] | None = None, limit: int = 2000) -> list[tuple[float, int, str, list[int]]]:
        """Finished episodes' per-step hits, in the order they were recorded, after the key
        ``(finished_at, test_index, algorithm)`` (exclusive; None: from the first): up to
        ``limit`` of ``(finished_at, test_index, algorithm, hits)``. A recorded episode never
        changes, so a reader that keeps the last key sees every episode exactly once."""
        key = after or (-1.0, -1, "")
        with self._reading() as db:
            rows = db.execute(
                "SELECT finished_at, test_index, algorithm, hits FROM episodes WHERE campaign_id=? AND status='done'"
                " AND (finished_at, test_index, algorithm) > (?, ?, ?) ORDER BY finished_at, test_index, algorithm LIMIT ?",
                (cid, *key, limit)).fetchall()
        return [(r[0], r[1], r[2], json.loads(r[3])) for r in rows]

    def episode(self, cid: str, test_index: int, algorithm: str) -> dict[str, Any] | None:
        with self._reading() as db:
            row = db.execute("SELECT * FROM episodes WHERE campaign_id=? AND test_index=? AND algorithm=?", (cid, test_index, algorithm)).fetchone()
        return None if row is None else _episode_dict(row)


def _where(**equal: Any) -> tuple[str, list[Any]]:
    """A ``WHERE column=? AND ...`` clause and its arguments for the filters that are set
    (column names come from the keyword names, never from input)."""
    columns = [name for name, value in equal.items() if value]
    return (" WHERE " + " AND ".join(f"{c}=?" for c in columns)) if columns else "", [equal[c] for c in columns]


def _campaign_dict(row: sqlite3.Row, counts: dict[str, int]) -> dict[str, Any]:
    d = dict(row)
    for k in ("overrides", "scenario", "algorithms", "results", "targeting"):
        if d.get(k) is not None:
            d[k] = json.loads(d[k])
    total = sum(counts.values())
    d["progress"] = {"done": counts.get("done", 0), "running": counts.get("running", 0), "pending": counts.get("pending", 0), "total": total}
    return d


_FINISH_SQL = ("UPDATE episodes SET status='done', hits=?, in_fov=?, estimates=?, pans=?, rewards=?, chosen=?, tx_index=?,"
               " bearings=?, ranges=?, latencies=?, trajectories=?, confidences=?, decided_step=?, model_check=?, tags=?, finished_at=?"
               " WHERE campaign_id=? AND test_index=? AND algorithm=? AND status IN ('pending', 'running')")


def _json_text(value: Any) -> str:
    """Compact JSON text of a stored list or object, encoded in Rust (``pydantic_core``; several
    times ``json.dumps``'s speed on float lists): floats in their shortest round-trip form, so
    ``json.loads`` reads back exactly the values ``json.dumps`` would have written; NaN and
    infinities as ``json.dumps`` writes them."""
    return to_json(value, inf_nan_mode="constants").decode()


def _finished_row(key: EpisodeKey, finished_at: float, *, hits: list[bool], in_fov: list[bool], estimates: list[float],
                  pans: list[float], rewards: list[float], chosen: list[int], tx_index: int, bearings: list[float],
                  ranges: list[float], latencies: list[float] | None, trajectories: list[dict] | None = None,
                  confidences: list[float] | None = None, decided_step: int | None = None,
                  model_check: dict | None = None, tags: dict | None = None) -> tuple:
    """The parameters of ``_FINISH_SQL`` for one finished test."""
    return (_json_text([int(h) for h in hits]), _json_text([int(f) for f in in_fov]), _json_text(estimates), _json_text(pans),
            _json_text(rewards), _json_text(chosen), tx_index, _json_text(bearings), _json_text(ranges),
            None if latencies is None else _json_text(latencies),
            None if trajectories is None else _json_text(trajectories),
            None if confidences is None else _json_text(confidences), decided_step,
            None if model_check is None else _json_text(model_check), None if tags is None else _json_text(tags), finished_at,
            key.campaign_id, key.test_index, key.algorithm)


def _episode_dict(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    for k in ("hits", "in_fov", "estimates", "pans", "rewards", "chosen", "bearings", "ranges", "latencies", "trajectories",
              "confidences", "model_check", "tags"):
        if d.get(k) is not None:
            d[k] = json.loads(d[k])
    return d
