"""Ra²ViPAS with the boxes' heights as a range cue (issue 20; ``range_cue.py``), as a policy of
its own so a campaign can run it beside the built-in and compare them on the same worlds::

    ra2vipas simulate --preset dynamic --set box_heights=true \\
        -a ra2vipas,ra2vipas.services.controller.heights_policy:Ra2ViPASHeights

The cue is off in the built-in (``ControllerSettings.height_cue``): measured, it does not change
the discovery rate on the worlds we have (docs/radio.md, "Box heights as a range cue"). It is
used only when the rig says its boxes carry heights (``SensorConfig.box_heights``); without them
this policy decides exactly as ``ra2vipas``.
"""

from __future__ import annotations

import dataclasses

from ra2vipas.services.controller.builtins import Ra2ViPAS
from ra2vipas.services.controller.contract import EpisodeContext
from ra2vipas.services.controller.policy import ControllerSettings


class Ra2ViPASHeights(Ra2ViPAS):
    """``ra2vipas`` with ``height_cue`` on: each track's box range against Rx(iso)'s level
    (``range_cue.RangeCue``), through the episode's public propagation model."""

    name = "ra2vipas-heights"
    summary = "Ra2ViPAS plus box heights as a range cue (when the rig's boxes carry heights)"

    def __init__(self, context: EpisodeContext, settings: ControllerSettings | None = None) -> None:
        super().__init__(context, dataclasses.replace(settings or ControllerSettings(), height_cue=True))
