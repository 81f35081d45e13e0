"""In-process campaigns and studies on every core (``ra2vipas simulate``, ``ra2vipas.simulate``).

A *point* is one campaign: a scenario, tests x algorithms episodes and a seed. ``run_points``
runs one point (a campaign) or many (a study) and returns each point's results object.

Design, and why it gives the same numbers on any number of workers:

* **Draws.** Every random draw of test k comes from (seed, k) (``SimulatedPlatform``), and the
  POD model of a point depends only on (scenario, seed): an episode gives the same outcome in
  whatever process runs it, after whatever ran before.
* **Work.** The POD model of each point is trained once, in a worker (a study's points train in
  parallel), and sent with every chunk of that point (a ``PODModel`` is small). A chunk is a
  few consecutive tests of one point, all its algorithms. Chunks are handed out round robin
  over the points, test by test (chunk 0 of every point, then chunk 1, ...), so a study's
  points progress together.
* **Reduction.** A worker returns per episode only its per-step hits, in-FoV flags and
  confidences (``EpisodeSummary``), never the trace; the parent consumes chunks in the order it
  submitted them and adds them to one ``AlgorithmTally`` per (point, algorithm), so every tally
  sees its tests in test order whatever the worker count: results are identical value for
  value to ``workers=1``, which runs the same chunks inline, without a pool.
* **Memory.** At most ``4 x workers`` chunks are in flight; the parent holds running sums and
  one scalar per test (``reduce``), so memory does not grow with tests x steps.
* **Processes.** A ``ProcessPoolExecutor`` whose workers start from a ``forkserver`` (``spawn``
  where there is none), never by forking the caller: the caller may run threads (a progress
  bar, a notebook, a server with a Zenoh session) that a fork would copy mid-operation. The
  fork server imports this module once (``set_forkserver_preload``, through
  ``engine_preload``, which also runs one tiny episode of every algorithm), so a worker starts
  in milliseconds, warm, with numpy, scikit-learn and the controller loaded, and, as importing
  ``ra2vipas`` does, with one BLAS thread: a worker is one core, and a threaded BLAS would
  sum in another order than ``workers=1``. Workers ignore SIGINT (the parent stops them) and
  exit by themselves when the parent is gone.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ra2vipas.services.controller.policy import ControllerSettings
from ra2vipas.services.orchestrator.reduce import AlgorithmTally, results_object
from ra2vipas.services.orchestrator.simulate import TestOutcome, TrainedPOD, run_test, train_pod
from ra2vipas.services.protocol.pod import PODModel
from ra2vipas.services.protocol.scenario import Scenario

IN_FLIGHT_PER_WORKER = 4  # chunks submitted ahead of the one being consumed, per worker
MAX_CHUNK_TESTS = 16
PARENT_POLL_S = 1.0


@dataclass(frozen=True)
class Point:
    """One campaign to run in-process."""

    preset: str
    scenario: Scenario
    tests: int
    seed: int
    algorithms: tuple[str, ...]
    stop_confidence: float = 0.0


@dataclass(frozen=True)
class EpisodeSummary:
    """What a worker sends back of one episode: the per-step flags the results need (``steps``
    long, an early decision held to the end), and nothing of the trace."""

    hits: np.ndarray  # (T,) bool: î_t = i*
    in_fov: np.ndarray  # (T,) bool: the Tx inside the FoV at gamma_hat_t
    confidences: np.ndarray | None  # (T,) float, None if the controller gave none
    decided_step: int | None
    steps_run: int  # control steps actually run (fewer after an early decision)
    tag_hits: np.ndarray | None = None  # (K, T) bool: a search for several tags, per tag (issue 21)
    tag_in_fov: np.ndarray | None = None  # (K, T) bool
    tag_confidences: np.ndarray | None = None  # (K, T) float
    tag_decided: tuple[int | None, ...] | None = None  # K values

    @classmethod
    def of(cls, outcome: TestOutcome) -> "EpisodeSummary":
        tags = outcome.tags
        return cls(hits=np.asarray(outcome.hits, dtype=bool), in_fov=np.asarray(outcome.in_fov, dtype=bool),
                   confidences=np.asarray(outcome.confidences, dtype=np.float64) if outcome.confidences else None,
                   decided_step=outcome.decided_step, steps_run=len(outcome.estimates),
                   tag_hits=None if tags is None else tags.hits, tag_in_fov=None if tags is None else tags.in_fov,
                   tag_confidences=None if tags is None else tags.held_confidences,
                   tag_decided=None if tags is None else tuple(tags.decided_steps))


@dataclass
class RunReport:
    """What ``run_points`` returns: each point's results object, in the order given, and the
    control steps run with the wall time of the episodes (after the first model was trained)."""

    results: list[dict[str, Any]]
    steps: int
    seconds: float
    workers: int
    worker_peak_rss_kb: int = 0  # the largest peak RSS a worker reported (this process's own with workers=1)

    @property
    def steps_per_second(self) -> float | None:
        return self.steps / self.seconds if self.seconds > 0 else None


class Interrupted(KeyboardInterrupt):
    """Ctrl-C during ``run_points``: ``report`` holds the results of the tests finished before
    it (each point's first tests, in test order, the same for any worker count), marked
    ``partial`` with ``tests_recorded`` per algorithm; a point with none is None (and ``report``
    is None if no test finished at all)."""

    def __init__(self, report: "RunReport | None", done: int, total: int) -> None:
        super().__init__()
        self.report = report
        self.study: dict[str, Any] | None = None  # run_study: the partial study results
        self.done = done
        self.total = total


def default_workers() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


# A worker process costs ~2-3 s of start-up (fork server, imports, loading the compiled kernels),
# so by default one runs only for each WORK_PER_WORKER units of work: control steps of every
# episode, and TRAINING_SAMPLE_COST per sample of each POD model trained (training 900 samples
# takes about as long as 4 500 control steps). 10 000 steps are 3-5 s of one core: a campaign of
# 2 tests runs in this process (3.3 s sooner than on two workers, measured), the paper
# campaign of 50 tests x 4 algorithms (24 000 steps) on two.
WORK_PER_WORKER = 10_000
TRAINING_SAMPLE_COST = 5


def workers_for(points: Sequence["Point"]) -> int:
    """The default number of worker processes for ``points``: one per core, but no more than
    the work pays for (results are identical for any number)."""
    steps = sum(p.tests * len(p.algorithms) * p.scenario.steps for p in points)
    training = sum({(p.scenario.model_dump_json(), p.seed): p.scenario.n_train for p in points}.values())
    return max(1, min(default_workers(), (steps + TRAINING_SAMPLE_COST * training) // WORK_PER_WORKER))


# -- what a worker runs ------------------------------------------------------------------------

def train(scenario: Scenario, seed: int) -> TrainedPOD:
    """The POD model of a point (``simulate.train_pod``), in whatever process runs it."""
    return train_pod(scenario, seed)


def run_chunk(scenario: Scenario, seed: int, first: int, stop: int, algorithms: Sequence[str], model: PODModel,
              stop_confidence: float = 0.0, settings: ControllerSettings | None = None,
              on_episode: Callable[[], None] | None = None) -> tuple[list[list[EpisodeSummary]], int]:
    """Tests ``first`` .. ``stop - 1`` of a point, every algorithm: ``[test][algorithm]``, and
    the peak resident memory of the process that ran them (kB)."""
    out = []
    for k in range(first, stop):
        row = []
        for a in algorithms:
            row.append(EpisodeSummary.of(run_test(scenario, seed, k, a, model, settings, stop_confidence)))
            if on_episode is not None:
                on_episode()
        out.append(row)
    return out, peak_rss_kb()


def peak_rss_kb() -> int:
    """This process's peak resident set size in kB (``ru_maxrss``; 0 where unknown)."""
    try:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    except (ImportError, OSError):
        return 0
    return int(peak // 1024 if sys.platform == "darwin" else peak)  # bytes on macOS, kB on Linux


def _init_worker(parent_pid: int) -> None:
    """Ctrl-C is the parent's to handle (it stops the pool); exit when the parent is gone (a
    forkserver's child is not the parent's child, so no PR_SET_PDEATHSIG: a watcher thread)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), name="engine-parent-watch", daemon=True).start()


def _exit_with_parent(parent_pid: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        try:
            os.kill(parent_pid, 0)
        except ProcessLookupError:
            os._exit(0)
        except PermissionError:  # alive, another user's (cannot be ours: the pid was reused)
            os._exit(0)


def _context() -> multiprocessing.context.BaseContext:
    """A ``forkserver`` context that preloads this module (``spawn`` where there is none)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload([__name__ + "_preload"])  # engine_preload: this module, and every worker starts warm
    return ctx


# -- the parent ------------------------------------------------------------------------------------

def worker_pool(workers: int) -> Executor:
    """The engine's executor: ``workers`` processes started warm from the fork server, that
    leave Ctrl-C to the parent and exit with it; for ``workers=1`` the same calls inline."""
    if workers == 1:
        return _Inline()
    return ProcessPoolExecutor(max_workers=workers, mp_context=_context(), initializer=_init_worker, initargs=(os.getpid(),))


class _Inline(Executor):
    """``workers=1``: the same calls, in this process, when they are submitted."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        f: Future = Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as err:  # noqa: BLE001 - handed to the caller through the future
            f.set_exception(err)
        return f


def chunk_tests(total_tests: int, workers: int) -> int:
    """Tests per chunk: small enough that the last chunks balance the workers (~32 chunks per
    worker), large enough that sending them costs nothing (at most 16 tests)."""
    if workers <= 1:
        return 1
    return max(1, min(MAX_CHUNK_TESTS, total_tests // (workers * 32)))


def plan(points: Sequence[Point], chunk: int) -> Iterator[tuple[int, int, int]]:
    """(point, first test, stop) round robin over the points, in test order within each: chunk
    0 of every point, then chunk 1, ..."""
    rounds = max(math.ceil(p.tests / chunk) for p in points)
    for r in range(rounds):
        for i, p in enumerate(points):
            first = r * chunk
            if first < p.tests:
                yield i, first, min(p.tests, first + chunk)


def run_points(points: Sequence[Point], workers: int | None = None, progress: Callable[[int, int], None] | None = None,
               settings: ControllerSettings | None = None,
               on_trained: Callable[[int, TrainedPOD], None] | None = None) -> RunReport:
    """Run every point's tests x algorithms episodes on ``workers`` processes (default: every
    core; 1: in this process) and return each point's results object.

    ``progress(done, total)`` is called in this process as episodes finish (after each episode
    with one worker, after each chunk with more); ``on_trained(point, pod)`` once per point when
    its POD model is ready, before its first episode is handed out.
    """
    if not points:
        raise ValueError("no point to run")
    workers = max(1, int(workers)) if workers else workers_for(points)
    total = sum(p.tests * len(p.algorithms) for p in points)
    work = sum(p.tests for p in points)
    if workers > 1:
        workers = min(workers, max(1, work))
    chunk = chunk_tests(work, workers)
    tallies = [{a: AlgorithmTally(p.scenario.steps, p.scenario.rf_period_s) for a in p.algorithms} for p in points]
    done = 0
    worker_rss = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total)

    models: list[Future] = []
    pool = worker_pool(workers)
    try:
        trained: dict[tuple[str, int], Future] = {}
        for p in points:  # every point's model first: a study's points train in parallel
            key = (p.scenario.model_dump_json(), p.seed)
            if key not in trained:
                trained[key] = pool.submit(train, p.scenario, p.seed)
            models.append(trained[key])
        for _ in range(workers - len(trained)):  # start every worker now, while the models train, not in the timed part
            pool.submit(os.getpid)
        started: float | None = None
        announced: set[int] = set()
        in_flight: deque[tuple[int, int, int, Future]] = deque()
        jobs = plan(points, chunk)

        def submit_next() -> bool:
            nonlocal started
            job = next(jobs, None)
            if job is None:
                return False
            i, first, stop = job
            p = points[i]
            trained_pod = models[i].result()
            if on_trained is not None and i not in announced:
                announced.add(i)
                on_trained(i, trained_pod)
            model = trained_pod.model
            if started is None:
                started = time.perf_counter()
            on_episode = tick if workers == 1 else None
            in_flight.append((i, first, stop, pool.submit(run_chunk, p.scenario, p.seed, first, stop, p.algorithms, model,
                                                          p.stop_confidence, settings, on_episode)))
            return True

        for _ in range(IN_FLIGHT_PER_WORKER * workers):
            if not submit_next():
                break
        while in_flight:
            i, first, stop, future = in_flight.popleft()
            rows, rss = future.result()
            worker_rss = max(worker_rss, rss)
            for k, test_row in enumerate(rows, start=first):
                for a, ep in zip(points[i].algorithms, test_row):
                    tallies[i][a].add(ep.hits, ep.in_fov, ep.confidences, ep.decided_step, ep.steps_run, test_index=k)
                    if ep.tag_hits is not None:
                        tallies[i][a].add_tags(ep.tag_hits, ep.tag_in_fov, ep.tag_confidences, ep.tag_decided)
                    if workers > 1:
                        tick()
            submit_next()
        seconds = time.perf_counter() - (started or time.perf_counter())
        pods = [m.result() for m in models]
    except KeyboardInterrupt:
        if isinstance(pool, ProcessPoolExecutor):
            _stop_pool(pool)
        raise Interrupted(_partial_report(points, tallies, models, workers, worker_rss), done, total) from None
    except BaseException:
        if isinstance(pool, ProcessPoolExecutor):
            _stop_pool(pool)
        raise
    if isinstance(pool, ProcessPoolExecutor):
        pool.shutdown(wait=True)
    steps = sum(t.steps_run for per in tallies for t in per.values())
    sps = steps / seconds if seconds > 0 else None
    results = [results_object(p.preset, p.scenario, p.tests, p.seed, pod, tallies[i], sps, p.stop_confidence)
               for i, (p, pod) in enumerate(zip(points, pods))]
    return RunReport(results=results, steps=steps, seconds=seconds, workers=workers, worker_peak_rss_kb=worker_rss)


def _partial_report(points: Sequence[Point], tallies: list[dict[str, AlgorithmTally]], models: list[Future], workers: int,
                    worker_rss: int) -> RunReport | None:
    """The results of the tests reduced before an interruption (``Interrupted``)."""
    results: list[dict[str, Any] | None] = []
    for p, per, model in zip(points, tallies, models):
        shown = {a: t for a, t in per.items() if t.tests}
        if not shown or not model.done() or model.cancelled() or model.exception() is not None:
            results.append(None)
            continue
        res = results_object(p.preset, p.scenario, p.tests, p.seed, model.result(), shown, None, p.stop_confidence)
        res["partial"] = True
        res["tests_recorded"] = {a: t.tests for a, t in shown.items()}
        results.append(res)
    if all(r is None for r in results):
        return None
    steps = sum(t.steps_run for per in tallies for t in per.values())
    return RunReport(results=results, steps=steps, seconds=0.0, workers=workers, worker_peak_rss_kb=worker_rss)  # type: ignore[arg-type]


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now (Ctrl-C, an error): drop queued chunks, terminate the workers, reap them."""
    processes = list(dict(getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    for p in processes:
        p.join(5.0)
        if p.is_alive():
            p.kill()
            p.join()


def run_study(preset: str, overrides: dict[str, Any], vary: dict[str, Sequence[Any]], tests: int, seed: int,
              algorithms: Sequence[str], stop_confidence: float = 0.0, workers: int | None = None,
              progress: Callable[[int, int], None] | None = None, settings: ControllerSettings | None = None,
              name: str | None = None) -> dict[str, Any]:
    """A parameter study in this process (``ra2vipas simulate --vary``): every point of the grid
    is a campaign with the same seed, all run together on ``workers`` processes, their points
    interleaved test by test; returns the study's results object (``study.study_results``), the
    same shape as ``GET /studies/{id}/results``.

    Raises
    ------
    study.StudyError
        A bad preset, parameter, value or grid (one line naming it).
    """
    from ra2vipas.services.orchestrator.study import check_size, expand, study_results

    grid = expand(preset, overrides, vary)
    check_size(len(grid), tests, len(algorithms))
    points = [Point(preset=preset, scenario=scenario, tests=tests, seed=seed, algorithms=tuple(algorithms),
                    stop_confidence=stop_confidence) for _, scenario in grid]
    resolved = {n: list(dict.fromkeys(values[n] for values, _ in grid)) for n in vary}
    meta = {"id": None, "name": name, "status": "done", "preset": preset, "overrides": dict(overrides), "vary": resolved,
            "algorithms": list(algorithms), "tests": tests, "seed": seed, "mode": "fast", "stop_confidence": stop_confidence}
    try:
        report = run_points(points, workers=workers, progress=progress, settings=settings)
    except Interrupted as stop:  # Ctrl-C: the study of the tests finished so far, marked partial, travels with it
        results = stop.report.results if stop.report is not None else [None] * len(grid)
        shown = [{"point": i, "values": values, "campaign_id": None, "status": "cancelled", "results": res,
                  "tests": (res or {}).get("tests_recorded")}
                 for i, ((values, _), res) in enumerate(zip(grid, results))]
        stop.study = study_results({**meta, "status": "cancelled"}, shown, None, partial=True)
        raise
    shown = [{"point": i, "values": values, "campaign_id": None, "status": "done", "results": res}
             for i, ((values, _), res) in enumerate(zip(grid, report.results))]
    out = study_results(meta, shown, report.steps_per_second)
    out["workers"] = report.workers
    return out
