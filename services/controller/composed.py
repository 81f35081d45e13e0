"""A policy as a composition of parts (issue 19): the loop that runs them, step by step.

``Composition(first_pan_rad, parts)`` runs one episode. Each ``step`` takes what the platform
sensed at pan s_t (a ``StepMeasurement``: the RSSI pair and the nu frames of anonymous box
bearings; ``rf`` may be None when no packet came) and:

1. ``iso.add``: the Rx(iso) statistics take the step's level (``rf_belief.IsoLevel``), or each of
   its Rx(iso) advertisements (protocol 1.3);
2. ``vision.update``: the vision belief takes the frames (``vision_belief``);
3. ``rf.update``: the RF belief takes the RSSI pair (``rf_belief``; unchanged without one), or
   ``rf.update_packets`` the step's advertisements (``rf_belief.Packets``: 0..n per receiver at
   their times; a step with none is a step without RF evidence, as ``rf=None``);
4. ``fusion.beliefs`` / ``fusion.answer``: the posterior over the hypotheses and gamma_hat_t
   (``fusion``);
5. ``acquisition.next_pan``: s_{t+1} (``acquisition``);
6. ``confidence``: the raw posterior of the answer through the confidence map (``confidence``).

It never sees ranges, identities or the true POD. The four built-ins are four such compositions
(``builtins.py``); a user's policy can hold one and swap any part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ra2vipas.services.controller.acquisition import Acquisition, Beliefs
from ra2vipas.services.controller.confidence import Confidence
from ra2vipas.services.controller.fusion import Fusion
from ra2vipas.services.controller.rf_belief import IsoLevel, PacketClock, Packets, RFBelief
from ra2vipas.services.controller.vision_belief import VisionBelief
from ra2vipas.services.protocol.measurements import StepMeasurement

_TWO_PI = 2.0 * math.pi


def wrapped(angle) -> float:
    """``float(wrap(angle))`` for one angle, in Python floats: the same double (numpy's float
    remainder and Python's are both fmod with the divisor's sign, +0.0 for a zero remainder)
    without the arrays."""
    return (float(angle) + math.pi) % _TWO_PI - math.pi


@dataclass(frozen=True)
class Decision:
    """The controller's answer to one step."""

    step: int
    next_pan_rad: float
    estimate_rad: float  # gamma_hat_t
    reward: float  # fused objective at the pan the sample was taken at
    probe: bool  # whether next_pan is a discrimination probe
    confidence: float = 0.0  # posterior probability that the target named by estimate_rad is the Tx
    raw_confidence: float = 0.0  # the same under the controller's own model, before calibration
    tx_walks: float = 0.0  # how likely the Tx walks, from Rx(dir) (a walking Tx may have left the answer)
    noise_correlation: float = 0.0  # rho of the RSSI noise, from Rx(iso) (fading: fewer independent samples)
    clutter_density: float = 0.0  # false boxes per frame per radian, from the tracker
    crowding: float = 0.0  # exp(-d / 1 deg), d the bearing gap from the answer to the nearest other track


@dataclass
class Parts:
    """The parts of a composed policy, one job each.

    Attributes
    ----------
    iso : IsoLevel
        Rx(iso)'s running statistics (read by the RF and vision beliefs and the confidence).
    rf : RFBelief
        The belief over the Tx bearing from the radio (``RFFilterBelief``, ``LobeBelief``, or
        ``RFBelief`` for none).
    vision : VisionBelief
        The camera's tracks and POD evidence (``CameraBelief``, or ``VisionBelief`` for none).
    fusion : Fusion
        Hypotheses' posterior and the answer.
    acquisition : Acquisition
        Where to look next.
    confidence : Confidence
        The reported confidence.
    """

    iso: IsoLevel
    rf: RFBelief
    vision: VisionBelief
    fusion: Fusion
    acquisition: Acquisition
    confidence: Confidence


def take_iso(p: Parts, m: StepMeasurement, clock: PacketClock, rf_period_s: float) -> Packets | None:
    """Rx(iso)'s readings of step m into ``p.iso``, each with its time since the episode's start;
    returns the step's packets (protocol 1.3: 0..n per receiver, tag 0's only: 1.4 steps may carry
    other tags' packets), or None for an RSSI pair or a step with no RF evidence (``m.rf`` None
    and no packet: the RF belief is then left as it was)."""
    if m.rf is not None:
        p.iso.add(m.rf.iso_rssi_dbm, int(m.step) * rf_period_s)
        return None
    if not m.advertisements():
        return None
    packets = Packets.of(m, rf_period_s)
    clock.take(packets)
    for when, z, _ in packets.iso:
        p.iso.add(z, when)
    return packets


def update_rf(p: Parts, s: float, m: StepMeasurement, packets: Packets | None) -> None:
    """The RF belief ``p.rf`` after step m at pan s: from its packets (``take_iso``'s) or its pair."""
    if packets is None:
        p.rf.update(s, m.rf, p.iso, p.vision.tracks)
    else:
        p.rf.update_packets(s, packets, p.iso, p.vision.tracks)


class Composition:
    """One episode of a composed policy: create it, call ``first_pan()``, then ``step`` for every
    sample.

    Parameters
    ----------
    first_pan_rad : float
        s_0, where the camera points at the start.
    parts : Parts
        What it believes, fuses, and how it chooses.
    rf_period_s : float
        T_RF: step t starts at t T_RF (an advertisement's time is that plus its offset).
    """

    def __init__(self, first_pan_rad: float, parts: Parts, rf_period_s: float = 0.1) -> None:
        self.parts = parts
        self.rf_period_s = float(rf_period_s)
        self.clock = PacketClock(rf_period_s)  # when the next BLE advertisement is due (packets only)
        self._first_pan = wrapped(first_pan_rad)

    def first_pan(self) -> float:
        """s_0, the pan angle of the first sample."""
        return self._first_pan

    @property
    def tracks(self):
        """The vision belief's ``BearingTracker`` (None without a camera)."""
        return self.parts.vision.tracks

    def step(self, m: StepMeasurement) -> Decision:
        """Take the measurement of step t (``StepMeasurement``; ``m.rf`` None: no RF sample this
        step, the RF belief is left as it was); return s_{t+1} and gamma_hat_t."""
        p = self.parts
        s, t = float(m.pan_rad), int(m.step)
        packets = take_iso(p, m, self.clock, self.rf_period_s)
        if p.vision.sees:
            p.vision.update(s, m.frames)
        update_rf(p, s, m, packets)
        l_tracks, l_missed = p.fusion.beliefs(p.rf, p.vision, p.iso)
        estimate, raw, post = p.fusion.answer(p.rf, l_tracks, l_missed, self._first_pan)
        reward = p.vision.mass_at(s, post) * p.rf.gain_at(s)
        due = self.clock.due(t + 1) if self.clock.last is not None else None
        next_pan, probe = p.acquisition.next_pan(Beliefs(t, p.rf, p.vision, l_tracks, post, due))
        cov = p.confidence.covariates(estimate, p.rf, p.vision, p.iso)
        return Decision(step=t, next_pan_rad=wrapped(next_pan), estimate_rad=wrapped(estimate), reward=reward, probe=probe,
                        confidence=round(p.confidence(raw, cov), 6), raw_confidence=float(raw), tx_walks=cov.tx_walks,
                        noise_correlation=cov.noise_correlation, clutter_density=cov.clutter_density, crowding=cov.crowding)

    def lobe_evidence(self) -> float | None:
        """The RF belief's model check (``RFBelief.lobe_evidence``)."""
        return self.parts.rf.lobe_evidence()

    @property
    def lobe(self) -> str | None:
        """``peak`` or ``dip``: the lobe orientation in use (None without Rx(dir))."""
        return self.parts.rf.lobe
