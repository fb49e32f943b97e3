"""Coarse extrinsic alignment: point-to-plane ICP of each LiDAR's scans against lidar0's map.

Hand-measured extrinsics are off by degrees and decimetres: a point 20 m away lands a metre from
its surface, too far for the plane association of the joint adjustment. This stage moves only the
extrinsic of one LiDAR: the target is lidar0's map (all its scans at the base poses, one point
per `coarse_voxel_m` voxel, each with the normal of its `coarse_neighbours` nearest neighbours,
kept where they are planar); the source is the LiDAR's scans, downsampled alike, placed at
T_world_base(t) T_base_lidar. Gauss-Newton on the point-to-plane residuals n . (w - q) with the
correspondence distance halved from `coarse_max_distance_m` to `coarse_min_distance_m` whenever
an iteration's step is small. Jacobian of a residual with respect to the extrinsic's step
eps = (omega, rho) (base frame, about the LiDAR's origin as in `composite.RigLayout.retract`),
y = R_base_lidar p, m = R_t^T n: [y x m, m].
The step may be restricted to a basis of directions (held directions stay put).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pa_cli.config import AdvancedPlanesConfig, CalibrateConfig
from pa_cli.core.clusters import neighbourhood_axes
from pa_cli.core.geometry import exp_so3
from pa_cli.io.maps import voxel_downsample

SETTLED_FRACTION = 0.1  # a step moving points less than this fraction of the correspondence distance: settled there
# Levenberg damping relative to the Hessian's diagonal: keeps a direction the map leaves free from taking a huge step.
COARSE_DAMPING = 1e-6


def voxel_points(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """One point (the first) per voxel of `voxel_size_m`."""
    return points[voxel_downsample(points, voxel_size_m)]


class PlanarTarget:
    """lidar0's map with per-point normals, planar points only, and its k-d tree."""

    def __init__(self, points_world: np.ndarray, config: CalibrateConfig, planes: AdvancedPlanesConfig) -> None:
        from scipy.spatial import cKDTree

        tree = cKDTree(points_world)
        _, nb = tree.query(points_world, k=config.coarse_neighbours)
        lam, vec = neighbourhood_axes(points_world, nb)
        planar = lam[:, 0] < planes.max_eigen_ratio * lam[:, 1]
        self.points = points_world[planar]
        self.normals = vec[planar, :, 0]
        self.tree = cKDTree(self.points)


def align_extrinsic(target: PlanarTarget, scans: Sequence[tuple[int, np.ndarray]], T_world_base: np.ndarray,
                    T_base_lidar: np.ndarray, config: CalibrateConfig, basis: np.ndarray | None = None
                    ) -> tuple[np.ndarray, dict]:
    """Refine one T_base_lidar (4, 4) by ICP of its scans [(base index t, (M, 3) points)] against
    `target`; returns the extrinsic and a report (iterations, inliers, RMS of the last iteration, m)."""
    basis = np.eye(6) if basis is None else basis
    base = np.concatenate([np.full(len(p), t) for t, p in scans])
    points = np.concatenate([p for _, p in scans])
    X = np.asarray(T_base_lidar, dtype=np.float64).copy()
    distance = config.coarse_max_distance_m
    iterations, rms, inliers = 0, float("nan"), 0
    for iterations in range(1, config.coarse_max_iterations + 1):  # noqa: B007 (the count is reported)
        y = points @ X[:3, :3].T  # base frame, relative to the LiDAR's origin
        R, t = T_world_base[base, :3, :3], T_world_base[base, :3, 3]
        w = np.einsum("mij,mj->mi", R, y + X[:3, 3]) + t
        dist, idx = target.tree.query(w, distance_upper_bound=distance)
        ok = np.isfinite(dist)
        inliers = int(np.count_nonzero(ok))
        if inliers < basis.shape[1]:
            break
        n = target.normals[idx[ok]]
        r = np.einsum("mi,mi->m", n, w[ok] - target.points[idx[ok]])
        m = np.einsum("mji,mj->mi", R[ok], n)
        J = np.hstack([np.cross(y[ok], m), m]) @ basis
        rms = float(np.sqrt(np.mean(r * r)))
        H = J.T @ J
        z = -np.linalg.solve(H + COARSE_DAMPING * np.diag(np.diag(H)), J.T @ r)
        step = basis @ z
        X[:3, :3] = exp_so3(step[None, :3])[0] @ X[:3, :3]
        X[:3, 3] += step[3:]
        if np.linalg.norm(step[:3]) * config.lever_arm_m + np.linalg.norm(step[3:]) < SETTLED_FRACTION * distance:
            if distance <= config.coarse_min_distance_m:
                break
            distance = max(0.5 * distance, config.coarse_min_distance_m)
    return X, {"iterations": iterations, "inliers": inliers, "rms_m": rms, "final_distance_m": distance}
