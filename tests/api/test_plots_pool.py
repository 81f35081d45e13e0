"""Figures through the API: drawn by renderer processes, cached, bounded, and cleaned up.

A real uvicorn server and SQLite file (``LiveAPI``) with the real renderer pool. To saturate
the pool deterministically, a test swaps the renderers' function for one that waits for a
gate file before drawing (it runs in the renderer process, so it must be importable there).
"""

from __future__ import annotations

import asyncio
import functools
import os
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from fastapi import HTTPException

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.orchestrator.api.app import create_app
from ra2vipas.services.orchestrator.api.render import FigureSource, PlotKey, PlotRenderer, Saturated
from ra2vipas.services.orchestrator.settings import OrchestratorSettings
from ra2vipas.services.protocol.scenario import build_scenario
from tests import http
from tests.api.live import SMALL, LiveAPI
from tests.conftest import restore_ctrl_c

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
WAIT_S = 60.0


def gated_draw(gate: str, job: plots.PlotJob) -> bytes:
    """Runs in a renderer process: wait until ``gate`` exists, then draw as usual."""
    while not os.path.exists(gate):
        time.sleep(0.01)
    return plots.draw_job(job)


def wait_until(predicate, what: str, timeout: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def gone(pid: int) -> bool:
    """The process has exited (a zombie waiting for its reaper counts as exited)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except (FileNotFoundError, ProcessLookupError):
        return True


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_MAGIC and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def run_campaign(server: LiveAPI, tests: int = 3, algorithms=("ra2vipas", "rapas"), seed: int = 5) -> str:
    with server.client() as http:
        r = http.post("/campaigns", json={"overrides": SMALL, "algorithms": list(algorithms), "tests": tests, "seed": seed})
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    assert server.wait(cid)["status"] == "done"
    return cid


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """The API with one renderer (capacity: 2 renders running or queued)."""
    live = LiveAPI(tmp_path_factory.mktemp("plots") / "plots.db").start()
    yield live
    live.stop()


@pytest.fixture(scope="module")
def campaign(server) -> str:
    return run_campaign(server)


@pytest.fixture()
def gate(server, tmp_path):
    """Renderers wait for the returned path to exist before drawing; always opened afterwards."""
    renderer = server.app.state.renderer
    path = tmp_path / "gate"
    renderer.render = functools.partial(gated_draw, str(path))
    yield path
    path.touch()
    wait_until(lambda: renderer.in_flight() == 0, "the gated renders to finish")
    renderer.render = plots.draw_job


FIGURES = [("/plots/dr", "dr", ()), ("/plots/pod", "pod", ()), ("/tests/1/rapas/plot", "episode", (1, "rapas"))]


@pytest.mark.parametrize("fmt", ["png", "svg"])
@pytest.mark.parametrize("path, kind, params", FIGURES, ids=[f[1] for f in FIGURES])
def test_a_figure_is_drawn_once_then_served_from_the_cache(server, campaign, path, kind, params, fmt):
    renderer = server.app.state.renderer
    key = PlotKey(campaign, kind, fmt, params)
    assert renderer.cached(key) is None
    with server.client() as http:
        before = renderer.stats.renders
        first = http.get(f"/campaigns/{campaign}{path}", params={"format": fmt})
        assert first.status_code == 200, first.text
        assert renderer.stats.renders == before + 1
        hits = renderer.stats.hits
        again = http.get(f"/campaigns/{campaign}{path}", params={"format": fmt})
    assert again.status_code == 200 and again.content == first.content
    assert renderer.stats.renders == before + 1, "the second request went to the renderers again"
    assert renderer.stats.hits == hits + 1
    assert renderer.cached(key) == first.content
    if fmt == "png":
        assert first.headers["content-type"] == "image/png"
        width, height = png_size(first.content)
        assert width > 500 and height > 300
    else:
        assert first.headers["content-type"].startswith("image/svg+xml")
        root = ET.fromstring(first.content)
        assert root.tag == "{http://www.w3.org/2000/svg}svg" and len(list(root.iter())) > 50


def test_the_accept_header_and_the_format_parameter_share_one_cached_figure(server, campaign):
    renderer = server.app.state.renderer
    with server.client() as http:
        by_query = http.get(f"/campaigns/{campaign}/tests/0/ra2vipas/plot", params={"format": "svg"})
        renders = renderer.stats.renders
        by_accept = http.get(f"/campaigns/{campaign}/tests/0/ra2vipas/plot", headers={"Accept": "image/svg+xml"})
    assert by_query.status_code == by_accept.status_code == 200
    assert by_accept.content == by_query.content and renderer.stats.renders == renders


def test_deleting_a_campaign_evicts_its_figures_and_only_its(server, campaign):
    renderer = server.app.state.renderer
    doomed = run_campaign(server, tests=1, algorithms=("rapas",), seed=11)
    with server.client() as http:
        for path in ("/plots/dr", "/plots/pod", "/tests/0/rapas/plot"):
            assert http.get(f"/campaigns/{doomed}{path}").status_code == 200
        assert http.get(f"/campaigns/{campaign}/plots/dr").status_code == 200
        doomed_keys = [PlotKey(doomed, "dr", "png"), PlotKey(doomed, "pod", "png"),
                       PlotKey(doomed, "episode", "png", (0, "rapas"))]
        assert all(renderer.cached(k) is not None for k in doomed_keys)
        figures, size = renderer.cache_size()
        assert http.delete(f"/campaigns/{doomed}").status_code == 204
        assert all(renderer.cached(k) is None for k in doomed_keys)
        assert renderer.cache_size()[0] == figures - 3 and renderer.cache_size()[1] < size
        assert renderer.cached(PlotKey(campaign, "dr", "png")) is not None
        for path in ("/plots/dr", "/plots/pod", "/tests/0/rapas/plot"):
            r = http.get(f"/campaigns/{doomed}{path}")
            assert r.status_code == 404 and "no campaign" in r.json()["detail"]


def test_a_render_in_flight_when_its_campaign_is_deleted_is_not_kept(server, gate):
    renderer = server.app.state.renderer
    doomed = run_campaign(server, tests=1, algorithms=("ra2vipas",), seed=12)
    with ThreadPoolExecutor(1) as pool, server.client() as http:
        pending = pool.submit(http.get, f"/campaigns/{doomed}/plots/dr")
        wait_until(lambda: renderer.in_flight() == 1, "the render to start")
        assert http.delete(f"/campaigns/{doomed}").status_code == 204
        gate.touch()
        assert pending.result(WAIT_S).status_code == 200  # asked before the delete: answered
    assert renderer.cached(PlotKey(doomed, "dr", "png")) is None


def test_a_saturated_pool_answers_503_with_retry_after_and_identical_requests_share_a_render(server, campaign, gate):
    renderer = server.app.state.renderer
    assert renderer.capacity == 2
    base = f"/campaigns/{campaign}/tests"
    stats = renderer.stats
    renders, shared, rejected = stats.renders, stats.shared, stats.rejected
    with ThreadPoolExecutor(4) as pool, server.client() as http:
        a = pool.submit(http.get, f"{base}/2/ra2vipas/plot")
        b = pool.submit(http.get, f"{base}/2/rapas/plot")
        wait_until(lambda: renderer.in_flight() == 2, "two renders in flight")
        a_again = pool.submit(http.get, f"{base}/2/ra2vipas/plot")
        wait_until(lambda: stats.shared == shared + 1, "the identical request to join the render in flight")

        refused = http.get(f"{base}/2/ra2vipas/plot", params={"format": "svg"})
        assert refused.status_code == 503
        assert refused.headers["content-type"] == "application/json"
        assert int(refused.headers["retry-after"]) >= 1
        assert "busy" in refused.json()["detail"]
        assert stats.rejected == rejected + 1
        # what is cached is still served while the renderers are saturated
        assert http.get(f"/campaigns/{campaign}/plots/dr").status_code == 200

        gate.touch()
        results = [f.result(WAIT_S) for f in (a, b, a_again)]
    assert [r.status_code for r in results] == [200, 200, 200]
    assert results[0].content == results[2].content != results[1].content
    assert results[0].content.startswith(PNG_MAGIC)
    assert stats.renders == renders + 2, "identical requests must share one render"
    with server.client() as http:
        assert http.get(f"{base}/2/ra2vipas/plot", params={"format": "svg"}).status_code == 200


def test_renderers_run_at_a_low_priority_under_the_normal_policy(server, campaign):
    renderer = server.app.state.renderer
    with server.client() as http:
        assert http.get(f"/campaigns/{campaign}/plots/dr").status_code == 200
    pids = renderer.pids()
    assert pids
    for pid in pids:
        assert os.getpriority(os.PRIO_PROCESS, pid) == 10
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER  # not SCHED_IDLE: see the next test


def test_a_figure_arrives_while_its_core_is_busy(server, campaign):
    """A busy machine slows a render but never starves it: with the renderer and a spinning
    nice-0 process pinned to one core, a figure not drawn yet still comes back (under SCHED_IDLE
    it never did: every request timed out for as long as the spinner ran). One core, so the
    test takes no CPU from the rest of the machine."""
    renderer = server.app.state.renderer
    key = PlotKey(campaign, "episode", "svg", (2, "rapas"))
    assert renderer.cached(key) is None
    with server.client() as http:  # the renderer process exists once it has drawn something
        assert http.get(f"/campaigns/{campaign}/plots/dr").status_code == 200
    [pid] = renderer.pids()
    core = min(os.sched_getaffinity(pid))
    before = os.sched_getaffinity(pid)
    spinner = subprocess.Popen([sys.executable, "-c", f"import os; os.sched_setaffinity(0, {{{core}}})\nwhile True: pass"])
    try:
        os.sched_setaffinity(pid, {core})
        with httpx.Client(base_url=server.url, timeout=2 * WAIT_S) as http:
            response = http.get(f"/campaigns/{campaign}/tests/2/rapas/plot", params={"format": "svg"})
    finally:
        spinner.kill()
        spinner.wait()
        os.sched_setaffinity(pid, before)
    assert response.status_code == 200 and b"<svg" in response.content
    assert renderer.cached(key) is not None


def test_a_killed_renderer_is_replaced(server, campaign):
    renderer = server.app.state.renderer
    with server.client() as http:
        assert http.get(f"/campaigns/{campaign}/tests/0/rapas/plot").status_code == 200
        old = renderer.pids()
        assert old
        assert renderer.cached(PlotKey(campaign, "episode", "png", (1, "ra2vipas"))) is None
        for pid in old:
            os.kill(pid, signal.SIGKILL)
        statuses = []

        def drawn() -> bool:  # a dead renderer may cost one 503; the next request gets a new one
            r = http.get(f"/campaigns/{campaign}/tests/1/ra2vipas/plot", params={"format": "png"})
            statuses.append(r.status_code)
            assert r.status_code in (200, 503), r.text
            return r.status_code == 200

        wait_until(drawn, "a figure after the renderer was killed")
    assert renderer.stats.restarts >= 1
    assert renderer.pids() and not set(renderer.pids()) & set(old)


def pod_job(fmt: str = "png") -> plots.PlotJob:
    return plots.PlotJob("pod", fmt, {"scenario": build_scenario("paper").model_dump(mode="json"),
                                      "model": {"rssi_grid_dbm": [-60.0, -20.0], "mean": [0.1, 0.9], "std": [0.1, 0.1]},
                                      "truth": None, "title": "t"})


def test_a_saturated_renderer_refuses_before_reading_and_a_failed_read_reaches_every_waiter(tmp_path):
    gate = tmp_path / "gate"

    async def scenario() -> None:
        renderer = PlotRenderer(1, capacity=1, render=functools.partial(gated_draw, str(gate))).start()
        reads: list[str] = []
        release = asyncio.Event()

        async def read_pod() -> FigureSource:
            reads.append("pod")
            return FigureSource(pod_job())

        async def read_missing() -> FigureSource:
            reads.append("missing")
            await release.wait()
            raise HTTPException(404, "no campaign 'x'")

        try:
            drawing = asyncio.create_task(renderer.figure(PlotKey("c", "pod", "png"), read_pod))
            while renderer.stats.renders < 1:
                await asyncio.sleep(0.01)
            with pytest.raises(Saturated) as refused:
                await renderer.figure(PlotKey("c", "pod", "svg"), read_pod)
            assert refused.value.retry_after >= 1 and reads == ["pod"], "a refused request must not read the store"
            gate.touch()
            assert (await drawing).startswith(PNG_MAGIC)

            first = asyncio.create_task(renderer.figure(PlotKey("x", "dr", "png"), read_missing))
            second = asyncio.create_task(renderer.figure(PlotKey("x", "dr", "png"), read_missing))
            while renderer.stats.shared < 1:
                await asyncio.sleep(0.01)
            release.set()
            for task in (first, second):
                with pytest.raises(HTTPException) as missing:
                    await task
                assert missing.value.status_code == 404
            assert reads == ["pod", "missing"] and renderer.in_flight() == 0 and renderer.stats.renders == 1
        finally:
            gate.touch()
            renderer.close()

    asyncio.run(scenario())


def test_plot_routes_document_the_503_and_its_retry_after_header():
    paths = create_app(OrchestratorSettings()).openapi()["paths"]
    for path in ("/campaigns/{campaign_id}/plots/dr", "/campaigns/{campaign_id}/plots/pod",
                 "/campaigns/{campaign_id}/tests/{test_index}/{algorithm}/plot"):
        doc = paths[path]["get"]["responses"]["503"]
        assert "Retry-After" in doc["headers"]
        assert doc["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorPublic")


def test_renderer_processes_exit_when_the_app_shuts_down_even_mid_render(tmp_path):
    live = LiveAPI(tmp_path / "stop.db").start()
    stopped = False
    try:
        cid = run_campaign(live, tests=1, algorithms=("ra2vipas",))
        renderer = live.app.state.renderer
        with live.client() as http:
            assert http.get(f"/campaigns/{cid}/plots/dr").status_code == 200
        pids = renderer.pids()
        assert len(pids) == 1 and not gone(pids[0])
        renderer.render = functools.partial(gated_draw, str(tmp_path / "never"))  # this render never ends by itself
        client = httpx.Client(base_url=live.url, timeout=WAIT_S)
        stuck = threading.Thread(target=lambda: _ignore_errors(client.get, f"/campaigns/{cid}/plots/pod"), daemon=True)
        stuck.start()
        wait_until(lambda: renderer.in_flight() == 1, "the stuck render")
        live.stop()
        stopped = True
        stuck.join(WAIT_S)
        client.close()
        assert all(gone(pid) for pid in pids), "a renderer process outlived the app"
        assert renderer.pids() == []
    finally:
        if not stopped:
            live.stop()


def _ignore_errors(fn, *args):
    try:
        fn(*args)
    except httpx.HTTPError:
        pass


CHILD = textwrap.dedent("""
    import asyncio, sys
    from ra2vipas.services.orchestrator import plots
    from ra2vipas.services.orchestrator.api.render import FigureSource, PlotKey, PlotRenderer
    from ra2vipas.services.protocol.scenario import build_scenario

    async def main():
        renderer = PlotRenderer(1).start()
        job = plots.PlotJob("pod", "png", {"scenario": build_scenario("paper").model_dump(mode="json"),
                                           "model": {"rssi_grid_dbm": [-60.0, -20.0], "mean": [0.1, 0.9], "std": [0.1, 0.1]},
                                           "truth": None, "title": "t"})
        async def read():
            return FigureSource(job)

        await renderer.figure(PlotKey("c", "pod", "png"), read)
        print(renderer.pids()[0], flush=True)
        await asyncio.sleep(600)

    if __name__ == "__main__":
        asyncio.run(main())
""")


def test_renderer_processes_exit_when_the_api_process_is_killed(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen([sys.executable, str(script)], cwd=root, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(root)}, start_new_session=True, preexec_fn=restore_ctrl_c)
    renderer_pid = None
    try:
        renderer_pid = int(proc.stdout.readline())
        assert not gone(renderer_pid)
        proc.kill()  # SIGKILL: no shutdown code runs in the API process
        proc.wait(WAIT_S)
        wait_until(lambda: gone(renderer_pid), "the orphaned renderer to exit")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT_S)
        proc.stdout.close()
        if renderer_pid is not None and not gone(renderer_pid):
            os.kill(renderer_pid, signal.SIGKILL)


def test_the_rate_limit_refuses_beyond_its_rate_and_refills():
    from ra2vipas.services.orchestrator.api.render import RateLimit

    limit = RateLimit(10.0, burst=3.0)
    t = 100.0
    limit._at = t
    assert [limit.try_acquire(now=t) for _ in range(4)] == [True, True, True, False]
    assert limit.try_acquire(now=t + 0.05) is False  # half a token
    assert limit.try_acquire(now=t + 0.15) is True  # refilled at 10 per second
    assert [limit.try_acquire(now=t + 10.0) for _ in range(4)] == [True, True, True, False]  # never more than the burst


def test_figure_requests_beyond_the_rate_get_503_with_retry_after(tmp_path):
    """An orchestrator serving at most 2 figure requests per second refuses the rest of a burst
    with 503 and Retry-After, before any work, and serves again a second later."""
    import time

    from tests.api.live import SMALL, LiveAPI

    server = LiveAPI(tmp_path / "rate.db", plot_rate=2.0).start()
    try:
        body = {"preset": "paper", "overrides": SMALL, "algorithms": ["rapas"], "tests": 1, "seed": 1}
        cid = http.post(f"{server.url}/campaigns", json=body, timeout=30).json()["id"]
        assert server.wait(cid)["status"] == "done"
        time.sleep(1.1)  # a full bucket
        codes = [http.get(f"{server.url}/campaigns/{cid}/plots/dr", timeout=60) for _ in range(6)]
        refused = [r for r in codes if r.status_code == 503]
        assert [r.status_code for r in codes[:2]] == [200, 200] and len(refused) >= 3
        assert all(r.headers["Retry-After"] == "1" and "figure requests per second" in r.json()["detail"] for r in refused)
        time.sleep(1.1)
        assert http.get(f"{server.url}/campaigns/{cid}/plots/dr", timeout=60).status_code == 200
    finally:
        server.stop()
