"""Verification of a loop candidate: register the two local maps, then measure their agreement.

Registration is GICP (small_gicp: generalized ICP, Segal et al. 2009), coarse then fine: a pass
with correspondences up to 4x `max_correspondence_m` pulls in the initial alignment, a second pass
at `max_correspondence_m` settles it. Each local map is prepared (downsampled, point covariances,
trees) once per use as a query or reference, not once per pass.

Agreement is measured independently of the registration's own cost: a query point is
*overlapping* when the reference has a point within `overlap_distance_m`, an *inlier* when its
distance to the reference surface (the plane through its nearest reference point, normal from
that point's neighbours) is within `inlier_distance_m`; fitness = inliers / overlapping points,
overlap = overlapping / all query points. Distances to the surface, not to the nearest point, so
the measure does not depend on the voxel sampling.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.core.clusters import neighbourhood_axes

COARSE_CORRESPONDENCE_FACTOR = 4.0  # the coarse pass reaches this many times max_correspondence_m
COVARIANCE_NEIGHBOURS = 10  # GICP point covariances from this many neighbours (small_gicp's own default)
NORMAL_NEIGHBOURS = 8  # points of the local plane fit giving a reference normal (a 3 x 3 patch of voxels)


@dataclass
class PreparedMap:
    """A local map made ready for registration once, however many candidates it takes part in:
    its points (anchor frame, m), small_gicp's cloud (downsampled to the voxel, with point
    covariances) and KdTree, and a scipy tree for the agreement measure."""

    points: np.ndarray  # (M, 3)
    cloud: Any
    gicp_tree: Any
    tree: Any


def prepare_local_map(points: np.ndarray, voxel_m: float) -> PreparedMap:
    """The PreparedMap of `points` (M, 3), downsampled to `voxel_m` for GICP."""
    import small_gicp
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    cloud, gicp_tree = small_gicp.preprocess_points(points, downsampling_resolution=voxel_m,
                                                    num_neighbors=COVARIANCE_NEIGHBOURS, num_threads=1)
    return PreparedMap(points, cloud, gicp_tree, cKDTree(points))


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
    for distance_m in (COARSE_CORRESPONDENCE_FACTOR * max_correspondence_m, max_correspondence_m):
        result = small_gicp.align(ref.cloud, query.cloud, ref.gicp_tree, T, registration_type="GICP",
                                  max_correspondence_distance=distance_m, num_threads=1)
        T = np.array(result.T_target_source)
        converged = converged and bool(result.converged)
    ref_points, tree = ref.points, ref.tree
    moved = query.points @ T[:3, :3].T + T[:3, 3]
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
        overlap=n_overlap / max(len(query.points), 1),
        rmse_m=float(np.sqrt(np.mean(distance_m[inliers] ** 2))) if inliers.any() else float("inf"),
        converged=converged,
    )


def _normals(points: np.ndarray, tree: object, index: np.ndarray) -> np.ndarray:
    """Unit normals (smallest principal axis of the NORMAL_NEIGHBOURS nearest points) at points[index]."""
    _, neighbours = tree.query(points[index], k=min(NORMAL_NEIGHBOURS, len(points)))
    return neighbourhood_axes(points, neighbours.reshape(len(index), -1))[1][:, :, 0]
