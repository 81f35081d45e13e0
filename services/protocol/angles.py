"""Angles on the circle, shared by every service (the numba kernels, ``controller/_kernels.py``
and ``controller/_tracker.py``, keep their own jitted copy: compiled code calls only
jitted functions, and numba's on-disk cache of one module does not see a change to a
jitted function it imports from another)."""

from __future__ import annotations

import numpy as np


def wrap(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle (or a difference of angles) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi
