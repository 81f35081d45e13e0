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


# -- the maps of a rig of BLE advertisements (``bench calibrate --adverts``) -------------------------

def test_a_ble_rig_reports_its_confidence_through_the_map_fitted_on_ble_packets(monkeypatch):
    """A controller whose rig hears BLE advertisements (``SensorConfig.radio`` "adverts") calibrates
    with ``ALGORITHM-adverts``; one on RSSI pairs, or of an algorithm without such a map, with the
    algorithm's own: each step's reported confidence is its map applied to the step's raw
    posterior and covariates."""
    from ra2vipas.services.controller import policy
    from ra2vipas.services.controller.confidence import ADVERTS_MAP_SUFFIX, Confidence, Covariates, shipped_maps
    from ra2vipas.services.orchestrator.simulate import train_pod
    from ra2vipas.services.protocol.scenario import build_scenario
    from ra2vipas.services.sensors.world import SimulatedPlatform

    maps = shipped_maps()
    assert policy.tuned_settings("ra2vipas", radio="adverts").confidence_calibration == maps["ra2vipas" + ADVERTS_MAP_SUFFIX]
    assert policy.tuned_settings("ra2vipas").confidence_calibration == maps["ra2vipas"]
    assert maps["ra2vipas" + ADVERTS_MAP_SUFFIX] != maps["ra2vipas"]
    for preset, radio in (("ble", "adverts"), ("paper", "pair")):
        scenario = build_scenario(preset, {"steps": 30})
        sensors = policy.sensor_config_from_scenario(scenario)
        assert sensors.radio == radio
        controller = policy.Controller("ra2vipas", sensors, train_pod(scenario, 3).model)
        own = maps["ra2vipas" + ADVERTS_MAP_SUFFIX] if radio == "adverts" else maps["ra2vipas"]
        other = maps["ra2vipas"] if radio == "adverts" else maps["ra2vipas" + ADVERTS_MAP_SUFFIX]
        assert controller.settings.confidence_calibration == own
        platform, pan, apart = SimulatedPlatform(scenario, 3, 0), controller.first_pan(), 0
        for t in range(scenario.steps):
            d = controller.step(platform.sense(t, pan))
            pan = d.next_pan_rad
            cov = Covariates(d.tx_walks, d.noise_correlation, d.clutter_density, d.crowding)
            assert d.confidence == pytest.approx(Confidence(own)(d.raw_confidence, cov), abs=1e-6)
            apart += abs(Confidence(other)(d.raw_confidence, cov) - d.confidence) > 1e-3
        assert apart > 0, f"{preset}: the other map gives the same confidences"
    # an algorithm without an adverts map keeps its own
    from ra2vipas.services.controller import confidence

    monkeypatch.setattr(confidence, "shipped_maps", lambda: {"rapas": maps["rapas"]})
    assert policy.tuned_settings("rapas", radio="adverts").confidence_calibration == maps["rapas"]


def test_calibrate_adverts_names_its_maps_and_refuses_what_does_not_belong(tmp_path):
    import json

    from ra2vipas.services.controller.confidence import write_maps

    report = calibration.calibrate(["ra2vipas"], tests=1, seed=7, scenarios=["ble"], adverts=True)
    assert report["adverts"] is True and list(report["algorithms"]) == ["ra2vipas-adverts"] and report["scenarios"] == ["ble"]
    assert report["algorithms"]["ra2vipas-adverts"]["samples"] == 120
    maps = tmp_path / "maps.json"
    maps.write_text(json.dumps({"maps": {}}))
    write_maps(report, maps)
    entry = json.loads(maps.read_text())["maps"]["ra2vipas-adverts"]
    assert entry["command"] == "ra2vipas bench calibrate --adverts -a ra2vipas --tests 1 --seed 7 --from-s 0 --write"
    with pytest.raises(ValueError, match="'paper'"):
        calibration.calibrate(["ra2vipas"], tests=1, seed=7, scenarios=["paper"], adverts=True)
    assert list(calibration.calibrate(["ra2vipas"], tests=1, seed=7, scenarios=["paper"])["algorithms"]) == ["ra2vipas"]


def test_a_joint_search_on_ble_packets_reports_through_its_own_joint_map():
    """Several tags heard as BLE advertisements: the joint search calibrates with
    ``ALGORITHM-joint-adverts``; on RSSI pairs with ``ALGORITHM-joint``."""
    from ra2vipas.services.controller.builtins import joint_search
    from ra2vipas.services.controller.confidence import shipped_maps
    from ra2vipas.services.controller.contract import episode_context
    from ra2vipas.services.controller.policy import sensor_config_from_scenario
    from ra2vipas.services.orchestrator.simulate import train_pod
    from ra2vipas.services.protocol.scenario import build_scenario

    maps = shipped_maps()
    for preset, name in (("ble", "ra2vipas-joint-adverts"), ("paper", "ra2vipas-joint")):
        scenario = build_scenario(preset, {"n_tags": 2, "steps": 5})
        context = episode_context(sensor_config_from_scenario(scenario), train_pod(scenario, 3).model, scenario, 3, 0)
        search = joint_search("ra2vipas", context, 2)
        assert all(tag.confidence.map == maps[name] for tag in search.parts), preset
    assert maps["ra2vipas-joint-adverts"] != maps["ra2vipas-joint"]
