"""Synthetic plane problems with known ground truth, for the tests and the benchmarks.

Import as `tests.synthetic_problems` (pytest puts the repository root on the path; the bench
scripts run with `PYTHONPATH=.`).

A trajectory of `n_scans` poses drives along x (1 m apart, random yaw and small roll/pitch);
each plane is a 6 m x 6 m patch near the trajectory with a random normal, observed by a window
of `window` consecutive scans (as along a real drive, which keeps the Hessian banded). Every
observation samples `points_per_observation` points on the patch (plus Gaussian noise along the
normal, `noise_m`), expressed in the scan frame and reduced to a point cluster. With `noise_seed`
the noise comes from its own generator: the same `seed` then gives the same poses, planes and
point positions, and only the noise changes (repeated noise realisations of one scene).
"""

from __future__ import annotations

import numpy as np

from pa_cli.adjust.common import exp_so3
from pa_cli.evaluation.perturbation import perturb_poses
from pa_cli.io.problem import PlaneProblem, make_problem

CHUNK_POINTS = 2_000_000  # points generated at once (bounds memory for large benchmarks)


def make_trajectory(n_scans: int, rng: np.random.Generator) -> np.ndarray:
    """Ground-truth T_world_scan (N, 4, 4): 1 m steps along x, yaw up to 30 deg, roll/pitch 3 deg."""
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    angles = np.column_stack([rng.normal(0, 0.05, n_scans), rng.normal(0, 0.05, n_scans),
                              rng.uniform(-0.5, 0.5, n_scans)])
    T[:, :3, :3] = exp_so3(angles)
    T[:, :3, 3] = np.column_stack([np.arange(n_scans, dtype=float), rng.normal(0, 0.5, n_scans),
                                   rng.normal(0, 0.1, n_scans)])
    return T


def make_scene(n_scans: int, n_planes: int, window: int, points_per_observation: int = 20,
               noise_m: float = 0.0, seed: int = 0, noise_seed: int | None = None
               ) -> tuple[PlaneProblem, np.ndarray]:
    """A plane problem and its ground-truth poses T_world_scan (N, 4, 4); problem poses = GT."""
    rng = np.random.default_rng(seed)
    noise_rng = rng if noise_seed is None else np.random.default_rng(noise_seed)
    window = min(window, n_scans)
    T_gt = make_trajectory(n_scans, rng)
    n_windows = n_scans - window + 1
    first_scan = np.arange(n_planes) % n_windows
    normals = rng.normal(size=(n_planes, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    middle = T_gt[first_scan + window // 2, :3, 3]
    centres = middle + rng.uniform(-10, 10, (n_planes, 3))
    # in-plane basis
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)

    plane_index = np.repeat(np.arange(n_planes), window)
    scan_index = (first_scan[:, None] + np.arange(window)[None, :]).ravel()
    n_obs = len(plane_index)
    M = points_per_observation
    clusters = np.empty((n_obs, 4, 4))
    step = max(1, CHUNK_POINTS // M)
    for lo in range(0, n_obs, step):  # chunks bound memory; each chunk is vectorised
        o = slice(lo, min(lo + step, n_obs))
        p = plane_index[o]
        uv = rng.uniform(-3, 3, (len(p), M, 2))
        q_world = (centres[p][:, None, :] + uv[..., :1] * t1[p][:, None, :] + uv[..., 1:] * t2[p][:, None, :]
                   + noise_rng.normal(0, 1, (len(p), M, 1)) * noise_m * normals[p][:, None, :])
        T = T_gt[scan_index[o]]
        R, t = T[:, :3, :3], T[:, :3, 3]
        q_scan = np.einsum("oji,omj->omi", R, q_world - t[:, None, :])  # R^T (q - t)
        qh = np.concatenate([q_scan, np.ones((len(p), M, 1))], axis=2)
        clusters[o] = np.einsum("omi,omj->oij", qh, qh)
    problem = make_problem(plane_index, scan_index, clusters, n_scans=n_scans, T_world_scan=T_gt)
    return problem, T_gt


def perturb(T_world_scan: np.ndarray, sigma_rot_rad: float, sigma_trans_m: float, seed: int = 0,
            keep_first: bool = True) -> np.ndarray:
    """R <- Exp(omega) R, t <- t + N(0, sigma_t^2 I), omega ~ N(0, sigma_R^2 I) (000 section 5.2),
    seeded: `pa_cli.evaluation.perturb_poses` with `np.random.default_rng(seed)`."""
    return perturb_poses(T_world_scan, sigma_rot_rad, sigma_trans_m, np.random.default_rng(seed), keep_first)
