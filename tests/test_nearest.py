"""minretarget.nearest against scipy's k-d tree (the twin): exact nearest distances."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from minretarget.nearest import build_grid, nearest


@pytest.mark.parametrize("seed", range(4))
def test_grid_finds_the_trees_nearest_distances(seed):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(int(rng.integers(1, 800)), 3)) * [0.3, 0.8, 0.1]
    queries = np.concatenate([points[:50] + rng.normal(scale=0.01, size=(min(50, len(points)), 3)),
                              rng.normal(size=(100, 3)) * 3.0])      # near and far, outside
    distances, indices = nearest(build_grid(points, cell=float(rng.uniform(0.01, 0.5))), queries)
    expected, _ = cKDTree(points).query(queries)
    np.testing.assert_allclose(distances, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(points[indices] - queries, axis=1), distances,
                               atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_an_outlier_neither_blows_up_the_grid_nor_misleads_it(seed):
    rng = np.random.default_rng(seed)
    points = np.concatenate([rng.normal(size=(500, 3)) * 0.3, [[1e4, 0.0, 0.0]]])
    grid = build_grid(points)                                 # the default cell
    assert len(grid.starts) <= 64 * len(points) + 2
    queries = np.concatenate([rng.normal(size=(200, 3)) * 0.5,     # inside, between points
                              rng.normal(size=(50, 3)) * 50.0])    # off the grid
    distances, _ = nearest(grid, queries)
    np.testing.assert_allclose(distances, cKDTree(points).query(queries)[0], atol=1e-9)


def test_bad_points_are_refused():
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        build_grid(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="finite"):
        build_grid([[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        nearest(build_grid(np.zeros((1, 3))), [[np.inf, 0.0, 0.0]])
