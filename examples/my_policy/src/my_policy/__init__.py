"""A greedy pointing policy: sweep once, then point where Rx(dir) said the Tx is, and name the
box nearest that pan. A third-party policy in under 100 lines (issue 19's example)."""

from __future__ import annotations

import math

import numpy as np

from ra2vipas import EpisodeContext, Policy, PolicyDecision

BINS = 72  # 5 degrees


def wrap(angle: float) -> float:
    return math.remainder(angle, 2.0 * math.pi)


class GreedyPolicy(Policy):
    """Sweep the circle in FoV-wide steps, then keep pointing at the bearing whose Rx(dir)
    readings say "aligned" best, and name the camera box nearest it.

    "Aligned" depends on the antenna: with a gain in dB (``db-gain``) the directional RSSI
    *peaks* at the Tx; under the paper's model (eq. 6) the RSSI in dBm is scaled by rho <= 1,
    so it *dips* (is most negative) when aligned. Pointing where Rx(dir) is strongest under
    the paper's model points away from the Tx.
    """

    name = "greedy"
    summary = "greedy: sweep, then point where Rx(dir) reads most aligned; name the nearest box"

    def __init__(self, context: EpisodeContext) -> None:
        super().__init__(context)
        rig = context.rig
        self.sign = -1.0 if rig.rx_dir == "paper" else 1.0  # how a reading's alignment score follows its RSSI
        self.sweep = [wrap(rig.initial_pan_rad + k * 2.0 * rig.fov_half_angle_rad)
                      for k in range(math.ceil(math.pi / rig.fov_half_angle_rad))]
        self.score_sum = np.zeros(BINS)
        self.score_n = np.zeros(BINS)
        self.boxes: list[float] = []  # box bearings seen (platform frame)

    def _bin(self, angle: float) -> int:
        return int(((wrap(angle) + math.pi) / (2.0 * math.pi)) * BINS) % BINS

    def _best_bearing(self) -> float:
        seen = self.score_n > 0
        if not seen.any():
            return self.context.rig.initial_pan_rad
        mean = np.where(seen, self.score_sum / np.maximum(self.score_n, 1), -np.inf)
        return wrap((int(np.argmax(mean)) + 0.5) * 2.0 * math.pi / BINS - math.pi)

    def step(self, measurement) -> PolicyDecision:
        pan = float(measurement.pan_rad)
        b = self._bin(pan)
        self.score_sum[b] += self.sign * measurement.rf.dir_rssi_dbm
        self.score_n[b] += 1
        for frame in measurement.frames:
            self.boxes.extend(wrap(pan + bearing) for bearing in frame.box_bearings_rad)  # boxes are relative to the axis
        self.boxes = self.boxes[-2000:]
        best = self._best_bearing()
        named = min(self.boxes, key=lambda g: abs(wrap(g - best)), default=best)
        t = int(measurement.step)
        if t + 1 < len(self.sweep):
            next_pan = self.sweep[t + 1]
        else:  # greedy: look at the best bearing, alternating a little either side to refine it
            next_pan = wrap(best + (0.05 if t % 2 else -0.05))
        return PolicyDecision(next_pan_rad=next_pan, estimate_rad=named)
