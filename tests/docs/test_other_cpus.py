"""Another machine, on this one (issue 18): the checks that compare what the code prints now
with numbers recorded on another machine (the README's check campaign and first tests, the
confidence maps, the frozen draws of the paper world, the checked-in survey) pass again in a
process whose numpy, OpenBLAS and numba are forced onto other kernels than this CPU's best:
numpy without its dispatched SIMD features (AVX-512 and AVX2 on x86-64, the optional NEON/SVE
extensions on ARM: ``NPY_DISABLE_CPU_FEATURES``), OpenBLAS on an older core's kernels
(``OPENBLAS_CORETYPE``), numba compiling for a generic CPU (``NUMBA_CPU_NAME``). Those move a
float's last bits as another CPU does, so the tolerances of
``services/orchestrator/reproducibility.py`` are exercised wherever the suite runs.

That child pytest is the suite's longest test (the checks again, on kernels numba compiles anew):
in a session that also runs tests/deploy, it starts with the first of those (``tests/conftest.py``),
whose tests mostly wait on network namespaces, Zenoh leases and retry timers, so it runs beside
them at a lower CPU priority (nice 10) on the CPU they leave idle, and this test, next in the
suite's order, waits for its end (run without them, it starts with this test). Nothing it runs uses a port, a network namespace or a file outside
its own temporary folder; it is killed if the session ends first."""

from __future__ import annotations

import atexit
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CROSS_MACHINE_CHECKS = [
    "tests/docs/test_readme_numbers.py",
    "tests/docs/test_confidence_maps.py",
    "tests/unit/test_dynamic_world.py::test_paper_worlds_draw_what_they_drew_before_the_dynamic_world",
    "tests/unit/test_dynamic_world.py::test_paper_training_and_other_antenna_draw_what_they_drew_before",
    "tests/unit/test_dynamic_world.py::test_parameters_of_an_effect_that_is_off_change_nothing",
    "tests/rigs/test_survey.py::test_the_checked_in_survey_is_what_the_recorder_makes",
]


# Run by that child only when the session runs it too (``tests/conftest.py``): the same check twice
# would cost the suite more CPU (the maps ~220 s, ~30 of them the BLE rigs', the documented
# campaigns' first tests ~45 s) for a check that compares within the same tolerances on either
# kernels, and that the child's kernels make harder (further from the machine that recorded the
# numbers).
ONLY_ON_OTHER_KERNELS = (
    "tests/docs/test_confidence_maps.py",
    "tests/docs/test_readme_numbers.py::test_the_first_tests_of_every_documented_campaign_are_what_the_code_prints_now",
)


def reduced_cpu_environment() -> dict[str, str]:
    """The variables that put numpy, OpenBLAS and numba on other kernels than this CPU's best."""
    from numpy._core import _multiarray_umath as umath

    dispatched = [f for f in umath.__cpu_dispatch__ if umath.__cpu_features__.get(f)]
    arm = platform.machine().lower() in ("aarch64", "arm64")
    env = {"OPENBLAS_CORETYPE": "ARMV8" if arm else "Nehalem", "NUMBA_CPU_NAME": "generic"}
    if dispatched:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(dispatched)
    return env


PROBE = """
import json
from numpy._core import _multiarray_umath as umath
from threadpoolctl import threadpool_info
import numba
print(json.dumps({"numpy": [f for f in umath.__cpu_dispatch__ if umath.__cpu_features__.get(f)],
                  "openblas": [i.get("architecture") for i in threadpool_info() if i["internal_api"] == "openblas"],
                  "numba": numba.config.CPU_NAME}))
"""


def _run(args: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=ROOT, env={**os.environ, **env}, capture_output=True, text=True,
                          timeout=timeout)


class CrossMachineRun:
    """``pytest CROSS_MACHINE_CHECKS`` in a child process on the reduced kernels, running from
    its creation on (in its own process group and temporary folder, its output in a file)."""

    def __init__(self) -> None:
        self._folder = tempfile.mkdtemp(prefix="ra2vipas-other-cpus-")
        self._log = open(os.path.join(self._folder, "pytest.log"), "w+")
        self._proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                                       "--basetemp", os.path.join(self._folder, "tmp"), *CROSS_MACHINE_CHECKS],
                                      cwd=ROOT, env={**os.environ, **reduced_cpu_environment()}, stdout=self._log,
                                      stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                      preexec_fn=lambda: os.nice(10))
        atexit.register(self.stop)

    def result(self, timeout: float) -> tuple[int, str]:
        """(exit code, the last 40 lines of its output) once it has ended."""
        code = self._proc.wait(timeout)
        self._log.seek(0)
        return code, "\n".join(self._log.read().splitlines()[-40:])

    def stop(self) -> None:
        """End it (its whole process group) if it still runs; remove its folder."""
        if self._proc.poll() is None:
            try:
                os.killpg(self._proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self._proc.wait()
        self._log.close()
        shutil.rmtree(self._folder, ignore_errors=True)


CROSS_MACHINE_TEST = "tests/docs/test_other_cpus.py::test_the_cross_machine_checks_pass_on_other_kernels"
START_BESIDE = "tests/deploy/"  # tests that mostly wait: the run starts with the first of them
_wanted: list[bool] = [False]
_started: list[CrossMachineRun] = []


def plan(nodeids: list[str]) -> None:
    """Note whether this session runs the test that waits for the cross-machine run (called by
    ``tests/conftest.py`` once collection is done)."""
    _wanted[0] = CROSS_MACHINE_TEST in nodeids


def start_beside(nodeid: str) -> None:
    """Start the cross-machine run if the test about to run is the first of ``START_BESIDE`` in
    a session that runs the test waiting for it (called by ``tests/conftest.py`` before each test)."""
    if _wanted[0] and not _started and nodeid.startswith(START_BESIDE):
        _started.append(CrossMachineRun())


def stop_started() -> None:
    for run in _started:
        run.stop()


def test_the_reduced_environment_really_changes_the_kernels():
    import json

    env = reduced_cpu_environment()
    probe = _run(["-c", "import numpy, scipy.linalg; " + PROBE], env, 60)
    assert probe.returncode == 0, probe.stderr
    seen = json.loads(probe.stdout.strip().splitlines()[-1])
    assert seen["numpy"] == [], f"numpy still dispatches {seen['numpy']}"
    assert seen["numba"] == "generic"
    assert all(arch and arch.lower() == env["OPENBLAS_CORETYPE"].lower() for arch in seen["openblas"]), seen["openblas"]


def test_the_cross_machine_checks_pass_on_other_kernels():
    if not _started:  # no tests/deploy in this session
        _started.append(CrossMachineRun())
    code, tail = _started[0].result(timeout=900)
    assert code == 0, tail


def test_what_the_suite_leaves_to_the_cross_machine_run_is_in_it():
    """A check the session deselects for the child (``ONLY_ON_OTHER_KERNELS``) is one it runs."""
    assert all(any(path.startswith(check) for check in CROSS_MACHINE_CHECKS) for path in ONLY_ON_OTHER_KERNELS)
