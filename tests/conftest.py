"""Shared fixtures and helpers of the unit suite.

Helpers are plain functions (importable as ``tests.conftest``) and are also exposed as
fixtures. The expensive one, a POD model learned on the paper's training process, is
trained once per session and shared.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from ra2vipas.services.controller.policy import Controller, ControllerSettings, sensor_config_from_scenario
from ra2vipas.services.orchestrator.reproducibility import differences as _differences
from ra2vipas.services.orchestrator.simulate import TrainedPOD, train_pod
from ra2vipas.services.protocol.scenario import Scenario, build_scenario
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import GroundTruth, SimulatedPlatform

SMALL = {"steps": 40, "n_train": 300}


def kill_process_groups(procs) -> None:
    """Kill every still-running process group a test started (``start_new_session=True``) and
    reap it: nothing a test starts outlives it, whatever happened."""
    import os
    import signal

    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(10)


def restore_ctrl_c() -> None:
    """``preexec_fn`` of a child a test will Ctrl-C: a runner started as a background job (``cmd &``
    in a script) ignores SIGINT, and its children inherit that, so a Python child would install
    no KeyboardInterrupt handler; the child gets the default disposition back, as under a terminal."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def untimed(results: dict) -> dict:
    """A results object without what depends on the wall clock (speeds, latencies, training
    time) or names the run (its campaign ``id``: null in this process), so two runs of the same
    campaign compare equal value for value."""
    import json

    out = json.loads(json.dumps(results))
    out.pop("id", None)
    out.pop("steps_per_second", None)
    out.pop("latency_ms", None)
    out["pod"].pop("train_seconds", None)
    return out


def differences(a, b, limit: int = 20) -> list[str]:
    """The paths where two JSON-like objects differ (at most ``limit``), exactly, for assertion
    messages that say where two results objects part instead of printing both (the comparison
    with stated tolerances across machines is ``reproducibility.differences``)."""
    return _differences(a, b, limit=limit)


def small_scenario(preset: str = "paper", **overrides) -> Scenario:
    """A paper scenario shortened for the unit suite (40 steps, 300 training samples)."""
    return build_scenario(preset, {**SMALL, **overrides})


def polar_positions(ranges_m, bearings_deg) -> np.ndarray:
    """(N, 2) positions from ranges [m] and bearings [deg]."""
    r = np.asarray(ranges_m, dtype=float)
    b = np.radians(np.asarray(bearings_deg, dtype=float))
    return np.column_stack([r * np.cos(b), r * np.sin(b)])


def make_platform(scenario: Scenario, positions_m, tx_index: int, seed: int = 0, test_index: int = 0) -> SimulatedPlatform:
    """A ``SimulatedPlatform`` whose world is the given layout instead of a random draw.

    The noise streams stay those of (seed, test_index); if the scenario makes targets walk,
    the walkers and their trajectories are drawn from that test's walk stream.
    """
    layout = GroundTruth(positions_m=np.asarray(positions_m, dtype=float).reshape(-1, 2), tx_index=int(tx_index))
    return SimulatedPlatform(scenario, seed, test_index, layout=layout)


def angle_error(a: float, b: float) -> float:
    """|wrap(a - b)| in radians."""
    return abs(float(physics.wrap(a - b)))


def new_controller(algorithm: str, scenario: Scenario, pod_model, settings: ControllerSettings | None = None) -> Controller:
    return Controller(algorithm, sensor_config_from_scenario(scenario), pod_model, settings)


def run_closed_loop(controller: Controller, platform: SimulatedPlatform, steps: int):
    """Let the controller choose the pans for ``steps`` steps; return the decisions."""
    pan = controller.first_pan()
    decisions = []
    for t in range(steps):
        d = controller.step(platform.sense(t, pan))
        decisions.append(d)
        pan = d.next_pan_rad
    return decisions


def run_open_loop(controller: Controller, platform: SimulatedPlatform, pans_rad):
    """Feed the controller the measurements taken at the given pans (its own choices ignored)."""
    return [controller.step(platform.sense(t, float(p))) for t, p in enumerate(pans_rad)]


def sweep_pans(n: int, rounds: int = 1, start_rad: float = 0.0) -> np.ndarray:
    """``rounds`` full turns of ``n`` evenly spaced pans each, wrapped to [-pi, pi)."""
    return np.asarray(physics.wrap(start_rad + 2.0 * math.pi * np.arange(n * rounds) / n), dtype=float)


@pytest.fixture(scope="session")
def paper_pod() -> TrainedPOD:
    """A POD model learned on the paper's training process (900 samples, seed 1)."""
    return train_pod(build_scenario("paper", {"n_train": 900}), seed=1)


@pytest.fixture(scope="session")
def small_pod() -> TrainedPOD:
    """A POD model learned on a short training episode (300 samples, seed 3)."""
    return train_pod(small_scenario(), seed=3)


@pytest.fixture
def platform_factory():
    return make_platform


# ``make test`` runs the suite on two pytest-xdist workers (``-n 2 --dist loadfile``), each test file
# whole in one worker, so a module's fixtures (a stack, a trained model) are built once. Tests that
# share something of the machine form one unit, run one after another in one worker: tests/deploy's
# network namespaces and the host-side addresses of their links, and the cross-machine run that
# starts beside them (tests/docs/test_other_cpus.py, see ``pytest_runtest_logstart``).
# (xdist's own ``--dist loadgroup`` would say this with marks, but it does not group on pytest 9.2:
# it renames node ids, which pytest no longer lets a plugin do — pytest-xdist issue 1386.)
SHARED_MACHINE_UNIT = ("tests/deploy/", "tests/docs/test_other_cpus.py")


def xdist_unit(nodeid: str) -> str:
    """The unit of work a test belongs to: ``machine`` for those of ``SHARED_MACHINE_UNIT``, else its file."""
    if nodeid.startswith(SHARED_MACHINE_UNIT):
        return "machine"
    return nodeid.split("::", 1)[0]


# The order units are handed to the workers: the longest first (longest-processing-time-first), so a
# run does not end with one worker on a long file while the other idles. xdist sorts units by their
# number of tests, which put a 40-second, one-test file among the last ones. A unit's seconds come
# from ``unit_seconds.json`` (measured: ``pytest -n 2 --dist loadfile --record-unit-seconds``); a unit
# it does not name counts ``SECONDS_PER_UNKNOWN_TEST`` per test.
UNIT_SECONDS = Path(__file__).with_name("unit_seconds.json")
SECONDS_PER_UNKNOWN_TEST = 0.5


def longest_units_first(nodeids: list[str], seconds: dict[str, float]) -> list[str]:
    """The node ids regrouped by unit (``xdist_unit``), the units in decreasing expected seconds (ties
    in collection order), each unit's tests in collection order."""
    units: dict[str, list[str]] = {}
    for nodeid in nodeids:
        units.setdefault(xdist_unit(nodeid), []).append(nodeid)
    expected = {unit: seconds.get(unit, SECONDS_PER_UNKNOWN_TEST * len(ids)) for unit, ids in units.items()}
    order = sorted(units, key=lambda unit: -expected[unit])  # stable: ties keep their collection order
    return [nodeid for unit in order for nodeid in units[unit]]


def _unit_seconds() -> dict[str, float]:
    try:
        return {str(k): float(v) for k, v in json.loads(UNIT_SECONDS.read_text()).items()}
    except (OSError, ValueError, AttributeError):
        return {}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--record-unit-seconds",
        action="store_true",
        help="write the measured seconds (set-up, call and tear-down of its tests) of each unit this "
        "run ran to tests/unit_seconds.json (which orders how make test hands units to its workers)",
    )


_measured: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _measured[xdist_unit(report.nodeid)] = _measured.get(xdist_unit(report.nodeid), 0.0) + report.duration


@pytest.hookimpl(optionalhook=True, tryfirst=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """``--dist loadfile`` with the machine's shared tests as one unit (``xdist_unit``), handed out in
    the workers' collection order (``longest_units_first``, not xdist's count of tests)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    config.option.loadscopereorder = False

    class FilesAndTheMachine(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_unit(nodeid)

    return FilesAndTheMachine(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A session that runs the cross-machine checks (tests/docs/test_other_cpus.py) leaves the
    confidence-map check and the documented campaigns' first tests (``ONLY_ON_OTHER_KERNELS``) to
    that run: refitting the four maps is the suite's dearest computation (~190 s of CPU), and the
    check on kernels other than this CPU's best is the harder of the two, with the same tolerances
    (further from the machine that recorded the numbers). ``pytest tests/docs`` runs them on this
    CPU's kernels.

    On an xdist worker the tests are put in the order their units are handed out (``longest_units_first``)."""
    from tests.docs.test_other_cpus import CROSS_MACHINE_TEST, ONLY_ON_OTHER_KERNELS

    if hasattr(config, "workerinput"):  # an xdist worker: its collection order is the order units are handed out
        position = {nodeid: i for i, nodeid in enumerate(longest_units_first([it.nodeid for it in items], _unit_seconds()))}
        items.sort(key=lambda item: position[item.nodeid])
    if not any(item.nodeid == CROSS_MACHINE_TEST for item in items):
        return
    left = [item for item in items if item.nodeid.startswith(ONLY_ON_OTHER_KERNELS)]
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = [item for item in items if not item.nodeid.startswith(ONLY_ON_OTHER_KERNELS)]


def pytest_collection_finish(session: pytest.Session) -> None:
    """The cross-machine checks on other CPU kernels (tests/docs/test_other_cpus.py) run in a
    child process beside tests/deploy when this session runs both (``pytest_runtest_logstart``)."""
    if not session.config.option.collectonly and not _xdist_controller(session.config):
        from tests.docs.test_other_cpus import plan

        plan([item.nodeid for item in session.items])


def _xdist_controller(config: pytest.Config) -> bool:
    """This process hands tests to pytest-xdist workers and runs none itself."""
    return bool(getattr(config.option, "numprocesses", None)) and not hasattr(config, "workerinput")


def pytest_configure(config: pytest.Config) -> None:
    """One POD model cache for the whole run (services/learner/model_cache.py): its processes, the
    xdist workers and the commands they start, share the models they train (a campaign and the
    ``simulate`` it is compared with train the same one), in a folder of their own, not the user's
    ~/.cache, removed when the run ends. The cross-machine run's kernels are in the cache's key, so
    it trains its own. A test about training itself turns the cache off (``RA2VIPAS_POD_CACHE=off``)."""
    if not hasattr(config, "workerinput") and "RA2VIPAS_POD_CACHE" not in os.environ:
        folder = tempfile.mkdtemp(prefix="ra2vipas-pod-cache-")
        os.environ["RA2VIPAS_POD_CACHE"] = folder
        config.add_cleanup(lambda: shutil.rmtree(folder, ignore_errors=True))


def pytest_runtest_logstart(nodeid: str, location) -> None:
    from tests.docs.test_other_cpus import start_beside

    start_beside(nodeid)


def pytest_sessionfinish(session: pytest.Session) -> None:
    from tests.docs.test_other_cpus import stop_started

    stop_started()
    if session.config.getoption("record_unit_seconds") and not hasattr(session.config, "workerinput"):
        merged = {**_unit_seconds(), **_measured}  # the units this run did not run keep their last measurement
        seconds = {unit: round(s, 1) for unit, s in sorted(merged.items(), key=lambda kv: -kv[1])}
        partial = UNIT_SECONDS.with_suffix(".partial")
        partial.write_text(json.dumps(seconds, indent=1) + "\n")
        partial.replace(UNIT_SECONDS)
