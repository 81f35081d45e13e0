"""The real ``ra2vipas`` command, run as a subprocess: output contract and error paths."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ra2vipas.services.orchestrator.simulate import run_campaign
from ra2vipas.services.protocol.scenario import build_scenario
from tests.cli.conftest import one_error_line

SMALL = ["--set", "steps=20", "--set", "n_train=200", "--set", "n_targets=8"]


def ra2vipas(*args: str, timeout: float = 300, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", *args], capture_output=True, text=True, timeout=timeout,
                          env=env)


def test_simulate_json_is_the_last_stdout_line_with_the_documented_shape():
    proc = ra2vipas("simulate", "--preset", "paper", "--tests", "3", "--seed", "7", "--algorithms", "ra2vipas,rapas", "--json", *SMALL)
    assert proc.returncode == 0, proc.stderr
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    assert set(results) >= {"preset", "scenario", "tests", "seed", "pod", "algorithms", "steps_per_second"}
    assert results["preset"] == "paper" and results["tests"] == 3 and results["seed"] == 7
    assert results["scenario"]["steps"] == 20 and results["scenario"]["n_targets"] == 8
    assert set(results["pod"]) == {"r2", "train_seconds"}
    assert list(results["algorithms"]) == ["ra2vipas", "rapas"]
    for block in results["algorithms"].values():
        assert len(block["dr"]) == 20
        assert all(0.0 <= v <= 1.0 for v in block["dr"])
        assert block["dr_final"] == block["dr"][-1]
        lo, hi = block["ci95"]
        assert 0.0 <= lo <= block["dr_final"] <= hi <= 1.0
        assert set(block) >= {"dr", "dr_final", "ci95", "time_to_dr90_s", "in_fov_final"}


def test_simulate_table_names_every_algorithm_and_the_pod_fit():
    proc = ra2vipas("simulate", "--tests", "2", *SMALL)
    assert proc.returncode == 0, proc.stderr
    for name in ("ra2vipas", "rapas", "ravipas", "sweep"):
        assert name in proc.stdout
    assert "POD regression R²" in proc.stdout


def test_simulate_writes_the_dr_plot(tmp_path):
    out = tmp_path / "dr.png"
    proc = ra2vipas("simulate", "--tests", "2", "--algorithms", "ra2vipas", "--plot", str(out), *SMALL)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--set", "n_targets=0"], "n_targets: expected an integer in [1, 500], got 0"),
        (["--set", "n_targets=abc"], "n_targets: expected an integer in [1, 500], got 'abc'"),
        (["--set", "rf_period_s=-0.0"], "rf_period_s: expected a number in (0.0, 10.0], got"),
        (["--set", "n_target=3"], "unknown scenario parameter 'n_target' (did you mean 'n_targets'?)"),
        (["--set", "rf_noise_db=-1"], "rf_noise_db: expected a number in [0.0, 30.0]"),
        (["--set", "placement=circle"], "placement: expected one of reference|uniform"),
        (["--set", "antenna_model=yagi"], "antenna_model: expected one of paper|db-gain"),
        (["--set", "nope=1"], "unknown scenario parameter 'nope'"),
        (["--set", "steps"], "--set expects NAME=VALUE"),
        (["--preset", "moon"], "unknown preset 'moon'"),
        (["--algorithms", "ra2vipas,magic"], "unknown policy 'magic'; installed: ra2vipas, rapas, ravipas, sweep"),
        (["--plot", "dr.jpg"], "--plot expects a .png or .svg"),
    ],
)
def test_bad_input_is_one_stderr_line_and_exit_code_2(args, needle):
    proc = ra2vipas("simulate", "--tests", "1", *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ") and needle in lines[0]
    assert "Traceback" not in proc.stderr


def test_presets_show_lists_every_parameter_with_its_range():
    proc = ra2vipas("presets", "show", "paper", "--json")
    assert proc.returncode == 0, proc.stderr
    obj = json.loads(proc.stdout.strip().splitlines()[-1])
    params = obj["parameters"]
    assert params["n_targets"] == {"value": 20, "allowed": "an integer in [1, 500]", "description": params["n_targets"]["description"]}
    assert params["antenna_curvature"]["value"] == 0.5
    assert params["placement"]["allowed"] == "one of reference|uniform"
    assert ra2vipas("presets", "show", "nope").returncode == 2


def test_bench_step_prints_timings_as_json():
    proc = ra2vipas("bench", "step", "--tests", "1", "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "controller-step" and report["steps"] == 120
    assert 0 < report["median_ms"] <= report["p99_ms"] and report["target_median_ms"] == 1.0
    assert report["overrides"] == {}


def test_bench_step_times_a_scenario_changed_by_set_and_refuses_a_bad_one():
    proc = ra2vipas("bench", "step", "--tests", "1", "--preset", "dynamic", "--set", "box_heights=true", "--set", "steps=30",
                    "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["overrides"] == {"box_heights": True, "steps": 30} and report["steps"] == 30
    bad = ra2vipas("bench", "step", "--set", "no_such_thing=1")
    assert bad.returncode == 2 and "no_such_thing" in one_error_line(bad)


def test_bench_calibrate_refits_only_the_maps_asked_for_and_names_a_bad_algorithm():
    """`bench calibrate -a ravipas` fits RaViPAS's map alone (seven coefficients, its ECE before
    and after on the fitting runs), on the worlds `--scenarios` names (two here, to stay cheap);
    an unknown name is one line and exit code 2."""
    worlds = ("--scenarios", "paper,dynamic")
    proc = ra2vipas("bench", "calibrate", "-a", "ravipas", "--tests", "2", *worlds, "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert list(report["algorithms"]) == ["ravipas"] and report["tests_per_scenario"] == 2 and report["seed"] == 1001
    assert report["scenarios"] == ["paper", "dynamic"]
    fit = report["algorithms"]["ravipas"]
    assert len(fit["map"]) == 7 and fit["samples"] == 2 * 2 * 120
    assert 0.0 <= fit["ece_fitted"] <= fit["ece_raw"]
    # --from-s 3: the samples taken 3 s or more after the start (step t's at (t + 1) x 0.1 s), and another map
    proc = ra2vipas("bench", "calibrate", "-a", "ravipas", "--tests", "2", *worlds, "--from-s", "3", "--json")
    later = json.loads(proc.stdout.strip().splitlines()[-1])
    assert later["from_s"] == 3.0 and later["algorithms"]["ravipas"]["samples"] == 2 * 2 * (120 - 29)
    assert later["algorithms"]["ravipas"]["map"] != fit["map"]
    # one worker or one per core, one algorithm or two (each world's POD model trained once for both):
    # the same steps in the same order, the same map
    proc = ra2vipas("bench", "calibrate", "-a", "rapas,ravipas", "--tests", "2", *worlds, "--workers", "1", "--json")
    both = json.loads(proc.stdout.strip().splitlines()[-1])["algorithms"]
    assert list(both) == ["rapas", "ravipas"] and both["ravipas"] == fit and both["rapas"]["map"] != fit["map"]
    proc = ra2vipas("bench", "calibrate", "-a", "ravipa")
    assert proc.returncode == 2 and "unknown policy 'ravipa'" in one_error_line(proc)
    proc = ra2vipas("bench", "calibrate", "--scenarios", "paper,mars")
    assert proc.returncode == 2 and "unknown world(s) 'mars'" in one_error_line(proc)
    proc = ra2vipas("bench", "calibrate", "--scenarios", "paper", "--write")
    assert proc.returncode == 2 and "--write ships maps fitted on every world" in one_error_line(proc)


def test_bench_calibrate_joint_fits_the_joint_searchs_map_on_every_tags_steps(tmp_path):
    """`bench calibrate --joint` (issue 21) fits ``ra2vipas-joint`` on every tag's steps of the
    worlds with several tags (3 + 3 + 2 + 3 tags), and writes it beside the others with the
    command that remakes it."""
    from ra2vipas.services.controller.confidence import write_maps

    proc = ra2vipas("bench", "calibrate", "--joint", "-a", "ra2vipas", "--tests", "2", "--from-s", "3", "--workers", "1", "--json",
                    timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["joint"] is True and report["scenarios"] == ["paper-3", "paper-uniform-3", "paper-2-shared", "ward"]
    fit = report["algorithms"]["ra2vipas-joint"]
    assert list(report["algorithms"]) == ["ra2vipas-joint"] and len(fit["map"]) == 7
    assert fit["samples"] == 2 * (3 + 3 + 2 + 3) * (120 - 29)
    maps = tmp_path / "maps.json"
    maps.write_text(json.dumps({"maps": {}}))
    write_maps(report, maps)
    entry = json.loads(maps.read_text())["maps"]["ra2vipas-joint"]
    assert entry["command"] == "ra2vipas bench calibrate --joint -a ra2vipas --tests 2 --seed 1001 --from-s 3 --write"


def test_bench_calibrate_adverts_fits_a_ble_rigs_map_on_the_ble_worlds():
    """`bench calibrate --adverts` fits ``ALGORITHM-adverts`` on the BLE worlds (one, two tests,
    here), with `--joint` ``ALGORITHM-joint-adverts`` on those with several tags; a world of RSSI
    pairs is not one of its worlds."""
    proc = ra2vipas("bench", "calibrate", "--adverts", "-a", "ra2vipas", "--tests", "2", "--scenarios", "ble", "--workers", "1",
                    "--json")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["adverts"] is True and report["scenarios"] == ["ble"] and list(report["algorithms"]) == ["ra2vipas-adverts"]
    assert report["algorithms"]["ra2vipas-adverts"]["samples"] == 2 * 120
    proc = ra2vipas("bench", "calibrate", "--adverts", "--joint", "-a", "ra2vipas", "--tests", "2", "--workers", "2", "--json",
                    timeout=300)
    assert proc.returncode == 0, proc.stderr
    joint = json.loads(proc.stdout.strip().splitlines()[-1])
    assert joint["joint"] is True and joint["adverts"] is True and list(joint["algorithms"]) == ["ra2vipas-joint-adverts"]
    assert joint["scenarios"] == ["ble-3", "ble-uniform-3", "ble-2-shared", "ble-ward"]
    assert joint["algorithms"]["ra2vipas-joint-adverts"]["samples"] == 2 * (3 + 3 + 2 + 3) * 120
    proc = ra2vipas("bench", "calibrate", "--adverts", "--scenarios", "dynamic")
    assert proc.returncode == 2 and "unknown world(s) 'dynamic'; choose among ble, ble-uniform" in one_error_line(proc)
    proc = ra2vipas("bench", "calibrate", "--adverts", "--scenarios", "ble", "--write")
    assert proc.returncode == 2 and "--write ships maps fitted on every world" in one_error_line(proc)


def test_bench_simulate_reports_both_speeds_the_speedup_and_peak_memory_as_json():
    """A small `bench simulate` (2 tests, one memory run of 3 short tests; one worker, so it
    stays cheap on a shared machine: `--workers 2 == --workers 1` has its own test): the keys
    issue 10 names; no speed is asserted."""
    proc = ra2vipas("bench", "simulate", "--tests", "2", "--workers", "1", "--memory-tests", "3", "--memory-steps", "5", "--json",
                    timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "simulate" and report["workers"] == 1 and report["tests"] == 2
    assert report["steps"] == 2 * 4 * 120 and report["identical"] is True
    assert report["steps_per_second_1"] > 0 and report["steps_per_second_n"] > 0
    # computed from the unrounded speeds, printed beside their rounded values: within a unit of the 3rd decimal
    assert report["speedup"] == pytest.approx(report["steps_per_second_n"] / report["steps_per_second_1"], abs=2e-3)
    assert len(report["cpu_loop_speedup"]) == 2 and report["target_speedup"] == 1.7
    [memory] = report["memory"]
    assert {k: memory[k] for k in ("tests", "steps", "algorithm", "workers", "episodes")} == {
        "tests": 3, "steps": 5, "algorithm": "rapas", "workers": 1, "episodes": 3}
    assert 0 < memory["parent_peak_rss_before_run_mb"] <= memory["parent_peak_rss_mb"] and memory["worker_peak_rss_mb"] > 0
    assert 0.0 <= memory["dr_final"] <= 1.0 and "parent_rss_growth_mb" in memory


def test_bench_mesh_measures_through_real_processes_and_leaves_nothing_behind():
    """A small `bench mesh` over both rig layouts (one process and one Zenoh session per rig, and
    a sensors and a controller process per rig): its parts run on their own stacks, the report
    carries the measured figures of each layout (and the DR the mesh reached, equal to the
    in-process campaign's): fast steps/s, realtime latency (on rig-1 while rig-2 runs fast
    campaigns: its pace meanwhile is reported, and its episodes are not in the realtime
    breakdown), and the orchestrator's peak memory over a campaign (VmHWM)."""
    mark, env = _marked_env()
    proc = ra2vipas("bench", "mesh", "--rigs", "1", "--tests", "2", "--realtime-tests", "1", "--memory-tests", "3",
                    "--memory-steps", "5", "--rig-layout", "both", "--json", timeout=400, env=env)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "mesh" and report["rigs"] == 1 and report["rig_layout"] == "one-process"
    assert set(report["by_layout"]) == {"one-process", "split"}
    assert {k: v for k, v in report.items() if k in report["by_layout"]["one-process"]} == report["by_layout"]["one-process"]
    expected = run_campaign("paper", build_scenario("paper"), 2, 1, ["ra2vipas", "rapas", "ravipas"])
    assert report["inprocess_steps_per_second_1"] > 0 and report["inprocess_cpu_ms_per_step"] > 0
    for layout, part in report["by_layout"].items():
        assert part["fast"]["steps"] == 2 * 3 * 120 and part["steps_per_second"] > 0
        assert part["realtime"]["samples"] == 119
        busy = part["realtime"]["beside_busy_rig"]
        assert busy["rig"] == "rig-2" and busy["campaigns"] >= 1 and busy["steps"] > 0 and busy["steps_per_second"] > 0, busy
        assert 0 < part["latency_ms"]["p50"] <= part["latency_ms"]["p99"]
        assert part["fast"]["dr_final"] == {a: s["dr_final"] for a, s in expected["algorithms"].items()}, layout
        assert part["fast"]["dr_final_equals_inprocess"] is True
        # the report divides unrounded figures and prints them rounded: recomputed from the printed ones, a
        # ratio can land one unit of its 3rd decimal away (0.7274 / 1.1666 -> 0.624 printed as 0.623)
        ratio = pytest.approx
        assert part["mesh_over_inprocess"] == ratio(part["steps_per_second"] / report["inprocess_steps_per_second_1"], abs=2e-3)
        cpu = part["fast"]["cpu_ms_per_step"]  # what a step cost the stack's processes, by service (issue 22)
        assert set(cpu) == {"rig", "controller", "sensors", "router", "orchestrator", "learner", "total"}
        if layout == "split":
            assert cpu["controller"] > 0 and cpu["sensors"] > 0 and cpu["rig"] == 0
        else:
            assert cpu["rig"] > 0 and cpu["controller"] == cpu["sensors"] == 0
        assert all(v >= 0 for v in cpu.values())
        assert cpu["total"] == pytest.approx(sum(v for k, v in cpu.items() if k != "total"), abs=1e-3)
        assert part["cpu_efficiency"] == ratio(report["inprocess_cpu_ms_per_step"] / cpu["total"], abs=2e-3)
        _check_breakdown(part["fast"]["step_breakdown"], episodes=6, steps=2 * 3 * 120)
        rt = part["realtime"]["step_breakdown"]
        assert rt["controller"]["steps"] == rt["sensors"]["steps"] == 120
        # the parts the services timed fit in the latency the sensors measured, to the timers' overlap: the sensors'
        # queue and decode times are means over every message they handle, not only the commands on the latency's path
        # (one realtime test: 120 steps; a fresh-clone run read -0.556 ms of transport on a 3.37 ms latency)
        assert rt["transport_ms"] >= -0.2 * rt["latency_ms"] - 0.1, (layout, rt)
    [memory] = report["memory"]
    assert {k: memory[k] for k in ("tests", "steps", "algorithm", "episodes")} == {
        "tests": 3, "steps": 5, "algorithm": "rapas", "episodes": 3}
    assert 0 < memory["orchestrator_rss_before_mb"] <= memory["orchestrator_peak_rss_mb"]
    assert 0 < memory["orchestrator_rss_after_mb"] <= memory["orchestrator_peak_rss_mb"]
    assert memory["orchestrator_pid"] > 0 and memory["seconds"] > 0
    small = run_campaign("paper", build_scenario("paper", {"steps": 5}), 3, 1, ["rapas"])
    assert memory["dr_final"] == small["algorithms"]["rapas"]["dr_final"]
    assert not _marked_processes(mark), "the benchmark's stacks left processes behind"
    assert not Path(f"/proc/{memory['orchestrator_pid']}").exists(), "the measured orchestrator outlived its benchmark"


def test_bench_orchestrator_scores_episodes_of_instant_rigs_and_leaves_nothing_behind():
    """`bench orchestrator` (issue 22): a stack without rigs, fake rigs at the wire level in the
    benchmark's process answering every episode at once; every episode is answered once, the
    campaign finishes, and the orchestrator's rate and CPU use are reported."""
    mark, env = _marked_env()
    proc = ra2vipas("bench", "orchestrator", "--tests", "20", "--rig-count", "2", "--window", "16", "--json", timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "orchestrator" and report["episodes"] == 60 and report["answered"] == 60
    assert report["episodes_per_second"] > 0 and report["orchestrator_cpu"] >= 0 and report["target_episodes_per_second"] == 1000
    assert not _marked_processes(mark), "the benchmark's stack left processes behind"


def _check_breakdown(b: dict, episodes: int, steps: int) -> None:
    """A fast-mode step breakdown of `bench mesh` adds up (issue 22): each node reported every
    episode and step; the stages, the transport and the step time are non-negative; the parts
    sum to the step time the controller measured as one interval (its span per step) within 2 %
    (the stages are contiguous: a gap in the timers would show here); and the transport derived
    from the controller's side (its wait minus the sensors' stages) agrees with the transport
    derived from the sensors' side (their wait minus the controller's stages) within 10 % of a
    step: two processes' timers, measured independently, account for the same step."""
    stages = ("queued_ms", "decode_ms", "compute_ms", "encode_ms", "publish_ms")
    for role in ("controller", "sensors"):
        part = b[role]
        assert part["episodes"] == episodes and part["steps"] == steps, (role, part)
        assert all(part[s] >= 0 for s in (*stages, "outside_ms", "span_ms")), (role, part)
    # each view has its episode edges (the controller's lacks the sensors' first step, the sensors' the controller's
    # last one; neither counts the wait for its first message, the episode's set-up, which once made a loaded
    # machine's views differ by 10 % of a step): a few percent of a step, which only shows where the transport is ~0
    # (a one-process rig, whose two nodes hand each other messages inside one session)
    edge = -0.05 * b["step_ms"]  # the same edge term for both views: each lacks one step of the other node
    assert b["step_ms"] > 0 and b["transport_ms"] >= edge and b["transport_ms_sensors_view"] >= edge, b
    assert b["parts_sum_ms"] == pytest.approx(b["step_ms"], rel=0.02), b
    own = sum(b["controller"][s] + b["sensors"][s] for s in stages)
    assert own + b["transport_ms"] == pytest.approx(b["parts_sum_ms"], abs=1e-3)
    assert abs(b["transport_ms"] - b["transport_ms_sensors_view"]) <= 0.1 * b["step_ms"], b


@pytest.mark.parametrize("args, words", [
    (["--memory-tests", "1000,ten"], "--memory-tests expects comma-separated integers, got '1000,ten'"),
    (["--memory-tests", "0"], "--memory-tests: a campaign has 1 to 10000 tests, got 0"),
    (["--memory-algorithm", "rapaz"], "unknown algorithm 'rapaz'"),
])
def test_bench_mesh_memory_usage_errors_are_one_line(args, words):
    proc = ra2vipas("bench", "mesh", *args)
    assert proc.returncode == 2 and words in one_error_line(proc)


MARK = "R2V_TEST_MARK"  # not RA2VIPAS_*: the stack passes on only the user settings of that family


def _marked_env() -> tuple[str, dict[str, str]]:
    """A mark, and the environment that carries it to a command and every process it starts."""
    import uuid

    mark = uuid.uuid4().hex
    return mark, {**os.environ, MARK: mark}


def _marked_processes(mark: str) -> set[int]:
    """The processes whose environment carries ``mark``: what one command started, alive still
    even when it was orphaned, and nothing that another test (another pytest-xdist worker) or
    another checkout runs at the same time."""
    wanted = f"{MARK}={mark}".encode()
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if wanted in (entry / "environ").read_bytes().split(b"\0"):
                    found.add(int(entry.name))
            except OSError:
                pass
    return found
