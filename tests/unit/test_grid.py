"""CircleGrid's shortcuts equal the direct computations they replace."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ra2vipas.services.controller.circle_gp import circular_kernel
from ra2vipas.services.controller.grid import CircleGrid


@pytest.mark.parametrize("points", [36, 360, 720])
def test_kernel_rows_windows_and_interpolation_match_direct_computation(points):
    g = CircleGrid(points)
    rng = np.random.default_rng(0)
    for idx in rng.integers(0, points, 10):
        a = float(g.angles[idx])
        np.testing.assert_allclose(g.kernel_row(a, 0.7, 2.0), circular_kernel(np.array([a]), g.angles, 0.7, 2.0)[0], atol=1e-12)
        direct = np.abs((g.angles - a + math.pi) % (2 * math.pi) - math.pi) <= 0.4 + 1e-12
        assert np.array_equal(g.window(a, 0.4), direct)
    off = 0.123456  # not a grid point: computed directly
    np.testing.assert_allclose(g.kernel_row(off, 0.7), circular_kernel(np.array([off]), g.angles, 0.7)[0], atol=1e-12)
    values = np.sin(g.angles)
    xs = rng.uniform(-math.pi, math.pi, 50)
    np.testing.assert_allclose(g.interp(values, xs), np.interp(xs, g.angles, values, period=2 * math.pi), atol=1e-12)


def test_arc_sum_wraps_around_the_circle():
    g = CircleGrid(360)
    centres = np.radians([179.5, -179.0, 0.0])
    weights = np.array([1.0, 2.0, 4.0])
    out = g.arc_sum(centres, weights, math.radians(10))
    assert out[g.nearest(math.pi - 1e-9)] == 3.0  # both targets near +-180 deg
    assert out[g.nearest(0.0)] == 4.0
    assert out[g.nearest(math.radians(90))] == 0.0
    assert g.arc_sum(np.empty(0), np.empty(0), 0.1).sum() == 0.0
