"""``ra2vipas bench dashboard``: how heavy and how fast the dashboard's pages are.

A finished campaign of TESTS tests x 4 algorithms x 120 steps is written straight into a new
SQLite file (synthetic outcomes with the shapes and sizes of real ones: hits, estimates, pans,
rewards, choices, confidences, 20 targets; its results object and POD model computed from
them), and a finished study of 8 points (n_targets) x up to 1000 tests x 4 algorithms (each
point's results object computed from synthetic outcomes); the orchestrator's app is served by
uvicorn on loopback (no rigs: nothing runs), and

* the server's render time of each page is timed over REPEATS requests (the campaign page of
  a 10 000-test campaign must render in < 1 s: its per-test table is paginated in SQL);
* a headless Chromium (Playwright, the system's browser) loads each page in a fresh context
  (cold cache) and again (warm): first paint, first contentful paint, DOMContentLoaded, load,
  bytes transferred (page weight) and requests.
"""

from __future__ import annotations

import json
import math
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ra2vipas.services.controller.registry import BUILTINS
from ra2vipas.services.orchestrator.metrics import summarize_algorithm
from ra2vipas.services.orchestrator.storage import Store
from ra2vipas.services.protocol.scenario import build_scenario

ALGORITHMS = list(BUILTINS)
STUDY_TESTS = 1000  # tests per point of the bench's study (at most)
SKILL = {"ra2vipas": (0.99, 8), "rapas": (0.92, 25), "ravipas": (0.68, 40), "sweep": (0.98, 80)}  # final hit rate, settling step


def seed_campaign(store: Store, tests: int, seed: int = 1, algorithms: list[str] | None = None) -> str:
    """Write a finished campaign of ``tests`` synthetic tests of every built-in (or of
    ``algorithms``: any names, a policy outside ``SKILL`` as a middling one); return its id."""
    algorithms = list(algorithms or ALGORITHMS)
    scenario = build_scenario("paper").model_dump(mode="json")
    steps, n = scenario["steps"], scenario["n_targets"]
    rng = np.random.default_rng(seed)
    cid = store.create_campaign(preset="paper", overrides={"n_targets": n}, scenario=scenario, algorithms=algorithms, tests=tests,
                                seed=seed, mode="fast", name=f"bench: {tests} tests")
    now = time.time()
    summaries = {}
    rows = []
    for algorithm in algorithms:
        rate, settle = SKILL.get(algorithm, (0.8, 30))
        finals = rng.random(tests) < rate
        settles = np.clip(rng.geometric(1.0 / settle, tests), 1, steps)
        t = np.arange(steps)[None, :]
        hits = np.where(finals[:, None], t >= settles[:, None], rng.random((tests, steps)) < 0.2)
        hits[:, -1] = finals
        confidences = np.clip(np.where(hits, 0.6 + 0.4 * rng.random((tests, steps)), 0.5 * rng.random((tests, steps))), 0, 1)
        summaries[algorithm] = summarize_algorithm(hits, hits, scenario["rf_period_s"], confidences)
        for k in range(tests):
            bearings = rng.uniform(-math.pi, math.pi, n)
            tx = int(rng.integers(n))
            chosen = np.where(hits[k], tx, (tx + 1) % n)
            estimates = bearings[chosen] + rng.normal(0, 0.01, steps)
            rows.append((json.dumps(hits[k].astype(int).tolist()), json.dumps(hits[k].astype(int).tolist()),
                         json.dumps(np.round(estimates, 6).tolist()), json.dumps(np.round(rng.uniform(-3.1, 3.1, steps), 6).tolist()),
                         json.dumps(np.round(rng.random(steps), 6).tolist()), json.dumps(chosen.tolist()), tx,
                         json.dumps(np.round(bearings, 6).tolist()), json.dumps(np.round(rng.uniform(0.5, 7, n), 4).tolist()),
                         json.dumps(np.round(confidences[k], 6).tolist()), now + len(rows) * 1e-4, cid, k, algorithm))
    with store.transaction() as db:
        db.executemany("UPDATE episodes SET status='done', rig='rig-1', hits=?, in_fov=?, estimates=?, pans=?, rewards=?, chosen=?,"
                       " tx_index=?, bearings=?, ranges=?, confidences=?, finished_at=? WHERE campaign_id=? AND test_index=? AND algorithm=?",
                       rows)
    grid = np.linspace(-80, -20, 120)
    from ra2vipas.services.protocol.scenario import Scenario
    from ra2vipas.services.sensors import physics

    true = physics.pod_of_rssi(Scenario.model_validate(scenario), grid)
    samples = rng.uniform(-75, -25, scenario["n_train"])
    store.set_pod_artifacts(cid, model={"rssi_grid_dbm": grid.tolist(), "mean": true.tolist(), "std": [0.05] * grid.size,
                                        "rf_noise_db": 3.0, "n_train": scenario["n_train"], "frames_per_rf": 10},
                            truth={"rssi_dbm": samples.tolist(), "pod": physics.pod_of_rssi(Scenario.model_validate(scenario), samples).tolist()})
    results = {"preset": "paper", "scenario": scenario, "tests": tests, "seed": seed, "pod": {"r2": 0.99, "train_seconds": 0.3},
               "algorithms": summaries, "steps_per_second": 3000.0}
    store.set_campaign(cid, status="done", started_at=now, finished_at=now + 1, pod_r2=0.99, pod_train_seconds=0.3,
                       results=json.dumps(results), steps_per_second=3000.0, pod_job="bench")
    return cid


STUDY_POINTS = [5, 10, 15, 20, 25, 30, 35, 40]  # n_targets of the bench's study


def seed_study(store: Store, tests: int, seed: int = 2) -> str:
    """Write a finished study over ``STUDY_POINTS`` (n_targets) of ``tests`` synthetic tests of
    every algorithm per point (each point's results object computed from synthetic hits and
    confidences); return its id."""
    from ra2vipas.services.orchestrator.study_store import StudyStore

    rng = np.random.default_rng(seed)
    points = []
    for n in STUDY_POINTS:
        points.append(({"n_targets": n}, build_scenario("paper", {"n_targets": n}).model_dump(mode="json")))
    sid, cids = StudyStore(store).create(preset="paper", overrides={}, vary={"n_targets": STUDY_POINTS}, points=points,
                                         algorithms=ALGORITHMS, tests=tests, seed=seed, mode="fast", name=f"bench: {tests} tests per point")
    now = time.time()
    for (overrides, scenario), cid in zip(points, cids):
        steps = scenario["steps"]
        summaries = {}
        for algorithm in ALGORITHMS:
            rate, settle = SKILL[algorithm]
            rate = rate * (1 - overrides["n_targets"] / 200)
            finals = rng.random(tests) < rate
            settles = np.clip(rng.geometric(1.0 / settle, tests), 1, steps)
            hits = np.where(finals[:, None], np.arange(steps)[None, :] >= settles[:, None], rng.random((tests, steps)) < 0.2)
            hits[:, -1] = finals
            confidences = np.clip(np.where(hits, 0.6 + 0.4 * rng.random((tests, steps)), 0.5 * rng.random((tests, steps))), 0, 1)
            summaries[algorithm] = summarize_algorithm(hits, hits, scenario["rf_period_s"], confidences)
        results = {"preset": "paper", "scenario": scenario, "tests": tests, "seed": seed, "pod": {"r2": 0.99, "train_seconds": 0.3},
                   "algorithms": summaries, "steps_per_second": 3000.0}
        with store.transaction() as db:
            db.execute("UPDATE episodes SET status='done', rig='rig-1', finished_at=? WHERE campaign_id=?", (now, cid))
        store.set_campaign(cid, status="done", started_at=now, finished_at=now + 1, pod_r2=0.99, pod_train_seconds=0.3,
                           results=json.dumps(results), steps_per_second=3000.0, pod_job="bench")
    return sid


class _Server:
    """The orchestrator's app on a loopback port, in this process (an in-memory bus, no rigs)."""

    def __init__(self, db_path: str) -> None:
        import uvicorn

        from ra2vipas.services.orchestrator.api.app import create_app
        from ra2vipas.services.orchestrator.settings import OrchestratorSettings
        from ra2vipas.services.transport.bus import MemoryBus

        self.bus = MemoryBus()
        app = create_app(OrchestratorSettings(host="127.0.0.1", port=0, db_path=db_path, plot_workers=1), bus_factory=lambda: self.bus)
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> str:
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("the orchestrator did not start")
            time.sleep(0.02)
        return f"http://127.0.0.1:{self.server.servers[0].sockets[0].getsockname()[1]}"

    def __exit__(self, *exc: Any) -> None:
        self.server.should_exit = True
        self.thread.join(20)
        self.bus.close()


def _stats(ms: list[float]) -> dict[str, float]:
    ordered = sorted(ms)
    return {"p50_ms": round(statistics.median(ordered), 1), "p95_ms": round(ordered[min(len(ordered) - 1, int(0.95 * len(ordered)))], 1),
            "max_ms": round(ordered[-1], 1), "bytes": None}


_PAINT = """() => {
  const nav = performance.getEntriesByType('navigation')[0];
  const paint = Object.fromEntries(performance.getEntriesByType('paint').map(e => [e.name, e.startTime]));
  const res = performance.getEntriesByType('resource');
  return {first_paint_ms: paint['first-paint'] ?? null, first_contentful_paint_ms: paint['first-contentful-paint'] ?? null,
          dom_content_loaded_ms: nav.domContentLoadedEventEnd, load_ms: nav.loadEventEnd,
          transferred_bytes: nav.transferSize + res.reduce((s, r) => s + r.transferSize, 0),
          decoded_bytes: nav.decodedBodySize + res.reduce((s, r) => s + r.decodedBodySize, 0),
          requests: 1 + res.length};
}"""


def run(tests: int = 10_000, repeats: int = 10, chromium: str | None = "/usr/bin/chromium") -> dict[str, Any]:
    """Seed, serve, measure; the report as a JSON-ready dict (``chromium=None``: server only)."""
    import httpx

    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-dashboard-") as tmp:
        db = str(Path(tmp) / "bench.db")
        store = Store(db)
        t0 = time.perf_counter()
        cid = seed_campaign(store, tests)
        sid = seed_study(store, min(tests, STUDY_TESTS))
        seed_s = time.perf_counter() - t0
        store.close()
        pages = {
            "campaigns": "/",
            "campaign": f"/ui/campaigns/{cid}",
            "campaign_missed_filter": f"/ui/campaigns/{cid}/tests?missed=true",
            "campaign_sorted_by_confidence_page_100": f"/ui/campaigns/{cid}/tests?sort=confidence&order=desc&offset={50 * 100}",
            "episode": f"/ui/campaigns/{cid}/tests/{tests // 2}/ra2vipas",
            "new_campaign": "/ui/new",
            "rigs": "/ui/rigs",
            "studies": "/ui/studies",
            "study": f"/ui/studies/{sid}",
        }
        report: dict[str, Any] = {"tests": tests, "algorithms": len(ALGORITHMS), "steps": 120, "episodes": tests * len(ALGORITHMS),
                                  "seed_seconds": round(seed_s, 2), "server": {}, "browser": None}
        with _Server(db) as url, httpx.Client(base_url=url, timeout=60, headers={"Accept-Encoding": "gzip"}) as http:
            for name, path in pages.items():
                times, size, wire = [], 0, 0
                for _ in range(repeats):
                    start = time.perf_counter()
                    r = http.get(path)
                    times.append((time.perf_counter() - start) * 1000)
                    r.raise_for_status()
                    size, wire = len(r.content), r.num_bytes_downloaded
                report["server"][name] = {**_stats(times), "bytes": size, "transferred_bytes": wire}
            report["campaign_page_under_1s"] = report["server"]["campaign"]["max_ms"] < 1000
            if chromium:
                report["browser"] = _browser(url, chromium, {k: v for k, v in pages.items() if not k.startswith("campaign_")})
    return report


def _measure(page) -> dict[str, Any]:
    """The paint and navigation timings once the paint entries are there (they may be
    recorded a moment after the load event)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function("performance.getEntriesByType('paint').length >= 2 && performance.getEntriesByType('navigation')[0].loadEventEnd > 0",
                               timeout=5000)
    except PlaywrightTimeout:  # a page that painted nothing new (a warm reload may not) reports null
        pass
    return page.evaluate(_PAINT)


def _browser(url: str, chromium: str, pages: dict[str, str]) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    out: dict[str, Any] = {"viewport": "1280x800"}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, headless=True, args=["--no-sandbox"])
        try:
            warmup = browser.new_context(base_url=url)  # the browser's own start-up is not the dashboard's
            warmup.new_page().goto("/ui/rigs", wait_until="load")
            warmup.close()
            for name, path in pages.items():
                # bypass_csp: the timing probes are the benchmark's scripts, which the pages' CSP (no eval) forbids
                context = browser.new_context(viewport={"width": 1280, "height": 800}, base_url=url, bypass_csp=True)
                page = context.new_page()
                page.goto(path, wait_until="load")
                cold = _measure(page)
                page.goto(path, wait_until="load")
                warm = _measure(page)
                context.close()
                out[name] = {"cold": {k: (round(v, 1) if isinstance(v, float) else v) for k, v in cold.items()},
                             "warm": {k: (round(v, 1) if isinstance(v, float) else v) for k, v in warm.items()}}
        finally:
            browser.close()
    return out
