"""Synthetic rig problems with known ground truth for the calibration tests (no ray casting).

Planes are square patches with given normals and centres; every (base pose, LiDAR) pair samples
points on every patch, expresses them in that LiDAR's frame (through T_world_base T_base_lidar),
adds Gaussian noise along the normal and reduces them to point clusters.
"""

from __future__ import annotations

import numpy as np

from pa_cli.calibration.composite import RigLayout
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3, rigid_inverse, tangent_basis, transform_points
from pa_cli.core.problem import FeatureProblem, make_problem


def rig_problem(T_world_base: np.ndarray, T_base_lidar: np.ndarray, normals: np.ndarray, centres: np.ndarray,
                half_size_m: float, points: int, noise_m: float, seed: int) -> tuple[FeatureProblem, RigLayout]:
    """The feature problem over virtual scans (t, k) (v = t K + k) and its layout."""
    rng = np.random.default_rng(seed)
    n_base, n_lidars = len(T_world_base), len(T_base_lidar)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    basis = tangent_basis(normals)
    plane_index, scan_index, clusters = [], [], []
    for t in range(n_base):
        for k in range(n_lidars):
            T_world_lidar = T_world_base[t] @ T_base_lidar[k]
            for i in range(len(normals)):
                uv = rng.uniform(-half_size_m, half_size_m, (points, 2))
                q = centres[i] + uv @ basis[i].T + rng.normal(0, noise_m, (points, 1)) * normals[i]
                clusters.append(points_to_cluster(transform_points(rigid_inverse(T_world_lidar[None])[0], q)))
                plane_index.append(i)
                scan_index.append(t * n_lidars + k)
    order = np.lexsort((scan_index, plane_index))
    problem = make_problem(np.array(plane_index)[order], np.array(scan_index)[order],
                           np.array(clusters)[order], n_scans=n_base * n_lidars)
    layout = RigLayout(np.repeat(np.arange(n_base), n_lidars), np.tile(np.arange(n_lidars), n_base),
                       n_base, n_lidars)
    return problem, layout


def random_rig(n_base: int, n_lidars: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Base poses (a drive with turns) and extrinsics (tens of cm, tens of degrees)."""
    T_world_base = np.tile(np.eye(4), (n_base, 1, 1))
    T_world_base[:, :3, :3] = exp_so3(np.column_stack([rng.normal(0, 0.05, n_base), rng.normal(0, 0.05, n_base),
                                                       rng.uniform(-0.6, 0.6, n_base)]))
    T_world_base[:, :3, 3] = np.column_stack([np.arange(n_base) * 1.5, rng.normal(0, 0.5, n_base),
                                              rng.normal(0, 0.1, n_base)])
    T_base_lidar = np.tile(np.eye(4), (n_lidars, 1, 1))
    T_base_lidar[1:, :3, :3] = exp_so3(rng.normal(0, 0.4, (n_lidars - 1, 3)))
    T_base_lidar[1:, :3, 3] = rng.normal(0, 0.5, (n_lidars - 1, 3))
    return T_world_base, T_base_lidar
