"""A uniform grid of pan angles on the circle, with the shortcuts that keep a control step cheap.

Pan commands are grid points, so a kernel row k(s, grid) for a grid point s is the row of
s = -pi rolled by its index: one precomputed template per (kernel, length scale) replaces a
fresh evaluation every step. Windows ("which grid angles lie within w of s") are likewise a
rolled template, and periodic interpolation is index arithmetic.
"""

from __future__ import annotations

import math

import numpy as np


class CircleGrid:
    """M evenly spaced angles in [-pi, pi)."""

    def __init__(self, points: int) -> None:
        self.size = int(points)
        self.step = 2.0 * math.pi / self.size
        self.angles = -math.pi + self.step * np.arange(self.size)
        self._rows: dict[tuple, np.ndarray] = {}
        self._windows: dict[float, np.ndarray] = {}

    def position(self, angle: float) -> float:
        """Fractional grid index of ``angle`` in [0, M)."""
        return ((angle + math.pi) / self.step) % self.size

    def on_grid(self, angle: float) -> int | None:
        """The index of ``angle`` if it is (numerically) a grid point, else None."""
        pos = self.position(angle)
        idx = int(round(pos)) % self.size
        return idx if abs(pos - round(pos)) < 1e-7 else None

    def nearest(self, angle: float) -> int:
        return int(round(self.position(angle))) % self.size

    def kernel_row(self, angle: float, length_scale: float, variance: float = 1.0) -> np.ndarray:
        """k(angle, grid) for the chordal squared-exponential kernel (see ``circle_gp``)."""
        idx = self.on_grid(angle)
        if idx is None:
            s = np.sin(0.5 * (angle - self.angles))
            return variance * np.exp(-2.0 * s * s / (length_scale * length_scale))
        key = (length_scale, variance)
        twice = self._rows.get(key)
        if twice is None:
            s = np.sin(0.5 * (self.angles[0] - self.angles))
            base = variance * np.exp(-2.0 * s * s / (length_scale * length_scale))
            twice = self._rows[key] = np.concatenate([base, base])
        return twice[self.size - idx : 2 * self.size - idx]  # == np.roll(base, idx), as a view

    def window(self, angle: float, half_width: float) -> np.ndarray:
        """Boolean mask of the grid angles within ``half_width`` of ``angle`` (wrapped)."""
        idx = self.on_grid(angle)
        if idx is None:
            return np.abs((self.angles - angle + math.pi) % (2 * math.pi) - math.pi) <= half_width
        twice = self._windows.get(half_width)
        if twice is None:
            d = np.abs((self.angles - self.angles[0] + math.pi) % (2 * math.pi) - math.pi)
            base = d <= half_width + 1e-12
            twice = self._windows[half_width] = np.concatenate([base, base])
        return twice[self.size - idx : 2 * self.size - idx]

    def interp(self, values: np.ndarray, angles: np.ndarray) -> np.ndarray:
        """Periodic linear interpolation of grid ``values`` at ``angles``."""
        pos = ((np.asarray(angles, dtype=float) + math.pi) / self.step) % self.size
        lo = np.floor(pos).astype(int) % self.size
        frac = pos - np.floor(pos)
        return values[lo] * (1.0 - frac) + values[(lo + 1) % self.size] * frac

    def arc_sum(self, centres: np.ndarray, weights: np.ndarray, half_width: float) -> np.ndarray:
        """For every grid angle, the sum of ``weights`` whose centre (rounded to the grid) lies
        within ``half_width`` of it: a difference array over two turns of the circle."""
        M = self.size
        w = int(math.floor(half_width / self.step + 1e-9))
        if len(centres) == 0:
            return np.zeros(M)
        if 2 * w + 1 >= M:
            return np.full(M, float(np.sum(weights)))
        first = (np.rint(self.position_array(centres)).astype(int) - w) % M
        diff = np.zeros(2 * M + 1)
        np.add.at(diff, first, weights)
        np.add.at(diff, first + 2 * w + 1, -np.asarray(weights, dtype=float))
        run = np.cumsum(diff)
        return run[:M] + run[M : 2 * M]

    def position_array(self, angles: np.ndarray) -> np.ndarray:
        return ((np.asarray(angles, dtype=float) + math.pi) / self.step) % self.size
