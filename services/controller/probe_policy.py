"""Ra²ViPAS whose probes take Rx(dir)'s offset as known (0), as a policy of its own so a campaign
can run it beside the built-in and measure what the built-in's probes gain on the same worlds::

    ra2vipas simulate --preset ble-recorded --tests 200 --seed 3 \\
        -a ra2vipas,ra2vipas.services.controller.probe_policy:Ra2ViPASKnownOffsetProbes

The built-in's probes read each bearing's predicted Rx(dir) packet with the offset its packets so
far estimate for that bearing (``ControllerSettings.packet_probe_offsets``,
``rf_filter.PacketBearingFilter.most_informative_pan``; docs/radio.md, "Probes that know the offset
is unknown"). On RSSI pairs (``paper``, ``paper-uniform``, ``dynamic``, a v1 node) both decide
exactly alike: the pair path's probe never had an offset to estimate.
"""

from __future__ import annotations

import dataclasses

from ra2vipas.services.controller.builtins import Ra2ViPAS
from ra2vipas.services.controller.contract import EpisodeContext
from ra2vipas.services.controller.policy import ControllerSettings


class Ra2ViPASKnownOffsetProbes(Ra2ViPAS):
    """``ra2vipas`` with ``packet_probe_offsets`` off: a probe's predictive variance takes
    Rx(dir)'s offset as 0 (what the built-in did before; the pair path's criterion)."""

    name = "ra2vipas-known-offset-probes"
    summary = "Ra2ViPAS whose probes take Rx(dir)'s offset as known (0), for paired comparisons on packets"

    def __init__(self, context: EpisodeContext, settings: ControllerSettings | None = None) -> None:
        super().__init__(context, dataclasses.replace(settings or ControllerSettings(), packet_probe_offsets=False))
