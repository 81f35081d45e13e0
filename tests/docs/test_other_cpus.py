"""Another machine, on this one (issue 18): the checks that compare what the code prints now
with numbers recorded on another machine (the README's check campaign and first tests, the
confidence maps, the frozen draws of the paper world, the checked-in survey) pass again in a
process whose numpy, OpenBLAS and numba are forced onto other kernels than this CPU's best:
numpy without its dispatched SIMD features (AVX-512 and AVX2 on x86-64, the optional NEON/SVE
extensions on ARM: ``NPY_DISABLE_CPU_FEATURES``), OpenBLAS on an older core's kernels
(``OPENBLAS_CORETYPE``), numba compiling for a generic CPU (``NUMBA_CPU_NAME``). Those move a
float's last bits as another CPU does, so the tolerances of
``services/orchestrator/reproducibility.py`` are exercised wherever the suite runs."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
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
    done = _run(["-m", "pytest", "-q", "-p", "no:cacheprovider", *CROSS_MACHINE_CHECKS], reduced_cpu_environment(), 900)
    tail = "\n".join((done.stdout + done.stderr).splitlines()[-40:])
    assert done.returncode == 0, tail
