"""The Gymnasium environment ra2vipas/PanSearch-v0: Gymnasium's contract, the same world and the
same score as ``simulate``, no truth before the end, clear errors."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from ra2vipas import envs
from ra2vipas.envs import ENV_ID, PanSearchEnv, encode_measurement, measurement_from_observation
from ra2vipas.services.controller.policy import Controller, sensor_config_from_scenario
from ra2vipas.services.orchestrator.simulate import run_test
from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement
from ra2vipas.services.protocol.scenario import ScenarioError
from ra2vipas.services.sensors.world import SimulatedPlatform

SHORT = {"steps": 40, "n_train": 300}
TRUTH_KEYS = {"truth", "tx_index", "ranges_m", "bearings_rad", "hits", "in_fov", "chosen", "step_bearings_rad"}


def scripted_rollout(env: PanSearchEnv, seed: int, test: int, algorithm: str = "ra2vipas"):
    """Drive the env with the built-in Controller, fed the measurement decoded from each
    observation; returns the rewards, the pans sensed, the named bearings and the last info."""
    obs, info = env.reset(seed=seed, options={"test": test})
    controller = Controller(algorithm, sensor_config_from_scenario(env.scenario), info["pod_model"])
    assert obs["pan"][0] == controller.first_pan()
    rewards, pans, named = [], [], []
    terminated = False
    while not terminated:
        m = measurement_from_observation(obs)
        assert m == info["measurement"]  # the observation carries the whole measurement
        decision = controller.step(m)
        pans.append(m.pan_rad)
        named.append(decision.estimate_rad)
        obs, reward, terminated, truncated, info = env.step(np.array([decision.next_pan_rad, decision.estimate_rad]))
        assert truncated is False
        rewards.append(reward)
    return rewards, pans, named, info


def test_check_env_passes():
    env = gymnasium.make(ENV_ID, overrides=SHORT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    # the one recommendation left: actions are angles in radians, not [-1, 1] (RescaleAction does that)
    messages = [str(w.message) for w in caught if "symmetric and normalized" not in str(w.message)]
    assert messages == []


def test_make_by_id_and_by_module_name():
    env = gymnasium.make(ENV_ID, preset="dynamic", overrides=SHORT, reward="final", max_boxes=8)
    assert isinstance(env.unwrapped, PanSearchEnv)
    assert env.unwrapped.scenario.clutter_rate > 0.0 and env.unwrapped.reward_kind == "final"
    assert env.observation_space["boxes"].shape == (env.unwrapped.scenario.frames_per_rf, 8)
    assert gymnasium.spec(ENV_ID).entry_point == "ra2vipas.envs:PanSearchEnv"
    assert isinstance(gymnasium.make("ra2vipas.envs:" + ENV_ID, overrides=SHORT).unwrapped, PanSearchEnv)


@pytest.mark.parametrize("preset,test", [("paper", 0), ("paper", 3), ("dynamic", 1)])
def test_scripted_controller_scores_as_simulate(preset, test):
    """A Controller driven through the env takes the same pans, names the same bearings and
    earns, step by step, the hits ``run_test`` scores (walkers: against the bearings at t)."""
    env = PanSearchEnv(preset, SHORT)
    rewards, pans, named, info = scripted_rollout(env, seed=5, test=test)
    outcome = run_test(env.scenario, 5, test, "ra2vipas", envs.trained_pod(env.scenario, 5).model)
    assert pans == outcome.pans
    assert named == outcome.estimates
    assert rewards == [float(h) for h in outcome.hits]
    assert info["truth"]["hits"].tolist() == outcome.hits
    assert info["truth"]["in_fov"].tolist() == outcome.in_fov
    assert info["truth"]["chosen"].tolist() == outcome.chosen
    assert info["boxes_dropped_total"] == 0


def test_the_pod_model_is_the_campaigns():
    env = PanSearchEnv("paper", SHORT)
    _, info = env.reset(seed=7)
    from ra2vipas.services.orchestrator.simulate import train_pod

    assert info["pod_model"] == train_pod(env.scenario, 7).model == env.pod_model
    assert info["sensor_config"] == sensor_config_from_scenario(env.scenario)
    assert (info["seed"], info["test"]) == (7, 0)


def test_seed_and_test_are_simulates_world():
    """reset(seed=s, options={"test": k}) senses the world of SimulatedPlatform(scenario, s, k);
    unseeded resets walk the campaign's tests in order; the same (seed, test) twice is the
    same episode."""
    env = PanSearchEnv("paper", SHORT)
    obs, _ = env.reset(seed=3, options={"test": 2})
    platform = SimulatedPlatform(env.scenario, 3, 2)
    expected, _ = encode_measurement(platform.sense(0, float(obs["pan"][0])), env.max_boxes)
    assert all(np.array_equal(obs[k], expected[k]) for k in expected)
    assert env.unwrapped.test_index == 2 and env.campaign_seed == 3

    env.reset(seed=3)
    assert env.test_index == 0
    env.reset()
    env.reset()
    assert (env.campaign_seed, env.test_index) == (3, 2)

    first = scripted_rollout(env, seed=3, test=1)
    second = scripted_rollout(PanSearchEnv("paper", SHORT), seed=3, test=1)
    assert first[:3] == second[:3]
    assert first[3]["truth"]["tx_index"] == second[3]["truth"]["tx_index"]
    other = scripted_rollout(env, seed=4, test=1)
    assert other[1] != first[1] or other[2] != first[2]


def test_constructor_seed_is_the_default_campaign():
    env = PanSearchEnv("paper", SHORT, seed=9)
    _, info = env.reset()
    assert (info["seed"], info["test"]) == (9, 0)
    _, info = env.reset()
    assert (info["seed"], info["test"]) == (9, 1)


def test_no_truth_before_termination():
    env = PanSearchEnv("dynamic", SHORT)
    obs, info = env.reset(seed=2)
    seen = [info]
    assert set(obs) == {"rssi", "pan", "step", "boxes", "mask"}
    for t in range(env.scenario.steps):
        obs, _, terminated, _, info = env.step(env.action_space.sample())
        assert terminated == (t == env.scenario.steps - 1)
        if not terminated:
            seen.append(info)
    for i in seen:
        assert not TRUTH_KEYS & set(i)
        assert isinstance(i["measurement"], StepMeasurement)
    truth = info["truth"]
    assert truth["tx_index"] == SimulatedPlatform(env.scenario, 2, 0).truth.tx_index
    assert truth["step_bearings_rad"].shape == (env.scenario.steps, env.scenario.n_targets)  # walkers
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(2))


def test_rewards():
    """'hit' pays each step's hit, 'final' only the last one, 'in_fov' the authors' figure."""
    runs = {}
    for kind in ("hit", "final", "in_fov"):
        env = PanSearchEnv("paper", SHORT, reward=kind)
        runs[kind] = scripted_rollout(env, seed=1, test=0)
    hits, in_fov = runs["hit"][3]["truth"]["hits"], runs["hit"][3]["truth"]["in_fov"]
    assert runs["hit"][0] == hits.astype(float).tolist()
    assert runs["final"][0] == [0.0] * (len(hits) - 1) + [float(hits[-1])]
    assert runs["in_fov"][0] == in_fov.astype(float).tolist()


def test_boxes_beyond_max_are_dropped_and_counted():
    frame = CameraFrame(box_bearings_rad=(-0.3, -0.1, 0.05, 0.2))
    m = StepMeasurement(step=4, pan_rad=0.5, rf=RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=-70.0), frames=(frame, CameraFrame()))
    obs, dropped = encode_measurement(m, 2)
    assert dropped == 2
    assert obs["boxes"].tolist() == [[-0.1, 0.05], [0.0, 0.0]]  # the two nearest the axis, in order
    assert obs["mask"].tolist() == [[1, 1], [0, 0]]
    assert measurement_from_observation(encode_measurement(m, 4)[0]) == m

    env = PanSearchEnv("dynamic", {**SHORT, "clutter_rate": 5.0}, max_boxes=2)
    obs, info = env.reset(seed=1)
    total = info["boxes_dropped"]
    for _ in range(5):
        obs, _, _, _, info = env.step(env.action_space.sample())
        assert obs in env.observation_space
        total += info["boxes_dropped"]
    assert total == info["boxes_dropped_total"] > 0


def test_pan_outside_the_circle_is_wrapped():
    env = PanSearchEnv("paper", SHORT)
    env.reset(seed=1)
    obs, *_ = env.step(np.array([3.0 * np.pi / 2.0, 0.0]))
    assert obs["pan"][0] == pytest.approx(-np.pi / 2.0)
    assert obs in env.observation_space


@pytest.mark.parametrize("kwargs,error,match", [
    ({"preset": "nope"}, ScenarioError, "unknown preset 'nope'"),
    ({"overrides": {"steps": 0}}, ScenarioError, "steps"),
    ({"overrides": {"n_targetz": 3}}, ScenarioError, "n_targetz"),
    ({"overrides": [("steps", 3)]}, TypeError, "overrides must be a dict"),
    ({"reward": "dr"}, ValueError, "unknown reward 'dr'; choose one of hit, final, in_fov"),
    ({"max_boxes": 0}, ValueError, "max_boxes must be a positive integer"),
    ({"max_boxes": 2.5}, TypeError, "max_boxes must be a positive integer"),
    ({"seed": -1}, ValueError, r"seed must be in \[0, "),
    ({"seed": "1"}, TypeError, "seed must be an integer"),
    ({"render_mode": "human"}, ValueError, "does not render"),
])
def test_bad_constructor_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        PanSearchEnv(**{"overrides": SHORT, **kwargs})


@pytest.mark.parametrize("reset,error,match", [
    ({"seed": -2}, ValueError, r"seed must be in \[0, "),
    ({"seed": 1.5}, TypeError, "seed must be an integer"),
    ({"options": {"test": -1}}, ValueError, r"options\['test'\] must be in \[0, "),
    ({"options": {"test": "3"}}, TypeError, r"options\['test'\] must be an integer"),
    ({"options": {"test": True}}, TypeError, r"options\['test'\] must be an integer"),
    ({"options": {"tests": 3}}, ValueError, "unknown reset option\\(s\\) 'tests'; PanSearch-v0 takes test"),
    ({"options": [("test", 3)]}, TypeError, "options must be a dict"),
])
def test_bad_reset_arguments(reset, error, match):
    env = PanSearchEnv("paper", SHORT)
    with pytest.raises(error, match=match):
        env.reset(**reset)


def test_bad_actions_and_step_before_reset():
    env = PanSearchEnv("paper", SHORT)
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(2))
    env.reset(seed=1)
    for action in (np.zeros(3), np.array([np.nan, 0.0]), 0.5):
        with pytest.raises(ValueError, match="2 finite numbers"):
            env.step(action)


def test_vector_env_runs_one_campaign_per_sub_env():
    vec = gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", overrides=SHORT)
    obs, info = vec.reset(seed=4)
    assert info["seed"].tolist() == [4, 5] and info["test"].tolist() == [0, 0]
    single, _ = PanSearchEnv("paper", SHORT).reset(seed=5)
    assert all(np.array_equal(obs[k][1], single[k]) for k in single)
    vec.close()
