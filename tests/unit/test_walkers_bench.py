"""``ra2vipas bench walkers`` (services/benchmarks/walkers.py): the DR split by whether the Tx walks,
and the bound of naming every walking Tx the camera boxed often enough at the pans the policy chose."""

from __future__ import annotations

import math

import pytest

from ra2vipas.services.benchmarks import walkers
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.world import SimulatedPlatform


def _row(hit: bool, walks: bool, boxed_at: list[int], steps: int = 30) -> dict:
    seen = [False] * steps
    for t in boxed_at:
        seen[t] = True
    return {"test": 0, "hit": hit, "walks": walks, "boxed": seen}


def test_the_bound_counts_right_only_walkers_boxed_often_and_lately():
    rows = [
        _row(True, False, []),  # a standing Tx found: stays right
        _row(False, False, list(range(10, 30))),  # a standing Tx missed: the bound never changes it
        _row(False, True, [12, 15, 20, 24, 28]),  # a walker boxed 5 of the last 20, once in the last 3: counted right
        _row(False, True, [12, 15, 20, 24]),  # boxed 4 times: not
        _row(False, True, [10, 12, 15, 20, 24, 26]),  # boxed 6 times, none in the last 3: not
        _row(True, True, []),  # a walker found: stays right
    ]
    report = walkers.summarize(rows, window=20, boxed=5, recent=3)
    assert report["dr"] == pytest.approx(2 / 6, abs=1e-4)
    assert (report["walking"]["tests"], report["walking"]["dr"]) == (4, 0.25)
    assert (report["standing"]["tests"], report["standing"]["dr"]) == (2, 0.5)
    assert report["bound"]["walking_tests_boxed"] == 1
    assert report["bound"]["dr"] == pytest.approx(3 / 6, abs=1e-4)


def test_boxed_steps_sees_the_tx_where_the_camera_looks_and_not_behind_it():
    scenario = build_scenario("paper")
    platform = SimulatedPlatform(scenario, 3, 0)
    tx = float(platform.truth.step_bearings_rad()[platform.truth.tx_index])
    at_tx = walkers.boxed_steps(SimulatedPlatform(scenario, 3, 0), [tx] * 40, math.radians(2.5))
    behind = walkers.boxed_steps(SimulatedPlatform(scenario, 3, 0), [float(wrap(tx + math.pi))] * 40, math.radians(2.5))
    assert at_tx.mean() > 0.5  # the paper's Tx lies where the POD is high: boxed in most steps looked at it
    assert not behind.any()


def test_the_report_does_not_depend_on_the_worker_count():
    one = walkers.run("dynamic", 4, 2, workers=1)
    two = walkers.run("dynamic", 4, 2, workers=2)
    assert one == two
    assert one["walking"]["tests"] + one["standing"]["tests"] == 4


@pytest.mark.parametrize("kwargs, words", [
    ({"window": 20, "boxed": 21, "recent": 3}, "boxed <= window"),
    ({"window": 5, "boxed": 2, "recent": 6}, "recent <= window"),
])
def test_a_window_the_bound_cannot_use_is_refused(kwargs, words):
    with pytest.raises(ValueError, match=words):
        walkers.validate("ble-dynamic", None, "ra2vipas", **kwargs)


def test_several_tags_are_refused():
    with pytest.raises(ValueError, match="one tag"):
        walkers.validate("ward", None, "ra2vipas", 20, 5, 3)
    assert walkers.validate("ble-dynamic", {"walking_fraction": 0.0}, "ra2vipas", 20, 5, 3) == "ra2vipas"
