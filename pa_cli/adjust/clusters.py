"""Point-cluster algebra (BALM2, Theorems 1 and 2), vectorised over all observations.

A cluster C = sum_k [p_k; 1][p_k; 1]^T (4x4, metres) of points p_k in the scan frame becomes the
world-frame cluster T C T^T under the pose T = T_world_scan; clusters of one plane add. From a
world cluster [[P, v], [v^T, N]] the scatter matrix about the centroid is S = P - v v^T / N (m^2).
Observations are sorted by plane (as `make_problem` guarantees), so per-plane sums are segment
sums (`np.add.reduceat`), never loops.
"""

from __future__ import annotations

import numpy as np


def plane_starts(plane_index: np.ndarray, n_planes: int) -> np.ndarray:
    """Offsets (n_planes + 1,) of each plane's observations in a plane-sorted observation list."""
    plane_index = np.asarray(plane_index)
    if len(plane_index) and np.any(np.diff(plane_index) < 0):
        raise ValueError("observations must be sorted by plane (use make_problem)")
    counts = np.bincount(plane_index, minlength=n_planes)
    starts = np.zeros(n_planes + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    return starts


def world_clusters(clusters_scan: np.ndarray, T_world_scan: np.ndarray, scan_index: np.ndarray) -> np.ndarray:
    """World-frame clusters T_j C_o T_j^T (O, 4, 4) of scan-frame clusters (O, 4, 4)."""
    T = T_world_scan[scan_index]
    return T @ clusters_scan @ T.transpose(0, 2, 1)


def sum_per_plane(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Segment sums of per-observation arrays (O, ...) over planes, given `plane_starts`."""
    return np.add.reduceat(values, starts[:-1], axis=0)


def scatter(plane_clusters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scatter matrices S (P, 3, 3) in m^2, centroids (P, 3) in m and point counts (P,)."""
    N = plane_clusters[:, 3, 3]
    v = plane_clusters[:, :3, 3]
    centroid = v / N[:, None]
    S = plane_clusters[:, :3, :3] - v[:, :, None] * centroid[:, None, :]
    S = 0.5 * (S + S.transpose(0, 2, 1))
    return S, centroid, N


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
