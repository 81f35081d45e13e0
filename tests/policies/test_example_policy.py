"""A third-party policy (examples/my_policy: its own pyproject with the entry point), installed
as a user would, runs everywhere a built-in runs and its results name it (issue 19)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import differences, untimed

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "my_policy"
RA2VIPAS = str(Path(sys.executable).with_name("ra2vipas"))
SMALL = ["--set", "steps=30", "--set", "n_train=300"]
PROVENANCE = {"greedy": {"package": "ra2vipas-my-policy", "version": "0.1.0"}}


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict[str, str]:
    """The example installed with pip into its own folder (not this venv), and the environment
    in which ra2vipas finds it: the entry point is all that makes it known."""
    target = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(EXAMPLE)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return {**os.environ, "PYTHONPATH": str(target)}


def _run(args: list[str], env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([RA2VIPAS, *args], env=env, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_the_example_is_under_100_lines_of_policy_code():
    code = [line for line in (EXAMPLE / "src" / "my_policy" / "__init__.py").read_text().splitlines() if line.strip()]
    assert len(code) <= 100


def test_an_installed_policy_is_listed_with_its_package(installed):
    out = _run(["policies", "--json"], installed)
    assert out.returncode == 0, out.stderr
    rows = {r["name"]: r for r in json.loads(out.stdout)}
    assert list(rows)[:4] == ["ra2vipas", "rapas", "ravipas", "sweep"]
    assert rows["greedy"]["package"] == "ra2vipas-my-policy" and rows["greedy"]["version"] == "0.1.0"
    assert not rows["greedy"]["builtin"] and rows["ra2vipas"]["builtin"]
    without = _run(["policies", "--json"], {k: v for k, v in installed.items() if k != "PYTHONPATH"})
    assert "greedy" not in {r["name"] for r in json.loads(without.stdout)}


def test_simulate_and_a_mesh_campaign_run_it_beside_a_builtin_and_agree(installed, tmp_path):
    sim = _run(["simulate", "-a", "greedy,ra2vipas", "--tests", "3", "--seed", "2", *SMALL, "--json"], installed)
    assert sim.returncode == 0, sim.stderr[-2000:]
    in_process = json.loads(sim.stdout.strip().splitlines()[-1])
    assert list(in_process["algorithms"]) == ["greedy", "ra2vipas"] and in_process["policies"] == PROVENANCE
    assert "calibration" not in in_process["algorithms"]["greedy"]  # it gives no confidence

    mesh = _run(["campaign", "start", "--embedded", "-a", "greedy,ra2vipas", "--tests", "3", "--seed", "2", *SMALL,
                 "--db", str(tmp_path / "r.db"), "--json"], installed, timeout=600)
    assert mesh.returncode == 0, mesh.stderr[-2000:]
    through_controllers = json.loads(mesh.stdout.strip().splitlines()[-1])
    assert through_controllers["policies"] == PROVENANCE
    assert "assumptions" not in through_controllers  # our rigs describe themselves; the policy's results say so
    for key in ("id", "warnings"):
        through_controllers.pop(key, None)
    assert untimed(through_controllers) == untimed(in_process), differences(untimed(through_controllers), untimed(in_process))


def test_a_policy_that_is_not_installed_is_refused_naming_the_installed_ones(tmp_path):
    out = _run(["simulate", "-a", "greedy", "--tests", "1", *SMALL], {k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert out.returncode == 2
    assert "unknown policy 'greedy'; installed: ra2vipas, rapas, ravipas, sweep, ra2vipas-seq (or give module:Class)" in out.stderr
