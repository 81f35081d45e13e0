"""How ``make test`` hands its tests to two workers (tests/conftest.py): each file whole, the tests that
share the machine (tests/deploy and the cross-machine run) as one unit, the longest units first."""

from __future__ import annotations

import json
from pathlib import Path

from tests.conftest import SECONDS_PER_UNKNOWN_TEST, UNIT_SECONDS, longest_units_first, xdist_unit

ROOT = Path(__file__).resolve().parents[2]


def test_the_longest_unit_goes_first_whatever_its_number_of_tests():
    nodeids = [
        "tests/api/test_many.py::a",
        "tests/api/test_many.py::b",
        "tests/api/test_many.py::c",
        "tests/deploy/test_x.py::a",
        "tests/docs/test_one_long.py::a",
        "tests/docs/test_other_cpus.py::a",
        "tests/deploy/test_y.py::a",
    ]
    order = longest_units_first(nodeids, {"tests/docs/test_one_long.py": 40.0, "machine": 100.0})
    assert order == [
        "tests/deploy/test_x.py::a",
        "tests/docs/test_other_cpus.py::a",
        "tests/deploy/test_y.py::a",
        "tests/docs/test_one_long.py::a",
        "tests/api/test_many.py::a",
        "tests/api/test_many.py::b",
        "tests/api/test_many.py::c",
    ]


def test_a_unit_without_a_measurement_counts_its_tests_and_ties_keep_the_collection_order():
    nodeids = ["tests/a.py::x", "tests/b.py::x", "tests/b.py::y", "tests/c.py::x", "tests/c.py::y"]
    seconds = {"tests/a.py": 2 * SECONDS_PER_UNKNOWN_TEST - 0.1}
    assert longest_units_first(nodeids, seconds) == [
        "tests/b.py::x",
        "tests/b.py::y",
        "tests/c.py::x",
        "tests/c.py::y",
        "tests/a.py::x",
    ]


def test_the_recorded_seconds_name_units_that_exist():
    seconds = json.loads(UNIT_SECONDS.read_text())
    assert seconds["machine"] == max(seconds.values())
    missing = [unit for unit in seconds if unit != "machine" and not (ROOT / unit).is_file()]
    assert not missing, f"tests/unit_seconds.json names files that are gone (rerun with --record-unit-seconds): {missing}"
    assert xdist_unit("tests/deploy/test_rig.py::t") == xdist_unit("tests/docs/test_other_cpus.py::t") == "machine"
