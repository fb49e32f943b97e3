"""The sensor's side of a plane landmark: an opaque surface is seen only from its front.

A LiDAR ray ends on the first surface it meets, so every point a scan sees on a surface lies
on the face turned towards the sensor. Two parallel faces close together - the two sides of
a wall, of a door leaf, of a slab - can fall into one landmark at detection when the voxels
hold both (the faces are a wall's thickness apart, often within the detection gates); the
adjustment would then pull the scans on either side of the wall together to make the faces
coplanar. The side a scan sees a landmark from is part of the landmark's identity:

- side of an observation (landmark l, scan j) = sign of n_l . (o_j - c_lj), with n_l the
  landmark's world normal, o_j the sensor (the scan frame's origin) and c_lj the centroid of
  the scan's points on the landmark, both in the world. In the scan frame o_j - c_lj is minus
  the scan-frame centroid, so the sign depends on the scan's rotation only, not on its
  translation error: a sensor metres from the plane is on the right side even when its
  position is centimetres off.
- grazing: when the angle between the mean ray (c_lj - o_j) and the plane is below
  `advanced.planes.side_grazing_angle_deg` the sign is decided by the normal's and the rotation's
  errors, not by the geometry; such an observation has no side (0).
- a landmark observed from both sides (at least one observation with each sign) holds two
  surfaces: the observations from the negative side become a new landmark (appended to the
  `Landmarks` rows), each side's plane is refit on its own observations, and its grazing
  observations are dropped (their face is unknown; every non-grazing one is kept on its
  side). A landmark seen from one side only, with or without grazing observations, is left
  exactly as it was, so scenes without two-sided planes give the same problem.

A surface thin enough to be one plane from both sides (a sign board) is split as well: two
landmarks on one plane, no bias, only the tie between the scans on its two sides is lost. The
split is not decided by the fitted offset between the sides: where a wall's faces were merged,
the association's trimming (around the merged plane) and the initial poses' errors blur that
offset to a few cm, the order of the gates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.core.clusters import fit_planes, sum_by_feature, transform_clusters
from pa_cli.planes.detect import Landmarks


def observation_sides(normal_world: np.ndarray, clusters_scan: np.ndarray, R_world_scan: np.ndarray,
                      grazing_angle_rad: float) -> np.ndarray:
    """Side (+1, -1, or 0 when grazing) of the sensor for each observation: `normal_world` (O, 3)
    its landmark's unit normal, `clusters_scan` (O, 4, 4) its scan-frame cluster, `R_world_scan`
    (O, 3, 3) its scan's rotation; grazing when the mean ray meets the plane at less than
    `grazing_angle_rad`."""
    centroid_scan = clusters_scan[:, :3, 3] / clusters_scan[:, 3, 3][:, None]
    to_sensor_world = -np.einsum("oij,oj->oi", R_world_scan, centroid_scan)
    along_normal = np.einsum("oi,oi->o", normal_world, to_sensor_world)
    distance = np.linalg.norm(to_sensor_world, axis=1)
    clear = np.abs(along_normal) >= np.sin(grazing_angle_rad) * distance
    return np.where(clear, np.sign(along_normal), 0.0).astype(np.int64)


@dataclass
class SideSplit:
    """Observations after splitting two-sided landmarks (same row order, grazing rows of
    two-sided landmarks removed) and what was done."""

    landmark: np.ndarray  # (O',) landmark id of each observation
    scan: np.ndarray  # (O',) scan index
    clusters: np.ndarray  # (O', 4, 4) scan-frame clusters
    range_clusters: np.ndarray  # (O', 4, 4)
    n_two_sided: int  # landmarks split in two
    n_points_dropped: int  # points of the removed grazing observations


def split_two_sided(landmark: np.ndarray, scan: np.ndarray, clusters: np.ndarray, range_clusters: np.ndarray,
                    T_world_scan: np.ndarray, landmarks: Landmarks, grazing_angle_deg: float,
                    point_labels: list | None = None) -> SideSplit | None:
    """Split every landmark observed from both sides of its plane (see the module docstring).

    `landmark`, `scan`, `clusters`, `range_clusters`: the association's observations;
    `landmarks` is extended IN PLACE by one row per two-sided landmark (the negative side), and
    the rows of both sides get the plane fit of their own observations (normal, centroid, RMS
    thickness as thickness and sigma, point count); the leaf tables are unchanged, so
    `landmarks.assign` still returns the original id for points of either face. `point_labels`
    (the landmark id of each point of each scan, or None) is relabelled the same way (-1 for
    the points of removed grazing observations). None when no landmark is two-sided (nothing
    changed).
    """
    T = np.asarray(T_world_scan, dtype=np.float64)
    side = observation_sides(landmarks.normal_world[landmark], clusters, T[scan, :3, :3],
                             np.deg2rad(grazing_angle_deg))
    L = landmarks.n_landmarks
    front = np.bincount(landmark, side > 0, minlength=L) > 0
    back = np.bincount(landmark, side < 0, minlength=L) > 0
    two_sided = np.flatnonzero(front & back)
    if len(two_sided) == 0:
        return None
    twin_of = np.full(L, -1, dtype=np.int64)
    twin_of[two_sided] = L + np.arange(len(two_sided))
    split = twin_of[landmark] >= 0
    new_landmark = np.where(split & (side < 0), twin_of[landmark], landmark)
    keep = ~(split & (side == 0))
    if point_labels is not None:
        for o in np.flatnonzero(split & (side <= 0)):
            labels = point_labels[scan[o]]
            labels[labels == landmark[o]] = new_landmark[o] if keep[o] else -1
    _refit_sides(landmarks, two_sided, new_landmark[keep], scan[keep], clusters[keep], T)
    return SideSplit(new_landmark[keep], scan[keep], clusters[keep], range_clusters[keep], len(two_sided),
                     int(clusters[~keep, 3, 3].sum()))


def _refit_sides(landmarks: Landmarks, two_sided: np.ndarray, landmark: np.ndarray, scan: np.ndarray,
                 clusters: np.ndarray, T_world_scan: np.ndarray) -> None:
    """Append the twin rows of `two_sided` landmarks and set both sides' planes to the fit of
    their own observations (clusters moved to the world relative to the detection centroid)."""
    L = landmarks.n_landmarks
    rows = np.concatenate([two_sided, L + np.arange(len(two_sided))])
    origin = np.concatenate([landmarks.centroid_world, landmarks.centroid_world[two_sided]])
    on = np.isin(landmark, rows)
    M = T_world_scan[scan[on]]
    M[:, :3, 3] -= origin[landmark[on]]
    C = sum_by_feature(transform_clusters(clusters[on], M), landmark[on], L + len(two_sided))[rows]
    evals, normal, centroid, n = fit_planes(C)
    thickness = np.sqrt(evals[:, 0] / n)

    def extended(values: np.ndarray, fitted: np.ndarray) -> np.ndarray:
        out = np.concatenate([values, values[two_sided]])
        out[rows] = fitted
        return out

    landmarks.normal_world = extended(landmarks.normal_world, normal)
    landmarks.centroid_world = extended(landmarks.centroid_world, origin[rows] + centroid)
    landmarks.thickness_m = extended(landmarks.thickness_m, thickness)
    landmarks.sigma_m = extended(landmarks.sigma_m, thickness)
    landmarks.count = extended(landmarks.count, n.astype(landmarks.count.dtype))
    landmarks.n_voxels = np.concatenate([landmarks.n_voxels, landmarks.n_voxels[two_sided]])  # same leaves
    landmarks.diagnostics["n_landmarks_two_sided"] = int(len(two_sided))
