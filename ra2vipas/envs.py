"""A Gymnasium environment for those who learn (or script) pan policies: ``ra2vipas/PanSearch-v0``.

Importing this module registers the environment with Gymnasium (Gymnasium 1.x has no plugin
discovery, so import it first, or name the module in the id)::

    import gymnasium as gym
    import ra2vipas.envs  # noqa: F401  (registers ra2vipas/PanSearch-v0)

    env = gym.make("ra2vipas/PanSearch-v0", preset="paper", overrides={"n_targets": 30})
    obs, info = env.reset(seed=1, options={"test": 0})  # test 0 of ``simulate --seed 1``
    pod_model = info["pod_model"]  # the learned POD model, p_hat_D(r)
    terminated = False
    while not terminated:
        action = np.array([next_pan_rad, named_bearing_rad])  # s_{t+1}, gamma_hat_t
        obs, reward, terminated, truncated, info = env.step(action)
    info["truth"]  # the ground truth, only now

One episode is one test of a campaign, the world ``simulate`` runs:

* **Seeds.** The Gymnasium seed *is* the campaign seed (``simulate --seed``) and the test index
  ``k`` is ``options["test"]``: ``reset(seed=s, options={"test": k})`` meets exactly the world
  of ``SimulatedPlatform(scenario, s, k)``, the one every algorithm of ``simulate --seed s``
  meets in its test k, and a policy gets the POD model ``train_pod(scenario, s)`` learned for
  that campaign. ``reset(seed=s)`` without a test is test 0; ``reset()`` without a seed goes
  on with the campaign already chosen, at the next test (k + 1), so ``reset(seed=s)``
  followed by ``reset()`` calls walks tests 0, 1, 2, ... of campaign s in order. Before any
  seeded reset the campaign is the constructor's ``seed`` or, when that is None, one drawn
  from ``np_random`` (fresh entropy, as Gymnasium does for an unseeded reset). A vector env
  (``gymnasium.make_vec``) reset with seed s seeds its sub-env i with s + i, so sub-env i runs
  campaign s + i (with that campaign's POD model), and each autoreset is its next test.
* **Steps.** ``reset`` senses step 0 at s_0, the scenario's initial pan (wrapped; the
  controller's ``first_pan``). Each ``step(action)`` then answers the measurement of step t:
  its named bearing gamma_hat_t is scored, and the platform senses step t + 1 at the pan
  angle s_{t+1} it names. After ``scenario.steps`` steps the episode terminates (the pan of
  the last action is not used, and the terminal observation repeats the last step's); it is
  never truncated.

Spaces
------
Action: ``Box(-pi, pi, shape=(2,), float64)``, ``[s_{t+1}, gamma_hat_t]`` in radians in the
paper's frame F_0: the next pan angle and the bearing the policy names as the transmitter's
after the measurement of step t. Any finite angle is accepted: one outside [-pi, pi] is
wrapped; one inside is used as given, bit for bit (so a scripted controller senses exactly
where it would in ``simulate``). For an RL library that wants [-1, 1], wrap the env in
``gymnasium.wrappers.RescaleAction``.

Observation: a ``Dict`` of fixed-size arrays encoding the ``StepMeasurement`` of step t, all
float64 but the mask:

=========  ======================  ==========================================================
key        shape                   content
=========  ======================  ==========================================================
``rssi``   (2,)                    z^(iso), z^(dir) [dBm], clipped to +-``RSSI_BOUND_DBM``
``pan``    (1,)                    s_t, the pan angle the step was sensed at [rad]
``step``   (1,)                    t, 0 ... steps - 1
``boxes``  (nu, max_boxes)         per camera frame, its boxes' bearings w.r.t. the optical
                                   axis [rad] in increasing order, padded with 0
``mask``   (nu, max_boxes) int8    1 where ``boxes`` holds a box
=========  ======================  ==========================================================

nu is the scenario's ``frames_per_rf``; ``max_boxes`` (constructor, default
``DEFAULT_MAX_BOXES``) bounds the boxes kept per frame. A frame with more keeps the
``max_boxes`` nearest the optical axis (in bearing order); the rest are dropped and counted
in ``info["boxes_dropped"]`` (this step) and ``info["boxes_dropped_total"]`` (this episode).
``measurement_from_observation`` turns an observation back into the ``StepMeasurement``,
exactly when nothing was dropped; ``info["measurement"]`` carries it whole either way.

Reward (constructor ``reward``):

* ``"hit"`` (default): 1.0 when gamma_hat_t names the Tx under the paper's association rule
  (eq. 11: the target whose bearing at step t is nearest gamma_hat_t is the one named;
  ``metrics.score_test``), else 0.0. The mean over tests of the reward of step t is DR_t
  (eq. 28), as ``simulate`` reports it.
* ``"final"``: the hit of the last step only (0.0 before): DR at T_W, a terminal-only reward.
* ``"in_fov"``: 1.0 when the Tx would be inside the field of view pointing at gamma_hat_t
  (the figure the authors' code reports).

Info: at reset, the campaign ``seed``, the ``test`` index, the ``scenario``, ``pod_model``
(a ``PODModel``) and ``pod_r2``, the rig's public description ``sensor_config``; at every
call, ``step``, ``measurement``, ``boxes_dropped`` and ``boxes_dropped_total``. No truth
until the episode terminates; the last ``step`` adds ``truth``: the Tx index, every target's
bearing and range at step 0, the bearings scored against (``step_bearings_rad``, (N,) or
(T, N) when targets walk) and the episode's per-step ``hits``, ``in_fov`` and ``chosen``
(i_hat_t) exactly as ``run_test`` scores them.
"""

from __future__ import annotations

import functools
import math
import numbers
from typing import Any, ClassVar

import numpy as np

try:
    import gymnasium
    from gymnasium import spaces
except ModuleNotFoundError as exc:  # pragma: no cover - depends on the install
    raise ModuleNotFoundError(
        "ra2vipas.envs needs Gymnasium: pip install 'ra2vipas[gym]' (or pip install gymnasium)"
    ) from exc

from ra2vipas.services.controller.policy import SensorConfig, sensor_config_from_scenario
from ra2vipas.services.orchestrator.metrics import score_episode, score_test
from ra2vipas.services.orchestrator.simulate import TrainedPOD, train_pod
from ra2vipas.services.protocol.angles import wrap
from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement
from ra2vipas.services.protocol.scenario import Scenario, build_scenario
from ra2vipas.services.sensors.world import SimulatedPlatform

__all__ = [
    "BOX_BOUND_RAD",
    "DEFAULT_MAX_BOXES",
    "ENV_ID",
    "REWARDS",
    "RSSI_BOUND_DBM",
    "PanSearchEnv",
    "encode_measurement",
    "measurement_from_observation",
    "trained_pod",
]

ENV_ID = "ra2vipas/PanSearch-v0"
REWARDS = ("hit", "final", "in_fov")
"""The reward choices (see the module docstring)."""
DEFAULT_MAX_BOXES = 32
"""Boxes kept per camera frame by default: more than the paper world (N = 20) can show, so
only heavy clutter or a crowded scenario ever drops one."""
RSSI_BOUND_DBM = 1.0e4
"""The RSSI observation's bounds [dBm]: far beyond any value a valid scenario produces
(values are clipped to them, so an observation is always inside its space)."""
BOX_BOUND_RAD = 2.0 * math.pi
"""The box bearings' bounds [rad]: a box lies within the half field of view (<= pi) plus its
bearing noise (clipped to them, like the RSSI)."""
MAX_SEED = 2**63 - 1
"""The largest campaign seed or test index (the wire's and the API's bound)."""
_OPTIONS = ("test",)


@functools.lru_cache(maxsize=8)
def trained_pod(scenario: Scenario, seed: int) -> TrainedPOD:
    """``train_pod(scenario, seed)``, the POD model ``simulate`` learns for campaign ``seed``,
    cached per (scenario, seed) in this process (a few environments, or a vector of them,
    share it)."""
    return train_pod(scenario, seed)


def encode_measurement(m: StepMeasurement, max_boxes: int) -> tuple[dict[str, np.ndarray], int]:
    """The fixed-size observation of one ``StepMeasurement`` and how many boxes it dropped.

    Parameters
    ----------
    m : StepMeasurement
        One step's measurement (nu frames).
    max_boxes : int
        Boxes kept per frame: the ``max_boxes`` nearest the optical axis, in bearing order.

    Returns
    -------
    obs : dict of ndarray
        ``rssi`` (2,), ``pan`` (1,), ``step`` (1,), ``boxes`` (nu, max_boxes) and
        ``mask`` (nu, max_boxes), as the module docstring describes them.
    dropped : int
        Boxes beyond ``max_boxes`` in any frame, left out of ``boxes``.
    """
    nu = len(m.frames)
    boxes = np.zeros((nu, max_boxes), dtype=np.float64)
    mask = np.zeros((nu, max_boxes), dtype=np.int8)
    dropped = 0
    for f, frame in enumerate(m.frames):
        kept = frame.box_bearings_rad
        if len(kept) > max_boxes:
            dropped += len(kept) - max_boxes
            kept = tuple(sorted(sorted(kept, key=abs)[:max_boxes]))
        boxes[f, :len(kept)] = kept
        mask[f, :len(kept)] = 1
    obs = {
        "rssi": np.clip(np.array([m.rf.iso_rssi_dbm, m.rf.dir_rssi_dbm], dtype=np.float64), -RSSI_BOUND_DBM, RSSI_BOUND_DBM),
        "pan": np.array([m.pan_rad], dtype=np.float64),
        "step": np.array([m.step], dtype=np.float64),
        "boxes": np.clip(boxes, -BOX_BOUND_RAD, BOX_BOUND_RAD),
        "mask": mask,
    }
    return obs, dropped


def measurement_from_observation(obs: dict[str, np.ndarray]) -> StepMeasurement:
    """The ``StepMeasurement`` an observation encodes (the inverse of ``encode_measurement``:
    exact, value for value, when no box was dropped or clipped), for a policy written against
    what the wire carries."""
    boxes = np.asarray(obs["boxes"], dtype=np.float64)
    mask = np.asarray(obs["mask"]).astype(bool)
    frames = tuple(CameraFrame(box_bearings_rad=tuple(row[keep].tolist())) for row, keep in zip(boxes, mask))
    rssi = np.asarray(obs["rssi"], dtype=np.float64)
    return StepMeasurement(
        step=int(np.asarray(obs["step"]).reshape(-1)[0]),
        pan_rad=float(np.asarray(obs["pan"]).reshape(-1)[0]),
        rf=RFSample(iso_rssi_dbm=float(rssi[0]), dir_rssi_dbm=float(rssi[1])),
        frames=frames,
    )


def _index(value: Any, what: str) -> int:
    """A campaign seed or test index: an integer in [0, MAX_SEED]."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{what} must be an integer in [0, {MAX_SEED}], got {value!r}")
    if not 0 <= int(value) <= MAX_SEED:
        raise ValueError(f"{what} must be in [0, {MAX_SEED}], got {int(value)}")
    return int(value)


class PanSearchEnv(gymnasium.Env):
    """One test of a ra2vipas campaign as a Gymnasium environment (see the module docstring).

    Parameters
    ----------
    preset : str
        Scenario preset (``paper``, ``paper-uniform``, ``dynamic``).
    overrides : dict, optional
        Scenario parameters over the preset, as ``simulate --set NAME=VALUE`` takes them.
    seed : int, optional
        The campaign seed of resets before any seeded one (None: drawn from ``np_random``).
    max_boxes : int
        Boxes kept per camera frame in the observation.
    reward : {"hit", "final", "in_fov"}
        What a step is rewarded for.
    render_mode : None
        No rendering.

    Attributes
    ----------
    scenario : Scenario
        The resolved scenario (fixed for the env's life: it sizes the spaces).
    sensor_config : SensorConfig
        The rig's public description a controller is built with.
    pod_model : PODModel or None
        The POD model of the current campaign (None before the first reset).
    campaign_seed, test_index : int or None
        The world of the current episode: ``SimulatedPlatform(scenario, campaign_seed, test_index)``.

    Raises
    ------
    ScenarioError
        An unknown preset or an invalid override (a ``ValueError`` naming the parameter).
    TypeError
        An argument of the wrong type (overrides not a dict, a seed or max_boxes not an integer).
    ValueError
        Any other bad value, with what was expected.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, preset: str = "paper", overrides: dict[str, Any] | None = None, seed: int | None = None,
                 max_boxes: int = DEFAULT_MAX_BOXES, reward: str = "hit", render_mode: str | None = None) -> None:
        if overrides is not None and not isinstance(overrides, dict):
            raise TypeError(f"overrides must be a dict of scenario parameters, got {type(overrides).__name__}")
        self.scenario: Scenario = build_scenario(preset, overrides)
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
        if isinstance(max_boxes, bool) or not isinstance(max_boxes, numbers.Integral):
            raise TypeError(f"max_boxes must be a positive integer, got {max_boxes!r}")
        if max_boxes < 1:
            raise ValueError(f"max_boxes must be a positive integer, got {max_boxes!r}")
        if render_mode is not None:
            raise ValueError(f"PanSearch-v0 does not render; render_mode must be None, got {render_mode!r}")
        self.preset = preset
        self.reward_kind = reward
        self.max_boxes = int(max_boxes)
        self.render_mode = None
        self._default_seed = None if seed is None else _index(seed, "seed")
        self.sensor_config: SensorConfig = sensor_config_from_scenario(self.scenario)
        sc = self.scenario
        nu = sc.frames_per_rf
        self.action_space = spaces.Box(low=-math.pi, high=math.pi, shape=(2,), dtype=np.float64)
        self.observation_space = spaces.Dict({
            "rssi": spaces.Box(-RSSI_BOUND_DBM, RSSI_BOUND_DBM, shape=(2,), dtype=np.float64),
            "pan": spaces.Box(-math.pi, math.pi, shape=(1,), dtype=np.float64),
            "step": spaces.Box(0.0, float(sc.steps - 1), shape=(1,), dtype=np.float64),
            "boxes": spaces.Box(-BOX_BOUND_RAD, BOX_BOUND_RAD, shape=(nu, self.max_boxes), dtype=np.float64),
            "mask": spaces.MultiBinary([nu, self.max_boxes]),
        })
        self.campaign_seed: int | None = None
        self.test_index: int | None = None
        self.pod_model = None
        self._pod: TrainedPOD | None = None
        self._platform: SimulatedPlatform | None = None
        self._bearings: np.ndarray | None = None
        self._t = 0
        self._done = True
        self._estimates: list[float] = []
        self._dropped_total = 0
        self._last_obs: dict[str, np.ndarray] | None = None
        self._last_measurement: StepMeasurement | None = None

    # -- Gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start test ``options["test"]`` of campaign ``seed`` (see the module docstring).

        Raises
        ------
        TypeError
            A seed or test that is not an integer, options that are not a dict.
        ValueError
            A seed or test outside [0, 2**63 - 1], an unknown option.
        """
        campaign = None if seed is None else _index(seed, "seed")
        options = {} if options is None else options
        if not isinstance(options, dict):
            raise TypeError(f"options must be a dict, got {type(options).__name__}")
        unknown = sorted(set(options) - set(_OPTIONS))
        if unknown:
            raise ValueError(f"unknown reset option(s) {', '.join(map(repr, unknown))}; PanSearch-v0 takes {', '.join(_OPTIONS)}")
        test = _index(options["test"], "options['test']") if "test" in options else None
        super().reset(seed=seed)
        if campaign is None:
            if self.campaign_seed is not None:
                campaign = self.campaign_seed
                if test is None:
                    test = self.test_index + 1
            elif self._default_seed is not None:
                campaign = self._default_seed
            else:
                campaign = int(self.np_random.integers(0, MAX_SEED, endpoint=True))
        if test is None:
            test = 0
        if test > MAX_SEED:
            raise ValueError(f"test index {test} is beyond {MAX_SEED}; reset with a seed to start over")
        sc = self.scenario
        self.campaign_seed, self.test_index = campaign, test
        self._pod = trained_pod(sc, campaign)
        self.pod_model = self._pod.model
        self._platform = SimulatedPlatform(sc, campaign, test)
        self._bearings = self._platform.truth.step_bearings_rad()
        self._t = 0
        self._done = False
        self._estimates = []
        self._dropped_total = 0
        first_pan = float(wrap(self.sensor_config.initial_pan_rad))  # the controller's first_pan()
        obs, info = self._sense(0, first_pan)
        info.update(seed=campaign, test=test, scenario=sc, pod_model=self.pod_model, pod_r2=self._pod.r2,
                    sensor_config=self.sensor_config)
        return obs, info

    def step(self, action):
        """Score gamma_hat_t, sense step t + 1 at s_{t+1}; see the module docstring.

        Raises
        ------
        gymnasium.error.ResetNeeded
            Before the first reset or after the episode terminated.
        ValueError
            An action that is not two finite angles.
        """
        if self._done:
            raise gymnasium.error.ResetNeeded("PanSearch-v0: call reset() before step() (and after an episode terminates)")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (2,) or not np.all(np.isfinite(a)):  # a wrong shape too is a bad value of this Box
            raise ValueError(f"the action is [next pan angle, named bearing] in radians: 2 finite numbers, got {action!r}")
        pan, named = float(a[0]), float(a[1])
        if not -math.pi <= pan <= math.pi:
            pan = float(wrap(pan))
        sc = self.scenario
        t = self._t
        truth = self._platform.truth
        bearings_t = self._bearings if self._bearings.ndim == 1 else self._bearings[t]
        hit, in_fov = score_test(np.array([named]), bearings_t, truth.tx_index, sc.fov_half_angle_rad)
        self._estimates.append(named)
        last = t + 1 >= sc.steps
        if self.reward_kind == "hit":
            reward = float(hit[0])
        elif self.reward_kind == "final":
            reward = float(hit[0]) if last else 0.0
        else:
            reward = float(in_fov[0])
        if last:
            self._done = True
            obs = {k: v.copy() for k, v in self._last_obs.items()}
            info = {"step": t, "measurement": self._last_measurement, "boxes_dropped": 0,
                    "boxes_dropped_total": self._dropped_total, "truth": self._truth_info()}
        else:
            self._t = t + 1
            obs, info = self._sense(t + 1, pan)
        return obs, reward, last, False, info

    # -- internals --------------------------------------------------------------------------
    def _sense(self, t: int, pan: float) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        m = self._platform.sense(t, pan)
        obs, dropped = encode_measurement(m, self.max_boxes)
        self._dropped_total += dropped
        self._last_obs, self._last_measurement = obs, m
        info = {"step": t, "measurement": m, "boxes_dropped": dropped, "boxes_dropped_total": self._dropped_total}
        return {k: v.copy() for k, v in obs.items()}, info

    def _truth_info(self) -> dict[str, Any]:
        """The episode's truth and its score, as ``run_test`` computes them."""
        sc = self.scenario
        truth = self._platform.truth
        hits, in_fov, chosen = score_episode(np.asarray(self._estimates), self._bearings, truth.tx_index,
                                             sc.fov_half_angle_rad, sc.steps)
        return {
            "tx_index": int(truth.tx_index),
            "bearings_rad": truth.bearings_rad.copy(),
            "ranges_m": truth.ranges_m.copy(),
            "step_bearings_rad": np.array(self._bearings, copy=True),
            "hits": np.asarray(hits, dtype=bool),
            "in_fov": np.asarray(in_fov, dtype=bool),
            "chosen": np.asarray(chosen, dtype=np.int64),
        }


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="ra2vipas.envs:PanSearchEnv")
