"""The Newton solver's centred pose tangent: derivatives, pose terms and independence of the world origin."""

from __future__ import annotations

import numpy as np

from pa_cli.adjust import plane_cost
from pa_cli.adjust.newton import NewtonModel, centre_blocks, centring, retract_centred, solve_newton
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.config import SolverConfig
from pa_cli.core.geometry import exp_so3, retract_left
from pa_testing.synthetic_problems import make_scene, perturb
from tests.unit.adjust.test_adjust_newton import random_problem

FAR_M = np.array([800.0, -300.0, 50.0])  # a world origin far from the scans: lever arms of ~1 km


def far_problem(seed: int):
    problem, T, _ = random_problem(seed)
    T = T.copy()
    T[:, :3, 3] += FAR_M
    return problem, T


def test_retract_centred_turns_each_scan_about_its_own_position():
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.5, (3, 3)))
    T[:, :3, 3] = rng.normal(0, 100, (3, 3))
    delta = rng.normal(0, 0.1, (3, 6))
    moved = retract_centred(T, delta)
    p_scan = rng.normal(0, 2, 3)
    for j in range(3):
        q = T[j, :3, :3] @ p_scan + T[j, :3, 3]
        expected = exp_so3(delta[j:j + 1, :3])[0] @ (q - T[j, :3, 3]) + T[j, :3, 3] + delta[j, 3:]
        np.testing.assert_allclose(moved[j, :3, :3] @ p_scan + moved[j, :3, 3], expected, atol=1e-9)
    # the same pose the left retraction reaches with rho = rho_c - (Exp(omega) - I) t
    R = exp_so3(delta[:, :3])
    rho_left = delta[:, 3:] - np.einsum("nij,nj->ni", R - np.eye(3), T[:, :3, 3])
    np.testing.assert_allclose(retract_left(T, np.hstack([delta[:, :3], rho_left])), moved, atol=1e-9)


def test_centred_gradient_and_hessian_match_central_differences_far_from_the_origin():
    problem, T = far_problem(1)
    fixed = 1
    lin = NewtonModel(problem, fixed_pose=fixed, eigen_gap_tolerance=0.0, centred=True).linearize(T)
    free = [j for j in range(problem.n_scans) if j != fixed]
    n = 6 * len(free)

    def f(x):
        delta = np.zeros((problem.n_scans, 6))
        delta[free] = x.reshape(-1, 6)
        return plane_cost(problem, retract_centred(T, delta))

    E, h = np.eye(n), 1e-4
    g_fd = np.array([(f(1e-6 * E[a]) - f(-1e-6 * E[a])) / 2e-6 for a in range(n)])
    assert np.linalg.norm(lin.g - g_fd) / np.linalg.norm(g_fd) < 1e-6
    H_fd = np.zeros((n, n))
    for a in range(n):
        for b in range(a, n):
            ea, eb = h * E[a], h * E[b]
            H_fd[a, b] = H_fd[b, a] = (f(ea + eb) - f(ea - eb) - f(eb - ea) + f(-ea - eb)) / (4 * h * h)
    assert np.linalg.norm(lin.H.hessian() - H_fd) / np.linalg.norm(H_fd) < 1e-6


def test_centred_pose_terms_are_the_left_blocks_moved_by_the_change_of_tangent():
    """With the odometry factors: the centred system is J^T H J plus the second-order term of the
    change of retraction, J = [[I, 0], [[t]x, I]] per scan, built from the left system densely."""
    problem, T = far_problem(2)
    rng = np.random.default_rng(3)
    odometry = OdometryFactors(retract_left(T, rng.normal(0, 0.01, (problem.n_scans, 6))),
                               OdometryModel(0.01, 0.05, 0.01, np.deg2rad(0.5), 0.01, np.deg2rad(0.01)))
    left = NewtonModel(problem, fixed_pose=0, terms=[odometry]).linearize(T)
    centred = NewtonModel(problem, fixed_pose=0, terms=[odometry], centred=True).linearize(T)
    K = centring(T)[1:]
    n = len(K)
    J = np.zeros((6 * n, 6 * n))
    second = np.zeros((6 * n, 6 * n))
    g_rho = left.gradient[1:, 3:]
    t = T[1:, :3, 3]
    for j in range(n):
        J[6 * j:6 * j + 6, 6 * j:6 * j + 6] = np.block([[np.eye(3), np.zeros((3, 3))], [K[j], np.eye(3)]])
        second[6 * j:6 * j + 3, 6 * j:6 * j + 3] = -0.5 * (np.outer(g_rho[j], t[j]) + np.outer(t[j], g_rho[j])
                                                           - 2.0 * (g_rho[j] @ t[j]) * np.eye(3))
    H_expected = J.T @ left.H.hessian() @ J + second
    np.testing.assert_allclose(centred.H.hessian(), H_expected, rtol=0, atol=1e-9 * np.abs(H_expected).max())
    np.testing.assert_allclose(centred.g, J.T @ left.g, rtol=0, atol=1e-10 * np.abs(left.g).max())


def test_centre_blocks_is_the_congruence_by_the_change_of_tangent():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(5, 6, 6))
    K_row, K_col = centring(_poses(rng, 5)), centring(_poses(rng, 5))
    for m in range(5):
        J_row = np.block([[np.eye(3), np.zeros((3, 3))], [K_row[m], np.eye(3)]])
        J_col = np.block([[np.eye(3), np.zeros((3, 3))], [K_col[m], np.eye(3)]])
        np.testing.assert_allclose(centre_blocks(X, K_row, K_col)[m], J_row.T @ X[m] @ J_col, atol=1e-9)


def _poses(rng, n):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return T


def test_solver_iterations_do_not_depend_on_the_world_origin():
    """The same sequence 20 km from the origin: the same iterations and optimum (in world-frame
    left coordinates it needed about twice the iterations and stopped short)."""
    problem, T_gt = make_scene(120, 480, 20, points_per_observation=10, noise_m=0.01, seed=5)
    T0 = perturb(T_gt, np.deg2rad(0.05), 0.005, seed=6)
    config = SolverConfig(max_iterations=30, cost_tolerance=1e-10)
    near = solve_newton(problem, T0, config)
    T_far = T0.copy()
    T_far[:, 0, 3] += 2e4
    far = solve_newton(problem, T_far, config)
    assert far.fields["stop_reason"] == near.fields["stop_reason"] == "cost_tolerance"
    assert abs(far.fields["iterations"] - near.fields["iterations"]) <= 1
    assert abs(far.fields["cost_final_m2"] / near.fields["cost_final_m2"] - 1) < 1e-9
