"""Relative-pose (odometry) factors: exact gradient, Gauss-Newton Hessian, and what they do in a solve.

In a corridor (floor, ceiling, two walls parallel to x) the planes leave every scan free along x.
With the factors, the solvers correct the five observed degrees of freedom exactly and keep the
relative motions along x where the odometry put them.
"""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel, relative_motions
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3
from pa_cli.core.geometry import retract_left as retract_poses
from pa_cli.core.problem import make_problem
from pa_testing.synthetic_problems import perturb

MODEL = OdometryModel(point_sigma_m=0.01, translation_sigma_m=0.02, translation_sigma_per_m=0.01,
                      rotation_sigma_rad=np.deg2rad(0.1), rotation_sigma_per_rad=0.02,
                      rotation_sigma_rad_per_m=np.deg2rad(0.01))


def _random_poses(n: int, rng: np.random.Generator) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.5, (n, 3)))
    T[:, :3, 3] = rng.normal(0, 5.0, (n, 3))
    return T


def test_sigmas_grow_with_distance_and_angle():
    s_t, s_r = MODEL.sigmas(np.array([0.0, 1.0, 10.0]), np.array([0.0, 0.0, np.deg2rad(30)]))
    np.testing.assert_allclose(s_t, [0.02, 0.03, 0.12])
    np.testing.assert_allclose(s_r, np.deg2rad([0.1, 0.11, 0.1 + 0.6 + 0.1]))


def test_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    T0 = _random_poses(5, rng)
    factors = OdometryFactors(T0, MODEL)
    T = retract_poses(T0, rng.normal(0, 0.2, (5, 6)))
    fd = _finite_difference_gradient(factors, T)
    np.testing.assert_allclose(factors.linearize(T).gradient, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_sigmas_per_axis_weigh_each_axis_and_keep_the_derivatives_exact():
    """Factors with a sigma per pair and axis (a registration's measured noise): each axis's residual is
    weighted by point_sigma^2 / sigma^2, the normalized residuals are the per-axis ratios' norms per block, and
    the gradient still matches finite differences."""
    rng = np.random.default_rng(5)
    T0 = _random_poses(5, rng)
    R_z, t_z = relative_motions(T0)
    sigmas = rng.uniform(0.5, 2.0, (4, 6)) * np.r_[np.full(3, np.deg2rad(0.05)), np.full(3, 0.01)]
    factors = OdometryFactors.from_motions(R_z, t_z, MODEL, sigmas)
    np.testing.assert_allclose(factors.weights, MODEL.point_sigma_m**2 / sigmas**2)
    T = retract_poses(T0, rng.normal(0, 0.01, (5, 6)))
    e = factors.residuals(T)
    assert factors.cost(T) == pytest.approx(np.sum(MODEL.point_sigma_m**2 * (e / sigmas) ** 2), rel=1e-12)
    np.testing.assert_allclose(factors.normalized_residuals(T),
                               np.column_stack([np.linalg.norm(e[:, :3] / sigmas[:, :3], axis=1),
                                                np.linalg.norm(e[:, 3:] / sigmas[:, 3:], axis=1)]))
    fd = _finite_difference_gradient(factors, T)
    np.testing.assert_allclose(factors.linearize(T).gradient, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    model = OdometryFactors.from_motions(R_z, t_z, MODEL)  # without sigmas: the model's, isotropic per block
    np.testing.assert_array_equal(model.sigmas, model.model_sigmas())
    np.testing.assert_array_equal(model.weights, OdometryFactors(T0, MODEL).weights)


def _finite_difference_gradient(term, T: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences (N, 6) of a pose term's cost along the left retraction."""
    fd = np.zeros((len(T), 6))
    for j in range(len(T)):
        for k in range(6):
            d = np.zeros((len(T), 6))
            d[j, k] = h
            fd[j, k] = (term.cost(retract_poses(T, d)) - term.cost(retract_poses(T, -d))) / (2 * h)
    return fd


def test_jacobians_match_finite_differences_away_from_the_measurement():
    rng = np.random.default_rng(4)
    T0 = _random_poses(3, rng)
    factors = OdometryFactors(T0, MODEL)
    T = retract_poses(T0, rng.normal(0, 0.3, (3, 6)))
    _, J_prev, J_next = factors.jacobians(T)
    h = 1e-6
    for j, pair, J in ((0, 0, J_prev[0]), (1, 0, J_next[0]), (1, 1, J_prev[1]), (2, 1, J_next[1])):
        fd = np.zeros((6, 6))
        for k in range(6):
            d = np.zeros((3, 6))
            d[j, k] = h
            e_plus, e_minus = factors.residuals(retract_poses(T, d)), factors.residuals(retract_poses(T, -d))
            fd[:, k] = (e_plus[pair] - e_minus[pair]) / (2 * h)
        np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-7)


def test_hessian_is_exact_at_the_measurement_and_block_tridiagonal():
    rng = np.random.default_rng(1)
    T0 = _random_poses(4, rng)
    factors = OdometryFactors(T0, MODEL)
    lin = factors.linearize(T0)
    assert lin.cost == pytest.approx(0.0, abs=1e-20) and np.abs(lin.gradient).max() < 1e-12
    H = _assembled_hessian(factors, T0)
    assert np.all(H[:6, 12:] == 0) and np.all(H[12:, :6] == 0)  # no coupling beyond neighbours
    fd = _finite_difference_hessian(factors, T0)
    np.testing.assert_allclose(H, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def _assembled_hessian(term, T: np.ndarray) -> np.ndarray:
    """The dense Gauss-Newton Hessian of a pose term from its diagonal and pair blocks."""
    n = 6 * len(T)
    lin = term.linearize(T)
    H = np.zeros((n, n))
    for j in range(len(T)):
        H[6 * j:6 * j + 6, 6 * j:6 * j + 6] = lin.pose_blocks[j]
    for (j, k), block in zip(term.pose_pairs(), lin.pair_blocks, strict=True):
        H[6 * j:6 * j + 6, 6 * k:6 * k + 6] = block
        H[6 * k:6 * k + 6, 6 * j:6 * j + 6] = block.T
    return H


def _finite_difference_hessian(term, T: np.ndarray, h: float = 1e-4) -> np.ndarray:
    """Central second differences of a pose term's cost along the left retraction."""
    n = 6 * len(T)
    fd = np.zeros((n, n))
    for a in range(n):
        for b in range(a, n):
            def f(sa, sb, a=a, b=b):
                d = np.zeros(n)
                d[a] += sa * h
                d[b] += sb * h
                return term.cost(retract_poses(T, d.reshape(len(T), 6)))
            fd[a, b] = fd[b, a] = (f(1, 1) - f(1, -1) - f(-1, 1) + f(-1, -1)) / (4 * h * h)
    return fd


def test_rigid_motion_of_all_poses_costs_nothing():
    rng = np.random.default_rng(2)
    T0 = _random_poses(4, rng)
    factors = OdometryFactors(T0, MODEL)
    G = _random_poses(1, rng)[0]
    assert factors.cost(G @ T0) == pytest.approx(0.0, abs=1e-18)
    R_rel, t_rel = relative_motions(G @ T0)
    np.testing.assert_allclose(t_rel, factors.t_z, atol=1e-9)


def _corridor(n_scans: int = 8, points_per_plane: int = 200, seed: int = 0):
    """Floor z=0, ceiling z=2.5, walls y=+-1.5, scans 0.5 m apart along x; exact points."""
    rng = np.random.default_rng(seed)
    T_gt = np.tile(np.eye(4), (n_scans, 1, 1))
    T_gt[:, :3, :3] = exp_so3(np.column_stack([rng.normal(0, 0.02, n_scans), rng.normal(0, 0.02, n_scans),
                                               rng.normal(0, 0.1, n_scans)]))
    T_gt[:, :3, 3] = np.column_stack([0.5 * np.arange(n_scans), rng.normal(0, 0.2, n_scans),
                                      1.2 + rng.normal(0, 0.05, n_scans)])
    planes = [(2, 0.0), (2, 2.5), (1, -1.5), (1, 1.5)]  # (axis, value)
    plane_index, scan_index, clusters = [], [], []
    for j in range(n_scans):
        for i, (axis, value) in enumerate(planes):
            q = rng.uniform([-5.0, -1.5, 0.0], [10.0, 1.5, 2.5], (points_per_plane, 3))
            q[:, axis] = value
            R, t = T_gt[j, :3, :3], T_gt[j, :3, 3]
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster((q - t) @ R))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans)
    return problem, T_gt


@pytest.mark.parametrize("solver", ["newton", "lm"])
def test_factors_hold_the_unobserved_direction_only(solver):
    problem, T_gt = _corridor()
    # odometry with the right motion along x but noise in the observed directions
    T_odo = T_gt.copy()
    T_init = perturb(T_gt, np.deg2rad(0.5), 0.05, seed=3, keep_first=True)
    T_init[:, 0, 3] = T_gt[:, 0, 3]  # x where the odometry says (the truth here)
    factors = OdometryFactors(T_odo, MODEL)
    result = solve(problem, T_init, SolverConfig(max_iterations=100, solver=solver), terms=[factors])
    T = result.T_world_scan
    assert result.report["converged"]
    assert plane_cost(problem, T) < 1e-6  # the planes' directions are decided by the planes
    np.testing.assert_allclose(T[:, :3, 3], T_gt[:, :3, 3], atol=1e-3)  # x held by the factors
    assert result.report["cost_final_m2"] == pytest.approx(plane_cost(problem, T))
    assert result.report["odometry_cost_final_m2"] < result.report["odometry_cost_initial_m2"]


def test_newton_and_lm_reach_the_same_optimum_with_factors():
    problem, T_gt = _corridor(seed=1)
    T_odo = perturb(T_gt, np.deg2rad(0.3), 0.03, seed=5, keep_first=True)
    T_init = perturb(T_gt, np.deg2rad(1.0), 0.1, seed=6, keep_first=True)
    factors = OdometryFactors(T_odo, MODEL)
    a = solve(problem, T_init, SolverConfig(max_iterations=200, solver="newton"), terms=[factors])
    b = solve(problem, T_init, SolverConfig(max_iterations=200, solver="lm"), terms=[factors])
    np.testing.assert_allclose(a.T_world_scan, b.T_world_scan, atol=1e-5)
