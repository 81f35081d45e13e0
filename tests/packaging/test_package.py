"""One top-level import package: a wheel installs ``ra2vipas`` only (no generic ``services`` or
``cli`` packages to collide with other projects), with every subpackage of the repository's
services/ and cli/ folders inside it; the Python API is importable from it."""

from __future__ import annotations

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_declared_packages_are_every_folder_of_services_and_cli():
    declared = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"ra2vipas"}
    for top in ("services", "cli"):
        for init in (ROOT / top).rglob("__init__.py"):
            found.add("ra2vipas." + init.parent.relative_to(ROOT).as_posix().replace("/", "."))
    assert declared == found


SETUPTOOLS_NOISE = ("BuildBackendWarning", "SetuptoolsDeprecationWarning", "SetuptoolsWarning", "is absent from the `packages`")


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, str]:
    """A wheel built from the checkout as ``pip install .`` builds it, and what pip printed."""
    out = tmp_path_factory.mktemp("wheel")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
                          check=True, capture_output=True, text=True, timeout=300)
    return next(out.glob("ra2vipas-*.whl")), proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def wheel(built) -> Path:
    return built[0]


def test_building_the_wheel_prints_no_setuptools_warning(built):
    """The dashboard's templates and static files are package data, declared as such: no
    "Package '...dashboard.templates' is absent from the `packages` configuration"."""
    noise = [line for line in built[1].splitlines() if any(word in line for word in SETUPTOOLS_NOISE)]
    assert not noise, noise


def test_make_setups_editable_install_prints_no_setuptools_warning(tmp_path):
    """``make setup``'s editable install (its command and environment, read from the Makefile),
    into a fresh virtual environment, prints no setuptools warning."""
    import re
    import shlex

    makefile = (ROOT / "Makefile").read_text()
    quiet = dict(kv.split("=", 1) for kv in shlex.split(re.search(r"^EDITABLE_QUIET := (.*)$", makefile, re.MULTILINE).group(1)))
    assert "$(EDITABLE_QUIET) $(BIN)/pip install" in makefile
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(tmp_path / "venv")], check=True, timeout=120)
    env = {k: v for k, v in __import__("os").environ.items() if k != "PYTHONWARNINGS"} | quiet
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(tmp_path / "venv/bin/python"), "install", "--quiet",
                           "--no-deps", "-e", str(ROOT)], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr
    noise = [line for line in (proc.stdout + proc.stderr).splitlines() if any(word in line for word in SETUPTOOLS_NOISE)]
    assert not noise, noise


def test_a_wheel_installs_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"ra2vipas"}
    assert "ra2vipas/services/controller/policy.py" in names and "ra2vipas/cli/main.py" in names
    entry = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    assert "ra2vipas = ra2vipas.cli.launch:main" in entry


def test_the_wheel_ships_the_gymnasium_env_and_its_extra(wheel):
    """``ra2vipas.envs`` is in the wheel; Gymnasium comes with the ``gym`` extra, not by default."""
    z = zipfile.ZipFile(wheel)
    assert "ra2vipas/envs.py" in z.namelist()
    metadata = z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))).decode()
    assert "Provides-Extra: gym" in metadata
    assert any(line.startswith("Requires-Dist: gymnasium") and "extra == \"gym\"" in line for line in metadata.splitlines())
    assert not any(line.startswith("Requires-Dist: gymnasium") and "extra" not in line for line in metadata.splitlines())


def test_the_wheel_ships_the_dashboards_templates_and_static_files(wheel):
    """The orchestrator serves its dashboard from the installed package (offline, no CDN)."""
    names = set(zipfile.ZipFile(wheel).namelist())
    folder = ROOT / "services/orchestrator/dashboard"
    expected = {f"ra2vipas/services/orchestrator/dashboard/{p.relative_to(folder).as_posix()}"
                for p in [*folder.glob("templates/*.html"), *folder.glob("static/**/*")] if p.is_file()}
    assert expected and expected <= names
    assert "ra2vipas/services/orchestrator/dashboard/static/vendor/LICENSES.txt" in names


def test_the_installed_layout_imports_without_the_checkout(wheel, tmp_path):
    """Unpacked elsewhere (no services/ beside it), the package finds its own subpackages."""
    zipfile.ZipFile(wheel).extractall(tmp_path)
    code = ("import ra2vipas, ra2vipas.services.protocol.keys as k, ra2vipas.cli.main; "
            "print(k.__file__); print(callable(ra2vipas.simulate), callable(ra2vipas.Client))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    first, second = out.stdout.splitlines()
    assert Path(first).is_relative_to(tmp_path) and second == "True True"


def test_importing_ra2vipas_pins_blas_to_one_thread_even_after_numpy():
    """A notebook imports numpy first: ra2vipas still runs its linear algebra on one BLAS
    thread, as every service does, so its results equal the services' to the last digit."""
    import subprocess
    import sys

    code = ("import os\n"
            "for v in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'): os.environ.pop(v, None)\n"
            "import numpy, threadpoolctl\n"
            "before = max(i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas')\n"
            "import ra2vipas\n"
            "after = max(i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas')\n"
            "print(before, after)\n")
    env = {k: v for k, v in __import__("os").environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout.split()
    assert out[1] == "1", out


def test_the_wheel_ships_the_recorded_channel_with_its_licence(wheel):
    """``ble-recorded`` runs from an installed package with no download (docs/radio.md)."""
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in ("cc0-tetam.npz", "LICENSE-cc0-tetam.txt", "README.md"):
        assert f"ra2vipas/services/sensors/data/{name}" in names, name
