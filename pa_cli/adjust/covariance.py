"""Per-scan pose covariance from the Hessian of the plane cost at the optimum.

Model. Each point's signed distance to its true plane is r_k = e_k with e_k i.i.d. N(0, sigma^2)
(sigma = the point-to-plane noise, m; noise within the plane does not move a flat plane's fit).
The cost tau = sum_k r_k^2 (m^2, planes at their optimum, NO factor 1/2) has, at the optimum,
the Gauss-Newton Hessian H = 2 J^T J (J = dr/dx over the pose parameters x, with the planes
profiled out: the Schur complement of the joint pose-plane normal matrix). The maximum
likelihood estimate then has, to first order (Gauss-Newton / Laplace approximation),

    Cov(x) = sigma^2 (J^T J)^-1 = 2 sigma^2 H^-1.

`pose_covariance` uses the exact Hessian of the solver (equal to the Gauss-Newton one up to
terms proportional to the residuals, which vanish on average at the optimum); where it is not
positive definite (poses not at a minimum) the Gauss-Newton Hessian is used and reported.
Pose priors or odometry factors that the solver adds to the cost enter H with their weights,
which are expressed in the same m^2 as the plane cost (their sigma_point is taken to be sigma).

Parameters x: per pose the world-frame left tangent of `pa_cli.geometry.retract_left`,
delta = (omega rad, rho m), T <- [[Exp(omega), rho], [0, 1]] T. The gauge pose is held fixed,
so every covariance is relative to it (the gauge pose's own covariance is zero).

Variance. Given (`point_sigma_m`): i.i.d., Cov = 2 sigma^2 H^-1. Otherwise estimated from the
residuals: the global sigma^2 = tau / (points - dof) with dof = 6 (scans - 1) + 3 planes (the
free poses and each plane's normal (2) and offset (1)) is reported, and the covariance uses one
variance per observation (scan j on plane i: its mean squared distance to the plane times
points / (points - dof)), because a LiDAR's noise is along the ray and the point-to-plane noise
of a surface seen at grazing incidence is a fraction of that of one seen head-on. With unequal
variances V the covariance of the (unweighted) estimate is the sandwich

    Cov(x) = (J^T P J)^-1 J^T P V P J (J^T P J)^-1 = 2 H^-1 W H^-1,   W = 2 J^T P V P J,

P projecting out each plane's parameters (`variance_information`); for V = sigma^2 I it is
2 sigma^2 H^-1 again. `noise_model="plane"` uses one variance per plane instead.

Computation. Only the 6x6 diagonal blocks of H^-1 are computed, by selected inversion
(`selected_inverse.py`). H is first re-expressed per pose in (omega, delta p) with
delta p = rho + omega x t the displacement of the scan origin (a block-diagonal congruence
that keeps the sparsity): this removes the lever arm of world-frame rotations about the origin,
which otherwise makes H ill-conditioned for scans far from it. The world-tangent covariance is
transformed back exactly.

File (`.npz`, `save_covariance` / `load_covariance`):

| array | shape | meaning |
|---|---|---|
| `covariance` | (N, 6, 6) | per scan, [omega rad, rho m] world-frame left tangent, relative to the gauge pose |
| `position_covariance_m2` | (N, 3, 3) | per scan, of the scan origin (world frame, m^2) |
| `position_sigma_m`, `rotation_sigma_rad` | (N,) | 1-sigma along the largest axis |
| `T_world_scan` | (N, 4, 4) | the poses the covariance belongs to |
| `point_sigma_m` | () | the given sigma, or the global residual sigma (m) |
| `point_sigma_source` | () str | `residual` or `given` |
| `gauge_pose` | () int | the fixed pose (its covariance is zero) |
| `n_points`, `dof` | () int | points on planes, parameters counted in the residual variance |
| `hessian` | () str | `exact` or `gauss-newton` |
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust.linalg import HessianPattern
from pa_cli.adjust.newton import NewtonModel
from pa_cli.adjust.selected_inverse import block_matrix, diagonal_blocks_of_inverse, diagonal_blocks_of_sandwich
from pa_cli.adjust.terms import PoseTerm
from pa_cli.clusters import plane_eigen, sum_per_plane
from pa_cli.errors import FormatError, InputError, SolverError
from pa_cli.geometry import log_so3, skew
from pa_cli.io.atomic import atomic_path
from pa_cli.problem import FEATURE_PLANE, FeatureProblem

PLANE_DOF = 3  # a plane's normal (2) and offset (1), fitted from the same residuals
POSE_DOF = 6
LEAST_CERTAIN_SCANS = 10  # scans listed in the report, least certain first


@dataclass
class PoseCovariance:
    """Per-scan pose covariances (see the module docstring for the frame and the file)."""

    covariance: np.ndarray  # (N, 6, 6): [omega rad, rho m], world-frame left tangent
    T_world_scan: np.ndarray  # (N, 4, 4)
    point_sigma_m: float
    point_sigma_source: str  # "residual" or "given"
    gauge_pose: int
    n_points: int
    dof: int
    hessian: str  # "exact" or "gauss-newton"

    def position_covariance_m2(self) -> np.ndarray:
        """(N, 3, 3) covariance of each scan origin (world frame, m^2): d p = -[t]x omega + rho."""
        J = origin_jacobian(self.T_world_scan)
        return J @ self.covariance @ J.transpose(0, 2, 1)

    def position_sigma_m(self) -> np.ndarray:
        """(N,) 1-sigma of each scan origin along its least certain axis (m)."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.position_covariance_m2())[:, -1], 0.0))

    def rotation_sigma_rad(self) -> np.ndarray:
        """(N,) 1-sigma of each rotation about its least certain axis (rad)."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.covariance[:, :3, :3])[:, -1], 0.0))


def origin_jacobian(T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3, 6) derivative of the scan origin t with respect to (omega, rho): [-[t]x, I]."""
    J = np.zeros((len(T_world_scan), 3, POSE_DOF))
    J[:, :, :3] = -skew(T_world_scan[:, :3, 3])
    J[:, :, 3:] = np.eye(3)
    return J


def residual_dof(n_scans: int, n_planes: int) -> int:
    """Parameters fitted from the residuals: 6 per free pose (one is the gauge) and 3 per plane."""
    return POSE_DOF * (n_scans - 1) + PLANE_DOF * n_planes


def residual_point_sigma(cost_m2: float, n_points: int, dof: int) -> float:
    """sigma (m) = sqrt(cost / (points - dof))."""
    if n_points <= dof:
        raise SolverError(f"{n_points} points on planes cannot estimate the point noise of {dof} parameters; "
                          "give it with --point-sigma-m.")
    return float(np.sqrt(max(cost_m2, 0.0) / (n_points - dof)))


def tangent_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(N, 6) error (omega rad, rho m) with T_est = [[Exp(omega), rho], [0, 1]] T_true."""
    R_err = T_est[:, :3, :3] @ T_true[:, :3, :3].transpose(0, 2, 1)
    omega = log_so3(R_err)
    rho = T_est[:, :3, 3] - np.einsum("nij,nj->ni", R_err, T_true[:, :3, 3])
    return np.hstack([omega, rho])


def nees(errors: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared e^T Sigma^-1 e per row of errors (..., 6); about 6 on average
    when the errors follow the covariance."""
    return np.einsum("...i,...i->...", errors, np.linalg.solve(covariance, errors[..., None])[..., 0])


def covariance_from_hessian(H: sp.spmatrix, free_poses: np.ndarray, T_world_scan: np.ndarray,
                            point_sigma_m: float | None = None, gradient_information: sp.spmatrix | None = None
                            ) -> np.ndarray:
    """(N, 6, 6) pose covariances from the reduced Hessian H (6 per free pose, in the order of
    `free_poses`, world-frame left tangent); zero blocks for the poses not in `free_poses`.

    With `point_sigma_m` (i.i.d. noise): 2 sigma^2 H^-1. Otherwise `gradient_information` M
    (the Hessian of the cost with every residual weighted by its variance, m^4) gives the
    sandwich 2 H^-1 M H^-1, the covariance of the unweighted estimate under unequal noise.
    """
    free_poses = np.asarray(free_poses, dtype=np.int64)
    # per pose x_world = A x_local, x_local = (omega, delta p): A = [[I, 0], [[t]x, I]]
    A = np.tile(np.eye(POSE_DOF), (len(free_poses), 1, 1))
    A[:, 3:, :3] = skew(T_world_scan[free_poses, :3, 3])

    def to_local(matrix: sp.spmatrix) -> sp.bsr_matrix:  # A^T matrix A, block by block
        blocks = block_matrix(matrix)
        row = np.repeat(np.arange(len(blocks.indptr) - 1), np.diff(blocks.indptr))
        data = A[row].transpose(0, 2, 1) @ blocks.data @ A[blocks.indices]
        return sp.bsr_matrix((data, blocks.indices, blocks.indptr), shape=blocks.shape)

    H_local = to_local(H)
    if gradient_information is None:
        if point_sigma_m is None:
            raise SolverError("covariance_from_hessian needs point_sigma_m or gradient_information.")
        blocks_local = point_sigma_m**2 * diagonal_blocks_of_inverse(H_local)
    else:
        blocks_local = diagonal_blocks_of_sandwich(H_local, to_local(gradient_information))
    out = np.zeros((len(T_world_scan), POSE_DOF, POSE_DOF))
    out[free_poses] = 2.0 * (A @ blocks_local @ A.transpose(0, 2, 1))
    return out


def observation_noise_variances(T_world_scan: np.ndarray, problem: FeatureProblem, moments: tuple,
                                starts: np.ndarray, pose_dof_factor: float) -> tuple[np.ndarray, tuple]:
    """Per-observation point-to-plane variance (O,) in m^2: the observation's mean squared distance
    to its plane at the optimum, times `pose_dof_factor` = points / (points - dof) (the share of
    the fitted parameters); also returns the `plane_eigen` outputs used."""
    eig = plane_eigen(T_world_scan, *moments, problem.scan_index, starts)
    S_o, c_o, _, vec, centroid, _ = eig
    n = vec[problem.plane_index, :, 0]
    dc = c_o - centroid[problem.plane_index]
    N_o = moments[3]
    rss = np.einsum("oi,oij,oj->o", n, S_o, n) + N_o * np.einsum("oi,oi->o", n, dc) ** 2
    return rss / N_o * pose_dof_factor, eig


def variance_information(pattern: HessianPattern, A_gn: np.ndarray, Bt_gn: np.ndarray, eig: tuple,
                         problem: FeatureProblem, moments: tuple, v_obs: np.ndarray,
                         pose_blocks: list[np.ndarray] = (),
                         pair_blocks: list[tuple[np.ndarray, np.ndarray]] = ()) -> sp.csc_matrix:
    """W = 2 J^T P V P J (reduced, CSC), half the covariance of the cost gradient when observation
    o's points have point-to-plane variance v_obs[o] (m^2), so that Cov = 2 H^-1 W H^-1: the
    Gauss-Newton Hessian of the cost with every residual weighted by its variance (m^4).

    J = d r / d x at the optimum, P projects out each plane's 3 parameters (plane coordinates
    q_1, q_2 (the in-plane eigenvectors, about the centroid) and q_3 (offset), information
    G = diag(lambda_2, lambda_3, N)). Per plane, with beta_j = Bt_gn of observation j
    (= sqrt(2) G^-1/2 J_pi^T J_x) and Q = G^-1/2 (sum_j v_j G_j) G^-1/2 (G_j the observation's
    share of G):

        W_jk = v_j A_gn,j [j = k] + beta_j^T (Q - (v_j + v_k) I) beta_k.

    The coupling is gamma_j^T Omega gamma_k with gamma_j = [beta_j; s_j beta_j], s_j = v_j / v
    (v the plane's mean variance, for scale) and Omega = [[Q, -v I], [-v I, 0]]; Omega has 3
    negative and 3 positive eigenvalues (Q is symmetric), whose eigen-directions give two
    rank-3 couplings of the form `pattern.assemble` sums. For v_j equal within each plane this
    is sum_planes v_i H_GN,i exactly. `pose_blocks` and `pair_blocks` (pose terms, already in
    m^4, see `HessianPattern.assemble`) are added.
    """
    S_o, c_o, lam, vec, centroid, N_plane = eig
    pidx = problem.plane_index
    N_o = moments[3]
    # G_j in the plane coordinates (q_1, q_2, q_3)
    E = vec[pidx][:, :, 1:]  # (O, 3, 2)
    d = np.einsum("oia,oi->oa", E, c_o - centroid[pidx])
    G_o = np.zeros((len(pidx), 3, 3))
    G_o[:, :2, :2] = E.transpose(0, 2, 1) @ S_o @ E + N_o[:, None, None] * d[:, :, None] * d[:, None, :]
    G_o[:, :2, 2] = G_o[:, 2, :2] = N_o[:, None] * d
    G_o[:, 2, 2] = N_o
    starts = np.r_[0, np.cumsum(np.bincount(pidx, minlength=problem.n_planes))]
    G_v = sum_per_plane(v_obs[:, None, None] * G_o, starts)
    g = np.column_stack([lam[:, 1], lam[:, 2], N_plane])
    with np.errstate(divide="ignore", invalid="ignore"):
        g_isqrt = np.where(g > 0, 1.0 / np.sqrt(np.where(g > 0, g, 1.0)), 0.0)
    v_mean = sum_per_plane(v_obs * N_o, starts) / N_plane
    scale = np.where(v_mean > 0, v_mean, 1.0)
    Omega = np.zeros((problem.n_planes, 6, 6))
    Omega[:, :3, :3] = g_isqrt[:, :, None] * G_v * g_isqrt[:, None, :]
    Omega[:, :3, 3:] = Omega[:, 3:, :3] = -scale[:, None, None] * np.eye(3)
    omega, U = np.linalg.eigh(Omega)  # ascending: 3 negative, then 3 positive
    U = U * np.sqrt(np.abs(omega))[:, None, :]
    s_obs = (v_obs / scale[pidx])[:, None, None]
    mix = (U[pidx, :3, :] + s_obs * U[pidx, 3:, :]).transpose(0, 2, 1)  # (O, 6 eigen-directions, 3)
    negative = pattern.assemble(v_obs[:, None, None] * A_gn, mix[:, :3] @ Bt_gn, pose_blocks,
                                pair_blocks).pose_hessian()
    positive = pattern.assemble(np.zeros_like(A_gn), mix[:, 3:] @ Bt_gn).pose_hessian()
    return (negative - positive).tocsc()


def plane_noise_variances(lambda_min_m2: np.ndarray, points_per_plane: np.ndarray, pose_dof_factor: float,
                          default_m2: float) -> np.ndarray:
    """Per-plane point-to-plane variance (P,) in m^2: lambda_min / (N - 3), times the share of the
    pose dof `pose_dof_factor` = (points - 3 planes) / (points - dof); `default_m2` for planes of
    at most 3 points (their residual is zero by construction)."""
    spare = points_per_plane - PLANE_DOF
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(spare > 0, np.maximum(lambda_min_m2, 0.0) / np.where(spare > 0, spare, 1.0), default_m2)
    return v * np.where(spare > 0, pose_dof_factor, 1.0)


NOISE_MODELS = ("observation", "plane")


def pose_covariance(problem: FeatureProblem, T_world_scan: np.ndarray, fixed_pose: int = 0,
                    point_sigma_m: float | None = None, eigen_gap_tolerance: float = 1e-6,
                    terms: Sequence[PoseTerm] = (), noise_model: str = "observation",
                    model: NewtonModel | None = None) -> PoseCovariance:
    """Covariance of every pose at (converged) poses T_world_scan; see the module docstring.

    With `point_sigma_m` the noise is i.i.d. with that sigma (2 sigma^2 H^-1). Otherwise the
    variances are estimated from the residuals, per observation (`noise_model="observation"`,
    `observation_noise_variances`) or per plane (`"plane"`, `plane_noise_variances`), and the
    sandwich 2 H^-1 W H^-1 (`variance_information`) is used. `terms` are the pose terms the
    solver minimised with the planes (prior, odometry factors): their Hessian blocks are part of
    H, and sigma^2 times them part of W. `model` reuses the solver's `NewtonModel` of the same
    problem, gauge and terms (its setup is then skipped).
    """
    if noise_model not in NOISE_MODELS:
        raise SolverError(f"unknown noise model '{noise_model}'; expected one of {', '.join(NOISE_MODELS)}.")
    n_edges = int(np.count_nonzero(problem.feature_kind != FEATURE_PLANE))
    if n_edges:
        raise SolverError(f"the pose covariance handles plane features only; the problem has {n_edges} edge "
                          "features (edges.enabled: false).")
    T = np.asarray(T_world_scan, dtype=np.float64)
    if model is None:
        model = NewtonModel(problem, fixed_pose, eigen_gap_tolerance, terms)
    plane_cost = model.feature_cost.parts[0][1]  # planes only: one part, the whole problem
    der = plane_cost.linearize(T)
    term_lins = [term.linearize(T) for term in model.terms]
    pose_blocks = [t.pose_blocks for t in term_lins]
    pair_blocks = [(term.pose_pairs(), t.pair_blocks) for term, t in zip(model.terms, term_lins, strict=True)]
    dof = residual_dof(problem.n_scans, problem.n_planes)
    sigma_residual = residual_point_sigma(der.cost, problem.n_points, dof)
    information = None
    if point_sigma_m is None:
        sigma, source = sigma_residual, "residual"
        v_obs, eig = observation_noise_variances(T, problem, plane_cost.moments, plane_cost.starts,
                                                 problem.n_points / (problem.n_points - dof))
        if noise_model == "plane":
            factor = (problem.n_points - PLANE_DOF * problem.n_planes) / (problem.n_points - dof)
            v_obs = plane_noise_variances(eig[2][:, 0], eig[5], factor, sigma**2)[problem.plane_index]
        information = variance_information(
            model.pattern, der.A_gn, der.Bt_gn, eig, problem, plane_cost.moments, v_obs,
            [sigma**2 * b for b in pose_blocks], [(pairs, sigma**2 * b) for pairs, b in pair_blocks])
    elif np.isfinite(point_sigma_m) and point_sigma_m > 0:
        sigma, source = float(point_sigma_m), "given"
    else:
        raise SolverError(f"the point sigma must be a positive number of metres; got {point_sigma_m} "
                          "(--point-sigma-m).")
    free = model.pattern.free_poses
    kind = "exact"
    try:
        H = model.pattern.assemble(der.A, der.Bt, pose_blocks, pair_blocks).pose_hessian()
        cov = covariance_from_hessian(H, free, T, sigma, information)
    except SolverError:
        kind = "gauss-newton"
        H = model.pattern.assemble(der.A_gn, der.Bt_gn, pose_blocks, pair_blocks).pose_hessian()
        cov = covariance_from_hessian(H, free, T, sigma, information)
    return PoseCovariance(covariance=cov, T_world_scan=T, point_sigma_m=sigma, point_sigma_source=source,
                          gauge_pose=int(fixed_pose), n_points=int(problem.n_points), dof=int(dof), hessian=kind)


def covariance_report(cov: PoseCovariance, time_s: float | None = None) -> dict[str, Any]:
    """Report entries: the noise used, per-scan 1-sigma position (m) and rotation (deg) along the
    least certain axis, and the `LEAST_CERTAIN_SCANS` scans with the largest position sigma."""
    pos = cov.position_sigma_m()
    rot_deg = np.rad2deg(cov.rotation_sigma_rad())
    free = np.flatnonzero(np.arange(len(pos)) != cov.gauge_pose)
    worst = free[np.argsort(-pos[free], kind="stable")[:LEAST_CERTAIN_SCANS]]
    report: dict[str, Any] = {
        "point_sigma_m": cov.point_sigma_m,
        "point_sigma_source": cov.point_sigma_source,
        "dof": cov.dof,
        "n_points": cov.n_points,
        "gauge_pose": cov.gauge_pose,
        "hessian": cov.hessian,
        "position_sigma_m": pos.tolist(),
        "rotation_sigma_deg": rot_deg.tolist(),
        "position_sigma_m_median": float(np.median(pos[free])) if len(free) else 0.0,
        "rotation_sigma_deg_median": float(np.median(rot_deg[free])) if len(free) else 0.0,
        "least_certain_scans": [{"scan": int(j), "position_sigma_m": float(pos[j]),
                                 "rotation_sigma_deg": float(rot_deg[j])} for j in worst],
    }
    if time_s is not None:
        report["time_s"] = time_s
    return report


def timed_pose_covariance(problem: FeatureProblem, T_world_scan: np.ndarray, **kwargs: Any
                          ) -> tuple[PoseCovariance, dict[str, Any]]:
    """`pose_covariance` and its `covariance_report` (with the wall time)."""
    t0 = time.perf_counter()
    cov = pose_covariance(problem, T_world_scan, **kwargs)
    return cov, covariance_report(cov, time.perf_counter() - t0)


def save_covariance(path: Path | str, cov: PoseCovariance, force: bool = False) -> None:
    """Write the covariance file (`.npz`, atomically; the arrays of the module docstring)."""
    arrays = {
        "covariance": cov.covariance,
        "position_covariance_m2": cov.position_covariance_m2(),
        "position_sigma_m": cov.position_sigma_m(),
        "rotation_sigma_rad": cov.rotation_sigma_rad(),
        "T_world_scan": cov.T_world_scan,
        "point_sigma_m": np.float64(cov.point_sigma_m),
        "point_sigma_source": np.str_(cov.point_sigma_source),
        "gauge_pose": np.int64(cov.gauge_pose),
        "n_points": np.int64(cov.n_points),
        "dof": np.int64(cov.dof),
        "hessian": np.str_(cov.hessian),
    }
    with atomic_path(path, force) as tmp, tmp.open("wb") as f:
        np.savez_compressed(f, **arrays)


def load_covariance(path: Path | str) -> PoseCovariance:
    """Read a covariance file written by `save_covariance`."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: covariance file not found.")
    try:
        with np.load(path, allow_pickle=False) as data:
            cov = PoseCovariance(covariance=data["covariance"], T_world_scan=data["T_world_scan"],
                                 point_sigma_m=float(data["point_sigma_m"]),
                                 point_sigma_source=str(data["point_sigma_source"]),
                                 gauge_pose=int(data["gauge_pose"]), n_points=int(data["n_points"]),
                                 dof=int(data["dof"]), hessian=str(data["hessian"]))
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: not a pose-covariance .npz with 'covariance', 'T_world_scan', "
                          f"'point_sigma_m', ... ({exc}).") from None
    n = len(cov.T_world_scan)
    if cov.covariance.shape != (n, POSE_DOF, POSE_DOF) or cov.T_world_scan.shape != (n, 4, 4):
        raise FormatError(f"{path}: 'covariance' has shape {cov.covariance.shape} and 'T_world_scan' "
                          f"{cov.T_world_scan.shape}; expected (N, 6, 6) and (N, 4, 4).")
    return cov
