"""``calibration.collect_many`` trains each world's POD model once for every algorithm and gives
each the very arrays ``collect`` gives it alone (so `bench calibrate` and the confidence-map
check fit the same maps as before, for a quarter of the training)."""

from __future__ import annotations

import numpy as np
import pytest

from ra2vipas.services.orchestrator import calibration


def test_collect_many_equals_one_collect_per_algorithm(monkeypatch):
    worlds = ["paper-uniform", "dynamic-static"]
    trained = []
    train = calibration.train_pod
    monkeypatch.setattr(calibration, "train_pod", lambda scenario, seed: trained.append(scenario) or train(scenario, seed))
    many = calibration.collect_many({"rapas": 0.0, "sweep": 3.0}, tests=1, seed=7, scenarios=worlds)
    assert len(trained) == 2, "one POD model per world, shared by the algorithms"
    for algorithm, from_s in (("rapas", 0.0), ("sweep", 3.0)):
        alone = calibration.collect(algorithm, tests=1, seed=7, scenarios=worlds, from_s=from_s)
        assert len(many[algorithm]) == 3
        for got, want in zip(many[algorithm], alone):
            np.testing.assert_array_equal(got, want)
    assert many["rapas"][0].size == 2 * 120 and many["sweep"][0].size == 2 * (120 - 29)


def test_an_unknown_world_is_named():
    with pytest.raises(ValueError, match="unknown calibration scenario.*'mars'"):
        calibration.collect_many({"rapas": 0.0}, tests=1, seed=7, scenarios=["paper", "mars"])
