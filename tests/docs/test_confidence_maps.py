"""The confidence maps the controllers ship with (services/controller/data/confidence_maps.json)
are what the command the file names for each fits now: `ra2vipas bench calibrate --tests 40
--seed 1001 --write`, Ra²ViPAS's with `--from-s 3`, and with `--adverts` the maps of a rig of BLE
advertisements (``ALGORITHM-adverts``, fitted on the BLE worlds; the RSSI pairs' maps, which such
a rig used before, are other maps there). A map is compared by what it does on the fitting data (its likelihood, the
confidences it gives, its ECE: ``calibration.map_agreement``), not by its coefficients' digits,
which another CPU moves. A change to a controller that moves its raw confidence fails here
until the maps are refitted (and `make docs` rerun).

In a session that also runs tests/docs/test_other_cpus.py (``make test``), this file runs in that
test's child, on kernels other than this CPU's best, only (``tests/conftest.py``); run alone, here."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.controller.confidence import ADVERTS_MAP_SUFFIX, shipped_entry, shipped_maps
from ra2vipas.services.controller.policy import ALGORITHMS
from ra2vipas.services.orchestrator.calibration import (
    ADVERTS_MAP_TOLERANCE,
    PACKET_SCENARIOS,
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


# -- a rig of BLE advertisements: ALGORITHM-adverts, within the refit's own spread across machines
# (another CPU moves these runs' episodes: calibration.ADVERTS_MAP_TOLERANCE, measured) -------------

@pytest.fixture(scope="module")
def adverts_fitting_data() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each adverts map's fitting runs, as `bench calibrate --adverts -a A` makes them."""
    return collect_many({a: shipped_entry(a + ADVERTS_MAP_SUFFIX)["from_s"] for a in ALGORITHMS}, tests=40, seed=1001,
                        scenarios=PACKET_SCENARIOS, workers=2)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_the_shipped_adverts_map_is_what_bench_calibrate_adverts_fits(adverts_fitting_data, algorithm):
    raw, covariates, hit = adverts_fitting_data[algorithm]
    name = algorithm + ADVERTS_MAP_SUFFIX
    entry = shipped_entry(name)
    assert entry["command"] == (f"ra2vipas bench calibrate --adverts -a {algorithm} --tests 40 --seed 1001 "
                                f"--from-s {entry['from_s']:g} --write")
    assert entry["from_s"] == shipped_entry(algorithm)["from_s"]  # the same steps as the RSSI pairs' map
    shipped = shipped_maps()[name].vector()
    refitted = fit_platt(raw, covariates, hit)
    drift = map_drift(map_agreement(raw, covariates, hit, shipped, refitted), ADVERTS_MAP_TOLERANCE)
    assert not drift, f"{name}: `{entry['command']}` fits {[round(v, 4) for v in refitted]}, the file ships {list(shipped)}: {drift}"
    pairs = map_agreement(raw, covariates, hit, shipped_maps()[algorithm].vector(), refitted)
    assert pairs["nll_nats"] > 4 * ADVERTS_MAP_TOLERANCE["nll_nats"], "the RSSI pairs' map is another map on BLE packets"


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_an_adverts_map_off_by_a_real_change_is_caught(adverts_fitting_data, algorithm):
    """The check can fail: the shipped map with its logit coefficient 30 % low or 50 % high."""
    raw, covariates, hit = adverts_fitting_data[algorithm]
    shipped = list(shipped_maps()[algorithm + ADVERTS_MAP_SUFFIX].vector())
    refitted = fit_platt(raw, covariates, hit)
    for factor in (0.7, 1.5):
        off = [shipped[0] * factor, *shipped[1:]]
        assert map_drift(map_agreement(raw, covariates, hit, off, refitted), ADVERTS_MAP_TOLERANCE), factor
