"""Point clusters (BALM2, Theorems 1 and 2): build, transform, sum and fit, vectorised.

A cluster C = sum_k [p_k; 1][p_k; 1]^T (4x4, metres) of points p_k in one frame holds everything
the plane fit and the plane-adjustment cost need of them: from C = [[P, v], [v^T, N]] the count is
N, the centroid c = v / N and the scatter about the centroid S = P - v v^T / N (m^2). Under a rigid
transform T_target_source the cluster becomes T C T^T (`transform_clusters`); clusters of one
feature add (`sum_by_feature`, or segment sums `sum_per_plane` when observations are sorted by
feature, as `pa_cli.core.problem.make_problem` guarantees). The best plane through a cluster's points
has the eigenvector of the smallest eigenvalue of S as normal and passes through c (`fit_planes`).

Clusters are built from points in one numba pass per scan (`pa_cli.core.point_moments`: sums
[1, x, y, z, xx, xy, xz, yy, yz, zz] per label) and packed by `clusters_from_moments`. This module
is numpy only: the solver, which never sees points, loads no numba kernel through it.

Range clusters K = sum_k w_k [p_k; 1][p_k; 1]^T with w_k = 1 / |p_k|^2 (`range_weights`,
`point_moments.weighted_clusters_by_label`) are the same sums with every point weighted by its inverse squared
distance from the scan frame's origin: for points in the sensor frame that is the range, and the
pose covariance's range noise model (`pa_cli.adjust.covariance`) reads the point-to-plane
variance of each point from it.
"""

from __future__ import annotations

import numpy as np

MIN_EIGENVALUE_M2 = 1e-300  # floor of lambda_mid in the normal uncertainty (no division by 0)
# floor of |p| in the range weight 1/|p|^2 (m): no LiDAR return on a surface is this close to the
# sensor, so it only bounds the weight of a spurious point at the origin (a driver's "no return")
RANGE_WEIGHT_FLOOR_M = 0.1


def points_to_cluster(points: np.ndarray) -> np.ndarray:
    """Point cluster sum [p;1][p;1]^T of (M, 3) points, as a (4, 4) float64 array."""
    ph = np.hstack([points, np.ones((len(points), 1))])
    return ph.T @ ph


def clusters_from_moments(sums: np.ndarray) -> np.ndarray:
    """(K, 4, 4) clusters from (K, 10) sums of [1, x, y, z, xx, xy, xz, yy, yz, zz]."""
    n, x, y, z, xx, xy, xz, yy, yz, zz = np.asarray(sums, dtype=np.float64).T
    return np.stack([np.stack([xx, xy, xz, x], -1), np.stack([xy, yy, yz, y], -1),
                     np.stack([xz, yz, zz, z], -1), np.stack([x, y, z, n], -1)], axis=1)


def range_weights(points: np.ndarray) -> np.ndarray:
    """(M,) weights 1 / |p|^2 (1/m^2) of (M, 3) points, |p| floored at `RANGE_WEIGHT_FLOOR_M`."""
    points = np.asarray(points, dtype=np.float64)
    return 1.0 / np.maximum(np.einsum("ki,ki->k", points, points), RANGE_WEIGHT_FLOOR_M**2)


def neighbourhood_axes(points: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal axes of each point's neighbourhood: `neighbours` (M, k) indexes `points` (k nearest
    points of each of M places); returns the ascending eigenvalues (M, 3) of the neighbourhoods'
    scatter (sums of squares about their means, m^2) and the eigenvectors (M, 3, 3) as columns, so
    [:, :, 0] is the local normal."""
    local = points[neighbours]
    centred = local - local.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))

def transform_clusters(clusters: np.ndarray, T_target_source: np.ndarray) -> np.ndarray:
    """Clusters (O, 4, 4) moved by rigid transforms (O, 4, 4), one per cluster: T C T^T."""
    return T_target_source @ clusters @ T_target_source.transpose(0, 2, 1)


def sum_by_feature(clusters: np.ndarray, feature_index: np.ndarray, n_features: int) -> np.ndarray:
    """Per-feature sums (n_features, 4, 4) of clusters (O, 4, 4) (any observation order)."""
    flat = clusters.reshape(len(clusters), 16)
    return np.stack([np.bincount(feature_index, flat[:, i], minlength=n_features) for i in range(16)],
                    -1).reshape(n_features, 4, 4)


def scatter(clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scatter matrices S (P, 3, 3) in m^2 (symmetrised), centroids (P, 3) in m and point counts (P,)."""
    N = clusters[:, 3, 3]
    v = clusters[:, :3, 3]
    centroid = v / N[:, None]
    S = clusters[:, :3, :3] - v[:, :, None] * centroid[:, None, :]
    S = 0.5 * (S + S.transpose(0, 2, 1))
    return S, centroid, N


def fit_planes(clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes of clusters (P, 4, 4): scatter eigenvalues (P, 3) ascending, clamped
    at 0 (m^2), unit normals (P, 3) (eigenvector of the smallest), centroids (P, 3) m, counts (P,)."""
    S, centroid, N = scatter(clusters)
    evals, evecs = np.linalg.eigh(S)
    return np.maximum(evals, 0.0), evecs[:, :, 0], centroid, N


def normal_sigma_rad(evals: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Standard deviation (rad) of fitted normals about their weakest in-plane axis,
    sqrt(lambda_min / (N - 3) / lambda_mid), from scatter eigenvalues (P, 3) and counts (P,)."""
    return np.sqrt(evals[:, 0] / np.maximum(count - 3, 1) / np.maximum(evals[:, 1], MIN_EIGENVALUE_M2))


# -- the plane-adjustment cost: per-plane eigen-decompositions from sorted observations ------------


def plane_starts(plane_index: np.ndarray, n_planes: int) -> np.ndarray:
    """Offsets (n_planes + 1,) of each plane's observations in a plane-sorted observation list."""
    plane_index = np.asarray(plane_index)
    if len(plane_index) and np.any(np.diff(plane_index) < 0):
        raise ValueError("observations must be sorted by plane (use make_problem)")
    counts = np.bincount(plane_index, minlength=n_planes)
    starts = np.zeros(n_planes + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    return starts



def sum_per_plane(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Segment sums of per-observation arrays (O, ...) over planes, given `plane_starts`."""
    return np.add.reduceat(values, starts[:-1], axis=0)



def central_moments(clusters_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-observation moments about the observation's own centroid, in the scan frame.

    Returns (eigenvalues (O,3) m^2 clamped at 0, eigenvectors (O,3,3) as columns, centroid (O,3)
    m, count (O,)) of S_o = P - v v^T / N. Computed once per problem. Working with centred,
    factored moments (parallel-axis theorem, S_o = sum_k mu_k w_k w_k^T) avoids the cancellation
    of P - v v^T / N with large world coordinates, and lets lambda_min be evaluated as a sum of
    non-negative terms (relative precision, so cost differences near a zero-cost optimum resolve).
    """
    S, centroid, N = scatter(clusters_scan)
    mu, w = np.linalg.eigh(S)
    return np.maximum(mu, 0.0), w, centroid, N



def plane_eigen(T_world_scan: np.ndarray, mu_scan: np.ndarray, w_scan: np.ndarray, c_scan: np.ndarray,
                N_obs: np.ndarray, scan_index: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, ...]:
    """World moments per observation and the eigen-decomposition of every plane's scatter.

    Input: per-observation factored central moments in the scan frame (`central_moments`).
    Returns (S_world (O,3,3), c_world (O,3), eigenvalues (P,3) ascending in m^2, eigenvectors
    (P,3,3) as columns, plane centroids (P,3) m, plane counts (P,)). The plane scatter is
    S = sum_o R S_o R^T + sum_o N_o (c_o - c)(c_o - c)^T (parallel-axis theorem); its smallest
    eigenvalue is re-evaluated as the Rayleigh quotient
    u^T S u = sum_o [sum_k mu_ok (u . R w_ok)^2 + N_o (u . (c_o - c))^2], a sum of non-negative terms.
    """
    R = T_world_scan[scan_index, :3, :3]
    w_world = R @ w_scan  # (O,3,3) world directions of the observation's principal axes
    S_world = (w_world * mu_scan[:, None, :]) @ w_world.transpose(0, 2, 1)
    c_world = np.einsum("oij,oj->oi", R, c_scan) + T_world_scan[scan_index, :3, 3]
    N_plane = sum_per_plane(N_obs, starts)
    centroid = sum_per_plane(N_obs[:, None] * c_world, starts) / N_plane[:, None]
    plane_of_obs = np.repeat(np.arange(len(N_plane)), np.diff(starts))
    dc = c_world - centroid[plane_of_obs]
    S = sum_per_plane(S_world + N_obs[:, None, None] * dc[:, :, None] * dc[:, None, :], starts)
    S = 0.5 * (S + S.transpose(0, 2, 1))
    lam, vec = np.linalg.eigh(S)
    u = vec[plane_of_obs, :, 0]
    proj = np.einsum("oi,oik->ok", u, w_world)
    terms = np.einsum("ok,ok->o", mu_scan, proj * proj) + N_obs * np.einsum("oi,oi->o", u, dc) ** 2
    lam[:, 0] = np.minimum(sum_per_plane(terms, starts), lam[:, 1])
    return S_world, c_world, lam, vec, centroid, N_plane

