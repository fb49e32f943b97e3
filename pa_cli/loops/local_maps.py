"""Local maps: consecutive scans merged under the odometry poses, in the frame of one anchor scan.

A local map covers `local_map_length_m` of odometry path. Its anchor is its middle scan; its
points (anchor frame, metres) are thinned to one centroid per `local_map_voxel_m` voxel. Over
such a short path the odometry is locally exact, so a local map is a dense, sharp snapshot of the
place even from a sparse sensor; loop closure compares and registers local maps, not scans.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass
class LocalMap:
    """Scans `first`..`last` (inclusive) merged in the frame of scan `anchor`."""

    first: int
    last: int
    anchor: int
    path_m: float  # odometry path length from scan 0 to the anchor (m)
    points_anchor: np.ndarray  # (M, 3) float64, anchor frame (m), one centroid per voxel
    T_anchor_scan: np.ndarray  # (last - first + 1, 4, 4) the odometry poses of its scans in the anchor frame


def path_lengths_m(T_world_scan: np.ndarray) -> np.ndarray:
    """Odometry path length from scan 0 to each scan (N,), metres."""
    steps_m = np.linalg.norm(np.diff(T_world_scan[:, :3, 3], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(steps_m)]


def segment_scans(path_m: np.ndarray, length_m: float) -> list[tuple[int, int]]:
    """Split scans into consecutive (first, last) runs covering about `length_m` of path each.

    A new run starts at the first scan at least `length_m` of path after the current run's
    first scan; a stationary sequence is one run.
    """
    runs = []
    first = 0
    for k in range(1, len(path_m)):
        if path_m[k] - path_m[first] >= length_m:
            runs.append((first, k - 1))
            first = k
    runs.append((first, len(path_m) - 1))
    return runs


def voxel_centroids(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One centroid per occupied voxel of edge `voxel_m` (M, 3), in small_gicp's voxel order (`voxelgrid_sampling`,
    one thread: the same order every run). Its voxel index has 21 bits per axis: points more than 2^20 voxels from
    the origin (524 km at 0.5 m) are dropped."""
    import small_gicp

    if len(points) == 0:
        return np.empty((0, 3))
    cloud = small_gicp.voxelgrid_sampling(np.asarray(points, dtype=np.float64), voxel_m, num_threads=1)
    return np.array(cloud.points()[:, :3])


def build_local_maps(points: Sequence[np.ndarray], T_world_scan: np.ndarray, length_m: float, voxel_m: float,
                     progress: Callable[[int, int], None] | None = None, thinned: bool = False) -> list[LocalMap]:
    """Local maps of the sequence under the odometry poses; each scan is read once, in order.

    `points[k]` is scan k in its sensor frame (N, 3), metres; `T_world_scan` (N, 4, 4) the odometry. Each scan is
    thinned to `voxel_m` centroids before it is merged, unless `thinned` says the scans hold one point per voxel of at
    most `voxel_m` already (KISS-ICP's frames): merged as they are, the local map's centroids then average those.
    """
    n_scans = len(T_world_scan)
    path_m = path_lengths_m(T_world_scan)
    maps = []
    done = 0
    for first, last in segment_scans(path_m, length_m):
        anchor = (first + last) // 2
        T_anchor_world = np.linalg.inv(T_world_scan[anchor])
        parts = []
        T_anchor_scan = T_anchor_world @ T_world_scan[first:last + 1]
        for k in range(first, last + 1):
            scan = np.asarray(points[k], dtype=np.float64)
            if not thinned:
                scan = voxel_centroids(scan, voxel_m)
            T = T_anchor_scan[k - first]
            parts.append(scan @ T[:3, :3].T + T[:3, 3])
            done += 1
            if progress is not None:
                progress(done, n_scans)
        maps.append(LocalMap(first=first, last=last, anchor=anchor, path_m=float(path_m[anchor]),
                             points_anchor=voxel_centroids(np.vstack(parts), voxel_m),
                             T_anchor_scan=T_anchor_scan))
    return maps
