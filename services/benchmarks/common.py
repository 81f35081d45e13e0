"""What several benchmarks share: percentiles, a process's CPU and memory from /proc, the local
stack a benchmark is handed (``Stack``, ``StackFactory``), a campaign run through its REST API,
and what a stack's processes measured and used while it ran (``CostListener``, ``StackCPU``)."""

from __future__ import annotations

import os
import time
from typing import Any, Callable, Protocol


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile of ``values``, nearest rank (one of the values)."""
    ordered = sorted(values)
    idx = min(len(ordered) - 1, max(0, round(q / 100.0 * (len(ordered) - 1))))
    return ordered[idx]


def load_average() -> list[float] | None:
    """The machine's 1, 5 and 15 minute load averages (None where the OS has none)."""
    return [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None


def _cpu_ticks(pid: int) -> int:
    """Clock ticks of CPU (user + system) a process has used so far; 0 if unreadable."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, ValueError, IndexError):
        return 0


def cpu_of(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    return _cpu_ticks(pid) / os.sysconf("SC_CLK_TCK")


def cpu_seconds(pids: dict[str, list[int]]) -> dict[str, float]:
    """CPU time (user + system) used so far by each named group of processes (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    return {name: sum(_cpu_ticks(pid) for pid in group) / tick for name, group in pids.items()}


def status_kb(pid: int, field: str) -> int | None:
    """A ``/proc/PID/status`` field in kB (``VmRSS``: resident now, ``VmHWM``: its peak), None if unreadable."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(f"{field}:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return None


def mb(kb: int | None) -> float | None:
    return None if kb is None else round(kb / 1024, 1)


class Stack(Protocol):
    """A local stack of the services as child processes (router, orchestrator, learner, rigs),
    as cli/stack.py's ``Stack`` is: ``start()`` raises a ``RuntimeError`` (one line) if it
    does not come up, ``stop()`` stops and reaps every process it started."""

    api_url: str  # the orchestrator's REST API
    router_endpoint: str | None  # the Zenoh router's endpoint, after start()
    credentials: Any  # None (an insecure stack), or the stack's Zenoh credentials: ``env()`` -> the variables to join it
    # its processes: each with ``name`` ("rig-1", "controller-rig-1", "orchestrator", ...), ``role`` ("rig", "sensors",
    # "controller", "router", ...) and ``proc`` (a Popen, or None)
    children: list

    def start(self) -> None: ...

    def stop(self) -> None: ...


class StackFactory(Protocol):
    """Makes a stack, not yet started, of ``rigs`` rigs (sensors + controller pairs), its
    database at ``db_path``, its logs in ``log_dir``, ``window`` episodes in flight per rig, its
    rigs laid out as ``rig_layout`` ("one-process" or "split"; None: the stack's default)."""

    def __call__(self, *, rigs: int, db_path: str, log_dir: str, window: int = 8, rig_layout: str | None = None) -> Stack: ...


def run_campaign(api: str, body: dict, timeout: float, poll: float = 0.1, on_running: Callable[[], None] | None = None,
                 on_done: Callable[[], None] | None = None) -> tuple[dict, float, str]:
    """Start a campaign, wait until it is done; its results, wall time and id. ``on_running()``
    is called when the poll first sees it running (its model trained, episodes handed out),
    ``on_done()`` when it sees it finished."""
    import httpx

    started = time.perf_counter()
    with httpx.Client(timeout=30) as client:  # one client: each new one loads the CA bundle (~75 ms of CPU)
        c = client.post(f"{api}/campaigns", json=body).json()
        deadline = time.monotonic() + timeout
        while c["status"] not in ("done", "failed", "cancelled"):
            if time.monotonic() > deadline:
                raise TimeoutError(f"campaign {c['id']} did not finish within {timeout:.0f} s")
            time.sleep(poll)
            c = client.get(f"{api}/campaigns/{c['id']}").json()
            if on_running is not None and c["status"] == "running":
                on_running()
                on_running = None
        if on_done is not None:
            on_done()
        wall = time.perf_counter() - started
        if c["status"] != "done":
            raise RuntimeError(f"campaign {c['id']} {c['status']}: {c.get('error')}")
        return client.get(f"{api}/campaigns/{c['id']}/results").json(), wall, c["id"]


def stack_bus(stack: Stack, workers: int | None = None):
    """A Zenoh client session on ``stack``'s router, with the stack's credentials."""
    from ra2vipas.services.transport.zenoh_bus import ZenohBus
    from ra2vipas.services.transport.zenoh_config import ZenohSettings

    env = stack.credentials.env() if stack.credentials is not None else {}
    settings = ZenohSettings.from_sources(mode="client", connect=[stack.router_endpoint], env=env)
    return ZenohBus(settings) if workers is None else ZenohBus(settings, workers=workers)


class CostListener:
    """Joins a stack's Zenoh network (its credentials) and keeps every episode result and
    timing report the rigs (or the one ``rig``) publish: the stage costs the nodes measured
    (``StepCosts``)."""

    def __init__(self, stack: Stack, rig: str | None = None) -> None:
        from ra2vipas.services.protocol import keys

        self.results: list[bytes] = []
        self.timings: list[bytes] = []
        self.bus = stack_bus(stack, workers=1)
        result_key = keys.episode_result(rig) if rig else keys.episode_result_all()
        timing_key = keys.episode_timing(rig) if rig else keys.episode_timing_all()
        self.bus.subscribe(result_key, lambda _k, p: self.results.append(p))
        self.bus.subscribe(timing_key, lambda _k, p: self.timings.append(p))

    def clear(self) -> None:
        self.results.clear()
        self.timings.clear()

    def breakdown(self, realtime: bool = False) -> dict:
        """``costs.step_breakdown`` over the episodes both nodes reported costs for."""
        from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeTiming
        from ra2vipas.services.transport.costs import step_breakdown

        ctl = {r.episode_id: r.costs for r in map(EpisodeResult.model_validate_json, list(self.results)) if r.costs is not None}
        timings = {t.episode_id: t for t in map(EpisodeTiming.model_validate_json, list(self.timings)) if t.costs is not None}
        both = [eid for eid in ctl if eid in timings]
        latencies = [v for eid in both for v in timings[eid].latencies_ms] if realtime else None
        return step_breakdown([ctl[e] for e in both], [timings[e].costs for e in both], latencies)

    def close(self) -> None:
        self.bus.close()


class StackCPU:
    """CPU seconds (user + system) a stack's processes use between ``start`` and ``stop``, by
    role: what a campaign costs the machine's cores, whatever else runs on them (a shared
    machine slows every process down, it does not make one use more CPU per step)."""

    ROLES = ("rig", "controller", "sensors", "router", "orchestrator", "learner")  # rig: a one-process rig (both nodes)

    def __init__(self, stack: Stack) -> None:
        self.pids = {c.name: c.proc.pid for c in stack.children if c.proc is not None}
        self.roles = {c.name: getattr(c, "role", "") or c.name.split("-")[0] for c in stack.children}
        self.at: dict[str, float] = {}
        self.used: dict[str, float] = {}

    def start(self) -> None:
        self.at = {name: cpu_of(pid) for name, pid in self.pids.items()}

    def stop(self) -> None:
        self.used = {name: cpu_of(pid) - self.at.get(name, 0.0) for name, pid in self.pids.items()} if self.at else {}

    def per_step_ms(self, steps: int) -> dict | None:
        """Per control step [ms of CPU], by role (summed over rigs) and in total."""
        if not self.used or not steps:
            return None
        out = {role: round(1e3 * sum(v for name, v in self.used.items() if self.roles.get(name) == role) / steps, 4)
               for role in self.ROLES}
        out["total"] = round(sum(out.values()), 4)
        return out
