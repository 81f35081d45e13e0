"""Box heights as a range cue (issue 20): range from the box against range from the RSSI.

A detector's box spans the angle h a person of height H subtends at horizontal range d. With the
camera's axis at about half the person's height, h = 2 atan(H / (2 d)), so

    d = H / (2 tan(h / 2)),     log10 d = log10 H - log10(2 tan(h / 2))            (1)

(with the axis at h_c instead, h = atan((H - h_c)/d) + atan(h_c/d); for H = 1.7 m, h_c = 1 m the
range from (1) is within 1.5 % of the true one beyond 1 m, far inside the height prior's spread).
The person's height is not known: a public prior, uniform over [1.5, 1.9] m (adults standing;
``ControllerSettings.person_height_m``), gives log10 H its mean m_H and variance v_H.

Rx(iso) reads the Tx through the log-distance path loss with log-normal shadowing (paper eq. 5):

    z_iso = kappa - 10 n log10(d / delta) + S + v,   S ~ N(0, sigma_S^2),  v ~ N(0, sigma_RF^2)   (2)

so if track i is the Tx, the level Rx(iso) reads, averaged over the time the track's boxes were
averaged, is Gaussian about the level its boxes predict:

    z_bar ~ N(mu_i, s_i^2),  mu_i = kappa - 10 n (m_H - y_i - log10 delta),
    s_i^2 = sigma_S^2 + floor^2 + Var(z_bar) + (10 n)^2 (v_H + Var(y_i))                    (3)

with y_i the mean of log10(2 tan(h/2)) over the track's boxes. ``RangeCue.log_likelihood`` is
log N(z_bar; mu_i, s_i^2) per track, less the log of its mean over the tracks scored (a log Bayes
factor against "the Tx's range is a detected target's at random"): a track whose box range agrees
with the RSSI's range is more likely the Tx. kappa, n, delta and sigma_S are the campaign's public propagation model (the
scenario's path-loss parameters, ``RangeModel.from_scenario``: what the operator configured,
never what the world drew); ``floor`` is the model's misfit (a recorded channel is not (2)).

A standing track is scored with every box it got and the whole episode's mean level; a walking
one (its range changes) with its boxes of the last ``walk_memory_s`` and the level of the last
``IsoLevel.recent_memory_s`` (both 1 s), exponentially weighted at their times, so that both sides
describe the same stretch of the walk.

Measured, the cue does not raise the discovery rate on the worlds we simulate (4 dB of shadowing
moves the likelihood of a 1.5x range ratio by ~0.3 nats; docs/radio.md), so the built-ins leave it
off (``ControllerSettings.height_cue``; ``heights_policy.Ra2ViPASHeights`` turns it on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LOG10_2 = math.log10(2.0)


@dataclass(frozen=True)
class RangeModel:
    """The public propagation model eq. (2) reads the level through, and its spread.

    Attributes
    ----------
    ref_dbm : float
        kappa, the RSSI at the reference distance [dBm].
    exponent : float
        n, the path-loss exponent.
    ref_distance_m : float
        delta, the reference distance [m].
    shadowing_db : float
        sigma_S, the log-normal shadowing's standard deviation [dB].
    """

    ref_dbm: float
    exponent: float
    ref_distance_m: float = 1.0
    shadowing_db: float = 0.0

    @classmethod
    def from_scenario(cls, scenario) -> "RangeModel":
        """The model a campaign's public scenario configures (a ``Scenario`` or its dump)."""
        get = scenario.get if isinstance(scenario, dict) else (lambda name, default=None: getattr(scenario, name, default))
        return cls(ref_dbm=float(get("path_loss_ref_dbm", -30.0)), exponent=float(get("path_loss_exponent", 2.0)),
                   ref_distance_m=float(get("path_loss_ref_distance_m", 1.0)), shadowing_db=float(get("shadowing_db", 0.0)))

    def level_dbm(self, log10_range: np.ndarray | float) -> np.ndarray | float:
        """kappa - 10 n log10(d / delta): the mean level eq. (2) predicts at log10 d."""
        return self.ref_dbm - 10.0 * self.exponent * (log10_range - math.log10(self.ref_distance_m))


def log10_span(heights_rad: np.ndarray) -> np.ndarray:
    """log10(2 tan(h / 2)) of angular heights h [rad] (eq. 1: log10 d = log10 H minus this)."""
    return LOG10_2 + np.log10(np.tan(0.5 * np.clip(heights_rad, 1e-6, 3.1)))


def height_prior(low_m: float, high_m: float) -> tuple[float, float]:
    """(m_H, v_H): the mean and variance of log10 H for H uniform on [low, high] (closed form:
    E[ln H] = (b ln b - a ln a)/(b - a) - 1, E[ln^2 H] likewise)."""
    a, b = float(low_m), float(high_m)
    if b - a < 1e-9:
        return math.log10(a), 0.0
    la, lb = math.log(a), math.log(b)
    m1 = (b * lb - a * la) / (b - a) - 1.0
    m2 = (b * (lb * lb - 2.0 * lb + 2.0) - a * (la * la - 2.0 * la + 2.0)) / (b - a)
    ln10 = math.log(10.0)
    return m1 / ln10, max(m2 - m1 * m1, 0.0) / ln10**2


class RecentStats:
    """Exponentially weighted sums of a value at irregular times: weight exp(-(t_now - t_k)/tau)
    (tau = inf: plain sums), with the sum of squared weights for the mean's effective count."""

    __slots__ = ("tau", "t", "w", "w2", "s", "s2")

    def __init__(self, tau: float) -> None:
        self.tau = tau
        self.t = None
        self.w = self.w2 = self.s = self.s2 = 0.0

    def add(self, values: np.ndarray | list[float], t: float) -> None:
        """Take ``values`` read at time ``t`` [s]."""
        self.add_sums(len(values), float(sum(values)), float(sum(v * v for v in values)), t)

    def add_sums(self, count: float, total: float, squares: float, t: float) -> None:
        """Take ``count`` values read at time ``t`` [s], given by their sum and sum of squares."""
        if self.t is not None and t > self.t and math.isfinite(self.tau):
            f = math.exp(-(t - self.t) / self.tau)
            self.w *= f
            self.w2 *= f * f
            self.s *= f
            self.s2 *= f
        self.t = t if self.t is None else max(self.t, t)
        self.w += count
        self.w2 += count
        self.s += total
        self.s2 += squares

    def mean_var(self) -> tuple[float, float, float]:
        """(weighted mean, weighted variance of the values, effective count (sum w)^2 / sum w^2)."""
        m = self.s / self.w
        return m, max(self.s2 / self.w - m * m, 0.0), self.w * self.w / max(self.w2, 1e-12)


class RangeCue:
    """Per camera track, the range its boxes' heights give, scored against the Tx's level on
    Rx(iso) (module docstring, eqs. 1-3).

    Parameters
    ----------
    model : RangeModel
        The public propagation model (eq. 2).
    person_height_m : (float, float)
        The public prior of a person's height, uniform on [low, high] [m].
    box_bearing_noise_rad : float
        The detector's bearing noise: a box joins the nearest track within ``gate_sigmas`` of it
        (at least 1 degree).
    walk_memory_s : float
        A walking track's (and the level's) memory.
    floor_db : float
        The model's misfit, added in quadrature to the spread.
    span_floor : float
        Least standard deviation of a track's mean log10 span (the boxes' noise may be correlated).
    weight : float
        Tempering of the log-likelihood (the POD evidence reads the same level: not independent).
    """

    def __init__(self, model: RangeModel, person_height_m: tuple[float, float] = (1.5, 1.9), box_bearing_noise_rad: float = 0.0,
                 walk_memory_s: float = 1.0, floor_db: float = 2.0, span_floor: float = 0.005, weight: float = 1.0,
                 gate_sigmas: float = 3.0) -> None:
        self.model = model
        self.m_h, self.v_h = height_prior(*person_height_m)
        self.gate = max(gate_sigmas * box_bearing_noise_rad, math.radians(1.0))
        self.walk_memory_s, self.floor_db, self.span_floor, self.weight = walk_memory_s, floor_db, span_floor, weight
        # per track id (stable, never reused), rows of (sum w, sum w^2, sum w y, sum w y^2): every box, and the recent
        # boxes weighted exp(-(t_now - t)/walk_memory_s)
        self._all = np.zeros((64, 4))
        self._recent = np.zeros((64, 4))
        self._t: float | None = None
        self.boxes = 0  # boxes with a height taken

    def update(self, pan_rad: float, frames, tracks, t: float) -> None:
        """Take step t's frames (after the tracker took them): each box with a height joins the
        nearest confirmed track within the gate, its log10 span to the track's statistics."""
        if not len(tracks):
            return
        counts = [len(h) if len(h) == len(f.box_bearings_rad) else 0 for f in frames for h in (getattr(f, "box_heights_rad", ()),)]
        total = sum(counts)
        if not total:
            return
        rel = np.fromiter((b for f, c in zip(frames, counts) if c for b in f.box_bearings_rad), dtype=float, count=total)
        heights = np.fromiter((h for f, c in zip(frames, counts) if c for h in f.box_heights_rad), dtype=float, count=total)
        bearings = tracks.bearing
        gaps = np.abs((pan_rad + rel[:, None] - bearings[None, :] + math.pi) % (2.0 * math.pi) - math.pi)
        nearest = np.argmin(gaps, axis=1)
        ok = gaps[np.arange(total), nearest] <= self.gate
        if self._t is not None and t > self._t and math.isfinite(self.walk_memory_s):
            f = math.exp(-(t - self._t) / self.walk_memory_s)
            self._recent *= np.array([f, f * f, f, f])
        self._t = t if self._t is None else max(self._t, t)
        if not ok.any():
            return
        spans = log10_span(heights[ok])
        rows = tracks.ids[nearest[ok]]
        if int(rows.max()) >= self._all.shape[0]:
            grow = max(int(rows.max()) + 1, 2 * self._all.shape[0])
            self._all = np.vstack([self._all, np.zeros((grow - self._all.shape[0], 4))])
            self._recent = np.vstack([self._recent, np.zeros((grow - self._recent.shape[0], 4))])
        add = np.column_stack([np.ones(spans.size), np.ones(spans.size), spans, spans * spans])
        np.add.at(self._all, rows, add)
        np.add.at(self._recent, rows, add)
        self.boxes += int(spans.size)

    def log_likelihood(self, tracks, iso) -> np.ndarray | None:
        """Per confirmed track, weight * [log N(z_bar; mu_i, s_i^2) (eq. 3) - log of its mean over
        the tracks scored]: a log Bayes factor against "the Tx's range is that of a detected target
        drawn at random", which is also what a track without boxes with heights, and the Tx the
        camera never detected, are taken to have (0). None before any Rx(iso) reading or box with a
        height.

        ``iso`` (``rf_belief.IsoLevel``) gives z_bar: the episode's mean level for a standing
        track, its recent level (``IsoLevel.recent``) for a walking one. Its noise's AR(1)
        correlation rho leaves n (1 - rho)/(1 + rho) independent readings under a mean of n."""
        n = len(tracks)
        if not n or not iso.n or not self.boxes:
            return None
        ids = tracks.ids
        known = ids < self._all.shape[0]
        walks = tracks.walking > 0.5
        stats = np.zeros((n, 4))
        stats[known] = np.where(walks[known, None], self._recent[ids[known]], self._all[ids[known]])
        scored = stats[:, 0] >= 1e-3
        out = np.zeros(n)
        if not scored.any():
            return None
        mean_all, sd_all = iso.mean_and_std()
        rho = iso.noise_correlation()
        infl = (1.0 + rho) / max(1.0 - rho, 1e-3)
        recent = iso.recent.mean_var() if iso.recent is not None and iso.recent.w >= 1e-3 else None
        z = np.full(n, mean_all)
        z_n = np.full(n, float(iso.n))
        if recent is not None:
            z[walks], z_n[walks] = recent[0], recent[2]
        w, w2, sy, sy2 = (stats[scored, k] for k in range(4))
        y = sy / w
        y_var = np.maximum(sy2 / w - y * y, 0.0) * w2 / (w * w)  # the weighted mean's variance: var / effective count
        var_y = np.maximum(y_var, self.span_floor**2)
        slope = 10.0 * self.model.exponent
        s2 = self.model.shadowing_db**2 + self.floor_db**2 + sd_all * sd_all * infl / z_n[scored] + slope * slope * (self.v_h + var_y)
        mu = self.model.level_dbm(self.m_h - y)
        out[scored] = -0.5 * ((z[scored] - mu) ** 2 / s2 + np.log(2.0 * math.pi * s2))
        top = float(out[scored].max())
        reference = top + math.log(float(np.mean(np.exp(out[scored] - top))))
        out[scored] -= reference
        return self.weight * out
