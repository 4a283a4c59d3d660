"""The correction's fast look-ups against the reference one (ivc.table.kernels.grid_point)."""

from __future__ import annotations

import numpy as np
import pytest

from ivc.table import kernels


def _table(rng, shape=(6, 7, 5), channels=9):
    padded = rng.normal(size=(shape[0] + 2, shape[1] + 2, shape[2] + 2, channels))
    valid_cells = rng.random((shape[0] - 1, shape[1] - 1, shape[2] - 1)) < 0.8
    return padded, valid_cells, np.array([-0.3, 0.1, -0.2]), 0.05, np.array(shape, dtype=np.int64)


@pytest.mark.parametrize("cubic", [True, False])
@pytest.mark.parametrize("channels", [9, 3])  # a field matrix (grid_value's nine registers) and a seed map
def test_separable_value_only_and_contains_equal_the_reference(cubic, channels):
    rng = np.random.default_rng(3)
    padded, valid_cells, origin, spacing, shape = _table(rng, channels=channels)
    extent = spacing * (shape - 1)
    points = origin + rng.uniform(-0.1, 1.1, size=(400, 3)) * extent  # some outside the grid
    points[:5] = origin + spacing * np.array([[0, 0, 0], [1, 2, 3], [5, 6, 4], [2.5, 0, 1], [0, 6, 0.5]])  # nodes
    C = padded.shape[3]
    w = [np.empty(4) for _ in range(6)]
    for p in points:
        value, gradient = np.empty(C), np.empty((C, 3))
        grid = (padded, valid_cells, origin, spacing, shape, cubic)
        inside = kernels.grid_point(grid, p, value, gradient, *w)
        v2, g2, scratch = np.empty(C), np.empty((C, 3)), np.empty((3, C))
        inside2 = kernels.grid_point_separable(grid, p, v2, g2, *w, scratch)
        np.testing.assert_allclose(v2, value, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g2, gradient, rtol=0, atol=1e-10)
        v3 = np.empty(C)
        inside3 = kernels.grid_value(grid, p, v3, *w)
        np.testing.assert_array_equal(v3, value)  # same weights, same order: identical
        assert inside == inside2 == inside3 == kernels.grid_contains(grid, p)
