"""Small synthetic plane-adjustment problems with known ground truth (tests and benchmarks).

Planes are observed by windows of consecutive scans, as a LiDAR moving along a path would see
them. Points are sampled on patches of each plane in the world frame, offset along the normal
by Gaussian noise, and mapped into the scan frame with the ground-truth pose.
"""

from __future__ import annotations

import numpy as np

from pa_cli.io.problem import PlaneProblem, make_problem


def _random_rotations(rng: np.random.Generator, n: int, max_angle_rad: float) -> np.ndarray:
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = rng.uniform(-max_angle_rad, max_angle_rad, size=n)
    K = np.zeros((n, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(0, 2, 1)
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def synthetic_problem(n_scans: int = 20, n_planes: int = 40, window: int = 6, points_per_obs: int = 30,
                      noise_m: float = 0.01, step_m: float = 1.0, seed: int = 0) -> PlaneProblem:
    """A `PlaneProblem` whose `T_world_scan` is the ground truth.

    Scans move `step_m` metres apart along x with small random rotations (up to 10 deg);
    plane i is observed by `window` consecutive scans starting at a random scan; each
    observation has `points_per_obs` points on a 4 m x 4 m patch near the plane's anchor,
    with Gaussian `noise_m` (m) along the normal (0 gives a noise-free, zero-cost problem).
    """
    rng = np.random.default_rng(seed)
    window = min(window, n_scans)
    T_world_scan = np.tile(np.eye(4), (n_scans, 1, 1))
    T_world_scan[:, :3, :3] = _random_rotations(rng, n_scans, np.deg2rad(10.0))
    T_world_scan[:, 0, 3] = step_m * np.arange(n_scans)
    T_world_scan[:, 1:3, 3] = rng.normal(scale=0.2, size=(n_scans, 2))
    normals = rng.normal(size=(n_planes, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    first_scan = rng.integers(0, n_scans - window + 1, size=n_planes)
    # anchor: a point ~5 m from the middle of the observing window
    mid = T_world_scan[first_scan + window // 2, :3, 3]
    anchor = mid + rng.normal(scale=5.0, size=(n_planes, 3))

    plane_index = np.repeat(np.arange(n_planes), window)
    scan_index = (first_scan[:, None] + np.arange(window)[None, :]).ravel()
    n_obs = len(plane_index)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    b1 = np.cross(normals, helper)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(normals, b1)
    uv = rng.uniform(-2.0, 2.0, size=(n_obs, points_per_obs, 2))
    h = rng.normal(scale=noise_m, size=(n_obs, points_per_obs, 1)) if noise_m > 0 else 0.0
    p = plane_index
    points_world = (anchor[p][:, None, :] + uv[..., :1] * b1[p][:, None, :] + uv[..., 1:] * b2[p][:, None, :]
                    + h * normals[p][:, None, :])
    T = T_world_scan[scan_index]
    points_scan = np.einsum("oba,okb->oka", T[:, :3, :3], points_world - T[:, None, :3, 3])
    ph = np.concatenate([points_scan, np.ones((n_obs, points_per_obs, 1))], axis=2)
    clusters = np.einsum("oka,okb->oab", ph, ph)
    return make_problem(plane_index, scan_index, clusters, n_scans=n_scans, T_world_scan=T_world_scan,
                        source="synthetic problem")
