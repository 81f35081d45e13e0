"""Turning the detector's anonymous boxes into targets in bearing, with detection statistics.

The camera reports, per frame, the bearings of its boxes relative to the optical axis and
nothing else: no identity, no range, no score, and in a cluttered scene some boxes are false
and some targets are hidden behind others. People may walk. ``BearingTracker`` follows every
target in bearing (a standing/walking IMM filter per track), associates each frame's boxes to
tracks, confirms new tracks before exposing them, and counts for each track the frames in
which it was well inside the field of view (n_i) and the detections in those frames (k_i), so
p~_i = k_i / n_i estimates that target's POD (paper eq. 9) without ever knowing which target
it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ra2vipas.services.controller import _tracker


@dataclass(frozen=True)
class TrackerSettings:
    """Tuning of the bearing tracker (angles in radians, times in seconds).

    ``q_walk`` is the spectral density of a walker's angular acceleration [rad^2/s^3] (a person
    at 1 m/s, 3 m away, turning ~30 deg/s^0.5 has |d omega/dt| ~ 0.2 rad/s^2);
    ``q_stand`` lets a standing target's bearing drift a little [rad^2/s]; ``p_switch`` is the
    per-step probability of starting or stopping to walk; ``tau_walk`` the memory of a walker's
    detection counts (its POD changes with its range); ``occlusion_rad`` how close two tracks
    must be for a missing box to be blamed on occlusion rather than counted as a miss.
    """

    q_walk: float = 0.05
    q_stand: float = 1e-8
    p_switch: float = 0.002
    gate_sigmas: float = 4.0
    tau_walk_s: float = 3.0
    omega0: float = 0.3
    occlusion_rad: float = math.radians(3.0)
    max_sd_rad: float = math.radians(60.0)


class BearingTracker:
    """Targets in bearing from anonymous per-frame boxes: an IMM filter per track (standing or
    walking), global-nearest-neighbour association, birth with confirmation, deletion, and the
    detection counts (k_i detections in n_i frames well inside the field of view) from which
    p~_i = k_i / n_i estimates target i's POD (paper eq. 9) without knowing which target it is.

    Only *confirmed* tracks are exposed (``bearing``, ``detections``, ``frames_in_view``, ...):
    a box that a clutter-prone detector reports once does not become a target.

    Why not a tracking library (e.g. Stone Soup)? A control step must cost well under a
    millisecond with dozens of tracks and hundreds of boxes; the step here is compiled
    (``ra2vipas.services.controller._tracker``: one track table, a kernel per stage), with
    standard, cited algorithms.

    Parameters
    ----------
    fov_half_angle : float
        Camera half field of view [rad].
    bearing_noise : float
        Standard deviation of a box bearing [rad].
    rf_period_s : float
        T_RF, the time between steps [s].
    capacity : int
        Most tracks kept.
    """

    def __init__(self, fov_half_angle: float, bearing_noise: float, rf_period_s: float = 0.1, capacity: int = 256,
                 max_pans: int = 100_000, settings: TrackerSettings | None = None) -> None:
        cfg = settings or TrackerSettings()
        sigma = max(bearing_noise, 1e-4)
        self.count_limit = fov_half_angle - 2.0 * sigma
        self.capacity = int(capacity)
        C = self.capacity
        self._prm = np.zeros(12)
        prm = self._prm
        prm[_tracker.DT] = rf_period_s
        prm[_tracker.SIGMA_B] = sigma
        prm[_tracker.Q_STAND] = cfg.q_stand
        prm[_tracker.Q_WALK] = cfg.q_walk
        prm[_tracker.P_SWITCH] = cfg.p_switch
        prm[_tracker.GATE2] = cfg.gate_sigmas**2
        prm[_tracker.COUNT_LIMIT] = self.count_limit
        prm[_tracker.OCCLUSION] = max(cfg.occlusion_rad, 4.0 * sigma)
        prm[_tracker.TAU_WALK] = cfg.tau_walk_s
        prm[_tracker.OMEGA0] = cfg.omega0
        prm[_tracker.MAX_SD] = cfg.max_sd_rad
        prm[_tracker.F_WALK] = 0.5
        self._tab = np.zeros(C, dtype=_tracker.TRACK)  # the track table: its first _n rows are the live tracks
        tab = self._tab
        # views of its columns
        self._x, self._P, self._mu, self._bearing, self._var = tab["x"], tab["P"], tab["mu"], tab["bearing"], tab["var"]
        self._k, self._n_frames, self._nbox, self._det_steps = tab["k"], tab["n_frames"], tab["n_boxes"], tab["det_steps"]
        self._confirmed, self._ids = tab["confirmed"], tab["id"]
        self._together = np.zeros((C, C))  # frames in which two tracks were both detected
        self._next_id = np.zeros(1, dtype=np.int64)
        self._own_views = np.zeros(360)
        self._cells = -np.pi + 2.0 * np.pi * np.arange(360) / 360
        self._clutter = np.zeros(2)
        self._pans = np.zeros(max_pans)
        self._frames_per_pan = np.zeros(max_pans)
        self._n_pans = 0
        self._n = 0
        self._view = np.arange(0)
        self._kept: dict = {}  # the confirmed tracks' columns as of _kept_for (``_read``)
        self._kept_for: np.ndarray | None = None

    def __len__(self) -> int:
        return self._view.size

    def _read(self, name: str, read):
        """``read()``, kept (read-only) until the tracks change: a step's readers (the fusion, the RF
        belief, the acquisition, the confidence) ask for the same columns many times. ``update`` sets
        a new ``_view``, which drops what was kept."""
        value = self._kept_value(name)
        if value is None:
            value = self._kept[name] = read()
            for array in value if isinstance(value, tuple) else (value,):
                if isinstance(array, np.ndarray):
                    array.setflags(write=False)  # (flags.writeable = False, without making a flags object)
        return value

    def _kept_value(self, name: str):
        """What ``_read`` kept of ``name`` for the current tracks, or None (dropping what was kept for
        others)."""
        try:
            if self._kept_for is self._view:
                return self._kept.get(name)
        except AttributeError:  # a tracker made without __init__
            pass
        self._kept, self._kept_for = {}, self._view
        return None

    # read-only views of the confirmed tracks
    @property
    def bearing(self) -> np.ndarray:
        value = self._kept_value("bearing")
        return value if value is not None else self._read("bearing", lambda: self._bearing[self._view])

    @property
    def ids(self) -> np.ndarray:
        """A stable id per track (kept while the track lives, never reused)."""
        return self._read("ids", lambda: self._ids[self._view])

    def components(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each track's bearing as its IMM mixture: means, standard deviations and weights of the
        (standing, walking) models, each of shape (n, 2)."""
        # = (self._x[v, :, 0], np.sqrt(np.maximum(self._P[v, :, 0, 0], 0.0)), self._mu[v]) for v = self._view
        return self._read("components", self._components)

    def _components(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self._view.size
        means, sds, weights = np.empty((n, 2)), np.empty((n, 2)), np.empty((n, 2))
        _tracker.components(self._tab, self._view, means, sds, weights)
        return means, sds, weights

    @property
    def walking(self) -> np.ndarray:
        """Probability that each track walks (the IMM's walking-model probability)."""
        return self._read("walking", lambda: self._mu[self._view, 1])

    @property
    def boxes(self) -> np.ndarray:
        return self._read("boxes", lambda: self._nbox[self._view])

    @property
    def detections(self) -> np.ndarray:
        return self._read("detections", lambda: self._k[self._view])

    @property
    def frames_in_view(self) -> np.ndarray:
        return self._read("frames_in_view", lambda: self._n_frames[self._view])

    @property
    def clutter_density(self) -> float:
        """False boxes per frame per radian of the field of view: boxes of tentative tracks that
        the camera looked at again and did not see, over every frame taken."""
        return float(self._clutter[0] / max(self._clutter[1], 1e-9) / (2.0 * max(self.count_limit, 1e-3)))

    def in_view(self, pan: float, bearings: np.ndarray | None = None) -> np.ndarray:
        """Mask of the tracks (or given bearings) well inside the field of view at ``pan``."""
        b = self.bearing if bearings is None else bearings
        return np.abs((b - pan + np.pi) % (2.0 * np.pi) - np.pi) <= self.count_limit

    def update(self, pan: float, frames, view_grid: np.ndarray | None = None) -> None:
        """Take the frames captured at pan angle ``pan`` (``CameraFrame`` objects) during one step.

        ``view_grid``: frames already taken of each bearing, on a uniform grid over [-pi, pi)
        (where the camera has not looked, a box is more likely a new target); by default the
        tracker keeps its own from the pans it was given."""
        nu = len(frames)
        if self._n_pans >= self._pans.size:
            raise ValueError("too many pans for this tracker")
        self._pans[self._n_pans] = pan
        self._frames_per_pan[self._n_pans] = nu
        self._n_pans += 1
        lengths = [len(f.box_bearings_rad) for f in frames]
        counts = np.fromiter(lengths, dtype=np.int64, count=nu)
        total = sum(lengths)  # int(counts.sum()), without numpy's reduction
        boxes = np.fromiter((b for f in frames for b in f.box_bearings_rad), dtype=float, count=total)
        self._n = _tracker.tracker_step(
            float(pan), boxes, counts, self._n, self._prm, self._tab, self._together, self._pans[: self._n_pans],
            self._frames_per_pan[: self._n_pans], self._clutter, self._own_views if view_grid is None else view_grid, self._next_id,
        )
        if view_grid is None:
            cells = np.abs((self._cells - pan + np.pi) % (2.0 * np.pi) - np.pi) <= self.count_limit
            self._own_views[cells] += nu
        self._view = self._confirmed[: self._n].nonzero()[0]  # np.flatnonzero of the 1-D mask, without its wrappers
        # the share of walkers among well-observed tracks (Laplace's rule): a new track's prior
        self._prm[_tracker.F_WALK] = min(max(self.walking_share(prior=0.5, strength=2.0), 0.02), 0.98)

    def walking_share(self, prior: float = 0.3, strength: float = 2.0) -> float:
        """The share of targets that walk, as the camera has seen them: tracks detected in at least
        three steps whose IMM says walking, over all such tracks, shrunk towards ``prior`` by
        ``strength`` pseudo-tracks (a Beta prior). The prior probability that the Tx, one of
        them, walks."""
        walkers, settled = self._settled()
        return (prior * strength + walkers) / (strength + settled)

    def walkers_seen(self) -> int:
        """How many tracks detected in at least three steps the IMM says walk."""
        return self._settled()[0]

    def _settled(self) -> tuple[int, int]:
        """(walkers, tracks) among the tracks detected in at least three steps (kept: ``_read``)."""
        def count() -> tuple[int, int]:
            walkers, settled = _tracker.settled_walkers(self._tab, self._n)
            return int(walkers), int(settled)
        return self._read("settled", count)

    def detection_rate(self) -> tuple[np.ndarray, np.ndarray]:
        """(p~_i, n_i): each track's empirical POD and the (discounted) frames it rests on."""
        n = self.frames_in_view
        return np.clip(self.detections / np.maximum(n, 1.0), 0.0, 1.0), n
