"""The rig descriptor: what it fixes, how a scenario is checked against it, how the controller
models its rig from it (and learns an unknown Rx(dir) response), and the warnings that stop a
wrong model from giving a silent DR 0.00."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from ra2vipas.services.controller.policy import Controller, sensor_config_from_descriptor, sensor_config_from_scenario
from ra2vipas.services.orchestrator.metrics import score_episode
from ra2vipas.services.orchestrator.rigcheck import TargetingError, dr_warnings, resolve_targeting, rig_notes
from ra2vipas.services.orchestrator.simulate import train_pod
from ra2vipas.services.protocol.rig import RigDescriptor, apply_rig_values, conflicts, rig_values
from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors.node import simulated_descriptor
from ra2vipas.services.sensors.world import SimulatedPlatform

HARDWARE = {"rig": "cam-1", "kind": "hardware", "vendor": "Acme", "model": "PanTilt 3", "frames_per_rf": 5, "rf_period_s": 0.2,
            "fov_half_angle_deg": 30.0, "box_bearing_noise_deg": 0.5, "rx_dir": {"model": "db-gain", "curvature": 0.5, "floor_db": -20.0}}


def test_a_hardware_rig_must_give_every_hardware_field():
    RigDescriptor.model_validate(HARDWARE)
    for name in ("frames_per_rf", "rx_dir", "fov_half_angle_deg"):
        with pytest.raises(ValidationError, match=name):
            RigDescriptor.model_validate({**HARDWARE, name: None})
    # a simulated rig may leave them all configurable
    assert simulated_descriptor("rig-1").configurable == ["frames_per_rf", "rf_period_s", "fov_half_angle_deg",
                                                          "box_bearing_noise_deg", "rx_dir"]
    with pytest.raises(ValidationError):
        RigDescriptor.model_validate({**HARDWARE, "rig": "a/b"})


def test_conflicts_name_every_contradicted_field_and_rig_values_resolve_them():
    d = RigDescriptor.model_validate(HARDWARE)
    sc = build_scenario("paper", {})
    found = {c.field: (c.campaign, c.rig) for c in conflicts(d, sc, "fast")}
    assert found == {"frames_per_rf": (10, 5), "rf_period_s": (0.1, 0.2), "fov_half_angle_deg": (22.5, 30.0),
                     "box_bearing_noise_deg": (0.25, 0.5), "antenna_model": ("paper", "db-gain")}
    fixed = apply_rig_values(d, sc)
    assert conflicts(d, fixed, "fast") == []
    assert fixed.n_targets == sc.n_targets and fixed.antenna_model.value == "db-gain"
    realtime_only = RigDescriptor.model_validate({**HARDWARE, "modes": ["realtime"]})
    assert [c.field for c in conflicts(realtime_only, fixed, "fast")] == ["mode"]
    assert conflicts(simulated_descriptor("rig-1"), sc, "fast") == []
    # an unknown Rx(dir) response fixes no antenna parameter
    unknown = RigDescriptor.model_validate({**HARDWARE, "rx_dir": {"model": "unknown"}})
    assert "antenna_model" not in rig_values(unknown)


def test_the_controller_models_the_rig_from_its_descriptor_not_the_scenario():
    d = RigDescriptor.model_validate(HARDWARE)
    sc = build_scenario("paper", {"steps": 30, "initial_pan_deg": 90.0})  # contradicts the rig on purpose
    cfg = sensor_config_from_descriptor(d, sc)
    assert cfg.frames_per_rf == 5 and cfg.rf_period_s == 0.2
    assert cfg.fov_half_angle_rad == pytest.approx(math.radians(30.0))
    assert cfg.box_bearing_noise_rad == pytest.approx(math.radians(0.5))
    assert cfg.rssi_grows_with_alignment is True and cfg.source == "descriptor" and cfg.rx_dir == "db-gain"
    assert cfg.steps == 30 and cfg.initial_pan_rad == pytest.approx(math.pi / 2)  # the campaign's to decide
    # configurable fields take the campaign's values (the simulator runs with them)
    sim = sensor_config_from_descriptor(simulated_descriptor("rig-1"), sc)
    assert sim == sensor_config_from_scenario(sc).__class__(**{**sensor_config_from_scenario(sc).__dict__, "source": "descriptor"})
    unknown = sensor_config_from_descriptor(RigDescriptor.model_validate({**HARDWARE, "rx_dir": {"model": "unknown"}}), sc)
    assert unknown.rssi_grows_with_alignment is None and unknown.rx_dir == "unknown"


def _episodes(world: str, grows: bool | None, tests: int, pod, algorithm: str = "rapas"):
    """Final hits, lobe evidences and learned lobes of ``tests`` episodes in a ``world`` antenna,
    the controller assuming ``grows`` (None: unknown)."""
    import dataclasses

    sc = build_scenario("paper", {"antenna_model": world, "steps": 60})
    hits, evidence, lobes = [], [], []
    for k in range(tests):
        cfg = dataclasses.replace(sensor_config_from_scenario(sc), rssi_grows_with_alignment=grows)
        ctl = Controller(algorithm, cfg, pod)
        platform = SimulatedPlatform(sc, 5, k)
        pan, estimates = ctl.first_pan(), []
        for t in range(sc.steps):
            d = ctl.step(platform.sense(t, pan))
            pan = d.next_pan_rad
            estimates.append(d.estimate_rad)
        h, _, _ = score_episode(np.array(estimates), platform.truth.step_bearings_rad(), platform.truth.tx_index,
                                sc.fov_half_angle_rad, sc.steps, None)
        hits.append(bool(h[-1]))
        evidence.append(ctl.lobe_evidence())
        lobes.append(ctl.lobe)
    return hits, evidence, lobes


@pytest.fixture(scope="module")
def pods():
    return {w: train_pod(build_scenario("paper", {"antenna_model": w, "n_train": 300}), 5).model for w in ("paper", "db-gain")}


@pytest.mark.parametrize("world,lobe", [("paper", "dip"), ("db-gain", "peak")])
def test_an_unknown_rx_dir_response_is_learned_from_the_data(pods, world, lobe):
    known_hits, known_evidence, _ = _episodes(world, world != "paper", 8, pods[world])
    hits, evidence, lobes = _episodes(world, None, 8, pods[world])
    assert lobes == [lobe] * 8  # every episode ends on the true orientation
    assert sum(hits) >= sum(known_hits) - 1 and sum(hits) >= 6
    assert min(evidence) > 0.0


def test_the_lobe_evidence_says_when_the_assumed_antenna_model_is_wrong(pods):
    hits, evidence, lobes = _episodes("db-gain", False, 6, pods["db-gain"])  # a dB-gain rig under the paper model
    assert sum(hits) <= 1 and lobes == ["dip"] * 6
    assert max(evidence) < 0.0 and float(np.median(evidence)) < -3.0  # the opposite orientation fits better, e^3 times in most
    _, right, _ = _episodes("db-gain", True, 6, pods["db-gain"])
    assert min(right) > -3.0


def _results(dr_final: dict[str, float], tests: int = 50, n_targets: int = 20) -> dict:
    return {"scenario": {"n_targets": n_targets, "antenna_model": "paper"}, "tests": tests,
            "algorithms": {a: {"dr_final": v} for a, v in dr_final.items()}}


def test_a_dr_far_below_chance_is_a_warning_naming_the_antenna_model():
    [text] = dr_warnings(_results({"ra2vipas": 0.0, "rapas": 0.0, "ravipas": 0.6, "sweep": 0.0}))
    assert "far below chance" in text and "'paper'" in text and "db-gain" in text and "rapas 0.00" in text
    assert "ravipas" not in text  # no Rx(dir): not part of the test
    assert dr_warnings(_results({"ra2vipas": 0.9, "rapas": 0.0})) == []  # one radio algorithm doing well: no
    assert dr_warnings(_results({"rapas": 0.0}, tests=20)) == []  # 0 of 20 at chance 0.05 is not evidence (p = 0.36)
    assert dr_warnings(_results({"rapas": 0.0}, n_targets=1)) == []


def test_rig_notes_record_the_scenario_assumptions_and_a_contradicted_antenna_model():
    agree = {"sensor_model": "descriptor", "rx_dir": "paper", "lobe": "dip", "lobe_evidence": 20.0}
    against = {"sensor_model": "descriptor", "rx_dir": "paper", "lobe": "dip", "lobe_evidence": -8.0}
    out = rig_notes({}, [("rig-1", agree)] * 4)
    assert "warnings" not in out and "assumptions" not in out
    out = rig_notes({}, [("rig-1", against)] * 3 + [("rig-1", agree)] + [("rig-2", None)])
    [text] = out["warnings"]
    assert "contradicts the assumed Rx(dir) response 'paper' in 3 of 4" in text and "db-gain" in text
    assert out["assumptions"]["rigs"] == ["rig-2"] and out["assumptions"]["episodes"] == 1 and out["assumptions"]["of"] == 5
    ravipas = {"sensor_model": "scenario", "rx_dir": "paper", "lobe": None, "lobe_evidence": None}
    assert rig_notes({}, [("rig-3", ravipas)])["assumptions"]["rigs"] == ["rig-3"]


def test_targeting_refuses_a_contradicted_rig_naming_each_field_unless_rig_values_are_used():
    sc = build_scenario("paper", {})
    cam = RigDescriptor.model_validate(HARDWARE)
    live = {"cam-1": cam, "sim-1": simulated_descriptor("sim-1"), "old-1": None}
    with pytest.raises(TargetingError) as err:
        resolve_targeting(sc, "fast", ["cam-1"], None, False, live)
    fields = [f for f, _ in err.value.errors]
    assert fields == ["scenario.frames_per_rf", "scenario.rf_period_s", "scenario.fov_half_angle_deg",
                      "scenario.box_bearing_noise_deg", "scenario.antenna_model"]
    assert "rig cam-1 is 'db-gain', the campaign says 'paper'" in str(err.value)
    with pytest.raises(TargetingError, match="rig cam-1"):
        resolve_targeting(sc, "fast", None, "hardware", False, live)
    fixed, targeting = resolve_targeting(sc, "fast", ["cam-1"], None, True, live)
    assert fixed.antenna_model.value == "db-gain" and fixed.frames_per_rf == 5
    assert targeting["rig_values"]["antenna_model"] == "db-gain" and targeting["rigs"] == ["cam-1"]
    # untargeted: runs on the rigs it agrees with; refused only when it agrees with none
    same, none = resolve_targeting(sc, "fast", None, None, False, live)
    assert same == sc and none is None
    with pytest.raises(TargetingError, match="antenna_model"):
        resolve_targeting(sc, "fast", None, None, False, {"cam-1": cam})
    # two rigs whose values disagree cannot both lend theirs
    other = RigDescriptor.model_validate({**HARDWARE, "rig": "cam-2", "frames_per_rf": 7})
    with pytest.raises(TargetingError, match="rigs cam-1 and cam-2 disagree"):
        resolve_targeting(sc, "fast", ["cam-1", "cam-2"], None, True, {"cam-1": cam, "cam-2": other})
    # an undescribed (v1) rig is never refused: it is modelled from the scenario
    assert resolve_targeting(sc, "fast", ["old-1"], None, False, live)[0] == sc
