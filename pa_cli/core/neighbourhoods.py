"""Gaussian fits of point neighbourhoods: the local entropy and normal of a map around query points.

`neighbourhood_fit` sums, for every query, the moments of the map points within a radius of it
(one numba pass over a grid of cells of that edge) and fits a Gaussian to them: the entropy of the
fit and the |z| of its normal. The map entropy of `pa_cli.evaluation.quality` is its mean; the
kernel lives here, below plane finding, so that the plane kernels' warm-up (`pa_cli.planes.warm_up`)
can load it too.
"""

from __future__ import annotations

import numba
import numpy as np

from pa_cli.core.point_moments import add_moments
from pa_cli.runtime.numba_cache import announce_compilation  # (and numba's cache folder: see that module)


@numba.njit(cache=True)
def first_not_below(sorted_keys, key):
    """np.searchsorted(sorted_keys, key) (side left) by bisection: numba's own searchsorted compiles
    for every comparison type numpy knows (about a second the first time)."""
    lo, hi = 0, len(sorted_keys)
    while lo < hi:
        mid = (lo + hi) // 2
        if sorted_keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True)
def _neighbourhood_moments(cell_keys, order_start, sorted_points, query_cells, queries, dims, radius_m, moments):
    """Add to moments (Q, 10), per query: count, sum of d and sum of d d^T (xx, xy, xz, yy, yz, zz)
    over the points within radius_m, d = point - query. Points are sorted by the key of their cell
    (edge radius_m), so a query's neighbours lie in the 27 cells around its own, each a run found by
    binary search. The output lives in the caller's array: a kernel that allocates compiles numba's
    allocation code on the first run."""
    n_queries = len(queries)
    r2 = radius_m * radius_m
    for q in range(n_queries):
        qx, qy, qz = queries[q, 0], queries[q, 1], queries[q, 2]
        for cx in range(query_cells[q, 0] - 1, query_cells[q, 0] + 2):
            if cx < 0 or cx >= dims[0]:
                continue
            for cy in range(query_cells[q, 1] - 1, query_cells[q, 1] + 2):
                if cy < 0 or cy >= dims[1]:
                    continue
                for cz in range(query_cells[q, 2] - 1, query_cells[q, 2] + 2):
                    if cz < 0 or cz >= dims[2]:
                        continue
                    key = (cx * dims[1] + cy) * dims[2] + cz
                    lo = first_not_below(cell_keys, key)
                    if lo == len(cell_keys) or cell_keys[lo] != key:
                        continue
                    hi = order_start[lo + 1]
                    for i in range(order_start[lo], hi):
                        dx = sorted_points[i, 0] - qx
                        dy = sorted_points[i, 1] - qy
                        dz = sorted_points[i, 2] - qz
                        if dx * dx + dy * dy + dz * dz <= r2:
                            add_moments(moments, q, 1.0, dx, dy, dz)


def neighbourhood_fit(points_world: np.ndarray, queries: np.ndarray, radius_m: float, min_neighbours: int,
                      min_sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(Q,) entropy (nats) of a Gaussian fit to the points within radius_m of each query point, and
    (Q,) |z| of its normal (the eigenvector of the smallest eigenvalue, world frame); both NaN for a
    query with fewer than min_neighbours neighbours (itself included when it is a map point).

    The covariance is the maximum-likelihood one (divided by the count); its eigenvalues are
    floored at min_sigma_m^2, so a noise-free planar neighbourhood gets a finite entropy. One pass
    over a grid of cells of edge radius_m: every query sums the moments of its neighbours centred
    on itself (no cancellation far from the origin), in memory linear in the points and queries
    however dense the map (single-threaded).
    """
    points_world = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    queries = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    out, normal_z = np.full(len(queries), np.nan), np.full(len(queries), np.nan)
    if len(points_world) == 0 or len(queries) == 0:
        return out, normal_z
    origin = points_world.min(axis=0)
    cells = np.floor((points_world - origin) / radius_m).astype(np.int64)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(keys, kind="stable")
    cell_keys, starts = np.unique(keys[order], return_index=True)
    order_start = np.append(starts, len(keys)).astype(np.int64)
    # queries far outside the map: clipped one cell beyond it, where they find no neighbour
    query_cells = np.clip(np.floor((queries - origin) / radius_m), -2, dims + 1).astype(np.int64)
    announce_compilation(KERNELS)  # the first run compiles it: say so once
    moments = np.zeros((len(queries), 10))
    _neighbourhood_moments(cell_keys, order_start, points_world[order], query_cells, queries, dims, float(radius_m),
                           moments)
    n = moments[:, 0]
    ok = n >= max(min_neighbours, 1)
    n, mean = n[ok, None], moments[ok, 1:4] / n[ok, None]
    second = moments[ok, 4:] / n
    cov = np.empty((int(ok.sum()), 3, 3))
    for slot, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        cov[:, a, b] = cov[:, b, a] = second[:, slot] - mean[:, a] * mean[:, b]
    eig, vec = np.linalg.eigh(cov)
    out[ok] = 0.5 * (3.0 * np.log(2.0 * np.pi * np.e) + np.log(np.maximum(eig, min_sigma_m**2)).sum(axis=1))
    normal_z[ok] = np.abs(vec[:, 2, 0])
    return out, normal_z


KERNELS = (_neighbourhood_moments,)  # what `neighbourhood_fit` compiles (`numba_cache.announce_compilation`)
