"""The pointing-policy contract: what any policy receives and returns (issue 19).

A *policy* decides, one RF sample at a time, where the pan camera looks next and which bearing
it names as the Tx's (gamma_hat_t, the paper's estimate, eq. 11 scores it). Ra²ViPAS, RaPAS,
RaViPAS and the sweep are four policies; a researcher's own is a fifth, found through the same
registry (``registry.py``) and run everywhere a built-in runs: ``ra2vipas simulate``, campaigns
over the mesh, studies, the robustness bench.

The contract, in the spirit of Gymnasium's ``Env`` and Stone Soup's sensor managers:

* ``Policy(context)``: one object per episode (test). ``context`` is an ``EpisodeContext``: the
  rig's public description (FoV, nu frames per RF sample, T_RF, the Rx(dir) response), the POD
  model the learner fitted (``PODModel``), the episode's public scenario and seed. Never truth:
  no target positions, ranges, identities or the Tx's index.
* ``first_pan() -> float``: s_0, the pan angle of the first sample.
* ``step(measurement) -> PolicyDecision`` for t = 0, 1, ...: ``measurement`` is the
  ``StepMeasurement`` of step t, exactly what the wire carries (the RSSI of Rx(iso) and
  Rx(dir), the nu frames of anonymous box bearings, the pan it was taken at); the decision
  carries the next pan angle s_{t+1}, the bearing it names now (gamma_hat_t) and, optionally, a
  confidence in [0, 1] that the target nearest that bearing is the Tx (early decisions use it).

Policies are plain Python objects: a unit test drives one without a network.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ra2vipas.services.protocol.measurements import StepMeasurement
from ra2vipas.services.protocol.pod import PODModel


@dataclass(frozen=True)
class RigDescription:
    """What a policy knows of its platform (the rig's descriptor, or the scenario's sensors for
    an undescribed rig): hardware, no world truth.

    Attributes
    ----------
    steps : int
        n_test, the samples of the episode.
    frames_per_rf : int
        nu, camera frames per RF sample.
    fov_half_angle_rad : float
        Half the camera's field of view.
    box_bearing_noise_rad : float
        Standard deviation of a box's bearing.
    initial_pan_rad : float
        Where the camera points at the start.
    rf_period_s : float
        T_RF, the time between two samples (and two decisions).
    rx_dir : str
        Rx(dir)'s response: ``paper`` (eq. 6: the RSSI in dBm scaled by rho, so it *dips*
        when aligned), ``db-gain`` (a gain in dB added to the path loss: it peaks when
        aligned) or ``unknown``.
    rx_dir_curvature : float or None
        a in rho = 1 - a Delta^2 (None: not known).
    rx_dir_floor_db : float
        db-gain: the lowest gain.
    """

    steps: int
    frames_per_rf: int
    fov_half_angle_rad: float
    box_bearing_noise_rad: float
    initial_pan_rad: float
    rf_period_s: float = 0.1
    rx_dir: str = "paper"
    rx_dir_curvature: float | None = None
    rx_dir_floor_db: float = -20.0


@dataclass(frozen=True)
class EpisodeContext:
    """What a policy receives when an episode starts.

    Attributes
    ----------
    rig : RigDescription
        The platform's public description.
    pod_model : PODModel
        p_hat_D(r): the camera's probability of detection against the Rx(iso) RSSI, learned
        self-supervised by the learner (Sec. III-A), with its std and the RSSI noise.
    scenario : dict
        The episode's public scenario parameters (``Scenario.model_dump()``): what the operator
        configured, not what the world drew.
    seed : int
        The campaign seed (a policy that draws random numbers seeds them from (seed, test)).
    test : int
        The test index k.
    sensors : Any
        The controller's ``SensorConfig`` built from the same description (the built-ins use it).
    stop_confidence : float
        The campaign's early-decision level (0: none): with several tags, a tag whose confidence
        reaches it is decided and stops steering the camera (issue 21).
    """

    rig: RigDescription
    pod_model: PODModel
    scenario: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    test: int = 0
    sensors: Any = None
    stop_confidence: float = 0.0


@dataclass(frozen=True)
class PolicyDecision:
    """A policy's answer to step t.

    Attributes
    ----------
    next_pan_rad : float
        s_{t+1}, wrapped to [-pi, pi).
    estimate_rad : float
        gamma_hat_t, the bearing named as the Tx's now.
    confidence : float or None
        Probability in [0, 1] that the target nearest ``estimate_rad`` is the Tx (None: the
        policy does not say; an early decision then never happens).
    reward : float or None
        The policy's own objective at the pan the sample was taken at, if it has one (plots).
    """

    next_pan_rad: float
    estimate_rad: float
    confidence: float | None = None
    reward: float | None = None


class Policy:
    """Base class of a pointing policy (see the module docstring for the contract).

    Subclasses set ``name`` (what campaigns, results and plots call it: lower case letters,
    digits, ``-``, ``_``, ``.``) and implement ``first_pan`` and ``step``. Register it in a
    package's ``pyproject.toml``::

        [project.entry-points."ra2vipas.policies"]
        greedy = "my_policy:GreedyPolicy"

    or name it as ``module:Class`` wherever a policy name is taken.
    """

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""

    def __init__(self, context: EpisodeContext) -> None:
        self.context = context

    def first_pan(self) -> float:
        """s_0: by default the rig's initial pan."""
        return float(math.remainder(self.context.rig.initial_pan_rad, 2.0 * math.pi))

    def step(self, measurement: StepMeasurement) -> PolicyDecision:  # pragma: no cover - abstract
        """Take the measurement of step t; return s_{t+1} and gamma_hat_t."""
        raise NotImplementedError


def rig_description(sensors: Any) -> RigDescription:
    """The public ``RigDescription`` of a controller ``SensorConfig``."""
    return RigDescription(steps=sensors.steps, frames_per_rf=sensors.frames_per_rf,
                          fov_half_angle_rad=sensors.fov_half_angle_rad, box_bearing_noise_rad=sensors.box_bearing_noise_rad,
                          initial_pan_rad=sensors.initial_pan_rad, rf_period_s=sensors.rf_period_s, rx_dir=sensors.rx_dir,
                          rx_dir_curvature=sensors.rx_dir_curvature, rx_dir_floor_db=sensors.rx_dir_floor_db)


def episode_context(sensors: Any, pod_model: PODModel, scenario: Any, seed: int, test: int,
                    stop_confidence: float = 0.0) -> EpisodeContext:
    """The ``EpisodeContext`` of an episode: ``sensors`` is the controller's ``SensorConfig``
    (from the rig's descriptor or the scenario), ``scenario`` a ``Scenario`` (its public
    parameters are passed on), ``stop_confidence`` the campaign's early-decision level."""
    return EpisodeContext(rig=rig_description(sensors), pod_model=pod_model, scenario=scenario.model_dump(mode="json"),
                          seed=seed, test=test, sensors=sensors, stop_confidence=float(stop_confidence))
