"""``ra2vipas bench mesh``: local stacks measured through their real processes: control steps
per second in fast mode, the sample-to-command latency in realtime mode, what each service's
step costs (``step_breakdown``, ``cpu_ms_per_step``) and the orchestrator's peak memory."""

from __future__ import annotations

import os
import tempfile
import threading
import time

from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.common import CostListener, Stack, StackCPU, StackFactory, mb, run_campaign, status_kb

TARGET_LATENCY_P99_MS = 3.0  # issue 22: with the campaign's other rig busy
TARGET_LATENCY_P50_MS = 1.0
BUSY_RIG = "rig-2"  # the realtime part's neighbour, kept busy in fast mode; the realtime campaign runs on rig-1


def target_steps_per_second(preset: str) -> int:
    return 2000 if preset == "dynamic" else 2200


def inprocess_steps_per_second(preset: str, tests: int, algorithms: list[str]) -> tuple[float, dict, float | None]:
    """The same campaign in-process on one worker (``simulate``): steps/s, DR_final per
    algorithm, and the CPU each control step cost this process [ms] (from its first episode on,
    like the steps/s: training excluded)."""
    from ra2vipas.services.orchestrator.engine import Point, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    cpu_at: list[float] = []
    run = run_points([Point(preset, build_scenario(preset), tests, 1, tuple(algorithms))], workers=1,
                     on_trained=lambda _i, _pod: cpu_at.append(time.process_time()))
    cpu_ms = 1e3 * (time.process_time() - cpu_at[0]) / run.steps if cpu_at and run.steps else None
    return run.steps_per_second or 0.0, {a: b["dr_final"] for a, b in run.results[0]["algorithms"].items()}, cpu_ms


class BusyRig:
    """Keeps one rig of a stack busy while another part of the benchmark runs: fast campaigns of
    ``preset`` on that rig alone, one after another, until ``stop``. ``mark()`` says how many of
    their control steps have finished so far, so a window's steps per second is two marks apart."""

    def __init__(self, api: str, rig: str, preset: str, algorithms: list[str]) -> None:
        import httpx

        self.body = {"preset": preset, "tests": 1000, "seed": 2, "algorithms": algorithms, "rigs": [rig]}
        self.http = httpx.Client(base_url=api, timeout=30)
        self._stopping = threading.Event()
        self._running = threading.Event()
        self._lock = threading.Lock()
        self._steps_before = 0  # steps of the campaigns finished
        self._current: tuple[str, int] | None = None  # (id, steps per episode) of the one running
        self.campaigns = 0
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name=f"busy-{rig}", daemon=True)

    def start(self, timeout: float = 300.0) -> None:
        self._thread.start()
        if not self._running.wait(timeout) or self.error:
            self.stop()
            raise RuntimeError(self.error or f"the busy rig's campaign did not start within {timeout:.0f} s")

    def _run(self) -> None:
        try:
            while not self._stopping.is_set():
                c = self.http.post("/campaigns", json=self.body).json()
                if "id" not in c:
                    raise RuntimeError(f"the busy rig's campaign was refused: {c}")
                with self._lock:
                    self._current = (c["id"], int(c["scenario"]["steps"]))
                    self.campaigns += 1
                while not self._stopping.is_set():
                    c = self.http.get(f"/campaigns/{c['id']}").json()
                    if c["status"] == "running":
                        self._running.set()
                    if c["status"] in ("done", "failed", "cancelled"):
                        break
                    time.sleep(0.2)
                if c["status"] == "failed":
                    raise RuntimeError(f"the busy rig's campaign failed: {c.get('error')}")
                with self._lock:
                    self._steps_before += c["progress"]["done"] * self._current[1]
                    self._current = None
        except Exception as err:  # said by start() or mark(), the benchmark fails with it
            self.error = f"{type(err).__name__}: {err}"
            self._running.set()

    def mark(self) -> tuple[float, int]:
        """(monotonic time, control steps the busy rig finished so far)."""
        with self._lock:
            now, before, current = time.monotonic(), self._steps_before, self._current
        if current is not None:
            before += self.http.get(f"/campaigns/{current[0]}").json()["progress"]["done"] * current[1]
        return now, before

    def stop(self) -> None:
        self._stopping.set()
        with self._lock:
            current = self._current
        if current is not None:
            try:
                self.http.post(f"/campaigns/{current[0]}/cancel")
            except Exception:  # the stack is stopped next anyway
                pass
        self._thread.join(30)
        self.http.close()


def mesh_memory(stack: Stack, tests: int, steps: int, algorithm: str) -> dict:
    """One campaign of ``tests`` tests on a freshly started stack: the orchestrator process's
    resident memory before the campaign, after it, and its peak over its whole life (VmHWM)."""
    pid = next((c.proc.pid for c in stack.children if c.name == "orchestrator" and c.proc is not None), None)
    if pid is None:
        raise RuntimeError("the stack has no orchestrator process")
    before = status_kb(pid, "VmRSS")
    body = {"preset": "paper", "overrides": {"steps": steps}, "tests": tests, "seed": 1, "algorithms": [algorithm]}
    results, wall, _ = run_campaign(stack.api_url, body, 7200, poll=0.5)
    after, peak = status_kb(pid, "VmRSS"), status_kb(pid, "VmHWM")
    if peak is None:
        raise RuntimeError(f"cannot read /proc/{pid}/status (the orchestrator's memory)")
    return {"tests": tests, "steps": steps, "algorithm": algorithm, "episodes": tests, "seconds": round(wall, 2),
            "steps_per_second": results["steps_per_second"], "orchestrator_pid": pid, "orchestrator_peak_rss_mb": mb(peak),
            "orchestrator_rss_before_mb": mb(before), "orchestrator_rss_after_mb": mb(after),
            "dr_final": results["algorithms"][algorithm]["dr_final"]}


def mesh(launch: StackFactory, *, rigs: int, window: int, tests: int, realtime_tests: int, memory_tests: list[int],
         memory_steps: int, memory_algorithm: str, preset: str, inprocess: bool, rig_layouts: tuple[str, ...] = ("one-process",),
         realtime_beside_busy: bool = True) -> dict:
    """Each part on a stack of its own made by ``launch`` (every one stopped afterwards): the
    PRESET campaign of ``tests`` tests x the active built-ins on ``rigs`` rigs in fast mode
    (0: skip; with ``inprocess``, also in-process on one worker), ``realtime_tests`` tests paced
    at T_RF on one rig (0: skip), and one campaign of each size in ``memory_tests``.

    With ``realtime_beside_busy`` the realtime part runs on a stack of two rigs, its campaign on
    rig-1 while rig-2 runs fast campaigns of the same preset throughout (``BusyRig``): the
    machine as a campaign with another rig at work leaves it. Without, it runs on one rig alone,
    and with ``rigs`` = 1 on the fast part's stack, after its campaign.
    The fast and realtime parts run once per layout of ``rig_layouts`` ("one-process": a rig's
    two nodes in one process and one Zenoh session; "split": two processes); the report's
    top-level figures are the first layout's, and ``by_layout`` has every layout's."""
    from ra2vipas.services.controller import registry

    algorithms = [a for a in registry.BUILTINS if a != "sweep"]  # the active built-ins
    report: dict = {"benchmark": "mesh", "preset": preset, "rigs": rigs, "window": window, "rig_layout": rig_layouts[0],
                    "targets": {"steps_per_second": target_steps_per_second(preset), "latency_p99_ms": TARGET_LATENCY_P99_MS,
                                "latency_p50_ms": TARGET_LATENCY_P50_MS},
                    "steps_per_second": None}
    parts = {layout: {"steps_per_second": None, "latency_ms": None} for layout in rig_layouts}
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:

        def stack_of(n: int, name: str, layout: str | None = None) -> Stack:
            return launch(rigs=n, db_path=os.path.join(tmp, f"{name}.db"), log_dir=os.path.join(tmp, f"logs-{name}"), window=window,
                          rig_layout=layout)

        def fast_part(stack: Stack, part: dict) -> None:
            listener = CostListener(stack)
            cpu = StackCPU(stack)
            body = {"preset": preset, "tests": tests, "seed": 1, "algorithms": algorithms}
            try:
                fast, fast_wall, _ = run_campaign(stack.api_url, body, 1800, on_running=cpu.start, on_done=cpu.stop)
                time.sleep(0.2)
                breakdown = listener.breakdown()
            finally:
                listener.close()
            part["fast"] = {
                "tests": tests, "algorithms": algorithms, "steps": tests * len(algorithms) * fast["scenario"]["steps"],
                "steps_per_second": fast["steps_per_second"], "wall_seconds_with_training": round(fast_wall, 3),
                "dr_final": {a: b["dr_final"] for a, b in fast["algorithms"].items()},
                "step_breakdown": breakdown,
                "cpu_ms_per_step": cpu.per_step_ms(tests * len(algorithms) * fast["scenario"]["steps"]),
            }
            part["steps_per_second"] = fast["steps_per_second"]

        def realtime_part(stack: Stack, part: dict, beside_busy: bool) -> None:
            listener = CostListener(stack, "rig-1" if beside_busy else None)  # not the busy rig's episodes
            busy = BusyRig(stack.api_url, BUSY_RIG, preset, algorithms) if beside_busy else None
            marks: list[tuple[float, int]] = []
            body = {"preset": preset, "tests": realtime_tests, "seed": 1, "algorithms": ["ra2vipas"], "mode": "realtime"}
            try:
                if busy is not None:
                    busy.start()
                    body["rigs"] = ["rig-1"]
                mark = (lambda: marks.append(busy.mark())) if busy is not None else None
                rt, rt_wall, _ = run_campaign(stack.api_url, body, 900, poll=1.0, on_running=mark, on_done=mark)
                time.sleep(0.2)
                breakdown = listener.breakdown(realtime=True)
                if busy is not None and busy.error:
                    raise RuntimeError(busy.error)
            finally:
                listener.close()
                if busy is not None:
                    busy.stop()
            part["latency_ms"] = rt.get("latency_ms")
            part["realtime"] = {"rigs": 1, "tests": realtime_tests, "samples": realtime_tests * (rt["scenario"]["steps"] - 1),
                                "wall_seconds": round(rt_wall, 3), "dr_final": rt["algorithms"]["ra2vipas"]["dr_final"],
                                "step_breakdown": breakdown, "beside_busy_rig": None}
            if busy is not None and len(marks) == 2:
                (t0, s0), (t1, s1) = marks
                # the neighbour's fast-mode pace while the realtime campaign ran (0 would mean it idled)
                part["realtime"]["beside_busy_rig"] = {"rig": BUSY_RIG, "preset": preset, "campaigns": busy.campaigns,
                                                       "steps": s1 - s0, "steps_per_second": round((s1 - s0) / (t1 - t0), 1) if t1 > t0 else None}

        # the realtime part runs on a rig of its own; alone (--realtime-alone) with --rigs 1 it runs on the fast part's
        # stack, after it (one stack start fewer per layout; its own campaign, so its breakdown and latency are its own)
        shared = rigs == 1 and tests and realtime_tests and not realtime_beside_busy
        for layout, part in parts.items() if tests else ():
            stack = stack_of(rigs, f"fast-{layout}", layout)
            what = "fast"
            try:
                stack.start()
                fast_part(stack, part)
                if shared:
                    what = "realtime"
                    realtime_part(stack, part, beside_busy=False)
            except (TimeoutError, RuntimeError) as err:  # a stack that did not start raises a RuntimeError too
                raise BenchmarkError(f"bench mesh ({what}, {layout} rigs): {err}") from err
            finally:
                stack.stop()
        if tests and inprocess:
            sps1, dr1, cpu1 = inprocess_steps_per_second(preset, tests, algorithms)
            report["inprocess_steps_per_second_1"] = round(sps1, 1)
            report["inprocess_cpu_ms_per_step"] = None if cpu1 is None else round(cpu1, 4)
            for part in parts.values():
                part["mesh_over_inprocess"] = round(part["steps_per_second"] / sps1, 3) if sps1 else None
                # per-core efficiency, independent of what else the machine runs: the CPU a control step costs
                # in process over what it costs the whole mesh (1.0: a mesh core does what an in-process core does)
                mesh_cpu = part["fast"]["cpu_ms_per_step"]
                part["cpu_efficiency"] = round(cpu1 / mesh_cpu["total"], 3) if cpu1 and mesh_cpu and mesh_cpu["total"] else None
                part["fast"]["dr_final_equals_inprocess"] = dr1 == part["fast"]["dr_final"]
        for layout, part in parts.items() if realtime_tests and not shared else ():
            stack = stack_of(2 if realtime_beside_busy else 1, f"realtime-{layout}", layout)
            try:
                stack.start()
                realtime_part(stack, part, beside_busy=realtime_beside_busy)
            except (TimeoutError, RuntimeError) as err:
                raise BenchmarkError(f"bench mesh (realtime, {layout} rigs): {err}") from err
            finally:
                stack.stop()
        report.update(parts[rig_layouts[0]])
        if len(rig_layouts) > 1:
            report["by_layout"] = parts
        if memory_tests:
            report["memory"] = []
        for size in memory_tests:
            stack = stack_of(rigs, f"memory-{size}", rig_layouts[0])
            try:
                stack.start()
                report["memory"].append(mesh_memory(stack, size, memory_steps, memory_algorithm))
            except (TimeoutError, RuntimeError) as err:
                raise BenchmarkError(f"bench mesh (memory, {size} tests): {err}") from err
            finally:
                stack.stop()
    return report
