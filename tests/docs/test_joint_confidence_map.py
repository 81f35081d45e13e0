"""The joint search's confidence maps (issue 21: `ra2vipas-joint` in
services/controller/data/confidence_maps.json, and `ra2vipas-joint-adverts` for a rig of BLE
advertisements) are what `bench calibrate --joint` (`--joint --adverts`) fits now, by what they do
(``calibration.map_agreement``, as tests/docs/test_confidence_maps.py checks the single-tag maps),
and each fits its joint searches better than the maps they used before.

Not in the cross-machine rerun (tests/docs/test_other_cpus.py): the joint searches' runs would
double the rerun's cost. The tolerances are their own (``calibration.JOINT_MAP_TOLERANCE``,
``JOINT_ADVERTS_MAP_TOLERANCE``): another CPU moves these maps' data further than the single-tag
maps' (measured, on this machine's other kernels for the BLE one)."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.controller.confidence import shipped_entry, shipped_maps
from ra2vipas.services.orchestrator.calibration import (
    JOINT_ADVERTS_MAP_TOLERANCE,
    JOINT_MAP_TOLERANCE,
    JOINT_PACKET_SCENARIOS,
    JOINT_SCENARIOS,
    MAP_TOLERANCE,
    collect_joint,
    fit_platt,
    map_agreement,
    map_drift,
)

# map: (its fitting worlds, `bench calibrate` flags, its tolerance, the maps its searches used before
# and how far (nats) they must be on its steps, the logit factors that must fail the check)
JOINT_MAPS = {
    # the single-tag map, which the joint search used before, is the worse fit; the check catches 10 %
    # (the single-tag maps' catches 5 %; this map is determined less sharply)
    "ra2vipas-joint": (JOINT_SCENARIOS, "--joint", JOINT_MAP_TOLERANCE, {"ra2vipas": 10 * MAP_TOLERANCE["nll_nats"]}, (0.9, 1.1)),
    # on BLE advertisements: neither the RSSI pairs' joint map nor the single-tag BLE map; another CPU
    # moves these runs' episodes, so the check catches the logit coefficient halved or doubled
    "ra2vipas-joint-adverts": (JOINT_PACKET_SCENARIOS, "--joint --adverts", JOINT_ADVERTS_MAP_TOLERANCE,
                               {"ra2vipas-joint": JOINT_ADVERTS_MAP_TOLERANCE["nll_nats"],
                                "ra2vipas-adverts": JOINT_ADVERTS_MAP_TOLERANCE["nll_nats"]}, (0.5, 2.0)),
}


@pytest.fixture(scope="module", params=sorted(JOINT_MAPS))
def joint_fit(request) -> tuple[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    name = request.param
    data = collect_joint("ra2vipas", tests=20, seed=1001, scenarios=JOINT_MAPS[name][0], from_s=shipped_entry(name)["from_s"],
                         workers=2)
    return name, data


def test_the_joint_searchs_map_is_what_bench_calibrate_joint_fits_and_beats_the_maps_used_before(joint_fit):
    """Issue 21: the joint search of several tags has its own map (`bench calibrate --joint`, on BLE
    advertisements `--joint --adverts`), fitted on every tag's steps in worlds with 2-3 tags; on
    those steps the maps the joint search used before are the worse fits."""
    name, (raw, covariates, hit) = joint_fit
    _, flags, tolerance, before, _ = JOINT_MAPS[name]
    entry = shipped_entry(name)
    assert entry["command"] == f"ra2vipas bench calibrate {flags} -a ra2vipas --tests 20 --seed 1001 --from-s 3 --write"
    shipped = shipped_maps()[name].vector()
    refitted = fit_platt(raw, covariates, hit)
    drift = map_drift(map_agreement(raw, covariates, hit, shipped, refitted), tolerance)
    assert not drift, f"`{entry['command']}` fits {[round(v, 4) for v in refitted]}, the file ships {list(shipped)}: {drift}"
    for other, nats in before.items():
        assert map_agreement(raw, covariates, hit, shipped_maps()[other].vector(), refitted)["nll_nats"] > nats, other


def test_a_joint_map_off_by_a_real_change_is_caught(joint_fit):
    """The check can fail: the shipped map with its logit coefficient off by the map's factors."""
    name, (raw, covariates, hit) = joint_fit
    shipped = list(shipped_maps()[name].vector())
    refitted = fit_platt(raw, covariates, hit)
    for factor in JOINT_MAPS[name][4]:
        off = [shipped[0] * factor, *shipped[1:]]
        assert map_drift(map_agreement(raw, covariates, hit, off, refitted), JOINT_MAPS[name][2]), (name, factor)
