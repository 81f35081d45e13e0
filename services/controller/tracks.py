"""Turning the detector's anonymous boxes into static targets with detection statistics.

The camera reports, per frame, the bearings of its boxes relative to the optical axis and
nothing else. Targets do not move during a test (paper Sec. II), so the controller clusters
box bearings into *tracks*: each box goes to the nearest track within a gate, one box per
track per frame (two boxes in one frame are two targets); a box that fits no track opens a new
one. Two tracks that come close and have never been seen in the same frame are one target
split by noise, and are merged.

For each track the tracker counts the frames in which it was well inside the field of view
(n_i) and the detections in those frames (k_i), so p~_i = k_i / n_i estimates that target's
POD (paper eq. 9) without ever knowing which target it is.
"""

from __future__ import annotations

import numpy as np


def wrap(angle):
    """Wrap an angle (or a difference of angles) to [-pi, pi)."""
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
    """

    def __init__(self, fov_half_angle: float, bearing_noise: float) -> None:
        sigma = max(bearing_noise, 1e-4)
        self.count_limit = fov_half_angle - 2.0 * sigma
        self.gate = 4.0 * sigma
        self.merge_distance = 3.0 * sigma
        self.bearing = np.empty(0)  # track bearings in F_0 [rad]
        self.boxes = np.empty(0)  # boxes assigned (for the running mean)
        self.detections = np.empty(0)  # k_i, detections while well inside the view
        self.frames_in_view = np.empty(0)  # n_i
        self._together = np.zeros((0, 0))  # frames in which two tracks were both detected
        self._pans: list[float] = []
        self._frames_per_pan: list[int] = []

    def __len__(self) -> int:
        return self.bearing.size

    def in_view(self, pan: float, bearings: np.ndarray | None = None) -> np.ndarray:
        """Mask of the tracks (or given bearings) well inside the field of view at ``pan``."""
        b = self.bearing if bearings is None else bearings
        return np.abs(wrap(b - pan)) <= self.count_limit

    def update(self, pan: float, frames) -> None:
        """Take the frames captured at pan angle ``pan`` (``CameraFrame`` objects).

        The common case (every box near a known track, at most one box per track per frame)
        is handled in one vectorised pass; frames with a new target or with two boxes
        competing for one track fall back to the greedy one-to-one assignment.
        """
        nu = len(frames)
        if len(self):
            self.frames_in_view += nu * self.in_view(pan)
        self._pans.append(pan)
        self._frames_per_pan.append(nu)
        counts = [len(f.box_bearings_rad) for f in frames]
        if sum(counts):
            boxes = np.fromiter((b for f in frames for b in f.box_bearings_rad), dtype=float, count=sum(counts))
            boxes = (boxes + pan + np.pi) % (2.0 * np.pi) - np.pi
            frame_of = np.repeat(np.arange(nu), counts)
            slow = self._assign_fast(pan, boxes, frame_of, nu)
            for f in slow:
                self._assign(pan, boxes[frame_of == f])
        self._merge()

    def _assign_fast(self, pan: float, boxes: np.ndarray, frame_of: np.ndarray, nu: int) -> list[int]:
        """Assign boxes to their nearest track in bulk; return the frames that need the slow path."""
        if not len(self):
            return sorted(set(frame_of.tolist()))
        diff = np.abs((boxes[:, None] - self.bearing[None, :] + np.pi) % (2.0 * np.pi) - np.pi)
        nearest = np.argmin(diff, axis=1)
        ok = diff[np.arange(boxes.size), nearest] < self.gate
        key = frame_of * len(self) + nearest
        clash = np.zeros(boxes.size, dtype=bool)
        if ok.sum() > 1:
            keys = key[ok]
            uniq, cnt = np.unique(keys, return_counts=True)
            clash[ok] = np.isin(keys, uniq[cnt > 1])
        slow_frames = np.unique(frame_of[~ok | clash])
        fast = ~np.isin(frame_of, slow_frames)
        if fast.any():
            tracks = nearest[fast]
            offsets = (boxes[fast] - self.bearing[tracks] + np.pi) % (2.0 * np.pi) - np.pi
            added = np.bincount(tracks, minlength=len(self)).astype(float)
            shift = np.bincount(tracks, weights=offsets, minlength=len(self))
            hit = added > 0
            self.boxes[hit] += added[hit]
            self.bearing[hit] = wrap(self.bearing[hit] + shift[hit] / self.boxes[hit])
            inside = self.in_view(pan)
            self.detections += added * inside
            seen = np.zeros((nu, len(self)))
            seen[frame_of[fast], tracks] = 1.0
            self._together += seen.T @ seen
            np.fill_diagonal(self._together, 0.0)
        return slow_frames.tolist()

    def _assign(self, pan: float, boxes: np.ndarray) -> None:
        """Greedy one-to-one assignment of one frame's boxes (nearest pairs first); boxes left
        over open new tracks."""
        used_tracks: list[int] = []
        used_boxes = np.zeros(boxes.size, dtype=bool)
        if len(self):
            dist = np.abs(wrap(boxes[:, None] - self.bearing[None, :]))
            pairs = np.argwhere(dist < self.gate)
            if pairs.size:
                for p in np.argsort(dist[pairs[:, 0], pairs[:, 1]], kind="stable"):
                    bi, ti = int(pairs[p, 0]), int(pairs[p, 1])
                    if used_boxes[bi] or ti in used_tracks:
                        continue
                    used_boxes[bi] = True
                    used_tracks.append(ti)
                    self.boxes[ti] += 1.0
                    self.bearing[ti] = wrap(self.bearing[ti] + wrap(boxes[bi] - self.bearing[ti]) / self.boxes[ti])
                    if abs(wrap(self.bearing[ti] - pan)) <= self.count_limit:
                        self.detections[ti] += 1.0
        for bi in np.flatnonzero(~used_boxes):
            used_tracks.append(self._open(float(boxes[bi]), pan))
        if len(used_tracks) > 1:
            idx = np.asarray(used_tracks)
            self._together[np.ix_(idx, idx)] += 1.0
            np.fill_diagonal(self._together, 0.0)

    def _open(self, bearing: float, pan: float) -> int:
        pans = np.asarray(self._pans)
        seen = np.abs(wrap(bearing - pans)) <= self.count_limit
        n_seen = float(np.dot(seen, self._frames_per_pan))  # all frames of the pans that had it in view
        self.bearing = np.append(self.bearing, bearing)
        self.boxes = np.append(self.boxes, 1.0)
        inside = abs(wrap(bearing - pan)) <= self.count_limit
        self.detections = np.append(self.detections, 1.0 if inside else 0.0)
        self.frames_in_view = np.append(self.frames_in_view, n_seen)
        m = self.bearing.size
        grown = np.zeros((m, m))
        grown[: m - 1, : m - 1] = self._together
        self._together = grown
        return m - 1

    def _merge(self) -> None:
        while len(self) > 1:
            dist = np.abs(wrap(self.bearing[:, None] - self.bearing[None, :]))
            np.fill_diagonal(dist, np.inf)
            fewer = np.minimum(self.boxes[:, None], self.boxes[None, :])
            candidates = (dist < self.merge_distance) & (self._together <= 0.05 * fewer)
            if not candidates.any():
                return
            i, j = np.unravel_index(np.argmin(np.where(candidates, dist, np.inf)), dist.shape)
            i, j = (int(i), int(j)) if i < j else (int(j), int(i))
            total = self.boxes[i] + self.boxes[j]
            self.bearing[i] = wrap(self.bearing[i] + wrap(self.bearing[j] - self.bearing[i]) * self.boxes[j] / total)
            self.boxes[i] = total
            self.detections[i] += self.detections[j]
            self.frames_in_view[i] = max(self.frames_in_view[i], self.frames_in_view[j])
            self._together[i, :] += self._together[j, :]
            self._together[:, i] += self._together[:, j]
            keep = np.arange(len(self)) != j
            self.bearing, self.boxes = self.bearing[keep], self.boxes[keep]
            self.detections, self.frames_in_view = self.detections[keep], self.frames_in_view[keep]
            self._together = self._together[np.ix_(keep, keep)]

    def detection_rate(self) -> tuple[np.ndarray, np.ndarray]:
        """(p~_i, n_i): each track's empirical POD and the frames it rests on."""
        n = self.frames_in_view
        return np.clip(self.detections / np.maximum(n, 1.0), 0.0, 1.0), n
