"""Verification of a loop candidate: register the two local maps, then measure their agreement.

Registration is GICP (small_gicp: generalized ICP, Segal et al. 2009), coarse then fine: a pass
on the maps thinned to COARSE_VOXEL_FACTOR x their voxel with correspondences up to
COARSE_CORRESPONDENCE_FACTOR x `max_correspondence_m` pulls in the initial alignment, a second
pass on the maps at their voxel and at `max_correspondence_m` settles it. Each local map is
prepared (downsampled, point covariances, trees) once per use as a query or reference, not once
per pass.

Agreement is measured independently of the registration's own cost: a query point is
*overlapping* when the reference has a point within `overlap_distance_m`, an *inlier* when its
distance to the reference surface (the plane through its nearest reference point, normal from
that point's GICP covariance, i.e. its COVARIANCE_NEIGHBOURS nearest neighbours) is within
`inlier_distance_m`; fitness = inliers / overlapping points, overlap = overlapping / all query
points. Distances to the surface, not to the nearest point, so the measure does not depend on the
voxel sampling.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

COARSE_CORRESPONDENCE_FACTOR = 4.0  # the coarse pass reaches this many times max_correspondence_m
# The coarse pass runs on the maps thinned to this many times their voxel: it only has to pull the alignment into
# the fine pass's reach (max_correspondence_m), and a quarter of the points (or fewer) make it that much cheaper.
COARSE_VOXEL_FACTOR = 2.0
COVARIANCE_NEIGHBOURS = 10  # GICP point covariances from this many neighbours (small_gicp's own default)


@dataclass
class PreparedMap:
    """A local map made ready for registration once, however many candidates it takes part in:
    its points (anchor frame, m), small_gicp's clouds (with point covariances) and KdTrees, at its
    voxel (`cloud`, `tree`) and coarser (`coarse_cloud`, `coarse_tree`), and the points of `cloud`."""

    points: np.ndarray  # (M, 3)
    cloud_points: np.ndarray  # (C, 3)
    cloud: Any
    tree: Any
    coarse_cloud: Any
    coarse_tree: Any


def prepare_local_map(points: np.ndarray, voxel_m: float) -> PreparedMap:
    """The PreparedMap of `points` (M, 3), downsampled to `voxel_m` (and COARSE_VOXEL_FACTOR x `voxel_m`) for GICP."""
    import small_gicp

    points = np.asarray(points, dtype=np.float64)
    cloud, tree = small_gicp.preprocess_points(points, downsampling_resolution=voxel_m,
                                               num_neighbors=COVARIANCE_NEIGHBOURS, num_threads=1)
    coarse_cloud, coarse_tree = small_gicp.preprocess_points(
        points, downsampling_resolution=COARSE_VOXEL_FACTOR * voxel_m, num_neighbors=COVARIANCE_NEIGHBOURS,
        num_threads=1)
    return PreparedMap(points, np.asarray(cloud.points())[:, :3], cloud, tree, coarse_cloud, coarse_tree)


@dataclass
class Registration:
    """The registration of a query local map onto a reference local map."""

    T_ref_query: np.ndarray  # (4, 4)
    fitness: float  # inliers / overlapping query points
    overlap: float  # overlapping / all query points
    rmse_m: float  # RMS nearest-neighbour distance of the inliers (m)
    converged: bool


def register_local_maps(ref: PreparedMap, query: PreparedMap, T_init: np.ndarray, max_correspondence_m: float,
                        inlier_distance_m: float, overlap_distance_m: float) -> Registration:
    """Register the `query` local map (query anchor frame) onto `ref` (reference anchor frame)."""
    import small_gicp

    T = np.asarray(T_init, dtype=np.float64)
    converged = True
    coarse_m = COARSE_CORRESPONDENCE_FACTOR * max_correspondence_m
    passes = ((ref.coarse_cloud, ref.coarse_tree, query.coarse_cloud, coarse_m),
              (ref.cloud, ref.tree, query.cloud, max_correspondence_m))
    for ref_cloud, ref_tree, query_cloud, distance_m in passes:
        result = small_gicp.align(ref_cloud, query_cloud, ref_tree, T, registration_type="GICP",
                                  max_correspondence_distance=distance_m, num_threads=1)
        T = np.array(result.T_target_source)
        converged = converged and bool(result.converged)
    moved = query.points @ T[:3, :3].T + T[:3, 3]
    index, squared_m2 = ref.tree.batch_nearest_neighbor_search(moved, num_threads=1)
    overlapping = np.asarray(squared_m2) <= overlap_distance_m ** 2
    index = np.asarray(index)[overlapping]
    n_overlap = len(index)
    distance_m = np.full(len(moved), np.inf)
    if n_overlap:
        normals = np.linalg.eigh(np.asarray(ref.cloud.covs())[index, :3, :3])[1][:, :, 0]
        distance_m[overlapping] = np.abs(np.einsum("ij,ij->i", moved[overlapping] - ref.cloud_points[index], normals))
    inliers = distance_m <= inlier_distance_m
    return Registration(
        T_ref_query=T,
        fitness=float(inliers.sum() / n_overlap) if n_overlap else 0.0,
        overlap=n_overlap / max(len(query.points), 1),
        rmse_m=float(np.sqrt(np.mean(distance_m[inliers] ** 2))) if inliers.any() else float("inf"),
        converged=converged,
    )
