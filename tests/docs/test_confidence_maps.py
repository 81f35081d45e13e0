"""The confidence maps the controllers ship with (``policy.TUNING``) are what the command their
comment names prints now: `ra2vipas bench calibrate --tests 40 --seed 1001`, Ra²ViPAS's with
`--from-s 3`. A change to a controller that moves its raw confidence fails here until the maps
are refitted (and `make docs` rerun)."""

from __future__ import annotations

import pytest

from ra2vipas.services.controller.policy import ALGORITHMS, TUNING
from ra2vipas.services.orchestrator.calibration import calibrate

FROM_S = {"ra2vipas": 3.0}


@pytest.mark.parametrize("from_s", sorted(set(FROM_S.values()) | {0.0}))
def test_the_shipped_confidence_maps_are_what_bench_calibrate_prints(from_s):
    algorithms = [a for a in ALGORITHMS if FROM_S.get(a, 0.0) == from_s]
    report = calibrate(algorithms, tests=40, seed=1001, from_s=from_s, workers=2)
    for algorithm in algorithms:
        shipped = tuple(TUNING[algorithm]["confidence_calibration"])
        assert tuple(report["algorithms"][algorithm]["map"]) == shipped, (
            f"{algorithm}: `ra2vipas bench calibrate -a {algorithm} --tests 40 --seed 1001 --from-s {from_s:g}` prints "
            f"{report['algorithms'][algorithm]['map']}, TUNING ships {list(shipped)}")
