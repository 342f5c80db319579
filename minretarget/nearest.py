"""Nearest neighbours among a few thousand points, on a uniform grid (the source fit's).

The fit asks, several times a frame, for each of ~1,000 points its nearest among ~1,500
others that have just moved: a k-d tree is rebuilt every time, and scipy's costs about a
millisecond to build and query at these sizes. A uniform grid is built by one counting sort
and queried ring by ring: after ring r (the box of cells within r of the query's), every
point not yet seen lies beyond one of the box's faces (those inside the grid), so the search
stops once the best distance so far is within the nearest such face. Exact, like the tree
(ties may pick another of the equally near points).
"""
from typing import NamedTuple

import numpy as np

from ._jit import kernel


MAX_CELLS_PER_POINT = 64


class Grid(NamedTuple):
    """Points sorted into cubic cells (``build_grid``)."""
    points: np.ndarray      # (N, 3) float64 the points, metres
    origin: np.ndarray      # (3,) float64 the low corner of cell (0, 0, 0)
    cell: float             # the cells' width, metres
    dims: np.ndarray        # (3,) int64 cells along each axis
    order: np.ndarray       # (N,) int64 point indices sorted by cell
    starts: np.ndarray      # (cells + 1,) int64 where each cell's run begins in ``order``


def build_grid(points, cell=None):
    """Sort points (N, 3), N >= 1, finite, into cells of ``cell`` metres (default: about two points
    a cell for a body's surface, from the points' spread) -> Grid."""
    points = np.ascontiguousarray(points, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not len(points):
        raise ValueError(f"points must have shape (N, 3) with N >= 1, got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points must be finite")
    return Grid(points, *_build_grid_kernel(points, 0.0 if cell is None else float(cell)))


@kernel
def _build_grid_kernel(points, cell):
    """``build_grid`` on checked points; ``cell`` 0: the default -> origin, cell, dims, order,
    starts (``Grid``'s fields after the points). Callable from other kernels."""
    low, high, extent = np.empty(3), np.empty(3), np.empty(3)
    for a in range(3):
        low[a] = high[a] = points[0, a]
    for n in range(1, len(points)):
        for a in range(3):
            low[a] = min(low[a], points[n, a])
            high[a] = max(high[a], points[n, a])
    for a in range(3):
        extent[a] = high[a] - low[a]
    if cell == 0.0:      # a surface of extent L holds ~N points in ~(L / cell)^2 cells
        cell = np.sqrt((extent[0] ** 2 + extent[1] ** 2 + extent[2] ** 2) / len(points))
    # at most MAX_CELLS_PER_POINT cells a point, however far an outlier stretches the grid
    volume = (extent[0] + 1e-9) * (extent[1] + 1e-9) * (extent[2] + 1e-9)
    cell = max(cell, (volume / (MAX_CELLS_PER_POINT * len(points))) ** (1 / 3), 1e-4)
    dims = np.empty(3, np.int64)
    for a in range(3):
        dims[a] = int(np.floor(extent[a] / cell)) + 1
    order = np.empty(len(points), np.int64)
    starts = np.empty(dims[0] * dims[1] * dims[2] + 1, np.int64)
    starts[:] = 0
    _sort_into_cells(points, low, cell, dims, order, starts)
    return low, cell, dims, order, starts


def nearest(grid, queries):
    """For each query (M, 3), the nearest grid point: distances (M,) float64, indices (M,)."""
    queries = np.ascontiguousarray(queries, np.float64)
    if queries.ndim != 2 or queries.shape[1] != 3 or not np.isfinite(queries).all():
        raise ValueError(f"queries must be finite, of shape (M, 3), got {queries.shape}")
    distances, indices = np.empty(len(queries)), np.empty(len(queries), np.int64)
    _nearest_kernel(grid.points, grid.origin, grid.cell, grid.dims, grid.order, grid.starts,
                    queries, distances, indices)
    return distances, indices


@kernel
def _cell_of(point, origin, cell, dims, out):
    for a in range(3):
        out[a] = min(max(int(np.floor((point[a] - origin[a]) / cell)), 0), dims[a] - 1)


@kernel
def _sort_into_cells(points, origin, cell, dims, order, starts):
    """Counting sort of the points by cell: cell c's points are order[starts[c]:starts[c+1]]."""
    index = np.empty(len(points), np.int64)
    where = np.empty(3, np.int64)
    for n in range(len(points)):
        _cell_of(points[n], origin, cell, dims, where)
        index[n] = (where[0] * dims[1] + where[1]) * dims[2] + where[2]
        starts[index[n] + 1] += 1
    for c in range(1, len(starts)):
        starts[c] += starts[c - 1]
    filled = np.empty(len(starts) - 1, np.int64)
    for c in range(len(filled)):
        filled[c] = starts[c]
    for n in range(len(points)):
        order[filled[index[n]]] = n
        filled[index[n]] += 1


@kernel
def _nearest_kernel(points, origin, cell, dims, order, starts, queries, distances, indices):
    home = np.empty(3, np.int64)
    for m in range(len(queries)):
        q = queries[m]
        _cell_of(q, origin, cell, dims, home)
        best, best_index = np.inf, -1
        ring = 0
        while True:
            for i in range(max(home[0] - ring, 0), min(home[0] + ring, dims[0] - 1) + 1):
                for j in range(max(home[1] - ring, 0), min(home[1] + ring, dims[1] - 1) + 1):
                    for k in range(max(home[2] - ring, 0), min(home[2] + ring, dims[2] - 1) + 1):
                        if max(abs(i - home[0]), max(abs(j - home[1]), abs(k - home[2]))) != ring:
                            continue                            # an inner ring's cell: done
                        c = (i * dims[1] + j) * dims[2] + k
                        for s in range(starts[c], starts[c + 1]):
                            n = order[s]
                            d = ((points[n, 0] - q[0]) ** 2 + (points[n, 1] - q[1]) ** 2
                                 + (points[n, 2] - q[2]) ** 2)
                            if d < best:
                                best, best_index = d, n
            # A point not yet seen lies beyond a face of the box of cells searched, one that
            # is not the grid's border: at least that face's distance from the query away.
            beyond = np.inf
            for a in range(3):
                if home[a] - ring > 0:
                    beyond = min(beyond, q[a] - (origin[a] + (home[a] - ring) * cell))
                if home[a] + ring < dims[a] - 1:
                    beyond = min(beyond, origin[a] + (home[a] + ring + 1) * cell - q[a])
            if beyond == np.inf or (best_index >= 0 and best <= beyond * beyond):
                break
            ring += 1
        distances[m] = np.sqrt(best)
        indices[m] = best_index
