"""Point moments per label in one numba pass: the clusters of labelled points (`pa_cli.core.clusters`).

`moments_by_label` sums [1, x, y, z, xx, xy, xz, yy, yz, zz] of the points of each label in point
order, `clusters_by_label` and `weighted_clusters_by_label` pack such sums (plain, or every point
weighted, e.g. by `clusters.range_weights`) into 4x4 clusters; `add_moments` is the one update all
the point kernels share (`pa_cli.planes.kernels`, `pa_cli.core.neighbourhoods`). Kept apart from the
cluster algebra so that what only handles clusters (the solver) never loads numba.
"""

from __future__ import annotations

import numba
import numpy as np

from pa_cli.core.clusters import clusters_from_moments
from pa_cli.runtime import numba_cache  # noqa: F401  (numba cache folder: see pa_cli/runtime/numba_cache.py)


def clusters_by_label(points: np.ndarray, labels: np.ndarray, min_points: int = 1
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Labels (K,) int64, ascending, with at least `min_points` points (negative labels skipped)
    and their point clusters (K, 4, 4), in the frame of the (M, 3) points."""
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    if len(labels) == 0 or labels.max() < 0:
        return np.empty(0, np.int64), np.empty((0, 4, 4))
    sums = moments_by_label(labels, np.ascontiguousarray(points, dtype=np.float64), int(labels.max()) + 1)
    keep = np.flatnonzero(sums[:, 0] >= max(min_points, 1))
    return keep.astype(np.int64), clusters_from_moments(sums[keep])


@numba.njit(cache=True)
def add_moments(sums: np.ndarray, row: int, w: float, x: float, y: float, z: float) -> None:
    """sums[row] += w [1, x, y, z, xx, xy, xz, yy, yz, zz] (numba; w = 1 adds the plain moments exactly)."""
    wx, wy, wz = w * x, w * y, w * z
    s = sums[row]
    s[0] += w
    s[1] += wx
    s[2] += wy
    s[3] += wz
    s[4] += wx * x
    s[5] += wx * y
    s[6] += wx * z
    s[7] += wy * y
    s[8] += wy * z
    s[9] += wz * z


@numba.njit(cache=True, nogil=True)
def moments_by_label(labels: np.ndarray, points: np.ndarray, n_labels: int) -> np.ndarray:
    """(n_labels, 10) sums [1, x, y, z, xx, xy, xz, yy, yz, zz] of the points with each label
    (labels < 0 skipped), accumulated in point order."""
    sums = np.zeros((n_labels, 10))
    for i in range(len(labels)):
        lm = labels[i]
        if lm < 0:
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        add_moments(sums, lm, 1.0, x, y, z)
    return sums


@numba.njit(cache=True)
def _weighted_moments(labels, points, weights, n_labels):
    """(n_labels, 10) sums w [1, x, y, z, xx, xy, xz, yy, yz, zz] per label (labels < 0 skipped)."""
    sums = np.zeros((n_labels, 10))
    for k in range(len(labels)):
        lab = labels[k]
        if lab >= 0:
            add_moments(sums, lab, weights[k], points[k, 0], points[k, 1], points[k, 2])
    return sums


def weighted_clusters_by_label(points: np.ndarray, labels: np.ndarray, n_labels: int,
                               weights: np.ndarray | None = None) -> np.ndarray:
    """(n_labels, 4, 4) sums of w_k [p_k; 1][p_k; 1]^T over the (M, 3) points with each label
    0..n_labels-1 (negative labels skipped; `weights` (M,), default 1), in the frame of the points."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    w = np.ones(len(points)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    return clusters_from_moments(_weighted_moments(np.ascontiguousarray(labels, dtype=np.int64), points, w,
                                                   int(n_labels)))
