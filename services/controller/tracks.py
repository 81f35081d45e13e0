"""Turning the detector's anonymous boxes into static targets with detection statistics.

The camera reports, per frame, the bearings of its boxes relative to the optical axis and
nothing else. Targets do not move during a test (paper Sec. II), so the controller clusters
box bearings into *tracks*: each box goes to the nearest track within a gate, one box per
track per frame (two boxes in one frame are two targets), nearest pairs first; a box that
fits no track opens a new one. Two tracks that come close and have (almost) never been seen
in the same frame are one target split by noise, and are merged.

For each track the tracker counts the frames in which it was well inside the field of view
(n_i) and the detections in those frames (k_i), so p~_i = k_i / n_i estimates that target's
POD (paper eq. 9) without ever knowing which target it is.

The per-frame assignment is a small loop over boxes and tracks run thousands of times per
second; it is compiled with numba (``ra2vipas.services.controller._kernels``).
"""

from __future__ import annotations

import math

import numpy as np

from ra2vipas.services.controller import _kernels


def wrap(angle):
    """Wrap an angle (or a difference of angles) to [-pi, pi)."""
    if isinstance(angle, float):
        return (angle + math.pi) % (2.0 * math.pi) - math.pi
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


class DetectionTracker:
    """Static-target tracks built from per-frame box bearings.

    Parameters
    ----------
    fov_half_angle : float
        Camera half field of view [rad].
    bearing_noise : float
        Standard deviation of a box bearing [rad]; sets the gate, the merge distance and the
        margin that keeps field-of-view edges out of the counts.
    capacity : int
        Most tracks kept; boxes that would open more are ignored.
    """

    def __init__(self, fov_half_angle: float, bearing_noise: float, capacity: int = 512, max_pans: int = 100_000) -> None:
        sigma = max(bearing_noise, 1e-4)
        self.count_limit = fov_half_angle - 2.0 * sigma
        self.gate = 4.0 * sigma
        self.merge_distance = 3.0 * sigma
        self.capacity = int(capacity)
        self._bearing = np.zeros(self.capacity)
        self._boxes = np.zeros(self.capacity)
        self._detections = np.zeros(self.capacity)
        self._frames_in_view = np.zeros(self.capacity)
        self._together = np.zeros((self.capacity, self.capacity))
        self._pans = np.zeros(max_pans)
        self._frames_per_pan = np.zeros(max_pans)
        self._n_pans = 0
        self._n = 0

    def __len__(self) -> int:
        return self._n

    # read-only views of the live tracks
    @property
    def bearing(self) -> np.ndarray:
        return self._bearing[: self._n]

    @property
    def boxes(self) -> np.ndarray:
        return self._boxes[: self._n]

    @property
    def detections(self) -> np.ndarray:
        return self._detections[: self._n]

    @property
    def frames_in_view(self) -> np.ndarray:
        return self._frames_in_view[: self._n]

    def in_view(self, pan: float, bearings: np.ndarray | None = None) -> np.ndarray:
        """Mask of the tracks (or given bearings) well inside the field of view at ``pan``."""
        b = self.bearing if bearings is None else bearings
        return np.abs((b - pan + np.pi) % (2.0 * np.pi) - np.pi) <= self.count_limit

    def update(self, pan: float, frames) -> None:
        """Take the frames captured at pan angle ``pan`` (``CameraFrame`` objects)."""
        nu = len(frames)
        if self._n_pans >= self._pans.size:
            raise ValueError("too many pans for this tracker")
        self._pans[self._n_pans] = pan
        self._frames_per_pan[self._n_pans] = nu
        self._n_pans += 1
        counts = np.fromiter((len(f.box_bearings_rad) for f in frames), dtype=np.int64, count=nu)
        total = int(counts.sum())
        boxes = np.fromiter((b for f in frames for b in f.box_bearings_rad), dtype=float, count=total)
        self._n = _kernels.tracker_step(
            float(pan), boxes, counts, self._bearing, self._boxes, self._detections, self._frames_in_view,
            self._together, self._n, self._pans[: self._n_pans], self._frames_per_pan[: self._n_pans],
            self.gate, self.merge_distance, self.count_limit,
        )

    def detection_rate(self) -> tuple[np.ndarray, np.ndarray]:
        """(p~_i, n_i): each track's empirical POD and the frames it rests on."""
        n = self.frames_in_view
        return np.clip(self.detections / np.maximum(n, 1.0), 0.0, 1.0), n
