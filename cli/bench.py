"""``ra2vipas bench ...``: the speed benchmarks the project ships (JSON for scripts)."""

from __future__ import annotations

import os
import statistics
import time
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail, print_json, stdout
from ra2vipas.cli.polish import deprecated, prefer
from ra2vipas.services.orchestrator.api.schemas import MAX_TESTS

app = typer.Typer(help="Speed benchmarks (print JSON with --json).", no_args_is_help=True)


def _complete_policies(incomplete: str) -> list[str]:
    """Shell completion of a policy name: every installed policy (``registry.names()``)."""
    from ra2vipas.services.controller import registry

    return [n for n in registry.names() if n.startswith(incomplete)]


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    idx = min(len(ordered) - 1, max(0, round(q / 100.0 * (len(ordered) - 1))))
    return ordered[idx]


@app.command("step")
def bench_step(
    algorithm: Annotated[str, typer.Option(help="Controller algorithm to time.")] = "ra2vipas",
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Episodes to time.")] = 10,
    seed: Annotated[int, typer.Option(min=0)] = 1,
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ...).")] = "paper",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Time one controller step (measurement in, decision out) on a preset's scenario, in-process.

    Reports the median and p99 over all steps and over the last step of each test (when the
    controller holds n_test = 120 samples). Targets: median <= 1 ms; on dynamic also p99 <= 3 ms.
    """
    from ra2vipas.services.controller.registry import BUILTINS

    if algorithm not in BUILTINS:  # it times the built-ins' Controller
        fail(f"unknown algorithm {algorithm!r}; choose from {', '.join(BUILTINS)}", EXIT_USAGE)
    from ra2vipas.services.controller.policy import Controller, sensor_config_from_scenario, tuned_settings
    from ra2vipas.services.orchestrator.simulate import train_pod
    from ra2vipas.services.protocol.scenario import PRESETS, build_scenario
    from ra2vipas.services.sensors.world import SimulatedPlatform

    if preset not in PRESETS:
        fail(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}", EXIT_USAGE)
    scenario = build_scenario(preset)
    pod = train_pod(scenario, seed)
    all_ms: list[float] = []
    last_ms: list[float] = []
    for k in range(tests):
        platform = SimulatedPlatform(scenario, seed, k)
        controller = Controller(algorithm, sensor_config_from_scenario(scenario), pod.model, tuned_settings(algorithm))
        pan = controller.first_pan()
        for t in range(scenario.steps):
            m = platform.sense(t, pan)
            started = time.perf_counter()
            decision = controller.step(m)
            elapsed = (time.perf_counter() - started) * 1e3
            all_ms.append(elapsed)
            pan = decision.next_pan_rad
        last_ms.append(elapsed)
    report = {
        "benchmark": "controller-step",
        "algorithm": algorithm,
        "preset": preset,
        "tests": tests,
        "steps": len(all_ms),
        "median_ms": round(statistics.median(all_ms), 4),
        "p99_ms": round(_percentile(all_ms, 99), 4),
        "median_ms_at_n_test": round(statistics.median(last_ms), 4),
        "pod_train_seconds": round(pod.train_seconds, 4),
        "target_median_ms": 1.0,
    }
    if as_json:
        print_json(report)
    else:
        stdout.print(
            f"controller step ({algorithm}): median {report['median_ms']:.3f} ms, p99 {report['p99_ms']:.3f} ms, "
            f"median at n=120 {report['median_ms_at_n_test']:.3f} ms over {report['steps']} steps"
        )


def _run_campaign(api: str, body: dict, timeout: float, poll: float = 0.1) -> tuple[dict, float]:
    results, wall, _ = _run_campaign_id(api, body, timeout, poll)
    return results, wall


def _run_campaign_id(api: str, body: dict, timeout: float, poll: float = 0.1, on_running=None,
                     on_done=None) -> tuple[dict, float, str]:
    """Start a campaign, wait until it is done; its results, wall time and id. ``on_running()``
    is called when the poll first sees it running (its model trained, episodes handed out),
    ``on_done()`` when it sees it finished."""
    import httpx

    started = time.perf_counter()
    c = httpx.post(f"{api}/campaigns", json=body, timeout=30).json()
    deadline = time.monotonic() + timeout
    while c["status"] not in ("done", "failed", "cancelled"):
        if time.monotonic() > deadline:
            raise TimeoutError(f"campaign {c['id']} did not finish within {timeout:.0f} s")
        time.sleep(poll)
        c = httpx.get(f"{api}/campaigns/{c['id']}", timeout=30).json()
        if on_running is not None and c["status"] == "running":
            on_running()
            on_running = None
    if on_done is not None:
        on_done()
    wall = time.perf_counter() - started
    if c["status"] != "done":
        raise RuntimeError(f"campaign {c['id']} {c['status']}: {c.get('error')}")
    return httpx.get(f"{api}/campaigns/{c['id']}/results", timeout=30).json(), wall, c["id"]


class _CostListener:
    """Joins a stack's Zenoh network (its credentials) and keeps every episode result and
    timing report the rigs publish: the stage costs the nodes measured (``StepCosts``)."""

    def __init__(self, stack) -> None:
        from ra2vipas.services.protocol import keys
        from ra2vipas.services.transport.zenoh_bus import ZenohBus
        from ra2vipas.services.transport.zenoh_config import ZenohSettings

        env = stack.credentials.env() if stack.credentials is not None else {}
        self.results: list[bytes] = []
        self.timings: list[bytes] = []
        self.bus = ZenohBus(ZenohSettings.from_sources(mode="client", connect=[stack.router_endpoint], env=env), workers=1)
        self.bus.subscribe(keys.episode_result_all(), lambda _k, p: self.results.append(p))
        self.bus.subscribe(keys.episode_timing_all(), lambda _k, p: self.timings.append(p))

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


class _StackCPU:
    """CPU seconds (user + system) a stack's processes use between ``start`` and ``stop``, by
    role: what a campaign costs the machine's cores, whatever else runs on them (a shared
    machine slows every process down, it does not make one use more CPU per step)."""

    ROLES = ("controller", "sensors", "router", "orchestrator", "learner")

    def __init__(self, stack) -> None:
        self.pids = {c.name: c.proc.pid for c in stack.children if c.proc is not None}
        self.at: dict[str, float] = {}
        self.used: dict[str, float] = {}

    def start(self) -> None:
        self.at = {name: _cpu_of(pid) for name, pid in self.pids.items()}

    def stop(self) -> None:
        self.used = {name: _cpu_of(pid) - self.at.get(name, 0.0) for name, pid in self.pids.items()} if self.at else {}

    def per_step_ms(self, steps: int) -> dict | None:
        """Per control step [ms of CPU], by role (summed over rigs) and in total."""
        if not self.used or not steps:
            return None
        out = {role: round(1e3 * sum(v for name, v in self.used.items() if name.split("-")[0] == role) / steps, 4)
               for role in self.ROLES}
        out["total"] = round(sum(out.values()), 4)
        return out


def _inprocess_steps_per_second(preset: str, tests: int, algorithms: list[str]) -> tuple[float, dict, float | None]:
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


@app.command("learner")
def bench_learner(
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ble, ...).")] = "dynamic",
    seeds: Annotated[str, typer.Option(help="Campaign seeds, e.g. 1-5 or 1,3,7.")] = "1-5",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Score the POD learner on each seed's training episode: R², the RMSE against the POD the
    RSSI predicts p*(r), and the oracle fit's RMSE (issue 20). Target on dynamic: RMSE <= 1.3 x
    the oracle's on every seed."""
    from ra2vipas.services.learner.pod import fit_pod, score_pod
    from ra2vipas.services.protocol.scenario import PRESETS, build_scenario
    from ra2vipas.services.sensors.world import TrainingEpisode

    if preset not in PRESETS:
        fail(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}", EXIT_USAGE)
    try:
        chosen = sorted({n for part in seeds.split(",") for n in (range(int(part.split("-")[0]), int(part.split("-")[1]) + 1)
                                                                  if "-" in part else [int(part)])})
    except ValueError:
        fail(f"--seeds: expected e.g. 1-5 or 1,3,7, got {seeds!r}", EXIT_USAGE)
    scenario = build_scenario(preset)
    rows = []
    for seed in chosen:
        episode = TrainingEpisode(scenario, seed)
        learned = fit_pod(list(episode.samples()))
        truth = episode.truth
        score = score_pod(learned.model, truth.rssi_dbm, truth.pod, truth.pod_at_range)
        rows.append({"seed": seed, "r2": round(score.r2, 4), "rmse": round(score.rmse, 4), "oracle_rmse": round(score.oracle_rmse, 4),
                     "ratio": round(score.rmse / max(score.oracle_rmse, 1e-9), 3), "train_seconds": round(learned.train_seconds, 3)})
    out = {"benchmark": "learner", "preset": preset, "seeds": rows,
           "within_1_3x_oracle": all(r["rmse"] <= 1.3 * r["oracle_rmse"] for r in rows)}
    if as_json:
        print_json(out)
        return
    for r in rows:
        stdout.print(f"seed {r['seed']}: R² {r['r2']:.3f}  RMSE vs p*(r) {r['rmse']:.3f}  oracle {r['oracle_rmse']:.3f}  "
                     f"({r['ratio']:.2f}x)  {r['train_seconds']:.2f} s")


@app.command("mesh")
def bench_mesh(
    rigs: Annotated[int, typer.Option("--rig-count", min=0, max=16, help="Sensor+controller pairs for fast mode (0: one per CPU core).")] = 0,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=0, max=16)] = None,
    window: Annotated[int, typer.Option(min=1, max=256, help="Episodes in flight per rig.")] = 8,
    tests: Annotated[int, typer.Option(min=0, max=1000, help="Tests of the fast-mode campaign (0: skip).")] = 50,
    realtime_tests: Annotated[int, typer.Option(min=0, max=64, help="Tests of the realtime campaign (0: skip); 8 tests give ~950 samples, so p99 rests on ~10 of them.")] = 8,
    memory_tests: Annotated[str, typer.Option(help="Campaign sizes whose orchestrator peak memory to measure, comma-separated, e.g. 1000,10000 (default: none).")] = "",
    memory_steps: Annotated[int, typer.Option(min=1, max=1000, help="n_test of the memory campaigns (short, so 10 000 tests take minutes).")] = 20,
    memory_algorithm: Annotated[str, typer.Option(help="The algorithm of the memory campaigns.")] = "rapas",
    preset: Annotated[str, typer.Option(help="Scenario preset of the fast and realtime campaigns (paper, dynamic, ...).")] = "paper",
    inprocess: Annotated[bool, typer.Option(help="Also run the fast campaign in-process on one worker: mesh_over_inprocess.")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Start local stacks and measure them through the real processes.

    Fast mode: the PRESET campaign (TESTS tests x ra2vipas, rapas, ravipas x 120 steps) in
    lockstep on RIG_COUNT rigs; reports control steps per second (target >= 2 200 on 2 cores
    for paper, >= 2 000 for dynamic).
    Realtime mode: REALTIME_TESTS tests paced at T_RF on one rig (one platform in the loop);
    reports the sample-to-command latency p50/p99 measured by the sensors (target p99 <= 5
    ms). Both report ``step_breakdown``: per step, each service's time queued on its event
    loop, decoding and validating, computing, encoding and publishing, as the services measured
    it, and the transport between them (services/transport/costs.py). The fast campaign is
    also run in-process on one worker: ``mesh_over_inprocess`` is mesh steps/s over that
    (``--no-inprocess`` skips it). ``cpu_ms_per_step`` is the CPU one control step of the fast
    campaign cost each service (summed over rigs; from the first episode on), and
    ``cpu_efficiency`` the in-process step's CPU over the mesh's: what a mesh core does of what
    an in-process core does, a ratio the machine's other load hardly moves. Memory (with --memory-tests): one campaign of each size (MEMORY_STEPS steps,
    MEMORY_ALGORITHM) on RIG_COUNT rigs, each on a fresh stack; reports the orchestrator
    process's peak resident memory (VmHWM) and its resident memory before and after (VmRSS).
    Every stack is stopped afterwards.

    Examples:

        ra2vipas bench mesh --json

        ra2vipas bench mesh --preset dynamic --realtime-tests 0 --json

        ra2vipas bench mesh --tests 0 --realtime-tests 0 --memory-tests 1000,10000 --json
    """
    import os
    import tempfile

    from ra2vipas.cli.stack import Stack, StackConfig, StackError, free_port
    from ra2vipas.services.controller import registry
    from ra2vipas.services.protocol.scenario import PRESETS

    if memory_algorithm not in registry.names():
        fail(f"unknown algorithm {memory_algorithm!r}; choose from {', '.join(registry.names())}", EXIT_USAGE)
    if preset not in PRESETS:
        fail(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}", EXIT_USAGE)
    sizes = _sizes(memory_tests, "--memory-tests")
    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count") or max(1, min(os.cpu_count() or 1, 16))
    algorithms = [a for a in registry.BUILTINS if a != "sweep"]  # the active built-ins
    report: dict = {"benchmark": "mesh", "preset": preset, "rigs": rigs, "window": window,
                    "targets": {"steps_per_second": 2000 if preset == "dynamic" else 2200, "latency_p99_ms": 5.0}, "steps_per_second": None}
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:

        def stack_of(n: int, name: str) -> Stack:
            return Stack(StackConfig(rigs=n, port=free_port(), db_path=os.path.join(tmp, f"{name}.db"), window=window,
                                     log_dir=os.path.join(tmp, f"logs-{name}"), log_level="WARNING"))

        if tests:
            stack = stack_of(rigs, "fast")
            try:
                stack.start()
                listener = _CostListener(stack)
                cpu = _StackCPU(stack)
                body = {"preset": preset, "tests": tests, "seed": 1, "algorithms": algorithms}
                try:
                    fast, fast_wall, _ = _run_campaign_id(stack.api_url, body, 1800, on_running=cpu.start, on_done=cpu.stop)
                    time.sleep(0.2)
                    breakdown = listener.breakdown()
                finally:
                    listener.close()
                report["fast"] = {
                    "tests": tests, "algorithms": algorithms, "steps": tests * len(algorithms) * fast["scenario"]["steps"],
                    "steps_per_second": fast["steps_per_second"], "wall_seconds_with_training": round(fast_wall, 3),
                    "dr_final": {a: b["dr_final"] for a, b in fast["algorithms"].items()},
                    "step_breakdown": breakdown,
                    "cpu_ms_per_step": cpu.per_step_ms(tests * len(algorithms) * fast["scenario"]["steps"]),
                }
                report["steps_per_second"] = fast["steps_per_second"]
            except (StackError, TimeoutError, RuntimeError) as err:
                fail(f"bench mesh (fast): {err}")
            finally:
                stack.stop()
            if inprocess:
                sps1, dr1, cpu1 = _inprocess_steps_per_second(preset, tests, algorithms)
                report["inprocess_steps_per_second_1"] = round(sps1, 1)
                report["mesh_over_inprocess"] = round(report["steps_per_second"] / sps1, 3) if sps1 else None
                # per-core efficiency, independent of what else the machine runs: the CPU a control step costs
                # in process over what it costs the whole mesh (1.0: a mesh core does what an in-process core does)
                report["inprocess_cpu_ms_per_step"] = None if cpu1 is None else round(cpu1, 4)
                mesh_cpu = report["fast"]["cpu_ms_per_step"]
                report["cpu_efficiency"] = round(cpu1 / mesh_cpu["total"], 3) if cpu1 and mesh_cpu and mesh_cpu["total"] else None
                report["fast"]["dr_final_equals_inprocess"] = dr1 == report["fast"]["dr_final"]
        report["latency_ms"] = None
        if realtime_tests:
            stack = stack_of(1, "realtime")
            try:
                stack.start()
                listener = _CostListener(stack)
                try:
                    rt, rt_wall = _run_campaign(stack.api_url, {"preset": preset, "tests": realtime_tests, "seed": 1,
                                                                "algorithms": ["ra2vipas"], "mode": "realtime"}, 900, poll=1.0)
                    time.sleep(0.2)
                    breakdown = listener.breakdown(realtime=True)
                finally:
                    listener.close()
                report["latency_ms"] = rt.get("latency_ms")
                report["realtime"] = {"rigs": 1, "tests": realtime_tests, "samples": realtime_tests * (rt["scenario"]["steps"] - 1),
                                      "wall_seconds": round(rt_wall, 3), "dr_final": rt["algorithms"]["ra2vipas"]["dr_final"],
                                      "step_breakdown": breakdown}
            except (StackError, TimeoutError, RuntimeError) as err:
                fail(f"bench mesh (realtime): {err}")
            finally:
                stack.stop()
        if sizes:
            report["memory"] = []
        for size in sizes:
            stack = stack_of(rigs, f"memory-{size}")
            try:
                stack.start()
                report["memory"].append(_mesh_memory(stack, size, memory_steps, memory_algorithm))
            except (StackError, TimeoutError, RuntimeError) as err:
                fail(f"bench mesh (memory, {size} tests): {err}")
            finally:
                stack.stop()
    if as_json:
        print_json(report)
        return
    if tests or realtime_tests:
        lat = report["latency_ms"] or {}
        stdout.print(f"mesh ({rigs} rigs): {report['steps_per_second']} control steps/s in fast mode (target 2200); "
                     f"realtime sample->command latency p50 {lat.get('p50')} ms, p99 {lat.get('p99')} ms (target p99 <= 5)")
    b = (report.get("fast") or {}).get("step_breakdown") or {}
    if b.get("step_ms") is not None:
        c = b["controller"]
        stdout.print(f"per step: controller busy {b['controller_busy_ms']} ms (compute {c['compute_ms']}, publish {c['publish_ms']}, "
                     f"decode {c['decode_ms']}, encode {c['encode_ms']}), sensors busy {b['sensors_busy_ms']} ms, transport "
                     f"{b['transport_ms']} ms; mesh over in-process (1 worker): {report.get('mesh_over_inprocess')}")
    for m in report.get("memory") or []:
        stdout.print(f"{m['tests']} tests ({m['steps']} steps, {m['algorithm']}, {rigs} rigs): orchestrator peak RSS "
                     f"{m['orchestrator_peak_rss_mb']} MB ({m['orchestrator_rss_before_mb']} MB before the campaign, "
                     f"{m['orchestrator_rss_after_mb']} MB after), {m['seconds']} s")


def _cpu_of(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


@app.command("orchestrator")
def bench_orchestrator(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests of the campaign (x 3 algorithms = episodes).")] = 1000,
    rig_count: Annotated[int, typer.Option(min=1, max=64, help="Fake rigs answering episodes.")] = 4,
    window: Annotated[int, typer.Option(min=1, max=1024, help="Episodes in flight per rig.")] = 64,
    preset: Annotated[str, typer.Option(help="Scenario preset (paper, dynamic, ...).")] = "paper",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """How many episodes one orchestrator scores and stores per second, with rigs faked at the
    wire level (services/rigs/instant.py: each EpisodeStart is answered at once by a
    precomputed EpisodeTruth and EpisodeResult), so nothing but the orchestrator does real work.

    Starts a stack without rigs (router, learner, orchestrator), joins it with RIG_COUNT
    instant rigs in this process and runs the PRESET campaign (TESTS tests x ra2vipas, rapas,
    ravipas). Reports ``episodes_per_second`` (the campaign's steps/s over its n_test: episodes
    over the orchestrator's own time from the campaign's first episode to its last, after
    training; target >= 1 000 for paper episodes), and the orchestrator's and the fake rigs'
    CPU use while it ran (in cores, polled every 0.25 s; 1.0 = one core: the orchestrator's
    scheduler thread, holding the GIL, saturates about there).

    Example:

        ra2vipas bench orchestrator --json
    """
    import tempfile

    import httpx

    from ra2vipas.cli.stack import Stack, StackConfig, StackError, free_port
    from ra2vipas.services.protocol.scenario import PRESETS
    from ra2vipas.services.rigs.instant import InstantRig
    from ra2vipas.services.transport.zenoh_bus import ZenohBus
    from ra2vipas.services.transport.zenoh_config import ZenohSettings

    if preset not in PRESETS:
        fail(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}", EXIT_USAGE)
    algorithms = ["ra2vipas", "rapas", "ravipas"]
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:
        stack = Stack(StackConfig(rigs=0, port=free_port(), db_path=os.path.join(tmp, "orchestrator.db"), window=window,
                                  log_dir=os.path.join(tmp, "logs"), log_level="WARNING"))
        bus = fakes = None
        try:
            stack.start()
            env = stack.credentials.env() if stack.credentials is not None else {}
            bus = ZenohBus(ZenohSettings.from_sources(mode="client", connect=[stack.router_endpoint], env=env))
            fakes = [InstantRig(bus, f"rig-{i}") for i in range(1, rig_count + 1)]
            orchestrator = next(c for c in stack.children if c.name == "orchestrator").proc.pid
            api = stack.api_url
            deadline = time.monotonic() + 30
            while len([r for r in httpx.get(f"{api}/rigs", timeout=10).json()["rigs"] if r["live"]]) < rig_count:
                if time.monotonic() > deadline:
                    raise StackError("the orchestrator did not see the fake rigs within 30 s")
                time.sleep(0.1)
            started = time.perf_counter()
            c = httpx.post(f"{api}/campaigns", json={"preset": preset, "tests": tests, "seed": 1, "algorithms": algorithms},
                           timeout=30).json()
            running_at = cpu_at = own_at = None
            while c["status"] not in ("done", "failed", "cancelled"):
                if time.perf_counter() - started > 1800:
                    raise TimeoutError(f"campaign {c['id']} did not finish within 1800 s")
                time.sleep(0.25)  # polls slowly: a request costs the orchestrator CPU
                c = httpx.get(f"{api}/campaigns/{c['id']}", timeout=30).json()
                if running_at is None and c["status"] == "running":
                    running_at, cpu_at, own_at = time.perf_counter(), _cpu_of(orchestrator), time.process_time()
            done_at, cpu_done, own_done = time.perf_counter(), _cpu_of(orchestrator), time.process_time()
            if c["status"] != "done":
                raise RuntimeError(f"campaign {c['id']} {c['status']}: {c.get('error')}")
            results = httpx.get(f"{api}/campaigns/{c['id']}/results", timeout=30).json()
        except (StackError, TimeoutError, RuntimeError, httpx.HTTPError) as err:
            fail(f"bench orchestrator: {err}")
        finally:
            for fake in fakes or []:
                fake.close()
            if bus is not None:
                bus.close()
            stack.stop()
    episodes = tests * len(algorithms)
    steps = results["scenario"]["steps"]
    seconds = done_at - (running_at or started)
    report = {
        "benchmark": "orchestrator", "preset": preset, "tests": tests, "episodes": episodes, "steps": steps,
        "fake_rigs": rig_count, "window": window,
        # the orchestrator's own clock: from the campaign's first episode to its last (its steps/s over n_test)
        "episodes_per_second": round(results["steps_per_second"] / steps, 1) if results.get("steps_per_second") else None,
        "seconds_polled": round(seconds, 3), "wall_seconds_with_training": round(done_at - started, 3),
        "orchestrator_cpu": round((cpu_done - (cpu_at or 0.0)) / seconds, 3) if seconds > 0 else None,
        "fake_rigs_cpu": round((own_done - (own_at or 0.0)) / seconds, 3) if seconds > 0 else None,
        "answered": sum(f.answered for f in fakes or []),
        "target_episodes_per_second": 1000,
        "load_average": [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None,
    }
    if as_json:
        print_json(report)
        return
    stdout.print(f"orchestrator: {report['episodes_per_second']} {preset} episodes/s scored and stored ({episodes} episodes, "
                 f"{rig_count} instant rigs x {window} in flight; target 1000); orchestrator CPU {report['orchestrator_cpu']} cores, "
                 f"fake rigs {report['fake_rigs_cpu']}")


def _sizes(text: str, option: str) -> list[int]:
    """Comma-separated campaign sizes (tests) of a memory benchmark; a usage error if malformed."""
    try:
        sizes = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        fail(f"{option} expects comma-separated integers, got {text!r}", EXIT_USAGE)
    bad = [n for n in sizes if not 1 <= n <= MAX_TESTS]
    if bad:
        fail(f"{option}: a campaign has 1 to {MAX_TESTS} tests, got {bad[0]}", EXIT_USAGE)
    return sizes


def _status_kb(pid: int, field: str) -> int | None:
    """A ``/proc/PID/status`` field in kB (``VmRSS``: resident now, ``VmHWM``: its peak), None if unreadable."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(f"{field}:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return None


def _mb(kb: int | None) -> float | None:
    return None if kb is None else round(kb / 1024, 1)


def _mesh_memory(stack, tests: int, steps: int, algorithm: str) -> dict:
    """One campaign of ``tests`` tests on a freshly started stack: the orchestrator process's
    resident memory before the campaign, after it, and its peak over its whole life (VmHWM)."""
    pid = next((c.proc.pid for c in stack.children if c.name == "orchestrator" and c.proc is not None), None)
    if pid is None:
        raise RuntimeError("the stack has no orchestrator process")
    before = _status_kb(pid, "VmRSS")
    body = {"preset": "paper", "overrides": {"steps": steps}, "tests": tests, "seed": 1, "algorithms": [algorithm]}
    results, wall = _run_campaign(stack.api_url, body, 7200, poll=0.5)
    after, peak = _status_kb(pid, "VmRSS"), _status_kb(pid, "VmHWM")
    if peak is None:
        raise RuntimeError(f"cannot read /proc/{pid}/status (the orchestrator's memory)")
    return {"tests": tests, "steps": steps, "algorithm": algorithm, "episodes": tests, "seconds": round(wall, 2),
            "steps_per_second": results["steps_per_second"], "orchestrator_pid": pid, "orchestrator_peak_rss_mb": _mb(peak),
            "orchestrator_rss_before_mb": _mb(before), "orchestrator_rss_after_mb": _mb(after),
            "dr_final": results["algorithms"][algorithm]["dr_final"]}


# -- bench plots ---------------------------------------------------------------------------------

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
                "ok_p50_ms": round(_percentile(ok_ms, 50), 1) if ok_ms else None,
                "ok_p99_ms": round(_percentile(ok_ms, 99), 1) if ok_ms else None}

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


def _cpu_seconds(pids: dict[str, list[int]]) -> dict[str, float]:
    """CPU time (user + system) used so far by each named group of processes (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for name, group in pids.items():
        total = 0
        for pid in group:
            try:
                with open(f"/proc/{pid}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
                total += int(fields[11]) + int(fields[12])
            except (OSError, IndexError, ValueError):
                pass
        out[name] = total / tick
    return out


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


@app.command("plots")
def bench_plots(
    clients: Annotated[int, typer.Option(min=1, max=500, help="Concurrent plot clients.")] = 50,
    readers: Annotated[int, typer.Option(min=1, max=64, help="Clients reading non-plot routes, each pausing "
                                                             f"{READ_PAUSE_S} s between requests.")] = 4,
    tests: Annotated[int, typer.Option(min=1, max=1000, help="Tests of the measured campaign (paper preset, "
                                                             "ra2vipas, rapas, ravipas).")] = 50,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the measured campaign.")] = 1,
    repeats: Annotated[int, typer.Option(min=1, max=10, help="Runs of the campaign without and with plot load, "
                                                             "alternating.")] = 3,
    fixtures: Annotated[int, typer.Option(min=1, max=10, help="Finished campaigns whose figures the plot clients ask for.")] = 2,
    fixture_tests: Annotated[int, typer.Option(min=1, max=1000, help="Tests of each finished campaign.")] = 20,
    rigs: Annotated[int, typer.Option("--rig-count", min=0, max=16, help="Rigs (0: one per CPU core).")] = 0,
    old_rigs: Annotated[Optional[int], deprecated("--rigs", "--rig-count", min=0, max=16)] = None,
    retry_cap: Annotated[float, typer.Option(min=0.0, max=60.0, help="Longest wait of a plot client after a 503 "
                                                                     "(it honours Retry-After up to this).")] = 1.0,
    client_nice: Annotated[int, typer.Option(min=0, max=19, help="Niceness of the plot clients' process (0: they compete "
                                                                 "for the CPU like the tester's clients did).")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Plots under load: start a local stack, finish FIXTURES campaigns, then run the paper
    campaign REPEATS times without and with CLIENTS plot clients asking for those campaigns'
    figures (DR, POD and every episode, PNG and SVG: most are not cached yet), while READERS
    clients read /campaigns, /campaigns/{id}, /campaigns/{id}/results and /health.

    Reports the p99 latency of those reads under plot load (target <= 200 ms) and how much the
    plot load slows the campaign: median control steps/s without over with, minus 1 (target
    <= 10 %). Every process is stopped afterwards.
    """
    import multiprocessing
    import queue
    import statistics as stats
    import tempfile

    import httpx

    from ra2vipas.cli.stack import Stack, StackConfig, StackError, free_port
    from ra2vipas.services.controller.registry import BUILTINS

    rigs = prefer(rigs, old_rigs, "--rigs", "--rig-count") or max(1, min(os.cpu_count() or 1, 16))
    algorithms = [a for a in BUILTINS if a != "sweep"]  # the active built-ins
    body = {"preset": "paper", "tests": tests, "seed": seed, "algorithms": algorithms}
    report: dict = {"benchmark": "plots", "rigs": rigs, "plot_clients": clients, "readers": readers,
                    "retry_cap_s": retry_cap, "client_nice": client_nice,
                    "campaign": {**body, "repeats": repeats}, "targets": PLOT_TARGETS}
    ctx = multiprocessing.get_context("spawn")
    load = None
    with tempfile.TemporaryDirectory(prefix="ra2vipas-bench-") as tmp:
        stack = Stack(StackConfig(rigs=rigs, port=free_port(), db_path=os.path.join(tmp, "plots.db"),
                                  log_dir=os.path.join(tmp, "logs"), log_level="WARNING"))
        try:
            stack.start()
            api = stack.api_url
            finished = []
            for i in range(fixtures):
                _, _, cid = _run_campaign_id(api, {**body, "tests": fixture_tests, "seed": 100 + i}, 1800)
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
                        cpu0 = _cpu_seconds(pids)
                        results, wall = _run_campaign(api, body, 1800)
                        cpu1 = _cpu_seconds({**pids, "renderers": _renderers_of(orchestrator)})
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
                           "read_p50_ms": round(_percentile(lat, 50), 1) if lat else None,
                           "read_p99_ms": round(_percentile(lat, 99), 1) if lat else None,
                           "cpu_seconds": {k: round(cpu1[k] - cpu0.get(k, 0.0), 2) for k in cpu1},
                           "_lat": lat}
                    if loaded:
                        run["plots"] = plot_stats
                    runs["with_plots" if loaded else "without_plots"].append(run)
        except (StackError, TimeoutError, RuntimeError, httpx.HTTPError) as err:
            fail(f"bench plots: {err}")
        finally:
            if load is not None and load.is_alive():
                load.terminate()
                load.join(10)
            stack.stop()

    def summary(group: list[dict]) -> dict:
        lat = [ms for r in group for ms in r.pop("_lat")]
        return {"steps_per_second": stats.median(r["steps_per_second"] for r in group),
                "read_p50_ms": round(_percentile(lat, 50), 1) if lat else None,
                "read_p99_ms": round(_percentile(lat, 99), 1) if lat else None,
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
    if as_json:
        print_json(report)
    else:
        stdout.print(f"non-plot reads under {clients} plot clients: p99 {report['read_p99_ms']} ms (target <= 200; "
                     f"{base['read_p99_ms']} ms without plots); campaign {base['steps_per_second']} -> "
                     f"{loaded_['steps_per_second']} control steps/s: slowdown {report['slowdown_pct']} % (target <= 10)")


@app.command("robustness")
def bench_robustness(
    tests: Annotated[int, typer.Option(min=2, max=MAX_TESTS, help="Paired tests per scenario.")] = 200,
    seed: Annotated[int, typer.Option(min=0, help="Campaign seed of every scenario.")] = 1,
    scenario: Annotated[Optional[list[str]], typer.Option("--scenario", help="Run only these scenarios (repeatable; default: all).")] = None,
    workers: Annotated[int, typer.Option(min=0, max=256, help="Worker processes (0: one per CPU core).")] = 0,
    algorithm: Annotated[Optional[list[str]], typer.Option("--algorithm", "-a", autocompletion=_complete_policies,
                                                           help="Add this policy's column and its paired difference against "
                                                                "Ra²ViPAS (repeatable): any installed policy (`ra2vipas policies`) "
                                                                "or module:Class.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Every algorithm on a spread of worlds (placement, crowds, noise, antenna shapes and
    models, fields of view, frame rates, clutter, walkers), paired test by test, beside the
    oracle reference (the Bayes-MAP choice given the true model, the true trajectories and a
    sweep's measurements: a bound, never a controller input).

    Per scenario: final DR of each algorithm with its Wilson 95 % interval, the paired
    difference Ra²ViPAS - best single cue with its 95 % interval (requirement: upper bound >= 0),
    and Ra²ViPAS / oracle. Takes minutes: ~20 scenarios x 200 tests x 4 algorithms. Each
    --algorithm adds that policy's column and Ra²ViPAS - it, paired the same way (with
    McNemar's exact p in --json); the other columns do not change.

    Example:

        ra2vipas bench robustness --algorithm greedy --scenario paper --scenario clutter
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ra2vipas.cli.output import stderr
    from ra2vipas.services.orchestrator import robustness

    try:
        with Progress(TextColumn("[bold]robustness[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("tests"), TimeElapsedColumn(),
                      console=stderr, transient=True) as bar:
            task = bar.add_task("tests", total=tests * len(scenario or robustness.SCENARIOS))
            report = robustness.run(tests, seed, scenario, workers or None, lambda done, total: bar.update(task, completed=done),
                                    algorithms=algorithm or ())
    except ValueError as err:  # an unknown scenario or policy (registry.UnknownPolicy)
        fail(str(err), EXIT_USAGE)
    if as_json:
        print_json(report)
        return
    from rich.table import Table

    columns = report.get("algorithms", robustness.ALGORITHMS)
    others = [a for a in columns if a not in robustness.ALGORITHMS]
    table = Table(title=f"Robustness: {tests} paired tests per scenario, seed {seed}; DR at the horizon")
    for col in ("scenario", *columns, "oracle", "Ra²ViPAS - best cue [95% CI]", *(f"Ra²ViPAS - {a} [95% CI]" for a in others),
                "Ra²ViPAS/oracle"):
        table.add_column(col, justify="left" if col == "scenario" else "right")

    def difference(d: dict, versus: str = "") -> str:
        lo, hi = d["difference_ci95"]
        return f"{d['difference']:+.3f} [{lo:+.3f}, {hi:+.3f}]{versus}" + ("" if d["not_worse"] else " ✗")

    for name, s in report["scenarios"].items():
        table.add_row(name, *(f"{s['dr'][a]:.3f}" if a in s["dr"] else "—" for a in (*columns, "oracle")), difference(s, f" vs {s['best_single_cue']}"),
                      *(difference(s["versus_ra2vipas"][a]) for a in others),
                      "—" if s["ra2vipas_over_oracle"] is None else f"{s['ra2vipas_over_oracle']:.3f}")
    stdout.print(table)
    for name, found in (report.get("policies") or {}).items():
        stdout.print(f"{name}: {found['package']} {found['version']}")


@app.command("calibrate")
def bench_calibrate(
    tests: Annotated[int, typer.Option(min=2, max=MAX_TESTS, help="Tests per scenario.")] = 40,
    seed: Annotated[int, typer.Option(min=0, help="Seed (use one no benchmark uses).")] = 1001,
    algorithms: Annotated[Optional[str], typer.Option("--algorithms", "-a", help="Comma-separated subset of: ra2vipas, rapas, ravipas, sweep (default: all); each map is fitted on its own runs, so a subset prints the same maps.")] = None,
    from_s: Annotated[float, typer.Option("--from-s", min=0.0, max=60.0, help="Fit on the steps whose sample is taken this many seconds or more after the start (0: every step).")] = 0.0,
    workers: Annotated[Optional[int], typer.Option(min=1, max=1024, help="Worker processes running the scenarios (default: the CPU count); the maps do not depend on it.")] = None,
    write: Annotated[bool, typer.Option("--write", help="Write the maps into the shipped file (services/controller/data/confidence_maps.json), one named coefficient each, with this command.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """Refit the controllers' confidence maps (Platt scaling with covariates the controller
    measures: how likely the Tx walks, the fading correlation, the clutter density, the crowding
    around the answer) on a mix of simulated scenarios, and print them with the expected
    calibration error before and after. The shipped maps (services/controller/data/confidence_maps.json)
    come from `ra2vipas bench calibrate --tests 40 --seed 1001 --write` (Ra²ViPAS's with `--from-s 3`)."""
    from ra2vipas.cli.output import stderr
    from ra2vipas.cli.simulate import parse_algorithms
    from ra2vipas.services.orchestrator.calibration import calibrate
    from ra2vipas.services.protocol.scenario import ScenarioError

    try:
        names = parse_algorithms(algorithms)
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    report = calibrate(names, tests, seed, progress=lambda what: stderr.print(f"calibrate: {what}"), from_s=from_s,
                       workers=workers or os.cpu_count() or 1)
    if write:
        from ra2vipas.services.controller.confidence import MAPS_FILE, write_maps

        write_maps(report)
        stderr.print(f"calibrate: wrote {', '.join(report['algorithms'])} into {MAPS_FILE}")
    if as_json:
        print_json(report)
    else:
        for name, a in report["algorithms"].items():
            stdout.print(f"{name}: map {tuple(a['map'])}; ECE {a['ece_raw']} -> {a['ece_fitted']} over {a['samples']} steps")


@app.command("dashboard")
def bench_dashboard(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests per algorithm of the synthetic finished campaign (4 algorithms, 120 steps).")] = 10000,
    repeats: Annotated[int, typer.Option(min=1, max=1000, help="Requests per page for the server's render time.")] = 10,
    chromium: Annotated[Optional[str], typer.Option(envvar="RA2VIPAS_CHROMIUM", help="Chromium executable for first paint and page weight.")] = "/usr/bin/chromium",
    no_browser: Annotated[bool, typer.Option("--no-browser", help="Time the server only.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """The dashboard's pages: server render time (the campaign page of a 10 000-test campaign:
    target < 1 s), and in a headless Chromium first paint, load and page weight, cold and warm."""
    from pathlib import Path

    from ra2vipas.services.benchmarks import dashboard

    if not no_browser and (not chromium or not Path(chromium).exists()):
        fail(f"no Chromium at {chromium!r} (install the Debian package chromium, set --chromium, or use --no-browser)", EXIT_USAGE)
    report = dashboard.run(tests=tests, repeats=repeats, chromium=None if no_browser else chromium)
    if as_json:
        print_json(report)
        return
    for name, s in report["server"].items():
        stdout.print(f"{name:42s} server p50 {s['p50_ms']:7.1f} ms  p95 {s['p95_ms']:7.1f} ms  {s['bytes'] / 1024:7.1f} KiB")
    for name, b in (report["browser"] or {}).items():
        if isinstance(b, dict):
            c = b["cold"]
            stdout.print(f"{name:42s} first paint {c['first_paint_ms']} ms, load {c['load_ms']} ms, "
                         f"{c['transferred_bytes'] / 1024:.1f} KiB in {c['requests']} requests (cold)")


def _memory_probe(tests: int, steps: int, algorithm: str, workers: int, seed: int) -> None:
    """Run one in-process campaign in this (fresh) process and print its peak memory as JSON:
    this process's (which reduces every outcome) and the largest worker's."""
    import json
    import resource

    from ra2vipas.services.orchestrator.engine import Point, peak_rss_kb, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    def current_rss_kb() -> int:
        try:
            with open("/proc/self/status") as f:
                return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
        except (OSError, StopIteration, ValueError):
            return 0

    scenario = build_scenario("paper", {"steps": steps})
    before = peak_rss_kb()
    rss_before = current_rss_kb()
    started = time.perf_counter()
    report = run_points([Point("paper", scenario, tests, seed, (algorithm,))], workers=workers)
    wall = time.perf_counter() - started
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"tests": tests, "steps": steps, "algorithm": algorithm, "workers": report.workers,
                      "episodes": tests, "seconds": round(wall, 2),
                      "steps_per_second": round(report.steps_per_second or 0.0, 1),
                      "parent_peak_rss_mb": round(own / 1024, 1), "parent_peak_rss_before_run_mb": round(before / 1024, 1),
                      "parent_rss_growth_mb": round((current_rss_kb() - rss_before) / 1024, 2),
                      "worker_peak_rss_mb": round(report.worker_peak_rss_kb / 1024, 1),
                      "dr_final": report.results[0]["algorithms"][algorithm]["dr_final"]}))


def _spin(loops: int = 3_000_000) -> float:
    """Seconds of a pure-Python loop: a yardstick of the CPU this process gets."""
    started = time.perf_counter()
    x = 0
    for i in range(loops):
        x += i
    return time.perf_counter() - started


def _cpu_available(workers: int) -> float:
    """The speedup a pure CPU loop gets on ``workers`` processes right now (1 on a busy machine,
    ``workers`` on an idle one with that many cores): what the simulate speedup can reach."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(_spin, [10_000] * workers))  # started
        alone = min(pool.submit(_spin).result() for _ in range(2))
        together = max(pool.map(_spin, [3_000_000] * workers))
    return round(workers * alone / together, 3)


@app.command("simulate")
def bench_simulate(
    tests: Annotated[int, typer.Option(min=1, max=MAX_TESTS, help="Tests of the speed campaign (paper scenario, every algorithm).")] = 30,
    workers: Annotated[int, typer.Option(min=0, max=1024, help="Workers of the parallel run (0: one per CPU core).")] = 0,
    seed: Annotated[int, typer.Option(min=0)] = 1,
    memory_tests: Annotated[str, typer.Option(help="Campaign sizes whose peak memory to measure, comma-separated ('' for none).")] = "1000,10000",
    memory_steps: Annotated[int, typer.Option(min=1, max=1000, help="n_test of the memory campaigns (short, so 10 000 tests take minutes, not an hour).")] = 20,
    memory_algorithm: Annotated[str, typer.Option(help="The algorithm of the memory campaigns.")] = "rapas",
    as_json: Annotated[bool, typer.Option("--json", help="One JSON line.")] = False,
) -> None:
    """`ra2vipas simulate` on one core and on every core, in the same run: steps/s of each, the
    speedup, and whether the two results objects are identical (they must be), beside
    ``cpu_loop_speedup``: what a pure CPU loop gains on as many processes just before and just
    after (the ceiling the machine's other load leaves; N on an idle N-core machine). Then the peak
    resident memory of campaigns of 1 000 and 10 000 tests, each in a fresh process: flat,
    because outcomes are reduced as they arrive and no per-step trace is kept.

    Target: speedup >= 1.7 on 2 cores. Timings are wall-clock: other load on the machine lowers them.
    """
    import json
    import subprocess
    import sys

    from ra2vipas.services.controller import registry
    from ra2vipas.services.orchestrator.engine import Point, default_workers, run_points
    from ra2vipas.services.protocol.scenario import build_scenario

    if memory_algorithm not in registry.names():
        fail(f"unknown algorithm {memory_algorithm!r}; choose from {', '.join(registry.names())}", EXIT_USAGE)
    sizes = _sizes(memory_tests, "--memory-tests")
    n = workers or default_workers()
    scenario = build_scenario("paper")
    point = Point("paper", scenario, tests, seed, registry.BUILTINS)
    available_before = _cpu_available(n)
    one = run_points([point], workers=1)
    many = run_points([point], workers=n)
    available_after = _cpu_available(n)

    def untimed(results: dict) -> dict:
        out = json.loads(json.dumps(results))
        out.pop("steps_per_second", None)
        out["pod"].pop("train_seconds", None)
        return out

    sps1, spsn = one.steps_per_second or 0.0, many.steps_per_second or 0.0
    report: dict = {
        "benchmark": "simulate", "workers": many.workers, "tests": tests, "steps": one.steps,
        "steps_per_second_1": round(sps1, 1), "steps_per_second_n": round(spsn, 1),
        "speedup": round(spsn / sps1, 3) if sps1 else None,
        "identical": untimed(one.results[0]) == untimed(many.results[0]),
        "cpu_loop_speedup": [available_before, available_after],
        "target_speedup": 1.7, "load_average": [round(v, 2) for v in os.getloadavg()] if hasattr(os, "getloadavg") else None,
        "memory": [],
    }
    for size in sizes:
        probe = subprocess.run(
            [sys.executable, "-c", f"from ra2vipas.cli.bench import _memory_probe; _memory_probe({size}, {memory_steps}, "
                                   f"{memory_algorithm!r}, {n}, {seed})"],
            capture_output=True, text=True, timeout=7200)
        if probe.returncode != 0:
            fail(f"the memory run of {size} tests failed: {(probe.stderr.strip().splitlines() or ['?'])[-1]}")
        report["memory"].append(json.loads(probe.stdout.strip().splitlines()[-1]))
    if as_json:
        print_json(report)
        return
    stdout.print(f"simulate, paper scenario, {tests} tests x {len(registry.BUILTINS)} algorithms ({one.steps} steps): "
                 f"{report['steps_per_second_1']:.0f} steps/s on 1 worker, {report['steps_per_second_n']:.0f} on {many.workers}: "
                 f"speedup {report['speedup']} (a CPU loop: {report['cpu_loop_speedup']}); results identical: {report['identical']}")
    for m in report["memory"]:
        stdout.print(f"{m['tests']} tests ({m['steps']} steps, {m['algorithm']}, {m['workers']} workers): peak RSS "
                     f"{m['parent_peak_rss_mb']} MB (parent, {m['parent_rss_growth_mb']:+} MB during the run), {m['worker_peak_rss_mb']} MB "
                     f"(largest worker), {m['seconds']} s")
