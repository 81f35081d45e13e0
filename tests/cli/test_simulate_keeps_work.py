"""``simulate`` never throws finished work away (issue 23, point 3): an output file that cannot
be written is refused before any test runs, and Ctrl-C prints the tests finished so far, marked
partial, and exits 130."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest

from tests.api.live import SMALL
from tests.cli.conftest import ROOT, one_error_line, ra2vipas
from tests.conftest import restore_ctrl_c

SETS = [f"--set={k}={v}" for k, v in SMALL.items()]


def test_a_bad_output_path_is_refused_before_any_test_runs(tmp_path):
    started = time.monotonic()
    proc = ra2vipas("simulate", "--tests", "5000", "-a", "rapas", "--plot", "/nonexistent/x.png", timeout=60)
    assert proc.returncode == 1 and proc.stdout == ""
    assert one_error_line(proc) == "error: --plot: cannot write /nonexistent/x.png: no such directory /nonexistent"
    assert time.monotonic() - started < 30  # 5000 tests would take minutes
    folder = tmp_path / "a-folder.svg"
    folder.mkdir()
    proc = ra2vipas("simulate", "--tests", "5000", "--reliability-plot", str(folder), timeout=60)
    assert proc.returncode == 1 and "is a directory" in one_error_line(proc)
    proc = ra2vipas("simulate", "--tests", "5000", "--vary", "n_targets=4,8", "--plot", "/nonexistent/s.png", timeout=60)
    assert proc.returncode == 1 and "no such directory /nonexistent" in one_error_line(proc)


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("RA2VIPAS_API", "RA2VIPAS_TOKEN")}


@pytest.fixture(scope="module")
def compiled() -> None:
    """One short simulate of the algorithms the Ctrl-C tests run: the numerical kernels they use
    are compiled and in the on-disk cache before any of them starts its clock."""
    subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "simulate", "--tests", "1", "-a", "rapas,sweep", "--workers", "1", *SETS],
                   capture_output=True, cwd=ROOT, env=_env(), timeout=300)


def _interrupted(*args: str, after_s: float) -> tuple[int, str, str]:
    """Run ``simulate ARGS``, Ctrl-C it ``after_s`` seconds after its episodes started, return
    (exit code, stdout, stderr). Its tests take the ``compiled`` fixture, so the numerical
    kernels are compiled and cached (a minute on a fresh machine) before the clock starts; a
    plain simulate also says when its episodes start ("POD model trained"), and the Ctrl-C waits
    for that line (or "POD model loaded", from the POD model cache). If no test had finished by then (it says so: a loaded machine, where its
    workers take seconds to start), it runs again and is interrupted after three times as long."""
    for wait_s in (after_s, 3 * after_s):
        code, out, err = _interrupt_once(args, wait_s)
        if code != 130 or "no test had finished" not in err:
            break
    return code, out, err


def _interrupt_once(args: tuple[str, ...], after_s: float) -> tuple[int, str, str]:
    env = {**_env(), "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", "simulate", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env, start_new_session=True, preexec_fn=restore_ctrl_c)
    try:
        said: list[str] = []
        if "--vary" not in args:
            deadline = time.monotonic() + 180
            while time.monotonic() < deadline:
                line = proc.stderr.readline()
                said.append(line)
                if not line or line.startswith(("POD model trained", "POD model loaded")):
                    break
        time.sleep(after_s)
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group: the workers too
        out, err = proc.communicate(timeout=60)
        return proc.returncode, out, "".join(said) + err
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_ctrl_c_on_simulate_prints_the_partial_table_and_exits_130(compiled):
    code, out, err = _interrupted("--tests", "3000", "-a", "rapas,sweep", "--seed", "4", "--workers", "2", *SETS, after_s=4.0)
    assert code == 130, (code, out[-800:], err[-2000:])
    said = " ".join(out.split())
    assert "partial results: the campaign stopped before its end" in said and "PARTIAL:" in said and "of 3000 tests" in said
    assert "Traceback" not in err and "interrupted after" in err and "the results above are partial" in err


def test_ctrl_c_on_simulate_json_prints_partial_results(compiled):
    import json

    code, out, err = _interrupted("--tests", "3000", "-a", "rapas", "--workers", "1", "--json", *SETS, after_s=3.0)
    assert code == 130, (code, out[-800:], err[-2000:])
    results = json.loads(out.strip().splitlines()[-1])
    assert results["partial"] is True and 0 < results["tests_recorded"]["rapas"] < 3000


def test_simulate_dynamic_says_at_once_that_it_trains_the_pod_model():
    """The first seconds (a minute on a first run: the numerical kernels compile) are not a blank
    terminal (issue 23, point 6): one line before the model trains, another when it is trained.
    "Before" is checked by order, not by a clock (which a busy machine stretches): the second line
    comes at least half the training time the command reports after the first. The POD model
    cache is off: the model is trained."""
    env = {**_env(), "RA2VIPAS_POD_CACHE": "off"}
    proc = subprocess.Popen([sys.executable, "-m", "ra2vipas.cli.main", "simulate", "--preset", "dynamic", "--tests", "1", "-a", "rapas",
                             "--set", "steps=20"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
                            start_new_session=True, preexec_fn=restore_ctrl_c)
    try:
        first = proc.stderr.readline()
        first_at = time.monotonic()
        second = proc.stderr.readline()
        gap = time.monotonic() - first_at
        rest = proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert first.startswith("training the POD model on 900 self-supervised samples (dynamic, seed 1), then 1 episodes"), first
    trained = re.match(r"POD model trained \(R² [0-9.]+\) after ([0-9.]+) s; running 1 episodes", second)
    assert trained, second
    assert gap >= 0.5 * float(trained.group(1)), f"the first line came {gap:.2f} s before the model was trained in {trained.group(1)} s"
    assert proc.returncode == 0, rest


def test_ctrl_c_on_a_study_prints_its_partial_rows_and_exits_130(compiled):
    code, out, err = _interrupted("--vary", "n_targets=6,8", "--tests", "3000", "-a", "rapas", "--workers", "1", *SETS[:2],
                                  after_s=10.0)
    assert code == 130, (code, out[-800:], err[-2000:])
    said = " ".join(out.split())
    assert "— partial" in said and "rapas" in said
    assert "Traceback" not in err and "the rows above are partial" in err


def test_a_second_simulate_loads_the_pod_model_from_the_cache_and_prints_the_same_results(tmp_path):
    """The POD model cache (services/learner/model_cache.py): the second run of a campaign says at
    once that its model is cached, loads it instead of training, and prints the same results (the
    pod block's training time is the first run's)."""
    import json

    env = {**_env(), "RA2VIPAS_POD_CACHE": str(tmp_path / "pods")}
    args = [sys.executable, "-m", "ra2vipas.cli.main", "simulate", "--tests", "2", "-a", "rapas", "--set", "steps=5", "--seed", "9",
            "--workers", "1", "--json"]
    runs = [subprocess.run(args, capture_output=True, text=True, cwd=ROOT, env=env, timeout=300) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    assert runs[0].stderr.startswith("training the POD model") and "POD model trained" in runs[0].stderr
    assert runs[1].stderr.startswith("the POD model of (paper, seed 9) is in the POD model cache"), runs[1].stderr
    assert "POD model loaded" in runs[1].stderr and "POD model trained" not in runs[1].stderr
    first, second = (json.loads(r.stdout.strip().splitlines()[-1]) for r in runs)
    assert len(list((tmp_path / "pods").glob("pod-*.json"))) == 1
    for results in (first, second):
        results.pop("steps_per_second", None)
    assert first == second
