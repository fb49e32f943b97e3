"""Verification of a loop candidate: register the two local maps, then measure their agreement.

Registration is GICP (small_gicp: generalized ICP, Segal et al. 2009), coarse then fine: a pass
with correspondences up to 4x `max_correspondence_m` pulls in the initial alignment, a second pass
at `max_correspondence_m` settles it. Agreement is measured independently of the registration's
own cost: a query point is *overlapping* when the reference has a point within
`overlap_distance_m`, an *inlier* when its distance to the reference surface (the plane through
its nearest reference point, normal from that point's neighbours) is within `inlier_distance_m`;
fitness = inliers / overlapping points, overlap = overlapping / all query points. Distances to
the surface, not to the nearest point, so the measure does not depend on the voxel sampling.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

COARSE_CORRESPONDENCE_FACTOR = 4.0  # the coarse pass reaches this many times max_correspondence_m
NORMAL_NEIGHBOURS = 8  # points of the local plane fit giving a reference normal (a 3 x 3 patch of voxels)


@dataclass
class Registration:
    """The registration of a query local map onto a reference local map."""

    T_ref_query: np.ndarray  # (4, 4)
    fitness: float  # inliers / overlapping query points
    overlap: float  # overlapping / all query points
    rmse_m: float  # RMS nearest-neighbour distance of the inliers (m)
    converged: bool


def register_local_maps(ref_points: np.ndarray, query_points: np.ndarray, T_init: np.ndarray, voxel_m: float,
                        max_correspondence_m: float, inlier_distance_m: float,
                        overlap_distance_m: float) -> Registration:
    """Register `query_points` (query anchor frame) onto `ref_points` (reference anchor frame)."""
    import small_gicp
    from scipy.spatial import cKDTree

    T = np.asarray(T_init, dtype=np.float64)
    converged = True
    for distance_m in (COARSE_CORRESPONDENCE_FACTOR * max_correspondence_m, max_correspondence_m):
        result = small_gicp.align(ref_points, query_points, T, registration_type="GICP",
                                  downsampling_resolution=voxel_m, max_correspondence_distance=distance_m,
                                  num_threads=1)
        T = np.array(result.T_target_source)
        converged = converged and bool(result.converged)
    moved = query_points @ T[:3, :3].T + T[:3, 3]
    tree = cKDTree(ref_points)
    nearest_m, index = tree.query(moved, distance_upper_bound=overlap_distance_m)
    overlapping = np.isfinite(nearest_m)
    n_overlap = int(overlapping.sum())
    distance_m = np.full(len(moved), np.inf)
    if n_overlap:
        normals = _normals(ref_points, tree, index[overlapping])
        distance_m[overlapping] = np.abs(np.einsum("ij,ij->i", moved[overlapping] - ref_points[index[overlapping]],
                                                   normals))
    inliers = distance_m <= inlier_distance_m
    return Registration(
        T_ref_query=T,
        fitness=float(inliers.sum() / n_overlap) if n_overlap else 0.0,
        overlap=n_overlap / max(len(query_points), 1),
        rmse_m=float(np.sqrt(np.mean(distance_m[inliers] ** 2))) if inliers.any() else float("inf"),
        converged=converged,
    )


def _normals(points: np.ndarray, tree: object, index: np.ndarray) -> np.ndarray:
    """Unit normals (smallest principal axis of the NORMAL_NEIGHBOURS nearest points) at points[index]."""
    _, neighbours = tree.query(points[index], k=min(NORMAL_NEIGHBOURS, len(points)))
    local = points[neighbours.reshape(len(index), -1)]
    centred = local - local.mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
    return vectors[:, :, 0]
