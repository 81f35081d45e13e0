"""The controller's parts (issue 19): RF belief, vision belief, fusion, acquisition, confidence,
and the built-ins as their compositions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.controller import builtins
from ra2vipas.services.controller.acquisition import GPUCB, Beliefs, ProbeSchedule, Sweep, WarmUpSweep
from ra2vipas.services.controller.composed import Composition, Parts
from ra2vipas.services.controller.confidence import Confidence
from ra2vipas.services.controller.fusion import Fusion
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.policy import (
    ALGORITHMS,
    Controller,
    ControllerSettings,
    sensor_config_from_scenario,
    tuned_settings,
)
from ra2vipas.services.controller.rf_belief import IsoLevel, LobeBelief, RFBelief, RFFilterBelief
from ra2vipas.services.controller.vision_belief import CameraBelief, PODLookup, VisionBelief
from ra2vipas.services.sensors.world import SimulatedPlatform
from tests.conftest import small_scenario


def _no_rf(m):
    """The same step as a receiver that heard no packet would deliver it (rf None)."""
    return m.model_copy(update={"rf": None})


def _state(rf: RFBelief) -> tuple:
    return rf.samples, rf.tx_walks, rf.log_likelihood.copy()


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_a_step_without_an_rf_sample_leaves_the_rf_belief_as_it_was(algorithm, small_pod):
    """A step with no RF sample: the RF belief and Rx(iso)'s statistics are unchanged, the
    vision belief still takes the frames, and a pan and an estimate are still chosen."""
    scenario = small_scenario("dynamic")
    controller = Controller(algorithm, sensor_config_from_scenario(scenario), small_pod.model)
    platform = SimulatedPlatform(scenario, 3, 0)
    parts = controller.parts
    pan = controller.first_pan()
    for t in range(12):
        pan = controller.step(platform.sense(t, pan)).next_pan_rad
    assert parts.rf.samples == (12 if parts.rf.listens else 0) and parts.iso.n == 12
    before, iso_n = _state(parts.rf), parts.iso.n
    frames_before = parts.vision.view_frames.sum() if parts.vision.sees else None
    m = platform.sense(12, pan)
    decision = controller.step(_no_rf(m))
    after = _state(parts.rf)
    assert after[:2] == before[:2] and np.array_equal(after[2], before[2])
    assert parts.iso.n == iso_n
    if parts.vision.sees:  # the camera's frames were taken all the same
        assert parts.vision.view_frames.sum() > frames_before
    assert math.isfinite(decision.next_pan_rad) and -math.pi <= decision.next_pan_rad < math.pi
    assert math.isfinite(decision.estimate_rad) and 0.0 <= decision.confidence <= 1.0
    # and the next step with RF goes on from there
    d = controller.step(platform.sense(13, decision.next_pan_rad))
    assert parts.rf.samples == (13 if parts.rf.listens else 0) and math.isfinite(d.next_pan_rad)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_an_episode_may_start_with_steps_without_rf(algorithm, small_pod):
    """No RF sample yet: the RF belief is its prior (flat l_RF for the lobes), the POD evidence
    has no level to predict the Tx's POD from, and the policy still pans and names a bearing."""
    scenario = small_scenario()
    controller = Controller(algorithm, sensor_config_from_scenario(scenario), small_pod.model)
    platform = SimulatedPlatform(scenario, 3, 1)
    pan = controller.first_pan()
    pans = []
    for t in range(4):
        d = controller.step(_no_rf(platform.sense(t, pan)))
        assert math.isfinite(d.next_pan_rad) and math.isfinite(d.estimate_rad)
        pan = d.next_pan_rad
        pans.append(pan)
    assert controller.parts.rf.samples == 0 and controller.parts.iso.n == 0
    assert len(set(pans)) == 4  # the warm-up (or the sweep) goes round all the same
    for t in range(4, 10):
        pan = controller.step(platform.sense(t, pan)).next_pan_rad
    assert controller.parts.rf.samples == (6 if controller.parts.rf.listens else 0)


@pytest.mark.parametrize("rx_dir", ["paper", "unknown"])
def test_tracks_born_in_steps_without_rf_are_scored(rx_dir, small_pod):
    """Tracks the camera confirms while no RF sample comes are followed by the RF belief (the
    filter's trajectory evidence, the generic lobe's recent fit) from then on."""
    import dataclasses

    scenario = small_scenario("dynamic")
    sensors = sensor_config_from_scenario(scenario)
    if rx_dir == "unknown":
        sensors = dataclasses.replace(sensors, rssi_grows_with_alignment=None, rx_dir="unknown", rx_dir_curvature=None)
    controller = Controller("ra2vipas", sensors, small_pod.model)
    assert isinstance(controller.parts.rf, LobeBelief if rx_dir == "unknown" else RFFilterBelief)
    platform = SimulatedPlatform(scenario, 3, 4)
    pan, seen = controller.first_pan(), set()
    for t in range(scenario.steps):
        m = platform.sense(t, pan)
        d = controller.step(m if t < 3 or t % 3 == 0 else _no_rf(m))
        if t % 3:
            seen |= set(controller.tracks.ids.tolist())
        pan = d.next_pan_rad
        assert math.isfinite(d.estimate_rad) and math.isfinite(pan)
    assert len(seen) >= 3


def test_the_built_ins_are_compositions_of_the_parts_they_need(small_pod):
    sensors = sensor_config_from_scenario(small_scenario())
    kinds = {}
    for name in ALGORITHMS:
        p = builtins.compose(name, sensors, small_pod.model, tuned_settings(name))
        acquisition = p.acquisition
        kinds[name] = (type(p.rf), type(p.vision), type(acquisition))
    assert kinds["ra2vipas"] == (RFFilterBelief, CameraBelief, WarmUpSweep)
    assert kinds["rapas"] == (LobeBelief, VisionBelief, WarmUpSweep)  # RaPAS hears no Rx(iso): the generic lobe
    assert kinds["ravipas"] == (RFBelief, CameraBelief, WarmUpSweep)
    assert kinds["sweep"] == (RFFilterBelief, CameraBelief, Sweep)
    p = builtins.compose("ra2vipas", sensors, small_pod.model, tuned_settings("ra2vipas"))
    assert isinstance(p.acquisition.then, ProbeSchedule) and isinstance(p.acquisition.then.then, GPUCB)


def test_a_user_composition_runs_like_a_builtin_with_the_same_parts(small_pod):
    """Parts put together by hand, as docs/policies.md shows, decide exactly as the built-in
    with the same parts does."""
    scenario = small_scenario()
    sensors = sensor_config_from_scenario(scenario)
    cfg = tuned_settings("ra2vipas")
    circle = CircleGrid(cfg.grid_points)
    pod = PODLookup(small_pod.model, cfg.min_pod_std)
    mine = Composition(sensors.initial_pan_rad, Parts(
        iso=IsoLevel(pod.rf_noise_db), rf=builtins.radio(circle, sensors, pod, cfg), vision=builtins.camera(circle, sensors, pod, cfg),
        fusion=Fusion(circle), acquisition=builtins.active_search(circle, sensors, cfg),
        confidence=Confidence(cfg.confidence_calibration)))
    theirs = Controller("ra2vipas", sensors, small_pod.model)
    a, b = SimulatedPlatform(scenario, 3, 2), SimulatedPlatform(scenario, 3, 2)
    pa, pb = mine.first_pan(), theirs.first_pan()
    for t in range(scenario.steps):
        da, db = mine.step(a.sense(t, pa)), theirs.step(b.sense(t, pb))
        assert da == db
        pa, pb = da.next_pan_rad, db.next_pan_rad


def test_iso_level_statistics():
    iso = IsoLevel(3.0)
    values = [-50.0, -52.0, -49.0, -51.0]
    for v in values:
        iso.add(v)
    mean, std = iso.mean_and_std()
    assert mean == pytest.approx(np.mean(values)) and std == pytest.approx(np.std(values, ddof=1))
    assert iso.noise_correlation() == 0.0  # fewer than 10 samples
    rng = np.random.default_rng(0)
    iso, z = IsoLevel(3.0), 0.0
    for _ in range(4000):  # AR(1) noise with rho 0.8
        z = 0.8 * z + rng.normal(0.0, 1.0)
        iso.add(-60.0 + z)
    assert iso.noise_correlation() == pytest.approx(0.8, abs=0.03)


def test_the_sweep_and_the_warm_up_go_evenly_round_the_circle():
    rf, vision = RFBelief(CircleGrid(36)), VisionBelief()

    def pans(acq, steps):
        return [acq.next_pan(Beliefs(t, rf, vision, np.empty(0), np.empty(0)))[0] for t in range(steps)]

    assert pans(Sweep(0.0, 4), 3) == pytest.approx([math.pi / 2, math.pi, 3 * math.pi / 2])
    then = Sweep(1.0, 1)  # after the warm-up: s_0 + 2 pi (t + 1)
    got = pans(WarmUpSweep(0.0, 3, then=then), 4)
    assert got[:2] == pytest.approx([2 * math.pi / 3, 4 * math.pi / 3]) and got[2] == pytest.approx(1.0 + 6 * math.pi)


def test_only_a_policy_that_hears_rx_dir_probes():
    circle = CircleGrid(36)
    schedule = ProbeSchedule(circle, then=Sweep(0.0, 10), every=2, start=0)
    deaf = Beliefs(1, RFBelief(circle), VisionBelief(), np.empty(0), np.empty(0))
    assert schedule.next_pan(deaf)[1] is False


def test_settings_still_reach_the_parts(small_pod):
    sensors = sensor_config_from_scenario(small_scenario())
    p = builtins.compose("ra2vipas", sensors, small_pod.model, ControllerSettings(beta=9.0, probe_every=3, warmup_steps=5))
    assert p.acquisition.steps == 5 and p.acquisition.then.every == 3 and p.acquisition.then.then.beta == 9.0


def test_the_composition_example_of_docs_policies_runs(small_pod):
    """docs/policies.md's composed policy (Ra²ViPAS's beliefs, plain GP-UCB) runs through the
    policy contract: no warm-up sweep, no probe, an estimate every step."""
    import pathlib
    import re

    from ra2vipas.services.controller.contract import episode_context

    text = (pathlib.Path(__file__).resolve().parents[2] / "docs" / "policies.md").read_text()
    code = next(block for block in re.findall(r"```python\n(.*?)```", text, re.S) if "class PlainUCB" in block)
    namespace: dict = {}
    exec(compile(code, "docs/policies.md", "exec"), namespace)
    scenario = small_scenario()
    sensors = sensor_config_from_scenario(scenario)
    policy = namespace["PlainUCB"](episode_context(sensors, small_pod.model, scenario, 3, 0))
    platform = SimulatedPlatform(scenario, 3, 0)
    pan = policy.first_pan()
    for t in range(10):
        d = policy.step(platform.sense(t, pan))
        assert not d.probe and math.isfinite(d.estimate_rad) and 0.0 <= d.confidence <= 1.0
        pan = d.next_pan_rad
    assert isinstance(policy.run.parts.acquisition, GPUCB)
