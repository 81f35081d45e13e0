"""Where to look next: the acquisition parts (issue 19), in the spirit of Stone Soup's sensor
managers. Each chooses s_{t+1} from the step's beliefs; some hand over to another (``then``),
so a schedule is a chain: ``WarmUpSweep(then=ProbeSchedule(then=GPUCB()))`` is Ra²ViPAS's.

* ``Sweep``: evenly round the circle, one turn per episode (non-active: what active sensing buys).
* ``WarmUpSweep``: ceil(pi / half-FoV) evenly spaced pans first, so every target is seen once.
* ``ProbeSchedule``: every ``every``-th step a discrimination probe: with a belief that can tell
  (the filter), the pan whose Rx(dir) reading the posterior of gamma is least sure of (largest
  predictive variance: the most informative sample, MacKay 1992); otherwise the pan where the two
  leading hypotheses predict the most different RSSI (Box & Hill 1967), alternating sides.
  Samples on the flanks of the lobe locate it, samples at its flat top do not.
* ``GPUCB``: GP-UCB on the fused objective (eq. 25): a(s) = U_D(s) (J_RF(s) + sqrt(beta)
  sigma(s)), J_RF the RF belief's predicted normalised lobe and U_D the posterior mass of
  candidate targets in view at s (1 where the camera has not looked yet).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ra2vipas.services.controller import _kernels
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.rf_belief import RFBelief
from ra2vipas.services.controller.vision_belief import VisionBelief
from ra2vipas.services.protocol.angles import wrap


@dataclass(slots=True)
class Beliefs:
    """What an acquisition reads at step t: the beliefs after the step, the tracks' unnormalised
    log-posteriors ``l_tracks`` and posterior probabilities ``post`` (the fusion's)."""

    t: int
    rf: RFBelief
    vision: VisionBelief
    l_tracks: np.ndarray
    post: np.ndarray
    packet_due: bool | None = None  # BLE advertisements: whether one is due in step t + 1 (None: not known, e.g. the 1.0 pair)


class Acquisition:
    """The acquisition interface: ``next_pan(beliefs) -> (s_{t+1}, whether it is a probe)``."""

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:  # pragma: no cover - abstract
        raise NotImplementedError


class Sweep(Acquisition):
    """s_{t+1} = s_0 + 2 pi (t + 1) / steps: one even turn over the episode (or the warm-up)."""

    def __init__(self, initial_pan_rad: float, steps: int) -> None:
        self.initial_pan_rad, self.steps = initial_pan_rad, max(steps, 1)

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:
        return self.initial_pan_rad + 2.0 * math.pi * (b.t + 1) / self.steps, False


class WarmUpSweep(Acquisition):
    """The first ``steps`` pans evenly round the circle, then ``then``'s."""

    def __init__(self, initial_pan_rad: float, steps: int, then: Acquisition) -> None:
        self.steps, self.then = steps, then
        self._sweep = Sweep(initial_pan_rad, steps)

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:
        if b.t + 1 < self.steps:
            return self._sweep.next_pan(b)
        return self.then.next_pan(b)


class ProbeSchedule(Acquisition):
    """A discrimination probe every ``every``-th step counted from ``start`` (0: never), else
    ``then``'s pan. Only a policy that hears Rx(dir) probes. On BLE advertisements, once the
    beacon's interval is known (``Beliefs.packet_due``), a probe in every ``due_every``-th step a
    packet is due and ``then``'s pan in the others (where no Rx(dir) reading will come, the camera's choice).

    Parameters
    ----------
    circle : CircleGrid
        The pan grid.
    every, start : int
        The schedule: steps t with (t + 1 - start) % every == 0.
    lobe_width_rad : float
        Width of the generic lobe whose flanks a probe aims at.
    informative : bool
        Use the RF belief's most informative pan when it has one.
    rf_peaks : bool
        Probe between the two best RF peaks, not the two best tracks (always when the Tx walks).
    due_every : int
        BLE: probe in every ``due_every``-th step a packet is due.
    """

    def __init__(self, circle: CircleGrid, then: Acquisition, every: int = 2, start: int = 0, lobe_width_rad: float = 1.0,
                 informative: bool = True, rf_peaks: bool = False, due_every: int = 1) -> None:
        self.circle, self.then, self.every, self.start = circle, then, every, start
        self.due_every = max(int(due_every), 1)
        self.lobe_width_rad, self.informative, self.rf_peaks = lobe_width_rad, informative, rf_peaks
        self._probes = 0
        self._due = 0

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:
        if b.packet_due is not None and b.t + 1 >= self.start and self.every:
            # BLE: a probe pays only in a step a packet will arrive in (the beacon's interval is regular)
            if b.packet_due and b.rf.listens and self._due_probe():
                pan = b.rf.informative_pan() if self.informative else None
                return (self._between_leaders(b) if pan is None else pan), True
            return self.then.next_pan(b)
        if b.rf.listens and self.every and (b.t + 1 - self.start) % self.every == 0:
            pan = b.rf.informative_pan() if self.informative else None
            return (self._between_leaders(b) if pan is None else pan), True
        return self.then.next_pan(b)

    def _due_probe(self) -> bool:
        """Whether this due packet's step is a probe: every ``every``-th of them."""
        self._due += 1
        return self._due % self.due_every == 0

    def _between_leaders(self, b: Beliefs) -> float:
        """The pan where the two leading hypotheses' lobes differ most, on alternating sides."""
        grid = self.circle.angles
        if b.l_tracks.size >= 2 and not self.rf_peaks and b.rf.tx_walks <= 0.5:
            top = np.argsort(-b.l_tracks)[:2]
            g1, g2 = b.vision.tracks.bearing[top[0]], b.vision.tracks.bearing[top[1]]
        else:
            order = np.argsort(-b.rf.log_likelihood)
            g1 = grid[order[0]]
            apart = np.abs(wrap(grid[order] - g1)) >= math.radians(3.0)
            g2 = grid[order[apart][0]] if apart.any() else g1 + math.radians(3.0)
        self._probes += 1
        arg = _kernels.probe(grid, float(g1), float(g2), self.lobe_width_rad, bool(self._probes % 2))
        return float(grid[arg])


class GPUCB(Acquisition):
    """argmax_s U_D(s) (J_RF(s) + sqrt(beta) sigma(s)) over the grid (eq. 25).

    Parameters
    ----------
    circle : CircleGrid
        The pan grid.
    frames_per_rf : int
        nu: a bearing seen in fewer than 2 nu frames counts as unseen (U_D = 1 there).
    beta : float
        The UCB exploration weight.
    use_mass : bool
        Weigh by U_D (with a camera).
    """

    def __init__(self, circle: CircleGrid, frames_per_rf: int, beta: float = 4.0, use_mass: bool = True) -> None:
        self.circle, self.frames_per_rf, self.beta, self.use_mass = circle, frames_per_rf, beta, use_mass
        self._none = np.zeros(circle.size)

    def next_pan(self, b: Beliefs) -> tuple[float, bool]:
        mean, sd, A, c = b.rf.gain_prediction()
        vision = b.vision
        use_mass = vision.sees and self.use_mass
        bearings = vision.tracks.bearing if b.post.size else np.empty(0)
        view = vision.view_frames if vision.sees else self._none
        limit = vision.tracks.count_limit if vision.sees else 0.0
        arg = _kernels.acquire(mean, c, A, sd, math.sqrt(self.beta), bearings, b.post if b.post.size else np.empty(0), view,
                               2.0 * self.frames_per_rf, self.circle.step, limit, use_mass)
        return float(self.circle.angles[arg]), False
