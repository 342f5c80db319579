"""minretarget.nearest against scipy's k-d tree (the twin): exact nearest distances."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from minretarget.nearest import _nearest_both_ways_kernel, build_grid, nearest, nearest_both_ways


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


@pytest.mark.parametrize("seed", range(4))
def test_both_ways_finds_the_trees_nearest_distances_each_way(seed):
    """The pairs in neighbouring cells and the search on from ring 2, against two trees:
    queries near the points (most settled by the pairs), far off and outside the grid."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(int(rng.integers(1, 800)), 3)) * [0.3, 0.8, 0.1]
    near = points[:300] + rng.normal(scale=0.02, size=(min(300, len(points)), 3))
    queries = np.concatenate([near, rng.normal(size=(int(rng.integers(1, 100)), 3)) * 3.0])
    grid = build_grid(points, cell=float(rng.uniform(0.01, 0.5)))
    distances, indices, back_distances, back_indices = nearest_both_ways(grid, queries)
    np.testing.assert_allclose(distances, cKDTree(points).query(queries)[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(back_distances, cKDTree(queries).query(points)[0], rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(points[indices] - queries, axis=1), distances,
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(queries[back_indices] - points, axis=1),
                               back_distances, atol=1e-12)


def test_both_ways_searches_on_only_for_every_strideth_query():
    rng = np.random.default_rng(7)
    points, queries = rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) * 2.0
    grid = build_grid(points, cell=0.2)
    out = (np.empty(200), np.empty(200, np.int64), np.empty(300), np.empty(300, np.int64))
    _nearest_both_ways_kernel(grid.points, grid.origin, grid.cell, grid.dims, grid.order,
                              grid.starts, queries, 3, *out)
    want = cKDTree(points).query(queries)[0]
    np.testing.assert_allclose(out[0][::3], want[::3], atol=1e-12)       # exact where asked
    assert (out[0] >= want - 1e-12).all()                                # else an upper bound
    np.testing.assert_allclose(out[2], cKDTree(queries).query(points)[0], atol=1e-12)


def test_bad_points_are_refused():
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        build_grid(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="finite"):
        build_grid([[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        nearest(build_grid(np.zeros((1, 3))), [[np.inf, 0.0, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        nearest_both_ways(build_grid(np.zeros((1, 3))), [[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="at least one"):
        nearest_both_ways(build_grid(np.zeros((1, 3))), np.zeros((0, 3)))
