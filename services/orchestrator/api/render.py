"""Figures off the request path: a bounded pool of renderer processes and a cache of what they drew.

matplotlib holds the GIL for the whole of a render (0.1-1 s of CPU), so drawing in the API
process stalled every route and the scheduler that runs in the same process (issue 14). Here:

* **Renderer processes.** ``PlotRenderer`` owns a ``ProcessPoolExecutor`` of ``workers``
  processes (``OrchestratorSettings.plot_workers``, env ``RA2VIPAS_PLOT_WORKERS``), started with
  ``spawn`` (the API process runs Zenoh's threads, so forking it is unsafe), at nice 10 so a
  campaign's services get the cores first (a renderer weighs about a tenth of a nice-0 process in
  Linux's scheduler), and exiting by themselves if the API process dies. A renderer that dies is
  replaced on the next request. Not ``SCHED_IDLE``: it runs only on a core nothing else
  wants, so while anything else keeps every core busy a figure never arrives (every figure
  request timed out after 30 s with three busy processes on two cores; at nice 10 the same
  figures took 7-17 s for 20 requests each).
* **Bounded.** At most ``capacity`` distinct renders are running or queued (two per worker by
  default); one more raises ``Saturated`` and the route answers 503 with ``Retry-After``
  instead of queueing. Concurrent requests for the same figure share one render.
* **Cached.** Rendered bytes are kept in an LRU cache bounded by their total size
  (``cachetools.LRUCache``), keyed by ``PlotKey`` (campaign id, figure kind, format,
  parameters); deleting a campaign evicts its figures.

**What may be cached.** Every figure the API can draw is immutable from the moment it can be
drawn, whatever the campaign's status, so every rendered figure is cached:

* the DR figure exists only for a campaign whose status is ``done``; a finished campaign
  (done, failed, cancelled) never changes status or results again (``Store.set_campaign``
  refuses), so the figure of a done campaign is final;
* an episode's figure exists only for an episode row whose status is ``done``:
  ``Store.finish_episode`` writes only pending or running rows and cancelling touches only
  pending or running ones, so a done row never changes, even inside a campaign that is still
  running (or is later cancelled);
* the POD figure exists once the learned model is stored. The scheduler writes ``pod_job``
  and R² before the model, and never trains a campaign again once ``pod_job`` is set
  (``Scheduler._start``), so a stored model, its truth and its R² never change; the route reads
  the model before the campaign row (so it sees the R² written before the model) and caches
  only when ``pod_job`` is set (``cacheable`` in ``FigureSource``).

The scenario, preset and seed in a figure are fixed when the campaign is created. Deletion is
the only change: the id then answers 404, and ``invalidate`` frees the memory and keeps a
render in flight for that campaign from being stored. Because of this, a cache hit needs no
database read at all: it is served on the event loop, with no thread hop.
"""

from __future__ import annotations

import asyncio
import functools
import math
import multiprocessing
import os
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Awaitable, Callable, NamedTuple

import cachetools
from fastapi import HTTPException, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from ra2vipas.services.orchestrator import plots
from ra2vipas.services.orchestrator.api.errors import responses
from ra2vipas.services.orchestrator.api.negotiate import IMAGE_CONTENT

CACHE_BYTES = 64 * 1024 * 1024  # rendered figures (PNG and SVG) kept in memory
NICENESS = 10  # renderer processes: low priority (services first), yet never starved by a busy machine
RETRY_AFTER_MAX_S = 30
PARENT_POLL_S = 1.0

SATURATED_DOC = {
    "description": "every renderer is busy and the render queue is full: retry after `Retry-After` seconds "
                   "(figures already drawn are served from the cache meanwhile)",
    "headers": {"Retry-After": {"description": "seconds to wait before retrying", "schema": {"type": "integer", "minimum": 1}}},
}


class PlotKey(NamedTuple):
    """What identifies one rendered figure."""

    campaign_id: str
    kind: str  # "dr", "pod", "episode"
    fmt: str  # "png", "svg"
    params: tuple = ()  # e.g. (test_index, algorithm) for an episode


class FigureSource(NamedTuple):
    """What a route read from the store for a figure that is not cached."""

    job: plots.PlotJob
    cacheable: bool = True


class Saturated(Exception):
    """Every renderer is busy and the queue is full; retry after ``retry_after`` seconds."""

    def __init__(self, retry_after: int, detail: str) -> None:
        super().__init__(detail)
        self.retry_after = retry_after


class RendererUnavailable(Exception):
    """The pool is closed, or a renderer process died during this render (it is replaced)."""


@dataclass
class RenderStats:
    """Counters since start: what the cache and the pool did."""

    hits: int = 0  # requests answered from the cache
    renders: int = 0  # renders sent to the pool
    shared: int = 0  # requests that waited for an identical render already in flight
    rejected: int = 0  # requests refused with Saturated
    failures: int = 0  # renders that raised (including a dead renderer)
    restarts: int = 0  # pools replaced after a renderer died


# -- in the renderer processes ---------------------------------------------------------------------

def _init_renderer(parent_pid: int, niceness: int) -> None:
    """Renderer start-up: a low CPU priority (``niceness``, under the normal scheduling policy so
    a busy machine slows a render but never starves it), exit with the API process, and import
    matplotlib's canvases now rather than during the first render."""
    try:
        os.nice(max(0, niceness - os.nice(0)))
    except OSError:
        pass
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), name="renderer-parent-watch", daemon=True).start()
    from matplotlib.backends import backend_agg, backend_svg  # noqa: F401  (the two formats' canvases)


def _exit_with_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(0)


def _timed(render: Callable[[plots.PlotJob], bytes], job: plots.PlotJob) -> tuple[bytes, float]:
    started = time.perf_counter()
    data = render(job)
    return data, time.perf_counter() - started


# -- in the API process ------------------------------------------------------------------------------

class RateLimit:
    """A token bucket: at most ``rate`` acquisitions per second on average, ``burst`` at once
    (``limits`` would do the same; this is the dozen lines it takes). Thread-safe."""

    def __init__(self, rate: float, burst: float | None = None) -> None:
        self.rate = float(rate)
        self.burst = float(burst if burst is not None else max(1.0, rate))
        self._tokens = self.burst
        self._at = time.monotonic()
        self._lock = threading.Lock()

    def try_acquire(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
            self._at = now
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                return True
            return False


# Figure requests served per second, cached or not (OrchestratorSettings.plot_rate,
# RA2VIPAS_PLOT_RATE): every request costs the orchestrator's CPU even when its bytes are cached,
# and on a small machine that CPU is the rigs'. Beyond it: 503 with Retry-After, before any work.
PLOT_RATE = 40.0


class PlotRenderer:
    """Renders figures in a pool of ``workers`` processes, at most ``capacity`` at a time
    (running or queued), and caches the bytes (at most ``cache_bytes`` in total).

    ``render`` is the function a renderer process runs on a ``PlotJob`` (module-level, so it
    can be pickled); ``start`` creates the pool (its processes start on first use) and
    ``close`` stops them. ``figure`` must be awaited on one event loop; ``cached`` and
    ``invalidate`` may be called from any thread.
    """

    def __init__(self, workers: int = 1, *, capacity: int | None = None, cache_bytes: int = CACHE_BYTES,
                 niceness: int = NICENESS, render: Callable[[plots.PlotJob], bytes] = plots.draw_job,
                 rate: float = PLOT_RATE) -> None:
        if workers < 1:
            raise ValueError(f"plot workers must be >= 1, got {workers}")
        self.workers = workers
        self.capacity = capacity if capacity is not None else 2 * workers
        if self.capacity < 1:
            raise ValueError(f"render capacity must be >= 1, got {self.capacity}")
        self.niceness = niceness
        self.render = render
        self.stats = RenderStats()
        self.limit = RateLimit(rate)  # figure requests per second, checked before anything else
        self._cache: cachetools.LRUCache = cachetools.LRUCache(maxsize=cache_bytes, getsizeof=len)
        self._lock = threading.Lock()
        self._inflight: dict[PlotKey, asyncio.Future] = {}  # what identical requests can share
        self._busy = 0  # figures being read, queued or drawn (what ``capacity`` bounds)
        self._epoch = 0  # bumped by every invalidation: a render that started before one is not stored
        self._tasks: set[asyncio.Task] = set()
        self._render_s = 0.5  # moving average of one render's duration in a renderer
        self._executor: ProcessPoolExecutor | None = None

    # -- life cycle -------------------------------------------------------------------------
    def start(self) -> "PlotRenderer":
        self._executor = self._new_executor()
        return self

    def _new_executor(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_renderer, initargs=(os.getpid(), self.niceness))

    def close(self, timeout: float = 2.0) -> None:
        """Stop the pool: cancel queued renders, let running ones finish for up to ``timeout``
        seconds, then terminate what is left; every renderer process is reaped."""
        with self._lock:
            ex, self._executor = self._executor, None
        if ex is not None:
            _stop_executor(ex, timeout)

    def pids(self) -> list[int]:
        """Process ids of the renderer processes running now."""
        ex = self._executor
        return [pid for pid, p in dict(getattr(ex, "_processes", None) or {}).items() if p.is_alive()]

    # -- cache --------------------------------------------------------------------------------
    def cached(self, key: PlotKey) -> bytes | None:
        with self._lock:
            data = self._cache.get(key)
            if data is not None:
                self.stats.hits += 1
            return data

    def cache_size(self) -> tuple[int, int]:
        """(figures, bytes) in the cache."""
        with self._lock:
            return len(self._cache), int(self._cache.currsize)

    def in_flight(self) -> int:
        """Figures being read from the store, queued or being drawn (what ``capacity`` bounds)."""
        with self._lock:
            return self._busy

    def invalidate(self, campaign_id: str) -> int:
        """Forget every figure of a campaign (it was deleted), including renders in flight;
        return how many cached figures were evicted."""
        with self._lock:
            self._epoch += 1
            for key in [k for k in self._inflight if k.campaign_id == campaign_id]:
                del self._inflight[key]
            stale = [k for k in self._cache if k.campaign_id == campaign_id]
            for key in stale:
                del self._cache[key]
            return len(stale)

    # -- rendering ----------------------------------------------------------------------------
    async def figure(self, key: PlotKey, read: Callable[[], Awaitable[FigureSource]]) -> bytes:
        """The figure's bytes: from the cache, from an identical request in flight, or read with
        ``read()`` and drawn in the pool.

        In that order, and the first two without touching the store: a request that finds the
        renderers saturated is refused before it reads anything, so a flood of plot requests
        costs one dictionary look-up each. What ``read()`` raises (e.g. a 404) is raised to
        every request waiting for that figure.

        Raises
        ------
        Saturated
            ``capacity`` figures are already being read, queued or drawn.
        RendererUnavailable
            The pool is closed, or the renderer died during this render.
        """
        loop = asyncio.get_running_loop()
        with self._lock:
            data = self._cache.get(key)
            if data is not None:
                self.stats.hits += 1
                return data
            future = self._inflight.get(key)
            if future is not None:
                self.stats.shared += 1
            else:
                if self._busy >= self.capacity:
                    self.stats.rejected += 1
                    retry = self.retry_after()
                    raise Saturated(retry, f"the figure renderers are busy ({self._busy} figures in progress, "
                                           f"{self.workers} renderer{'s' if self.workers > 1 else ''}): retry in {retry} s")
                self._busy += 1
                future = self._inflight[key] = loop.create_future()
                # its own task: a client that disconnects cancels its request, not the render others wait for
                task = loop.create_task(self._produce(key, read, future, self._epoch))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)
        return await asyncio.shield(future)

    async def _produce(self, key: PlotKey, read: Callable[[], Awaitable[FigureSource]], future: asyncio.Future,
                       epoch: int) -> None:
        source = None
        executor = None
        try:
            source = await read()
            with self._lock:
                executor = self._executor
                cf = self._submit(source.job)
                self.stats.renders += 1
            data, seconds = await asyncio.wrap_future(cf)
        except BaseException as err:  # noqa: BLE001 - handed to every waiter
            with self._lock:
                self._busy -= 1
                if self._inflight.get(key) is future:
                    del self._inflight[key]
                if isinstance(err, BrokenProcessPool):
                    self.stats.failures += 1
                    self._restart(executor)
                    err = RendererUnavailable("a figure renderer stopped during this render; it was restarted, retry")
                elif source is not None:
                    self.stats.failures += 1
            if isinstance(err, asyncio.CancelledError):  # the event loop is stopping
                future.cancel()
                raise
            if not future.done():
                future.set_exception(err)
                future.exception()  # retrieved: nobody may be waiting any more
            return
        with self._lock:
            self._busy -= 1
            if self._inflight.get(key) is future:
                del self._inflight[key]
            self._render_s = 0.8 * self._render_s + 0.2 * seconds
            if source.cacheable and epoch == self._epoch:
                try:
                    self._cache[key] = data
                except ValueError:  # larger than the whole cache
                    pass
        if not future.done():
            future.set_result(data)

    def retry_after(self) -> int:
        """Seconds until the queue has drained at the current render speed (at least 1)."""
        return max(1, min(RETRY_AFTER_MAX_S, math.ceil(self._render_s * self.capacity / self.workers)))

    def _submit(self, job: plots.PlotJob) -> Future:
        """Send a job to the pool (called with the lock held)."""
        if self._executor is None:
            raise RendererUnavailable("the figure renderers are stopped")
        try:
            return self._executor.submit(_timed, self.render, job)
        except BrokenProcessPool:  # a renderer died since the last render: replace the pool once
            self._restart(self._executor)
            return self._executor.submit(_timed, self.render, job)

    def _restart(self, broken: ProcessPoolExecutor | None) -> None:
        """Replace a broken pool (called with the lock held)."""
        if broken is None or self._executor is not broken:
            return
        self._executor = self._new_executor()
        self.stats.restarts += 1
        broken.shutdown(wait=False, cancel_futures=True)


def _stop_executor(ex: ProcessPoolExecutor, timeout: float) -> None:
    # The executor keeps its processes and manager thread in private attributes; shutdown(wait=True)
    # would wait for ever on a render that does not end, so the processes are joined here with a
    # deadline and terminated after it.
    processes = list(dict(getattr(ex, "_processes", None) or {}).values())
    manager = getattr(ex, "_executor_manager_thread", None)
    ex.shutdown(wait=False, cancel_futures=True)
    deadline = time.monotonic() + timeout
    for p in processes:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in processes:
        if p.is_alive():
            p.terminate()
            p.join(2.0)
        if p.is_alive():
            p.kill()
            p.join()
    if manager is not None:
        manager.join(timeout)


# -- what the plot routes share ----------------------------------------------------------------------

def get_renderer(request: Request) -> PlotRenderer:
    return request.app.state.renderer


async def serve_figure(request: Request, key: PlotKey, read: Callable[[], FigureSource]) -> Response:
    """The figure ``key`` as a response (``PlotRenderer.figure``); ``read`` runs in a worker
    thread only when the figure must be drawn, and raises the route's 404/409.

    Raises 503 with ``Retry-After`` when the renderers are saturated, or when figure requests
    come faster than ``PLOT_RATE`` per second (checked first: a refused request costs nothing).
    """
    renderer = get_renderer(request)
    if not renderer.limit.try_acquire():
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE,
                            f"more than {renderer.limit.rate:g} figure requests per second: retry later", headers={"Retry-After": "1"})
    try:
        data = await renderer.figure(key, functools.partial(run_in_threadpool, read))
    except Saturated as err:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(err),
                            headers={"Retry-After": str(err.retry_after)}) from None
    except RendererUnavailable as err:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(err), headers={"Retry-After": "1"}) from None
    return Response(data, media_type=plots.MEDIA_TYPES[key.fmt])


def plot_responses(e409: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI responses of a plot route: the figure, or 404/409/422, or 503 with ``Retry-After``."""
    out = {200: {"content": IMAGE_CONTENT, "description": "the figure"},
           **responses(404, 409, 422, 503, e409=e409, e503=SATURATED_DOC["description"])}
    out[503]["headers"] = SATURATED_DOC["headers"]
    return out
