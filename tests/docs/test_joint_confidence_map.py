"""The joint search's confidence map (issue 21: `ra2vipas-joint` in
services/controller/data/confidence_maps.json) is what `bench calibrate --joint` fits now, by what
it does (``calibration.map_agreement``, as tests/docs/test_confidence_maps.py checks the single-tag
maps), and it fits the joint searches better than the single-tag map they used before.

Not in the cross-machine rerun (tests/docs/test_other_cpus.py): the joint searches' runs would
double the rerun's cost. Its tolerance is its own (``calibration.JOINT_MAP_TOLERANCE``): another CPU
moved this map's data further than the single-tag maps' (measured there)."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.controller.confidence import shipped_entry, shipped_maps
from ra2vipas.services.orchestrator.calibration import (
    JOINT_MAP_TOLERANCE,
    MAP_TOLERANCE,
    collect_joint,
    fit_platt,
    map_agreement,
    map_drift,
)


@pytest.fixture(scope="module")
def joint_fitting_data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return collect_joint("ra2vipas", tests=20, seed=1001, from_s=shipped_entry("ra2vipas-joint")["from_s"], workers=2)


def test_the_joint_searchs_map_is_what_bench_calibrate_joint_fits_and_beats_the_single_tag_map(joint_fitting_data):
    """Issue 21: the joint search of several tags has its own map (`bench calibrate --joint`),
    fitted on every tag's steps in worlds with 2-3 tags; on those steps the single-tag map, which
    the joint search used before, is the worse fit."""
    raw, covariates, hit = joint_fitting_data
    entry = shipped_entry("ra2vipas-joint")
    assert entry["command"] == "ra2vipas bench calibrate --joint -a ra2vipas --tests 20 --seed 1001 --from-s 3 --write"
    shipped = shipped_maps()["ra2vipas-joint"].vector()
    refitted = fit_platt(raw, covariates, hit)
    drift = map_drift(map_agreement(raw, covariates, hit, shipped, refitted), JOINT_MAP_TOLERANCE)
    assert not drift, f"`{entry['command']}` fits {[round(v, 4) for v in refitted]}, the file ships {list(shipped)}: {drift}"
    single = map_agreement(raw, covariates, hit, shipped_maps()["ra2vipas"].vector(), refitted)
    assert single["nll_nats"] > 10 * MAP_TOLERANCE["nll_nats"]  # the single-tag map is another map on these steps


def test_a_joint_map_off_by_a_real_change_is_caught(joint_fitting_data):
    """The check can fail: the shipped map with its logit coefficient 10 % off is another map
    under the joint tolerance (the single-tag maps' check catches 5 %; this map is determined
    less sharply, calibration.JOINT_MAP_TOLERANCE)."""
    raw, covariates, hit = joint_fitting_data
    shipped = list(shipped_maps()["ra2vipas-joint"].vector())
    refitted = fit_platt(raw, covariates, hit)
    for factor in (0.9, 1.1):
        off = [shipped[0] * factor, *shipped[1:]]
        assert map_drift(map_agreement(raw, covariates, hit, off, refitted), JOINT_MAP_TOLERANCE), factor
