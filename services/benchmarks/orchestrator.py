"""``ra2vipas bench orchestrator``: how many episodes one orchestrator scores and stores per
second, with rigs faked at the wire level (services/rigs/instant.py), so nothing but the
orchestrator does real work."""

from __future__ import annotations

import os
import tempfile
import time

from ra2vipas.services.benchmarks import BenchmarkError
from ra2vipas.services.benchmarks.common import StackFactory, cpu_of, load_average, stack_bus

TARGET_EPISODES_PER_SECOND = 1000
ALGORITHMS = ["ra2vipas", "rapas", "ravipas"]


def orchestrator(launch: StackFactory, *, tests: int, rig_count: int, window: int, preset: str) -> dict:
    """A stack without rigs made by ``launch`` (router, learner, orchestrator; stopped
    afterwards), joined by ``rig_count`` instant rigs in this process, runs the PRESET campaign
    of ``tests`` tests x ``ALGORITHMS``: episodes per second on the orchestrator's own clock,
    and the orchestrator's and the fake rigs' CPU use while it ran (in cores)."""
    import httpx

    from ra2vipas.services.rigs.instant import InstantRig

    algorithms = list(ALGORITHMS)
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:
        stack = launch(rigs=0, db_path=os.path.join(tmp, "orchestrator.db"), log_dir=os.path.join(tmp, "logs"), window=window)
        bus = fakes = client = None
        try:
            stack.start()
            bus = stack_bus(stack)
            fakes = [InstantRig(bus, f"rig-{i}") for i in range(1, rig_count + 1)]
            orchestrator = next(c for c in stack.children if c.name == "orchestrator").proc.pid
            api = stack.api_url
            client = httpx.Client()  # one client: each new one loads the CA bundle (~75 ms of CPU)
            deadline = time.monotonic() + 30
            while len([r for r in client.get(f"{api}/rigs", timeout=10).json()["rigs"] if r["live"]]) < rig_count:
                if time.monotonic() > deadline:
                    raise RuntimeError("the orchestrator did not see the fake rigs within 30 s")
                time.sleep(0.1)
            started = time.perf_counter()
            c = client.post(f"{api}/campaigns", json={"preset": preset, "tests": tests, "seed": 1, "algorithms": algorithms},
                            timeout=30).json()
            running_at = cpu_at = own_at = None
            while c["status"] not in ("done", "failed", "cancelled"):
                if time.perf_counter() - started > 1800:
                    raise TimeoutError(f"campaign {c['id']} did not finish within 1800 s")
                time.sleep(0.25)  # polls slowly: a request costs the orchestrator CPU
                c = client.get(f"{api}/campaigns/{c['id']}", timeout=30).json()
                if running_at is None and c["status"] == "running":
                    running_at, cpu_at, own_at = time.perf_counter(), cpu_of(orchestrator), time.process_time()
            done_at, cpu_done, own_done = time.perf_counter(), cpu_of(orchestrator), time.process_time()
            if c["status"] != "done":
                raise RuntimeError(f"campaign {c['id']} {c['status']}: {c.get('error')}")
            results = client.get(f"{api}/campaigns/{c['id']}/results", timeout=30).json()
        except (TimeoutError, RuntimeError, httpx.HTTPError) as err:  # a stack that did not start raises a RuntimeError too
            raise BenchmarkError(f"bench orchestrator: {err}") from err
        finally:
            if client is not None:
                client.close()
            for fake in fakes or []:
                fake.close()
            if bus is not None:
                bus.close()
            stack.stop()
    episodes = tests * len(algorithms)
    steps = results["scenario"]["steps"]
    seconds = done_at - (running_at or started)
    return {
        "benchmark": "orchestrator", "preset": preset, "tests": tests, "episodes": episodes, "steps": steps,
        "fake_rigs": rig_count, "window": window,
        # the orchestrator's own clock: from the campaign's first episode to its last (its steps/s over n_test)
        "episodes_per_second": round(results["steps_per_second"] / steps, 1) if results.get("steps_per_second") else None,
        "seconds_polled": round(seconds, 3), "wall_seconds_with_training": round(done_at - started, 3),
        "orchestrator_cpu": round((cpu_done - (cpu_at or 0.0)) / seconds, 3) if seconds > 0 else None,
        "fake_rigs_cpu": round((own_done - (own_at or 0.0)) / seconds, 3) if seconds > 0 else None,
        "answered": sum(f.answered for f in fakes or []),
        "target_episodes_per_second": TARGET_EPISODES_PER_SECOND,
        "load_average": load_average(),
    }
