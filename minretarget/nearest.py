"""Nearest neighbours among a few thousand points, on a uniform grid (the source fit's).

The fit asks, several times a frame, for each of ~1,000 points its nearest among ~1,500
others that have just moved: a k-d tree is rebuilt every time, and scipy's costs about a
millisecond to build and query at these sizes. A uniform grid is built by one counting sort
and queried ring by ring: after ring r (the box of cells within r of the query's), every
point not yet seen lies beyond one of the box's faces (those inside the grid), so the search
stops once the best distance so far is within the nearest such face. Exact, like the tree
(ties may pick another of the equally near points).

The fit wants both ways at once: each cloud point's nearest model point and each model
point's nearest cloud point (``nearest_both_ways``). The moved points are sorted into the
fixed cloud's grid and every pair of points in neighbouring cells is measured once, for
both (on the shipped sample about 42,000 distances a Gauss-Newton step in 9,200 runs of
three cells, where the two ring searches measured about 69,000 in 64,000 cell visits; the
answers are the same but for ties). A point whose nearest lies beyond the faces of its
3 x 3 x 3 cells (about 4 %) searches on from ring 2, its best so far the bound, skipping
cells farther than that.
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
    queries = _checked_queries(queries)
    distances, indices = np.empty(len(queries)), np.empty(len(queries), np.int64)
    _nearest_kernel(grid.points, grid.origin, grid.cell, grid.dims, grid.order, grid.starts,
                    queries, distances, indices)
    return distances, indices


def nearest_both_ways(grid, queries):
    """Each query's (M, 3) nearest grid point, and each grid point's nearest query: distances
    (M,) float64, indices (M,), then distances (N,), indices (N,) (the grid's points' order)."""
    queries = _checked_queries(queries)
    if not len(queries):
        raise ValueError("queries must hold at least one point")
    distances, indices = np.empty(len(queries)), np.empty(len(queries), np.int64)
    back_distances, back_indices = np.empty(len(grid.points)), np.empty(len(grid.points),
                                                                         np.int64)
    _nearest_both_ways_kernel(grid.points, grid.origin, grid.cell, grid.dims, grid.order,
                              grid.starts, queries, 1, distances, indices, back_distances,
                              back_indices)
    return distances, indices, back_distances, back_indices


def _checked_queries(queries):
    queries = np.ascontiguousarray(queries, np.float64)
    if queries.ndim != 2 or queries.shape[1] != 3 or not np.isfinite(queries).all():
        raise ValueError(f"queries must be finite, of shape (M, 3), got {queries.shape}")
    return queries


@kernel
def _cell_index(x, origin, cell, count):
    """Along one axis, the index of the cell holding coordinate x, clamped to the grid's
    ``count`` cells."""
    return min(max(int(np.floor((x - origin) / cell)), 0), count - 1)


@kernel
def _cell_of(point, origin, cell, dims, out):
    for a in range(3):
        out[a] = _cell_index(point[a], origin[a], cell, dims[a])


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
    for m in range(len(queries)):
        x, y, z = queries[m, 0], queries[m, 1], queries[m, 2]
        best, best_index = _search(
            points, origin, cell, dims, order, starts, x, y, z,
            _cell_index(x, origin[0], cell, dims[0]), _cell_index(y, origin[1], cell, dims[1]),
            _cell_index(z, origin[2], cell, dims[2]),
            np.inf, -1, np.int64(-1))
        distances[m] = np.sqrt(best)
        indices[m] = best_index


@kernel
def _search(points, origin, cell, dims, order, starts, x, y, z, home0, home1, home2, best,
            best_index, done):
    """The ring search for (x, y, z), in cell (home0, home1, home2) (clamped to the grid),
    whose rings 0 to ``done`` are searched (-1: none) and gave the squared distance ``best``
    to point ``best_index`` (inf and -1: none) -> (squared distance, index) of the nearest
    point. After ring r, a point not yet seen lies beyond a face of the box of cells within r
    of the query's that is not the grid's border: the search ends once the best is within
    the nearest such face, or the box covers the grid."""
    ring = done
    while True:
        if ring >= 0:
            beyond = np.inf
            if home0 - ring > 0:
                beyond = min(beyond, x - (origin[0] + (home0 - ring) * cell))
            if home0 + ring < dims[0] - 1:
                beyond = min(beyond, origin[0] + (home0 + ring + 1) * cell - x)
            if home1 - ring > 0:
                beyond = min(beyond, y - (origin[1] + (home1 - ring) * cell))
            if home1 + ring < dims[1] - 1:
                beyond = min(beyond, origin[1] + (home1 + ring + 1) * cell - y)
            if home2 - ring > 0:
                beyond = min(beyond, z - (origin[2] + (home2 - ring) * cell))
            if home2 + ring < dims[2] - 1:
                beyond = min(beyond, origin[2] + (home2 + ring + 1) * cell - z)
            if beyond == np.inf or (best_index >= 0 and best <= beyond * beyond):
                return best, best_index
        ring += 1
        for i in range(max(home0 - ring, 0), min(home0 + ring, dims[0] - 1) + 1):
            # A cell whose box lies farther than the best so far holds nothing nearer: skipped,
            # axis by axis.
            gap0 = _gap(x, origin[0] + i * cell, cell)
            if gap0 > best:
                continue
            shell0 = i == home0 - ring or i == home0 + ring
            for j in range(max(home1 - ring, 0), min(home1 + ring, dims[1] - 1) + 1):
                gap01 = gap0 + _gap(y, origin[1] + j * cell, cell)
                if gap01 > best:
                    continue
                # Only the ring's own cells: all of a row on the ring, else its two ends.
                whole = shell0 or j == home1 - ring or j == home1 + ring or ring == 0
                low, high = max(home2 - ring, 0), min(home2 + ring, dims[2] - 1)
                k = low if whole else home2 - ring
                while k <= high:
                    if k >= low and gap01 + _gap(z, origin[2] + k * cell, cell) <= best:
                        c = (i * dims[1] + j) * dims[2] + k
                        for s in range(starts[c], starts[c + 1]):
                            n = order[s]
                            d = ((points[n, 0] - x) ** 2 + (points[n, 1] - y) ** 2
                                 + (points[n, 2] - z) ** 2)
                            if d < best:
                                best, best_index = d, n
                    k += 1 if whole else 2 * ring


@kernel
def _nearest_both_ways_kernel(points, origin, cell, dims, order, starts, queries, stride,
                              distances, indices, back_distances, back_indices):
    """``nearest_both_ways`` on arrays, the queries' nearest grid points wanted at every
    ``stride``-th query only (the others' are the nearest among the pairs, maybe none: inf).
    ``_search``'s ring argument is an int64, not a literal: a literal would compile it again."""
    one = np.int64(1)
    cells = len(starts) - 1
    query_order, query_starts = np.empty(len(queries), np.int64), np.empty(cells + 1, np.int64)
    query_starts[:] = 0
    _sort_into_cells(queries, origin, cell, dims, query_order, query_starts)
    # The queries in cell order, and their best so far: each cell's run is contiguous.
    sorted_queries = np.empty((len(queries), 3))
    best = np.empty(len(queries))
    best_index = np.empty(len(queries), np.int64)
    for t in range(len(queries)):
        for a in range(3):
            sorted_queries[t, a] = queries[query_order[t], a]
        best[t] = np.inf
        best_index[t] = -1
    for i in range(dims[0]):
        for j in range(dims[1]):
            for k in range(dims[2]):
                c = (i * dims[1] + j) * dims[2] + k
                low, high = max(k - 1, 0), min(k + 1, dims[2] - 1) + 1
                # The cell's grid points two at a time against the queries in the 3 x 3 x 3
                # cells around it (an odd one out paired with a point at infinity): each run
                # of queries walked once for both. A query meets them in the same order.
                for s in range(starts[c], starts[c + 1], 2):
                    n, other = order[s], order[min(s + 1, starts[c + 1] - 1)]
                    x, y, z = points[n, 0], points[n, 1], points[n, 2]
                    x2, y2, z2 = np.inf, np.inf, np.inf
                    if s + 1 < starts[c + 1]:
                        x2, y2, z2 = points[other, 0], points[other, 1], points[other, 2]
                    own, own_index, own2, own_index2 = np.inf, -1, np.inf, -1
                    for u in range(max(i - 1, 0), min(i + 1, dims[0] - 1) + 1):
                        for v in range(max(j - 1, 0), min(j + 1, dims[1] - 1) + 1):
                            row = (u * dims[1] + v) * dims[2]     # k - 1..k + 1: one run
                            # As slices indexed from 0: numba then knows the index is not
                            # negative and skips its wraparound arithmetic (a fifth of the
                            # instructions here).
                            first, last = query_starts[row + low], query_starts[row + high]
                            run, run_best, run_index = (sorted_queries[first:last],
                                                        best[first:last],
                                                        best_index[first:last])
                            for e in range(last - first):
                                qx, qy, qz = run[e, 0], run[e, 1], run[e, 2]
                                d = (qx - x) ** 2 + (qy - y) ** 2 + (qz - z) ** 2
                                d2 = (qx - x2) ** 2 + (qy - y2) ** 2 + (qz - z2) ** 2
                                if d < own:
                                    own, own_index = d, first + e
                                if d2 < own2:
                                    own2, own_index2 = d2, first + e
                                if d < run_best[e]:
                                    run_best[e], run_index[e] = d, n
                                if d2 < run_best[e]:
                                    run_best[e], run_index[e] = d2, other
                    for g in range(s, min(s + 2, starts[c + 1])):
                        n = order[g]
                        if g > s:
                            own, own_index = own2, own_index2
                        if own_index >= 0:                    # its sorted place -> its index
                            own_index = query_order[own_index]
                        # Rings 0 and 1 are done: exact if the nearest lies within the
                        # faces of the 3 x 3 x 3 cells around its own, else it searches on.
                        own, own_index = _search(queries, origin, cell, dims, query_order,
                                                 query_starts, points[n, 0], points[n, 1],
                                                 points[n, 2], i, j, k, own, own_index, one)
                        back_distances[n], back_indices[n] = np.sqrt(own), own_index
    for i in range(dims[0]):
        for j in range(dims[1]):
            for k in range(dims[2]):
                c = (i * dims[1] + j) * dims[2] + k
                for t in range(query_starts[c], query_starts[c + 1]):
                    m = query_order[t]
                    if m % stride == 0:
                        best[t], best_index[t] = _search(points, origin, cell, dims, order,
                                                         starts, queries[m, 0], queries[m, 1],
                                                         queries[m, 2], i, j, k, best[t],
                                                         best_index[t], one)
                    distances[m], indices[m] = np.sqrt(best[t]), best_index[t]


@kernel
def _gap(x, low, cell):
    """The squared distance from coordinate x to the cell [low, low + cell], less a hair
    (1e-9 of the cell) that covers the rounding of which cell a point was sorted into."""
    slack = 1e-9 * cell
    if x < low - slack:
        return (low - slack - x) ** 2
    if x > low + cell + slack:
        return (x - low - cell - slack) ** 2
    return 0.0
