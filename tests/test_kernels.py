"""Compiled kernels against the plain computations they replace."""

import numpy as np
import pytest

from slamtka.solver.kernels import nearest_points


@pytest.mark.parametrize("n_points", [1, 7, 900])
def test_nearest_points_is_the_exact_nearest_neighbour(n_points):
    """Queries on the outline, beside it and hundreds of cells away all get the point at
    the least distance (brute force), whatever the grid's cell size."""
    rng = np.random.default_rng(n_points)
    points = rng.uniform(0.0, 300.0, (n_points, 2)) + [100.0, -50.0]
    queries = np.vstack([points + rng.normal(0.0, 2.0, points.shape),
                         rng.uniform(-2000.0, 2000.0, (200, 2))])
    brute = np.min(np.linalg.norm(queries[:, None] - points[None], axis=2), axis=1)
    for cell in (0.5, 10.0, 1000.0):
        found = nearest_points(points, queries, cell)
        np.testing.assert_allclose(np.linalg.norm(queries - points[found], axis=1), brute,
                                   rtol=0, atol=1e-9)
