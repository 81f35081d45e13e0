"""The four policies ra2vipas ships (paper Sec. IV-B, plus one), behind the policy contract
(``contract.py``) and registered through the same entry-point group as anyone's
(``ra2vipas.policies`` in pyproject.toml):

* ``ra2vipas``: fuses Rx(dir), Rx(iso) and the camera, GP-UCB on the fused objective (eq. 25);
* ``rapas``: Rx(dir) only (the paper's RaPAS baseline);
* ``ravipas``: the camera and Rx(iso) only (the paper's RaViPAS baseline);
* ``sweep``: fuses both but pans evenly round the circle (what active sensing buys).

Each runs the ``Controller`` of ``policy.py`` with its own tuning (``TUNING``).
"""

from __future__ import annotations

from typing import ClassVar

from ra2vipas.services.controller.contract import EpisodeContext, Policy
from ra2vipas.services.controller.policy import Controller, ControllerSettings, Decision
from ra2vipas.services.protocol.measurements import StepMeasurement


class BuiltinPolicy(Policy):
    """A built-in: the ``Controller`` with this policy's algorithm. Its decisions are the
    controller's ``Decision`` (the contract's fields plus the confidence map's covariates)."""

    algorithm: ClassVar[str] = ""
    reads_rx_dir: ClassVar[bool] = True
    """Whether its decisions use the directional receiver's readings (``rigcheck``: a wrong
    Rx(dir) model shows in these policies' DR)."""

    def __init__(self, context: EpisodeContext, settings: ControllerSettings | None = None) -> None:
        super().__init__(context)
        self.controller = Controller(self.algorithm, context.sensors, context.pod_model, settings)

    def first_pan(self) -> float:
        return self.controller.first_pan()

    def step(self, measurement: StepMeasurement) -> Decision:
        return self.controller.step(measurement)


class Ra2ViPAS(BuiltinPolicy):
    name = algorithm = "ra2vipas"
    summary = "Ra2ViPAS: Rx(dir) + Rx(iso) + camera fused, GP-UCB over the pan angle"


class RaPAS(BuiltinPolicy):
    name = algorithm = "rapas"
    summary = "RaPAS: Rx(dir) only"


class RaViPAS(BuiltinPolicy):
    name = algorithm = "ravipas"
    summary = "RaViPAS: camera + Rx(iso) only"
    reads_rx_dir = False


class Sweep(BuiltinPolicy):
    name = algorithm = "sweep"
    summary = "sweep: both cues fused, pans evenly round the circle (non-active)"
