"""What a policy believes about the Tx's bearing from the radio: the RF belief parts (issue 19).

An RF belief turns the RSSI samples of Rx(iso) and Rx(dir) into l_RF(gamma), a log-likelihood
(or log-posterior) of "the Tx is at bearing gamma" on the pan grid, and into P(the Tx walks).
Three implementations share one interface (``RFBelief``), so a policy swaps one for another:

* ``RFBelief`` itself: no radio (RaViPAS); l_RF is flat.
* ``RFFilterBelief``: the rig says how Rx(dir) responds (paper eq. 6 or the dB-gain model):
  ``RFBearingFilter``, a grid Bayes filter over the Tx bearing with standing and walking motion
  models; it scores camera tracks by their whole trajectories.
* ``LobeBelief``: the response is not known, or only Rx(dir) is heard (RaPAS): ``LobeGP``,
  Rx(dir)'s RSSI over the pan as a GP with a generic lobe basis whose profile log-likelihood is
  the paper's J_RF (eq. 24) without knowing rho, beside ``RecentLobe`` for a walking Tx.

``IsoLevel`` keeps the statistics of Rx(iso) that the RF and vision beliefs both read (the mean
level predicts the Tx's POD, Sec. III-A; its lag-1 correlation tempers the RF evidence).

Every ``update`` accepts a step without an RF sample (``rf=None``: a real BLE receiver often
hears no packet in a step): the belief over the bearing is then left as it was (only the set of
camera tracks it scores follows the camera's).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from ra2vipas.services.controller.circle_gp import LobeGP, RecentLobe
from ra2vipas.services.controller.grid import CircleGrid
from ra2vipas.services.controller.range_cue import RecentStats
from ra2vipas.services.controller.rf_filter import RFBearingFilter, logsumexp


class RFSample(Protocol):
    """One step's RSSI pair (``protocol.measurements.RFSample``): dBm of Rx(iso) and Rx(dir)."""

    iso_rssi_dbm: float
    dir_rssi_dbm: float


Packet = tuple[float, float, "int | None"]
"""One advertisement as the RF beliefs read it: (time [s] since the episode's start, RSSI [dBm],
advertising channel or None)."""


class Packets:
    """One step's advertisements split by receiver, each with its time since the episode's start
    (t T_RF + its offset in the step), in arrival order.

    Attributes
    ----------
    iso, dir : list of Packet
        Rx(iso)'s and Rx(dir)'s packets this step (either may be empty).
    """

    __slots__ = ("iso", "dir")

    def __init__(self, iso: list[Packet], dir_: list[Packet]) -> None:
        self.iso, self.dir = iso, dir_

    @classmethod
    def of(cls, measurement, rf_period_s: float) -> "Packets":
        """The packets of tag 0 in a ``StepMeasurement`` (its ``adverts``) taken at step t."""
        start = int(measurement.step) * float(rf_period_s)
        iso: list[Packet] = []
        dir_: list[Packet] = []
        for a in measurement.advertisements():
            (iso if a.receiver == "iso" else dir_).append((start + float(a.offset_s), float(a.rssi_dbm), a.channel))
        iso.sort(key=lambda p: p[0])
        dir_.sort(key=lambda p: p[0])
        return cls(iso, dir_)


class PacketClock:
    """When Rx(dir)'s next advertisement is due: a BLE beacon advertises every interval I plus a
    random 0-10 ms advDelay (a receiver may lose some). I is the median of the gaps between
    Rx(dir)'s packets (within 5 ms: one event) no longer than 1.3 times the shortest; events then
    come at last + k I. Rx(iso)'s packets are not used: two receivers need not hear the same
    events (a recorded channel's are two recordings).

    Parameters
    ----------
    rf_period_s : float
        T_RF, the step's length.
    slack_s : float
        advDelay's range: an event may come this late.
    """

    def __init__(self, rf_period_s: float, slack_s: float = 0.01) -> None:
        self.period, self.slack = float(rf_period_s), float(slack_s)
        self.last: float | None = None
        self.gaps: list[float] = []

    def take(self, packets: "Packets") -> None:
        """Take a step's packets (their times)."""
        for time_s in sorted(p[0] for p in packets.dir):
            if self.last is not None:
                gap = time_s - self.last
                if gap <= 0.005:
                    continue
                self.gaps.append(gap)
            self.last = time_s

    def interval(self) -> float | None:
        """I, once three gaps are known (None before)."""
        if len(self.gaps) < 3:
            return None
        shortest = min(self.gaps)
        return float(np.median([g for g in self.gaps if g <= 1.3 * shortest]))

    def due(self, step: int) -> bool | None:
        """Whether an event is due in step ``step`` ([step T_RF, (step + 1) T_RF)); None before
        the interval is known."""
        interval = self.interval()
        if interval is None or self.last is None:
            return None
        start = step * self.period
        k = max(math.ceil((start - self.slack - self.last) / interval), 1)
        return self.last + k * interval < start + self.period


class IsoLevel:
    """Running statistics of Rx(iso)'s RSSI: its mean, standard deviation and the lag-1
    correlation of its noise.

    Parameters
    ----------
    default_std_db : float
        The RSSI noise sigma_RF to assume until three samples give an estimate (the POD model's).
    """

    recent_memory_s = 1.0
    """Memory of the recent level (``recent``): a walking Tx's range, and so its level, change."""

    def __init__(self, default_std_db: float) -> None:
        self.default_std_db = float(default_std_db)
        self.n = 0
        self._sum = self._sq = self._diff_sq = 0.0
        self._prev: float | None = None
        self.recent: RecentStats | None = None  # the level's exponentially weighted recent statistics, once a time is given

    def add(self, iso_dbm: float, t: float | None = None) -> None:
        """Take one Rx(iso) sample [dBm], read at time ``t`` [s] since the episode's start (the
        recent level, weighted exp(-(t_now - t)/``recent_memory_s``), needs it)."""
        if t is not None:
            if self.recent is None:
                self.recent = RecentStats(self.recent_memory_s)
            self.recent.add_sums(1.0, iso_dbm, iso_dbm * iso_dbm, t)
        self.n += 1
        self._sum += iso_dbm
        self._sq += iso_dbm**2
        if self._prev is not None:
            self._diff_sq += (iso_dbm - self._prev) ** 2
        self._prev = iso_dbm

    def mean_and_std(self) -> tuple[float, float]:
        """Mean level z_iso and the noise's standard deviation (at least 0.1 dB); needs n >= 1."""
        mean = self._sum / self.n
        var = max(self._sq / self.n - mean * mean, 0.0)
        sigma = math.sqrt(var * self.n / (self.n - 1)) if self.n > 2 else self.default_std_db
        return mean, max(sigma, 0.1)

    def noise_correlation(self) -> float:
        """rho, the lag-1 correlation of the RSSI noise: for AR(1) noise, Var(z_t - z_t-1) =
        2 sigma^2 (1 - rho). A walking Tx's drift reads as correlation, which only makes the RF
        evidence count less. 0 before 10 samples; at most 0.95."""
        if self.n < 10:
            return 0.0
        _, sigma = self.mean_and_std()
        rho = 1.0 - (self._diff_sq / (self.n - 1)) / (2.0 * sigma * sigma)
        return min(max(rho, 0.0), 0.95)


class RFBelief:
    """The RF belief interface, and its "no radio" implementation (l_RF flat, nothing learned).

    Attributes
    ----------
    listens : bool
        Whether it uses Rx(dir) at all (a policy without it never probes).
    exact : bool
        Whether ``log_likelihood`` is a Bayes filter's normalised posterior (the fusion then
        neither tempers it nor mixes standing and walking itself, and scores each camera track
        by ``track_loglik``'s trajectory evidence).
    log_likelihood : ndarray of shape (M,)
        l_RF(gamma) on the pan grid after the last sample.
    tx_walks : float
        P(the Tx walks), from Rx(dir).
    samples : int
        RF samples taken so far.
    """

    listens = False
    exact = False

    def __init__(self, circle: CircleGrid) -> None:
        self.circle = circle
        self.log_likelihood = np.zeros(circle.size)
        self.tx_walks = 0.0
        self.samples = 0

    def update(self, pan_rad: float, rf: RFSample | None, iso: IsoLevel, tracks=None) -> None:
        """Take step t's RF sample, taken at pan ``pan_rad`` (None: no packet this step, the
        belief is unchanged); ``iso`` already holds its Rx(iso) reading, ``tracks`` is the
        camera's ``BearingTracker`` after this step (None without a camera)."""

    def update_packets(self, pan_rad: float, packets: Packets, iso: IsoLevel, tracks=None) -> None:
        """Take step t's BLE advertisements (protocol 1.3; ``Packets``: 0..n per receiver, at
        their times), heard at pan ``pan_rad``; ``iso`` already holds its Rx(iso) packets. A
        belief that cannot read packets takes them as no RF evidence (``update`` with None)."""
        self.update(pan_rad, None, iso, tracks)

    def track_loglik(self, tracks) -> np.ndarray:
        """l_RF of each confirmed camera track, shape (n,)."""
        return np.zeros(len(tracks))

    def gain_at(self, pan_rad: float) -> float:
        """J_RF(s): the normalised antenna response expected at pan s (1: no opinion)."""
        return 1.0

    def gain_prediction(self) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(mean, sd, A, c) of Rx(dir)'s predicted reading over the grid of pans: J_RF(s) =
        (mean - c) / A, its uncertainty sd / |A| (A = 0: no opinion)."""
        flat = np.zeros(self.circle.size)
        return flat, flat, 0.0, 0.0

    def informative_pan(self) -> float | None:
        """The pan whose next Rx(dir) sample says most about gamma, if this belief can tell."""
        return None

    def lobe_evidence(self) -> float | None:
        """log-likelihood ratio of the lobe orientation in use against the opposite one (None
        without Rx(dir) samples)."""
        return None

    @property
    def lobe(self) -> str | None:
        """``peak`` or ``dip``: the lobe orientation in use (None without Rx(dir))."""
        return None


def lobe_gp(circle: CircleGrid, steps: int, noise_db: float, noise_correlation: float, lobe_sign: int,
            lobe_width_rad: float = 1.0, residual_length_scale_rad: float = 0.5, residual_std_db: float = 3.0) -> LobeGP:
    """The generic lobe GP of an episode: white noise of std sigma sqrt(1 - rho^2) (the AR(1)
    innovation's, at least 0.1 dB), room for ``steps`` samples."""
    white = max(noise_db * math.sqrt(1.0 - noise_correlation**2), 0.1)
    return LobeGP(circle, noise_var=white**2, lobe_width=lobe_width_rad, lobe_sign=lobe_sign,
                  residual_length_scale=residual_length_scale_rad, residual_var=residual_std_db**2, capacity=max(steps, 1))


def _lobe_evidence(gp: LobeGP) -> float | None:
    if gp.n_ == 0:
        return None
    used = float(gp.lobe_fit()[0].max())
    return used - float(gp.lobe_fit(-gp.lobe_sign)[0].max())


class LobeBelief(RFBelief):
    """l_RF from the generic lobe: ``LobeGP`` over every sample ("the Tx stands") mixed with
    ``RecentLobe`` over the recent ones ("the Tx walks").

    Parameters
    ----------
    gp : LobeGP
        The all-sample lobe fit (``lobe_gp``).
    recent : RecentLobe
        The recent-samples lobe fit (its ``forget`` is the memory).
    learn_lobe : bool
        The Rx(dir) response is unknown: the lobe's orientation (a peak, or the paper's dip) is
        learned from the data, step by step.
    ar1 : bool
        The standing lobe's noise is AR(1) with rho from Rx(iso), rather than white with its
        evidence scaled by (1 - rho) / (1 + rho).
    walk_prior : float
        Prior probability that the Tx walks.
    walk_penalty : float
        Nats the recent lobe must gain to count as motion.
    """

    listens = True

    def __init__(self, gp: LobeGP, recent: RecentLobe, learn_lobe: bool = False, ar1: bool = True, walk_prior: float = 0.3,
                 walk_penalty: float = 2.0) -> None:
        super().__init__(gp.circle)
        self.gp, self.recent = gp, recent
        self.learn_lobe, self.ar1 = learn_lobe, ar1
        self.walk_prior, self.walk_penalty = walk_prior, walk_penalty
        self.fit: tuple[int, float, float] | None = None  # the best standing lobe: centre index, amplitude A, offset c

    def update(self, pan_rad, rf, iso, tracks=None) -> None:
        if rf is None:  # l_RF and P(walks) unchanged; the tracks it follows are the camera's now
            if tracks is not None and self.samples:
                self.recent.follow_tracks(tracks.ids.tolist(), tracks.bearing.tolist())
            return
        self._take(pan_rad, (rf.dir_rssi_dbm,), iso, tracks)

    def update_packets(self, pan_rad, packets, iso, tracks=None) -> None:
        """Each Rx(dir) packet is one sample of the lobe at the step's pan (its channel offset and
        spread are the lobe's white noise and residual); no Rx(dir) packet: as ``rf=None``."""
        if not packets.dir:
            self.update(pan_rad, None, iso, tracks)
            return
        self._take(pan_rad, tuple(z for _, z, _ in packets.dir), iso, tracks)

    def _take(self, pan_rad: float, dir_dbm: tuple[float, ...], iso: IsoLevel, tracks) -> None:
        self.samples += 1
        if self.ar1:  # in steps of 0.05: each change refits the samples so far
            self.gp.set_noise_correlation(round(iso.noise_correlation() * 20.0) / 20.0)
        if self.gp.n_ + len(dir_dbm) > self.gp.capacity:  # packets: more than one sample a step
            self.gp.capacity = self.gp.n_ + len(dir_dbm) + self.gp.capacity
        for z in dir_dbm:
            self.gp.add(pan_rad, z)
            self.recent.add(pan_rad, z)
        if self.learn_lobe:
            self._learn_lobe()
        if tracks is not None:
            self.recent.follow(tracks.ids.tolist(), tracks.bearing.tolist())
        l_static, amplitude, offset = self.gp.lobe_fit()
        best = int(np.argmax(l_static))
        self.fit = (best, float(amplitude[best]), float(offset[best]))
        self.log_likelihood = self._mixture(l_static, best, iso)

    def _mixture(self, l_static: np.ndarray, best: int, iso: IsoLevel) -> np.ndarray:
        """l_RF over the lobe centre now: a mixture of "the Tx stands" (the lobe fitted to every
        sample) and "the Tx walks" (the lobe fitted to recent samples), weighted by how much
        better the recent samples fit a lobe elsewhere than where all samples put it (a
        generalised likelihood ratio, less a penalty for the freedom to move). Both are scaled by
        (1 - rho) / (1 + rho), the share of independent information in AR(1) noise, and
        normalised over the circle (so a track's walking score is on the same footing)."""
        rho = iso.noise_correlation()
        self._kappa = kappa = (1.0 - rho) / (1.0 + rho)
        l_recent = self.recent.profile()
        moved = float(l_recent.max() - l_recent[best]) * kappa
        prior = self.walk_prior
        logit = math.log(prior / (1.0 - prior)) + moved - self.walk_penalty
        self.tx_walks = 1.0 / (1.0 + math.exp(-min(max(logit, -50.0), 50.0)))
        stand = l_static if self.ar1 else kappa * l_static  # an AR(1) lobe fit has the correlation in it
        walk = kappa * l_recent
        self._stand_rf = stand - logsumexp(stand)
        self._walk_norm = logsumexp(walk)
        walk = walk - self._walk_norm
        self._log_stand, self._log_walk = math.log(max(1.0 - self.tx_walks, 1e-300)), math.log(max(self.tx_walks, 1e-300))
        return np.logaddexp(self._log_stand + self._stand_rf, self._log_walk + walk)

    def track_loglik(self, tracks) -> np.ndarray:
        """Each track standing where it is (the all-sample lobe at its bearing), or walking as the
        track did (the recent lobe along its trajectory), mixed as in ``_mixture``."""
        if self.fit is None:
            return np.zeros(len(tracks))
        stand = self.circle.interp(self._stand_rf, tracks.bearing)
        walk = self._kappa * self.recent.follow_profile(tracks.ids.tolist()) - self._walk_norm
        return np.logaddexp(self._log_stand + stand, self._log_walk + walk)

    def gain_at(self, pan_rad: float) -> float:
        """The normalised posterior mean of the best standing lobe at s."""
        if self.fit is None or self.fit[1] == 0.0:
            return 1.0
        j, A, c = self.fit
        return (self.gp.mean_at(pan_rad, j, A, c) - c) / A

    def gain_prediction(self):
        """The standing lobe's GP posterior; a walking Tx's mean is the recent lobe."""
        if self.fit is None:
            return super().gain_prediction()
        j, A, c = self.fit
        mean, sd = self.gp.posterior(j, A, c)
        if self.tx_walks > 0.5:  # a walking Tx is where the recent samples put it
            mean = self.recent.mean()
            _, A, c = self.recent.best_
        return mean, sd, A, c

    def lobe_evidence(self) -> float | None:
        """The best profile likelihood over the lobe centre (``LobeGP.lobe_fit``) with the
        amplitude's sign as used, minus the same with the sign flipped, over every Rx(dir) sample:
        strongly negative when the directional RSSI contradicts the assumed antenna model."""
        return _lobe_evidence(self.gp)

    @property
    def lobe(self) -> str:
        return "peak" if self.gp.lobe_sign > 0 else "dip"

    def _learn_lobe(self) -> None:
        """Use the lobe orientation the samples so far support best (the larger maximised profile
        likelihood of the two signs of A, a generalised likelihood ratio with the same number of
        parameters on both sides). Both lobe fits keep sufficient statistics that do not depend on
        the sign, so switching costs nothing but the next profile."""
        evidence = self.lobe_evidence()
        if evidence is not None and evidence < 0.0:
            self.gp.lobe_sign = -self.gp.lobe_sign
            self.recent.lobe_sign = self.gp.lobe_sign


class RFFilterBelief(RFBelief):
    """l_RF from ``RFBearingFilter``, the grid Bayes filter over the Tx bearing that knows the
    rig's Rx(dir) response (each sample scored by it, the level read from Rx(iso): the same
    channel, eq. 5).

    Parameters
    ----------
    rff : RFBearingFilter
        The filter.
    check : LobeGP
        A generic lobe fitted to the same samples once asked (``lobe_evidence``: the model check
        that the assumed response is the rig's).
    walk_prior_from_tracks : bool
        P(the Tx walks) a priori = the share of camera tracks seen walking (the Tx is one of
        the targets), shrunk towards ``walk_prior``.
    walk_prior : float
        Prior probability that the Tx walks.
    rate_walkers : int
        On packets, the walking model gets its bearing rate (``PacketBearingFilter.engage_rates``)
        once the camera has seen this many people walk (0: never).
    """

    listens = True
    exact = True

    def __init__(self, rff: RFBearingFilter, check: LobeGP, walk_prior_from_tracks: bool = True, walk_prior: float = 0.3,
                 rate_walkers: int = 0) -> None:
        super().__init__(rff.circle)
        self.rff, self.check = rff, check
        self.rate_walkers = int(rate_walkers)
        self.walk_prior_from_tracks, self.walk_prior = walk_prior_from_tracks, walk_prior
        self._dir_samples: list[tuple[float, float]] = []

    def update(self, pan_rad, rf, iso, tracks=None) -> None:
        if rf is None:  # the posterior unchanged; the tracks it follows are the camera's now
            if tracks is not None:
                means, _, weights = tracks.components()
                self.rff.follow_tracks(tracks.ids.tolist(), means, weights)
            return
        self.samples += 1
        self._dir_samples.append((pan_rad, rf.dir_rssi_dbm))  # for the lobe's model check, fitted once asked
        self.rff.add(pan_rad, rf.iso_rssi_dbm, rf.dir_rssi_dbm)
        self._after_sample(tracks)

    def _after_sample(self, tracks) -> None:
        if tracks is not None:
            if self.rate_walkers and not getattr(self.rff, "rates_engaged", True) and self.rff.packets \
                    and tracks.walkers_seen() >= self.rate_walkers:
                self.rff.engage_rates()  # packets, and the camera has seen people walk: a walking Tx has a bearing rate
            if self.walk_prior_from_tracks:  # the Tx is one of the targets: it walks as often as they do
                self.rff.walk_prior = min(max(tracks.walking_share(self.walk_prior), 0.01), 0.99)
            self.rff.follow(tracks.ids.tolist(), *tracks.components())
        self.log_likelihood = self.rff.log_posterior()
        self.tx_walks = self.rff.p_walk

    def update_packets(self, pan_rad, packets, iso, tracks=None) -> None:
        """The filter's packet likelihood (``PacketBearingFilter.add_packets``: one term per
        Rx(dir) packet, channel offsets marginalised, irregular times); a step whose packets do
        not move the bearing (no Rx(dir) packet) is as ``rf=None``."""
        if not hasattr(self.rff, "add_packets"):
            raise TypeError("this RF filter reads the 1.0 pair only; build it as a PacketBearingFilter to read adverts")
        self._dir_samples.extend((pan_rad, z) for _, z, _ in packets.dir)
        if not self.rff.add_packets(pan_rad, packets.iso, packets.dir):
            self.update(pan_rad, None, iso, tracks)
            return
        self.samples += 1
        self._after_sample(tracks)

    def track_loglik(self, tracks) -> np.ndarray:
        """Each track's trajectory evidence, on the footing of ``log_likelihood`` (the normalised
        posterior of the Tx's bearing)."""
        return self.rff.track_evidence(tracks.ids.tolist(), less=self.rff._joint()[1])

    def gain_at(self, pan_rad: float) -> float:
        """The antenna gain expected at s under the filter's posterior of gamma."""
        return float(self.rff.response.gain_over(pan_rad, self.circle) @ self.rff.posterior())

    def gain_prediction(self):
        mean, sd = self.rff.predicted_gain()
        return mean, sd, 1.0, 0.0

    def informative_pan(self) -> float:
        return self.rff.most_informative_pan()

    def lobe_evidence(self) -> float | None:
        if self._dir_samples:  # fit the generic lobe to the filter's samples now, once (in one pass)
            self.check.extend([s for s, _ in self._dir_samples], [z for _, z in self._dir_samples])
            self._dir_samples.clear()
        return _lobe_evidence(self.check)

    @property
    def lobe(self) -> str:
        return "peak" if self.check.lobe_sign > 0 else "dip"
