"""The recorded channel (``radio: recorded``; issue 20, docs/radio.md): each receiver's packets,
which arrive, when and at what whole-dBm RSSI, drawn from real recordings rather than a formula.

Per test (all draws from the test's ``radio`` stream, at the start): Rx(iso) and Rx(dir) each
become one of the channel file's receivers, two different ones (so Rx(dir) is "a recording of
its own"), the platform standing where that receiver stood, the scene turned by a random angle
about it. At step t the Tx at p_t (range d_t) is heard through the recording, of that receiver,
whose beacon stood at the matching distance (|distance - d_t|, in metres) and nearest the place
p_t maps to in the real building (a quarter of that distance counts): as the Tx walks, the
recordings change with the real map's spatial shadowing. Each receiver reads its recordings
from a random time on, continuously: the packets of step t are those recorded in
[c + t T_RF, c + (t + 1) T_RF) (wrapping round the recording). Rx(dir) adds the antenna's
response, Rx(dir)'s level minus Rx(iso)'s (a gain in dB under ``db-gain``), rounded to
``rssi_step_db``; a packet it pushes below the weakest RSSI the file holds is lost.
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.protocol.measurements import Advertisement
from ra2vipas.services.protocol.scenario import Scenario
from ra2vipas.services.sensors import channel_file
from ra2vipas.services.sensors.radio import RECEIVERS, _new_advert, quantise

POSITION_WEIGHT = 0.25
"""Metres of distance mismatch one metre of position mismatch costs when a recording is chosen."""


class RecordedSchedule:
    """One test's packets from a recorded channel (same interface as ``radio.PacketSchedule``)."""

    tag = 0  # protocol 1.4: which tag's packets these are, and its address (None: not reported)
    address: str | None = None

    def __init__(self, sc: Scenario, rng: np.random.Generator, tx_path_m: np.ndarray, receivers: int = 2,
                 rx: np.ndarray | None = None, turn_rad: float | None = None) -> None:
        self.scenario = sc
        self.channel = ch = channel_file.by_name(sc.radio_channel)
        path = np.asarray(tx_path_m, dtype=float).reshape(-1, 2)
        self.steps = path.shape[0]
        self.period = sc.rf_period_s
        n_rx = ch.rx_pos.shape[0]
        # the receivers and the scene's turn are the rig's: another tag (protocol 1.4) shares tag 0's
        self.rx = rng.choice(n_rx, size=receivers, replace=n_rx < receivers) if rx is None else np.asarray(rx)
        self.turn_rad = turn = rng.uniform(-math.pi, math.pi) if turn_rad is None else float(turn_rad)
        rot = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        self.cursor = rng.uniform(0.0, 1.0, size=receivers)  # fraction of the first recording's length
        dist = ch.distances_m()
        ranges = np.hypot(path[:, 0], path[:, 1])
        self.recording = np.empty((receivers, self.steps), dtype=np.int64)
        for r, rx in enumerate(self.rx):
            mine = np.flatnonzero(ch.rec_receiver == rx)
            if mine.size == 0:
                raise channel_file.ChannelFileError(f"channel {sc.radio_channel!r}: receiver {rx} has no recording")
            real = ch.rx_pos[rx, :2] + path @ rot.T  # (T, 2) where the Tx stands in the real building
            cost = np.abs(dist[mine][None, :] - ranges[:, None]) + POSITION_WEIGHT * np.linalg.norm(
                ch.rec_point[mine][None, :, :2] - real[:, None, :], axis=2)
            self.recording[r] = mine[np.argmin(cost, axis=1)]
        self._times = {int(m): ch.times_s(int(m)) for m in np.unique(self.recording)}
        self._rssi = {int(m): ch.rssi_of(int(m)) for m in self._times}
        self._start = [float(self.cursor[r]) * float(ch.rec_seconds[self.recording[r, 0]]) for r in range(receivers)]
        self.floor_dbm = float(ch.meta.get("sensitivity_dbm", -128))

    def packets(self, step: int, levels_dbm: tuple[float, ...]) -> tuple[Advertisement, ...]:
        """The advertisements of step ``step`` (in arrival order); ``levels_dbm`` are the
        noiseless levels the formula would give, used only for Rx(dir)'s antenna response."""
        sc = self.scenario
        t = min(step, self.steps - 1)
        out = []
        for r in range(self.recording.shape[0]):
            m = int(self.recording[r, t])
            times, rssi = self._times[m], self._rssi[m]
            length = float(self.channel.rec_seconds[m])
            lo = (self._start[r] + step * self.period) % length
            gain = 0.0 if r == 0 else float(levels_dbm[r] - levels_dbm[0])
            for shift, a, b in ((0.0, lo, lo + self.period), (length, lo - length, lo + self.period - length)):
                if b <= 0.0:
                    continue
                i, j = np.searchsorted(times, [max(a, 0.0), b])
                for k in range(int(i), int(j)):
                    value = float(quantise(sc, rssi[k] + gain)) if gain else float(rssi[k])
                    if value < self.floor_dbm:
                        continue
                    out.append((times[k] + shift - lo, RECEIVERS[r], value))
        out.sort()
        return tuple(_new_advert(rx, min(max(v, -200.0), 50.0), None, max(0.0, float(off)), self.tag, self.address) for off, rx, v in out)
