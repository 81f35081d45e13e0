"""``ra2vipas bench plots``: plots under load. A local stack finishes a few campaigns, then runs
the paper campaign without and with many plot clients asking for those campaigns' figures,
while other clients read the API's non-plot routes: the p99 of those reads under plot load and
how much the plot load slows the campaign."""

from __future__ import annotations

import os
import time

from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.common import StackFactory, cpu_seconds, percentile, run_campaign

PLOT_TARGETS = {"read_p99_ms": 200.0, "slowdown_pct": 10.0}
READ_PAUSE_S = 0.05  # each reader's pause between two requests
DRAIN_S = 3.0  # after a run with plot load: the renders still queued (at most a few) finish


def _plot_urls(campaigns: list[dict]) -> dict[str, list[str]]:
    """Every figure of the finished ``campaigns``, by kind, in both formats."""
    urls: dict[str, list[str]] = {"dr": [], "pod": [], "episode": []}
    for c in campaigns:
        for fmt in ("png", "svg"):
            urls["dr"].append(f"/campaigns/{c['id']}/plots/dr?format={fmt}")
            urls["pod"].append(f"/campaigns/{c['id']}/plots/pod?format={fmt}")
            urls["episode"] += [f"/campaigns/{c['id']}/tests/{k}/{a}/plot?format={fmt}"
                                for k in range(c["tests"]) for a in c["algorithms"]]
    return urls


def _plot_load(api: str, urls: dict[str, list[str]], clients: int, seed: int, retry_cap_s: float, niceness: int,
               ready, stop, out) -> None:
    """A process of ``clients`` concurrent plot clients (asyncio + httpx) at ``niceness``: each
    picks a figure kind, then one of its figures, at random, asks for it, and asks again as soon
    as it has the answer; after a 503 it waits ``Retry-After`` seconds (at most ``retry_cap_s``)."""
    import asyncio
    import random

    import httpx

    if niceness:
        os.nice(niceness)

    async def main() -> dict:
        counts: dict[str, int] = {}
        ok_ms: list[float] = []

        async def client(i: int) -> None:
            rng = random.Random(seed * 1000 + i)
            # one connection per client, as 50 separate users would have
            async with httpx.AsyncClient(base_url=api, timeout=120.0) as http:
                while True:
                    url = rng.choice(urls[rng.choice(kinds)])
                    started = time.perf_counter()
                    try:
                        r = await http.get(url)
                    except httpx.HTTPError:
                        counts["error"] = counts.get("error", 0) + 1
                        await asyncio.sleep(0.1)
                        continue
                    counts[str(r.status_code)] = counts.get(str(r.status_code), 0) + 1
                    if r.status_code == 200:
                        ok_ms.append((time.perf_counter() - started) * 1e3)
                    elif r.status_code == 503:
                        await asyncio.sleep(min(retry_cap_s, float(r.headers.get("retry-after") or 1)))

        kinds = sorted(urls)
        tasks = [asyncio.create_task(client(i)) for i in range(clients)]
        started = time.perf_counter()
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.05)
        seconds = time.perf_counter() - started
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        requests = sum(counts.values())
        return {"clients": clients, "seconds": round(seconds, 2), "requests": requests,
                "requests_per_second": round(requests / seconds, 1) if seconds else None, "status": counts,
                "ok_p50_ms": round(percentile(ok_ms, 50), 1) if ok_ms else None,
                "ok_p99_ms": round(percentile(ok_ms, 99), 1) if ok_ms else None}

    out.put(asyncio.run(main()))


class _Readers:
    """``n`` threads reading the API's non-plot routes in turn, recording each latency."""

    def __init__(self, api: str, paths: list[str], n: int) -> None:
        import threading

        self.api, self.paths, self.n = api, paths, n
        self.stop_event = threading.Event()
        self.samples: list[tuple[float, int]] = []
        self.threads = [threading.Thread(target=self._run, args=(i,), daemon=True) for i in range(n)]

    def _run(self, i: int) -> None:
        import httpx

        with httpx.Client(base_url=self.api, timeout=120.0) as http:
            k = i
            while not self.stop_event.is_set():
                path = self.paths[k % len(self.paths)]
                k += 1
                started = time.perf_counter()
                try:
                    status = http.get(path).status_code
                except httpx.HTTPError:
                    status = 0
                self.samples.append(((time.perf_counter() - started) * 1e3, status))
                self.stop_event.wait(READ_PAUSE_S)

    def __enter__(self) -> "_Readers":
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop_event.set()
        for t in self.threads:
            t.join(130.0)


def _renderers_of(pid: int) -> list[int]:
    """The figure renderer processes of the orchestrator ``pid`` (its multiprocessing children)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    parent = int(f.read().rsplit(")", 1)[1].split()[1])
                if parent == pid:
                    with open(f"/proc/{entry}/cmdline", "rb") as f:
                        if b"spawn_main" in f.read():
                            found.append(int(entry))
            except (OSError, IndexError, ValueError):
                pass
    return found


def plots(launch: StackFactory, *, clients: int, readers: int, tests: int, seed: int, repeats: int, fixtures: int,
          fixture_tests: int, rigs: int, retry_cap: float, client_nice: int) -> dict:
    """On a stack of ``rigs`` rigs made by ``launch`` (stopped afterwards, with every process
    started here): ``fixtures`` finished campaigns of ``fixture_tests`` tests, then the paper
    campaign (``tests`` tests, ``seed``) ``repeats`` times without and with ``clients`` plot
    clients (``retry_cap``: their longest wait after a 503; ``client_nice``: their niceness),
    while ``readers`` clients read /campaigns, /campaigns/{id}, /campaigns/{id}/results and
    /health."""
    import multiprocessing
    import queue
    import statistics as stats
    import tempfile

    import httpx

    from ra2vipas.services.controller.registry import BUILTINS

    algorithms = [a for a in BUILTINS if a != "sweep"]  # the active built-ins
    body = {"preset": "paper", "tests": tests, "seed": seed, "algorithms": algorithms}
    report: dict = {"benchmark": "plots", "rigs": rigs, "plot_clients": clients, "readers": readers,
                    "retry_cap_s": retry_cap, "client_nice": client_nice,
                    "campaign": {**body, "repeats": repeats}, "targets": PLOT_TARGETS}
    ctx = multiprocessing.get_context("spawn")
    load = None
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:
        stack = launch(rigs=rigs, db_path=os.path.join(tmp, "plots.db"), log_dir=os.path.join(tmp, "logs"))
        try:
            stack.start()
            api = stack.api_url
            finished = []
            for i in range(fixtures):
                _, _, cid = run_campaign(api, {**body, "tests": fixture_tests, "seed": 100 + i}, 1800)
                finished.append({"id": cid, "tests": fixture_tests, "algorithms": algorithms})
            urls = _plot_urls(finished)
            report["figures"] = {k: len(v) for k, v in urls.items()}
            warm = httpx.get(f"{api}{urls['dr'][0]}", timeout=120)  # the first request starts the renderer process
            if warm.status_code != 200:
                raise RuntimeError(f"the first figure failed: {warm.status_code} {warm.text[:200]}")
            orchestrator = next(c.proc.pid for c in stack.children if c.name == "orchestrator")
            report["renderer_processes"] = len(_renderers_of(orchestrator))
            read_paths = ["/campaigns", f"/campaigns/{finished[0]['id']}", f"/campaigns/{finished[0]['id']}/results", "/health"]
            groups = {"rigs": [c.proc.pid for c in stack.children if c.name.startswith(("sensors", "controller"))],
                      "orchestrator": [orchestrator]}

            runs: dict[str, list[dict]] = {"without_plots": [], "with_plots": []}
            for _ in range(repeats):
                for loaded in (False, True):
                    ready, stop, out = ctx.Event(), ctx.Event(), ctx.Queue()
                    with _Readers(api, read_paths, readers) as reading:
                        if loaded:
                            load = ctx.Process(target=_plot_load, name="plot-clients", daemon=True,
                                               args=(api, urls, clients, seed, retry_cap, client_nice, ready, stop, out))
                            load.start()
                            if not ready.wait(60):
                                raise RuntimeError("the plot clients did not start")
                            time.sleep(1.0)  # let the load settle before the campaign starts
                        pids = {**groups, "renderers": _renderers_of(orchestrator),
                                "plot_clients": [load.pid] if loaded else []}
                        cpu0 = cpu_seconds(pids)
                        results, wall, _ = run_campaign(api, body, 1800)
                        cpu1 = cpu_seconds({**pids, "renderers": _renderers_of(orchestrator)})
                        if loaded:
                            stop.set()
                            try:
                                plot_stats = out.get(timeout=180)
                            except queue.Empty:
                                raise RuntimeError("the plot clients did not report") from None
                            load.join(30)
                            load = None
                            time.sleep(DRAIN_S)  # renders still queued finish before the next run
                    lat = [ms for ms, status in reading.samples if status == 200]
                    errors = sum(1 for _, status in reading.samples if status != 200)
                    run = {"steps_per_second": results["steps_per_second"], "wall_seconds": round(wall, 2),
                           "reads": len(reading.samples), "read_errors": errors,
                           "read_p50_ms": round(percentile(lat, 50), 1) if lat else None,
                           "read_p99_ms": round(percentile(lat, 99), 1) if lat else None,
                           "cpu_seconds": {k: round(cpu1[k] - cpu0.get(k, 0.0), 2) for k in cpu1},
                           "_lat": lat}
                    if loaded:
                        run["plots"] = plot_stats
                    runs["with_plots" if loaded else "without_plots"].append(run)
        except (TimeoutError, RuntimeError, httpx.HTTPError) as err:  # a stack that did not start raises a RuntimeError too
            raise BenchmarkError(f"bench plots: {err}") from err
        finally:
            if load is not None and load.is_alive():
                load.terminate()
                load.join(10)
            stack.stop()

    def summary(group: list[dict]) -> dict:
        lat = [ms for r in group for ms in r.pop("_lat")]
        return {"steps_per_second": stats.median(r["steps_per_second"] for r in group),
                "read_p50_ms": round(percentile(lat, 50), 1) if lat else None,
                "read_p99_ms": round(percentile(lat, 99), 1) if lat else None,
                "reads": len(lat), "runs": group}

    base, loaded_ = summary(runs["without_plots"]), summary(runs["with_plots"])
    slowdown = (base["steps_per_second"] / loaded_["steps_per_second"] - 1.0) * 100.0
    report.update({
        "read_p99_ms": loaded_["read_p99_ms"],
        "slowdown_pct": round(slowdown, 1),
        "met": {"read_p99_ms": loaded_["read_p99_ms"] is not None and loaded_["read_p99_ms"] <= PLOT_TARGETS["read_p99_ms"],
                "slowdown_pct": slowdown <= PLOT_TARGETS["slowdown_pct"]},
        "without_plots": base, "with_plots": loaded_,
    })
    return report
