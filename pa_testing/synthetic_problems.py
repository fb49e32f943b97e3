"""Synthetic plane problems with known ground truth, for the tests and the benchmarks.

Import as `pa_testing.synthetic_problems` (pytest puts the repository root on the path; the bench
scripts run with `PYTHONPATH=.`).

A trajectory of `n_scans` poses drives along x (1 m apart, random yaw and small roll/pitch);
each plane is a 6 m x 6 m patch near the trajectory with a random normal, observed by a window
of `window` consecutive scans (as along a real drive, which keeps the Hessian banded). Every
observation samples `points_per_observation` points on the patch (plus Gaussian noise along the
normal, `noise_m`; with `shared_noise_m` and `shared_tilt_rad` an offset and a tilt about its centroid
shared by all its points),
expressed in the scan frame and reduced to a point cluster. With `noise_seed`
the noise comes from its own generator: the same `seed` then gives the same poses, planes and
point positions, and only the noise changes (repeated noise realisations of one scene).

Also shared by the tests: `random_poses`, `fd_pose_gradient` (finite differences along the left
retraction), `RelativeTranslations` (a pose term with pose pairs) and `planes_seen_by_every_scan` (a small
problem whose points are kept, for brute-force Jacobians).
"""

from __future__ import annotations

import numpy as np

from pa_cli.adjust.terms import TermLinearization
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3, retract_left, skew, tangent_basis
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.evaluation.perturbation import perturb_poses

CHUNK_POINTS = 2_000_000  # points generated at once (bounds memory for large benchmarks)


def random_poses(n: int, rng: np.random.Generator, rotation_sigma_rad: float = 0.5,
                 translation_sigma_m: float = 5.0) -> np.ndarray:
    """Random T_world_scan (N, 4, 4): rotation vectors and positions drawn from zero-mean normals."""
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, rotation_sigma_rad, (n, 3)))
    T[:, :3, 3] = rng.normal(0, translation_sigma_m, (n, 3))
    return T


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
               noise_m: float = 0.0, seed: int = 0, noise_seed: int | None = None, shared_noise_m: float = 0.0,
               shared_tilt_rad: float = 0.0) -> tuple[FeatureProblem, np.ndarray]:
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
    basis = tangent_basis(normals)
    t1, t2 = basis[:, :, 0], basis[:, :, 1]

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
        if shared_noise_m > 0:  # one offset along the normal shared by all points of an observation
            q_world = q_world + noise_rng.normal(0, shared_noise_m, (len(p), 1, 1)) * normals[p][:, None, :]
        if shared_tilt_rad > 0:  # one tilt about the observation's centroid shared by its points
            slope = noise_rng.normal(0, shared_tilt_rad, (len(p), 1, 2))
            lever = np.sum(slope * (uv - uv.mean(axis=1, keepdims=True)), axis=2, keepdims=True)
            q_world = q_world + lever * normals[p][:, None, :]
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


class RelativeTranslations:
    """A pose-pair term: w sum_j |t_{j+1} - t_j - d_j|^2 (m^2), exact gradient, Gauss-Newton Hessian."""

    name = "relative"

    def __init__(self, T_world_scan, weight, rng):
        self.d = np.diff(T_world_scan[:, :3, 3], axis=0) + rng.normal(0, 0.05, (len(T_world_scan) - 1, 3))
        self.w = weight

    def pose_pairs(self):
        n = len(self.d)
        return np.column_stack([np.arange(n), np.arange(1, n + 1)])

    def _residuals(self, T):
        return np.diff(T[:, :3, 3], axis=0) - self.d

    def residuals(self, T):
        """Whitened residuals sqrt(w) e (3 (N - 1),): cost = |residuals|^2."""
        return np.sqrt(self.w) * self._residuals(T).ravel()

    def cost(self, T):
        return float(self.w * np.sum(self._residuals(T) ** 2))

    def linearize(self, T):
        """With the left retraction, d t_j = -[t_j]x omega_j + rho_j."""
        e = self._residuals(T)
        t = T[:, :3, 3]
        J_a = np.concatenate([skew(t[:-1]), -np.tile(np.eye(3), (len(e), 1, 1))], axis=2)  # d e_j / d pose j
        J_b = np.concatenate([-skew(t[1:]), np.tile(np.eye(3), (len(e), 1, 1))], axis=2)  # / d pose j+1
        gradient = np.zeros((len(T), 6))
        np.add.at(gradient, np.arange(len(e)), 2 * self.w * np.einsum("nki,nk->ni", J_a, e))
        np.add.at(gradient, np.arange(1, len(e) + 1), 2 * self.w * np.einsum("nki,nk->ni", J_b, e))
        diag = np.zeros((len(T), 6, 6))
        np.add.at(diag, np.arange(len(e)), 2 * self.w * np.einsum("nki,nkj->nij", J_a, J_a))
        np.add.at(diag, np.arange(1, len(e) + 1), 2 * self.w * np.einsum("nki,nkj->nij", J_b, J_b))
        return TermLinearization(self.cost(T), gradient, diag, 2 * self.w * np.einsum("nki,nkj->nij", J_a, J_b))


def fd_pose_gradient(cost, T_world_scan: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central finite differences (N, 6) of cost(T) along the left retraction's step (omega, rho)."""
    n = len(T_world_scan)
    fd = np.zeros((n, 6))
    for j in range(n):
        for k in range(6):
            d = np.zeros((n, 6))
            d[j, k] = h
            fd[j, k] = (cost(retract_left(T_world_scan, d)) - cost(retract_left(T_world_scan, -d))) / (2 * h)
    return fd


def corridor_scene(n_scans: int, noise_m: float, rng: np.random.Generator, noise_rng: np.random.Generator,
                   window: int = 3, points_per_observation: int = 20) -> tuple[FeatureProblem, np.ndarray]:
    """Scans 1 m apart along x whose planes all have normals with no x component (a corridor
    without end walls): the planes leave every scan's translation along x free, so pose terms
    (odometry factors) decide it. Plane points carry N(0, noise_m^2) along the normal."""
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, 0, 3] = np.arange(n_scans, dtype=np.float64)
    n_planes = 3 * n_scans
    normals = rng.normal(size=(n_planes, 3))
    normals[:, 0] = 0.0
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    first = np.arange(n_planes) % (n_scans - window + 1)
    centres = T[first + window // 2, :3, 3] + rng.uniform(-8, 8, (n_planes, 3))
    basis = tangent_basis(normals)
    plane_index = np.repeat(np.arange(n_planes), window)
    scan_index = (first[:, None] + np.arange(window)).ravel()
    uv = rng.uniform(-3, 3, (len(plane_index), points_per_observation, 2))
    p = plane_index
    q_world = (centres[p][:, None] + uv[..., :1] * basis[p, :, 0][:, None] + uv[..., 1:] * basis[p, :, 1][:, None]
               + noise_rng.normal(0, noise_m, (len(p), points_per_observation, 1)) * normals[p][:, None])
    q_scan = q_world - T[scan_index, :3, 3][:, None]  # the poses have no rotation
    qh = np.concatenate([q_scan, np.ones((len(p), points_per_observation, 1))], axis=2)
    clusters = np.einsum("omi,omj->oij", qh, qh)
    return make_problem(plane_index, scan_index, clusters, n_scans=n_scans, T_world_scan=T), T


def projected_information(rows_x: list[np.ndarray], rows_feature: list[np.ndarray], variances: list[np.ndarray]
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Dense W = 2 J^T P V P J and H = 2 J^T P J of one feature's residuals: per observation its residuals'
    rows over the poses (k, 6 N), over the feature's parameters (k, p) and their covariance (k, k); P projects
    out the feature's parameters (the brute-force check of the pose covariance's sandwich)."""
    Jx, Jf = np.vstack(rows_x), np.vstack(rows_feature)
    V = np.zeros((len(Jx), len(Jx)))
    first = np.cumsum([0] + [len(v) for v in variances])
    for v, lo in zip(variances, first, strict=False):
        V[lo:lo + len(v), lo:lo + len(v)] = v
    P = np.eye(len(V)) - Jf @ np.linalg.solve(Jf.T @ Jf, Jf.T)
    return 2.0 * Jx.T @ P @ V @ P @ Jx, 2.0 * Jx.T @ P @ Jx


def planes_seen_by_every_scan(rng: np.random.Generator, n_scans: int, n_planes: int, observe
                              ) -> tuple[FeatureProblem, np.ndarray, list[np.ndarray]]:
    """Poses scattered about the origin (0.2 rad, 2 m), planes with random normals about it (5 m), and every
    plane seen by every scan: `observe(i, j, centre, basis, normal)` gives scan j's points of plane i (world
    frame; `basis` (2, 3) the plane's in-plane directions, drawn from `rng`). Returns the problem, the poses
    T_world_scan and the points (world frame, in observation order)."""
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.2, (n_scans, 3)))
    T[:, :3, 3] = rng.normal(0, 2.0, (n_scans, 3))
    normals = rng.normal(size=(n_planes, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centres = rng.normal(0, 5.0, (n_planes, 3))
    plane_index, scan_index, clusters, points_world = [], [], [], []
    for i in range(n_planes):
        basis = np.linalg.svd(normals[i][None, :])[2][1:]  # two in-plane directions
        for j in range(n_scans):
            q = observe(i, j, centres[i], basis, normals[i])
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster((q - T[j, :3, 3]) @ T[j, :3, :3]))
            points_world.append(q)
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans,
                           T_world_scan=T)
    return problem, T, points_world
