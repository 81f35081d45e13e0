"""The confidence maps the controllers ship with (services/controller/data/confidence_maps.json)
are what the command the file names for each fits now: `ra2vipas bench calibrate --tests 40
--seed 1001 --write`, Ra²ViPAS's with `--from-s 3`. A map is compared by what it does on the fitting data (its likelihood, the
confidences it gives, its ECE: ``calibration.map_agreement``), not by its coefficients' digits,
which another CPU moves. A change to a controller that moves its raw confidence fails here
until the maps are refitted (and `make docs` rerun).

In a session that also runs tests/docs/test_other_cpus.py (``make test``), this file runs in that
test's child, on kernels other than this CPU's best, only (``tests/conftest.py``); run alone, here."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.controller.confidence import shipped_entry, shipped_maps
from ra2vipas.services.controller.policy import ALGORITHMS
from ra2vipas.services.orchestrator.calibration import (
    collect_many,
    fit_platt,
    map_agreement,
    map_drift,
)


@pytest.fixture(scope="module")
def fitting_data() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each map's fitting runs (as `bench calibrate -a A` makes them: ``collect_many`` gives every
    algorithm the arrays ``collect`` gives it alone, tests/unit/test_calibration.py)."""
    return collect_many({a: shipped_entry(a)["from_s"] for a in ALGORITHMS}, tests=40, seed=1001, workers=2)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_the_shipped_confidence_map_is_what_bench_calibrate_fits(fitting_data, algorithm):
    raw, covariates, hit = fitting_data[algorithm]
    shipped = shipped_maps()[algorithm].vector()
    refitted = fit_platt(raw, covariates, hit)
    drift = map_drift(map_agreement(raw, covariates, hit, shipped, refitted))
    assert shipped_entry(algorithm)["command"] == (f"ra2vipas bench calibrate -a {algorithm} --tests 40 --seed 1001 "
                                                   f"--from-s {shipped_entry(algorithm)['from_s']:g} --write")
    assert not drift, (f"{algorithm}: `{shipped_entry(algorithm)['command']}` fits {[round(v, 4) for v in refitted]}, "
                       f"the file ships {list(shipped)}: {drift}")


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_a_map_off_by_a_small_real_change_is_caught(fitting_data, algorithm):
    """The check can fail: the shipped map with its logit coefficient 5 % off is another map."""
    raw, covariates, hit = fitting_data[algorithm]
    shipped = list(shipped_maps()[algorithm].vector())
    off = [shipped[0] * 1.05, *shipped[1:]]
    assert map_drift(map_agreement(raw, covariates, hit, off, fit_platt(raw, covariates, hit)))
