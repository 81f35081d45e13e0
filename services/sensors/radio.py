"""Real radios in the simulator (issue 20; docs/radio.md): BLE advertisements instead of the
paper's one RSSI pair per T_RF.

The beacon (the Tx) advertises every ``adv_interval_s`` plus BLE's random advDelay, uniform in
[0, ``adv_delay_max_s``] (Bluetooth Core Spec. Vol 6 Part B 4.4.2.2.1), on the three advertising
channels 37, 38, 39. Each receiver listens on one channel at a time, 37 -> 38 -> 39 in turn,
``scan_interval_s`` on each, from a random phase: of every advertising event it hears at most
the packet on its channel, and misses it with probability ``packet_loss_{iso,dir}`` or when the
RSSI would be below ``rx_sensitivity_dbm``. A heard packet's RSSI is the noiseless level (path
loss, shadowing and, for Rx(dir), the antenna's response at the pan of the step it arrives in)
plus the receiver's offset on that channel (N(0, ``channel_offset_db``^2), drawn once per test:
frequency-selective fading) plus the per-packet spread (N(0, ``rf_noise_db``^2); AR(1) over the
packets' irregular times with correlation exp(-dt/``fading_corr_s``) when that is > 0), reported
quantised to ``rssi_step_db``.

Every random number of a test is drawn when it starts, from the test's own ``radio`` stream
(``world.Streams``), whatever the pans: event times, scan phases, channel offsets, losses and
noise. A step's packets are the events in [t T_RF, (t+1) T_RF), with their time offsets in it.
Pure numpy; the truth (which events were lost, the noiseless levels) stays here.
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.measurements import Advertisement
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.sensors import physics

_new_advert = builder(Advertisement, "receiver", "rssi_dbm", "channel", "offset_s", "tag", "address")  # model_construct, cheaper

RECEIVERS = ("iso", "dir")
CHANNELS = (37, 38, 39)


def advertising_times(sc: Scenario, rng: np.random.Generator, duration_s: float) -> np.ndarray:
    """The beacon's advertising events in [0, duration): the first at a uniform phase in
    [0, T_adv), then every T_adv + advDelay, advDelay ~ U(0, adv_delay_max_s)."""
    mean = sc.adv_interval_s + 0.5 * sc.adv_delay_max_s
    n = int(math.ceil(duration_s / mean * 1.2)) + 8
    gaps = sc.adv_interval_s + rng.uniform(0.0, sc.adv_delay_max_s, size=n)
    t = rng.uniform(0.0, sc.adv_interval_s) + np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    while t[-1] < duration_s:  # never in practice (20 % margin); kept for tiny intervals
        more = sc.adv_interval_s + rng.uniform(0.0, sc.adv_delay_max_s, size=n)
        t = np.concatenate([t, t[-1] + np.cumsum(more)])
    return t[t < duration_s]


def scan_channels(sc: Scenario, phase_s: float, times_s: np.ndarray) -> np.ndarray:
    """The channel a receiver whose scan started ``phase_s`` before t = 0 listens on at each time."""
    k = np.floor((np.asarray(times_s) + phase_s) / sc.scan_interval_s).astype(np.int64)
    return np.asarray(CHANNELS)[k % 3]


def irregular_ar1(innovations: np.ndarray, times_s: np.ndarray, tau_s: float) -> np.ndarray:
    """A stationary AR(1) sampled at irregular ``times_s``: x_0 = e_0,
    x_k = phi_k x_{k-1} + sqrt(1 - phi_k^2) e_k, phi_k = exp(-(t_k - t_{k-1}) / tau)
    (an Ornstein-Uhlenbeck process seen at those times); white when tau = 0."""
    e = np.asarray(innovations, dtype=float)
    if tau_s <= 0.0 or e.size == 0:
        return e.copy()
    phi = np.exp(-np.diff(times_s) / tau_s)
    x = np.empty_like(e)
    x[0] = e[0]
    for k in range(1, e.size):
        x[k] = phi[k - 1] * x[k - 1] + math.sqrt(1.0 - phi[k - 1] ** 2) * e[k]
    return x


def quantise(sc: Scenario, rssi_dbm: np.ndarray) -> np.ndarray:
    """RSSI as reported: ``rssi_step_db`` * round(RSSI / step) (halves up); unchanged when the step is 0."""
    if sc.rssi_step_db <= 0.0:
        return np.asarray(rssi_dbm, dtype=float)
    return sc.rssi_step_db * np.floor(np.asarray(rssi_dbm, dtype=float) / sc.rssi_step_db + 0.5)


class PacketSchedule:
    """One test's advertisements as each receiver would hear them, drawn at once.

    ``times_s`` (K,) the advertising events; per receiver r (0 iso, 1 dir): ``channel[r]`` the
    channel it hears each event on, ``heard[r]`` whether the packet survives the loss,
    ``offset_db[r]`` its channel offset plus per-packet spread (before the level is added,
    before quantisation and sensitivity); ``first[t]`` the first event of step t.
    """

    tag = 0  # protocol 1.4: which tag's packets these are, and its address (None: not reported)
    address: str | None = None

    def __init__(self, sc: Scenario, rng: np.random.Generator, steps: int, receivers: int = 2,
                 scan_phases_s: np.ndarray | None = None) -> None:
        self.scenario = sc
        period = sc.rf_period_s
        self.times_s = advertising_times(sc, rng, steps * period)
        k = self.times_s.size
        # the receivers' scan phases are the rig's: another tag's schedule (protocol 1.4) shares tag 0's
        phases = rng.uniform(0.0, 3.0 * sc.scan_interval_s, size=receivers) if scan_phases_s is None else np.asarray(scan_phases_s)
        self.scan_phases_s = phases
        offsets = rng.normal(0.0, sc.channel_offset_db, size=(receivers, 3))
        self.channel_offsets_db = offsets  # truth: receiver r's offset on channel 37 + c
        loss = np.array([sc.packet_loss_iso, sc.packet_loss_dir][:receivers])
        self.heard = rng.random((receivers, k)) >= loss[:, None]
        spread = rng.normal(0.0, sc.rf_noise_db, size=(receivers, k))
        self.channel = np.stack([scan_channels(sc, phases[r], self.times_s) for r in range(receivers)])
        self.offset_db = np.stack([offsets[r, self.channel[r] - 37] + irregular_ar1(spread[r], self.times_s, sc.fading_corr_s)
                                   for r in range(receivers)])
        self.step_of = np.minimum((self.times_s / period).astype(np.int64), steps - 1)
        self.first = np.searchsorted(self.step_of, np.arange(steps + 1))
        self.period = period

    def events(self, step: int) -> range:
        return range(int(self.first[step]), int(self.first[step + 1]))

    def packets(self, step: int, levels_dbm: tuple[float, ...]) -> tuple[Advertisement, ...]:
        """The advertisements of step ``step``, in arrival order, when receiver r's noiseless
        level during the step is ``levels_dbm[r]``."""
        sc = self.scenario
        out = []
        start = step * self.period
        for k in self.events(step):
            for r, level in enumerate(levels_dbm):
                if not self.heard[r, k]:
                    continue
                rssi = float(quantise(sc, level + self.offset_db[r, k]))
                if rssi < sc.rx_sensitivity_dbm:
                    continue
                out.append(_new_advert(RECEIVERS[r], min(max(rssi, -200.0), 50.0), int(self.channel[r, k]),
                                       max(0.0, float(self.times_s[k] - start)), self.tag, self.address))
        return tuple(out)


def step_levels(sc: Scenario, iso_mean_dbm: float, pan_rad: float, tx_bearing_rad: float) -> tuple[float, float]:
    """The noiseless (iso, dir) levels of a step: g(d) + S at the Tx, and Rx(dir)'s response at the pan."""
    return iso_mean_dbm, physics.directional_rssi_scalar(sc, iso_mean_dbm, pan_rad - tx_bearing_rad)


# -- boxes with a size -------------------------------------------------------------------------

def angular_height(sc: Scenario, height_m: np.ndarray | float, range_m: np.ndarray | float) -> np.ndarray:
    """The angle a standing target of height H at horizontal range d spans in a camera whose
    axis is ``camera_height_m`` above the floor: atan((H - h_c)/d) + atan(h_c/d) [rad]."""
    d = np.maximum(np.asarray(range_m, dtype=float), 1e-3)
    h = np.asarray(height_m, dtype=float)
    return np.arctan((h - sc.camera_height_m) / d) + np.arctan(sc.camera_height_m / d)


def noisy_heights(sc: Scenario, rng: np.random.Generator, true_rad: np.ndarray) -> np.ndarray:
    """Measured angular heights: the true ones times (1 + N(0, box_height_noise^2)), kept in (0, pi)."""
    noisy = true_rad * (1.0 + rng.normal(0.0, sc.box_height_noise, size=np.shape(true_rad)))
    return np.clip(noisy, 1e-4, math.pi - 1e-3)


def clutter_heights(sc: Scenario, rng: np.random.Generator, count: int) -> np.ndarray:
    """Plausible heights of ``count`` false boxes: a person-sized thing (height as the targets')
    at a range uniform between ``min_target_range_m`` and the arena's corner."""
    h = rng.uniform(sc.target_height_min_m, sc.target_height_max_m, size=count)
    d = rng.uniform(max(sc.min_target_range_m, 0.3), sc.arena_half_width_m * math.sqrt(2.0), size=count)
    return noisy_heights(sc, rng, angular_height(sc, h, d))
