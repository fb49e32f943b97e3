"""The second-order plane adjustment engine: derivatives, cost, gauge, recovery, convergence."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.newton import FeatureCost, NewtonModel
from pa_cli.adjust.terms import TermLinearization
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3, retract_left
from pa_cli.core.problem import make_problem
from pa_testing.synthetic_problems import make_scene, perturb

LEVELS = [(0.1, 0.01), (1.0, 0.1), (2.0, 0.2), (3.0, 0.3)]  # (sigma_rot_deg, sigma_trans_m), seed 000


def random_problem(seed: int, n_scans: int = 4, n_planes: int = 5, thickness_m: float = 0.1):
    """Random poses, random thick planes: returns (problem, T_world_scan, points[plane][scan] scan frame)."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.4, (n_scans, 3)))
    T[:, :3, 3] = rng.normal(0, 2, (n_scans, 3))
    plane_index, scan_index, clusters, points = [], [], [], {}
    for i in range(n_planes):
        R_plane = exp_so3(rng.normal(0, 1, (1, 3)))[0]
        centre = rng.normal(0, 3, 3)
        for j in range(n_scans):
            local = rng.normal(0, 1, (15, 3)) * [2.0, 1.0, thickness_m]
            q_world = local @ R_plane.T + centre
            p_scan = (q_world - T[j, :3, 3]) @ T[j, :3, :3]
            points[i, j] = p_scan
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster(p_scan))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans)
    return problem, T, points


def dense_hessian(problem, T_world_scan, eigen_gap_tolerance=0.0):
    """Cost, full gradient (6N,) and full dense Hessian (6N, 6N) including every pose, by plain loops
    (any feature kinds)."""
    der = FeatureCost(problem, eigen_gap_tolerance).linearize(T_world_scan)
    starts = FeatureCost(problem).starts
    n6 = 6 * problem.n_scans
    H = np.zeros((n6, n6))
    j = problem.scan_index
    for o in range(len(j)):
        H[6 * j[o]:6 * j[o] + 6, 6 * j[o]:6 * j[o] + 6] += der.A[o]
    for i in range(problem.n_planes):
        obs = np.arange(starts[i], starts[i + 1])
        for a in obs:
            for b in obs:
                H[6 * j[a]:6 * j[a] + 6, 6 * j[b]:6 * j[b] + 6] -= der.Bt[a].T @ der.Bt[b]
    return der.cost, der.gradient.ravel(), H


def fd_gradient(problem, T, h=1e-6):
    n = 6 * problem.n_scans
    E = np.eye(n)
    return np.array([(plane_cost(problem, retract_left(T, (h * E[a]).reshape(-1, 6)))
                      - plane_cost(problem, retract_left(T, (-h * E[a]).reshape(-1, 6)))) / (2 * h)
                     for a in range(n)])


def fd_hessian(problem, T, h=1e-4):
    """(6N, 6N) Hessian of the feature cost by central second differences along the left retraction."""
    n = 6 * problem.n_scans
    E = np.eye(n)

    def f(x):
        return plane_cost(problem, retract_left(T, x.reshape(-1, 6)))

    H_fd = np.zeros((n, n))
    for a in range(n):
        for b in range(a, n):
            ea, eb = h * E[a], h * E[b]
            H_fd[a, b] = H_fd[b, a] = (f(ea + eb) - f(ea - eb) - f(eb - ea) + f(-ea - eb)) / (4 * h * h)
    return H_fd


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_and_hessian_match_central_differences_of_cost(seed):
    problem, T, _ = random_problem(seed)
    _, g, H = dense_hessian(problem, T)
    g_fd = fd_gradient(problem, T)
    assert np.linalg.norm(g - g_fd) / np.linalg.norm(g_fd) < 1e-6
    H_fd = fd_hessian(problem, T)
    # Second differences of the cost lose ~eps * cost / h^2 of precision; compare on the scale of H.
    assert np.linalg.norm(H - H_fd) / np.linalg.norm(H_fd) < 1e-6


def test_hessian_matches_central_differences_of_gradient():
    problem, T, _ = random_problem(3, n_scans=5, n_planes=6)
    _, _, H = dense_hessian(problem, T)
    n, h = 6 * problem.n_scans, 1e-5
    H_fd = np.zeros((n, n))
    for a in range(n):
        e = np.zeros(n)
        e[a] = h
        g_plus = dense_hessian(problem, retract_left(T, e.reshape(-1, 6)))[1]
        g_minus = dense_hessian(problem, retract_left(T, -e.reshape(-1, 6)))[1]
        H_fd[:, a] = (g_plus - g_minus) / (2 * h)
    # d/dx of g(retract(x)) is H plus a term from composing retractions (antisymmetric part of
    # the left Jacobian), which vanishes at a stationary point only; symmetrise and compare the
    # translation-translation blocks exactly, where retractions commute.
    idx = np.concatenate([np.arange(6 * j + 3, 6 * j + 6) for j in range(problem.n_scans)])
    sub = np.ix_(idx, idx)
    assert np.linalg.norm(H[sub] - H_fd[sub]) / np.linalg.norm(H_fd[sub]) < 1e-6


def test_sparse_assembly_equals_dense_reduced_hessian():
    problem, T, _ = random_problem(4, n_scans=6, n_planes=8)
    _, g, H = dense_hessian(problem, T, eigen_gap_tolerance=1e-6)
    fixed = 2
    model = NewtonModel(problem, fixed_pose=fixed)
    lin = model.linearize(T)
    keep = np.array([a for a in range(6 * problem.n_scans) if a // 6 != fixed])
    np.testing.assert_allclose(lin.H.hessian(), H[np.ix_(keep, keep)], rtol=0, atol=1e-10 * np.abs(H).max())
    np.testing.assert_allclose(lin.g, g[keep], rtol=0, atol=1e-12 * np.abs(g).max())


class _PairTerm:
    """A pose term with random blocks on the diagonal and on given pose pairs (for assembly tests)."""

    name = "pairs"

    def __init__(self, n_scans, pairs, seed):
        rng = np.random.default_rng(seed)
        self.pairs = np.asarray(pairs)
        self.diag = rng.normal(size=(n_scans, 6, 6))
        self.diag += self.diag.transpose(0, 2, 1)  # Hessian blocks H_jj are symmetric
        self.off = rng.normal(size=(len(pairs), 6, 6))

    def cost(self, T):
        return 0.0

    def linearize(self, T):
        return TermLinearization(0.0, np.zeros((len(T), 6)), self.diag, self.off)

    def pose_pairs(self):
        return self.pairs

    def add_to(self, H):
        """Add the term's blocks to a dense (6N, 6N) Hessian in place."""
        for j, block in enumerate(self.diag):
            H[6 * j:6 * j + 6, 6 * j:6 * j + 6] += block
        for (j, k), block in zip(self.pairs, self.off, strict=True):
            H[6 * j:6 * j + 6, 6 * k:6 * k + 6] += block
            H[6 * k:6 * k + 6, 6 * j:6 * j + 6] += block.T


def test_pose_term_blocks_land_in_the_sparse_hessian():
    """Pair blocks of a pose term go to H_jk (transposed to H_kj), also for pairs sharing no plane."""
    problem, T, _ = random_problem(4, n_scans=6, n_planes=8)
    sub = make_problem(problem.plane_index[problem.scan_index < 3], problem.scan_index[problem.scan_index < 3],
                       problem.clusters[problem.scan_index < 3], n_scans=6)  # scans 3..5 see no plane
    term = _PairTerm(6, [(0, 1), (4, 3), (2, 5)], seed=1)
    _, _, H = dense_hessian(sub, T, eigen_gap_tolerance=1e-6)
    term.add_to(H)
    lin = NewtonModel(sub, fixed_pose=0, terms=[term]).linearize(T)
    np.testing.assert_allclose(lin.H.hessian(), H[6:, 6:], rtol=0, atol=1e-10 * np.abs(H).max())


def test_cost_equals_brute_force_pca_planes():
    problem, T, points = random_problem(5, n_scans=4, n_planes=6)
    brute = 0.0
    for i in range(6):
        q = np.vstack([points[i, j] @ T[j, :3, :3].T + T[j, :3, 3] for j in range(4)])
        centred = q - q.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
        brute += np.sum((centred @ normal) ** 2)
    assert plane_cost(problem, T) == pytest.approx(brute, rel=1e-10)


def test_cost_invariant_to_rigid_motion_and_gauge_null_space():
    problem, T, _ = random_problem(6)
    G = np.eye(4)
    G[:3, :3] = exp_so3(np.array([[0.3, -0.2, 0.5]]))[0]
    G[:3, 3] = [1.0, -2.0, 3.0]
    assert plane_cost(problem, G @ T) == pytest.approx(plane_cost(problem, T), rel=1e-11)
    _, g, H = dense_hessian(problem, T)
    # a common left step (omega, rho) on every pose is one rigid motion of the whole map
    Z = np.tile(np.eye(6), (problem.n_scans, 1))  # (6N, 6)
    assert np.abs(g @ Z).max() < 1e-9 * np.abs(g).max()
    # translations commute with everything: H annihilates them anywhere; for rotations the
    # curvature along the motion vanishes (z^T H z = 0) and H z = 0 holds at a stationary point
    assert np.abs(H @ Z[:, 3:]).max() < 1e-9 * np.abs(H).max()
    assert np.abs(Z.T @ H @ Z).max() < 1e-9 * np.abs(H).max()
    T_opt = solve(problem, T, SolverConfig()).T_world_scan
    _, g_opt, H_opt = dense_hessian(problem, T_opt)
    assert np.abs(H_opt @ Z).max() < 1e-7 * np.abs(H_opt).max()


@pytest.mark.parametrize("level", [1, 2, 3, 4])
def test_exact_recovery_noise_free(level):
    sigma_rot_deg, sigma_trans_m = LEVELS[level - 1]
    problem, T_gt = make_scene(40, 200, 8, points_per_observation=15, seed=level)
    T0 = perturb(T_gt, np.deg2rad(sigma_rot_deg), sigma_trans_m, seed=100 + level)
    result = solve(problem, T0, SolverConfig())
    T = result.T_world_scan
    assert result.report["converged"]
    assert result.report["iterations"] <= 30
    assert np.abs(T[:, :3, 3] - T_gt[:, :3, 3]).max() < 1e-6
    dR = np.einsum("nji,njk->nik", T[:, :3, :3], T_gt[:, :3, :3])
    angle = np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angle.max() < 1e-7  # rad; ~1e-6 m at the scene's 10 m lever arms
    costs = [result.report["cost_initial_m2"]] + [h["cost_m2"] for h in result.report["history"]]
    assert np.all(np.diff(costs) <= 0)  # never accepts a cost increase


def test_quadratic_convergence_near_optimum():
    problem, T_gt = make_scene(30, 150, 6, points_per_observation=15, noise_m=0.01, seed=7)
    model = NewtonModel(problem)
    tight = SolverConfig(cost_tolerance=0.0, gradient_tolerance=0.0, step_tolerance=1e-14)
    T_opt = solve(problem, T_gt, tight).T_world_scan
    # the damped loop takes a step only when the cost falls: at the cost's floating-point floor
    # (relative 1e-15) that leaves the poses up to ~1e-7 m from the optimum, as rounding falls;
    # two pure Newton steps from there reach it
    for _ in range(2):
        T_opt = retract_left(T_opt, model.linearize(T_opt).solve(0.0)[0])
    T = perturb(T_opt, np.deg2rad(0.05), 0.005, seed=8)
    grad_norms = []
    for _ in range(6):  # pure Newton steps (no damping)
        lin = model.linearize(T)
        grad_norms.append(lin.gradient_norm)
        step, predicted = lin.solve(0.0)
        assert step is not None and predicted > 0
        T = retract_left(T, step)
    assert np.abs(T[:, :3, 3] - T_opt[:, :3, 3]).max() < 1e-8
    # the first step is pre-asymptotic; below 1e-10 m^2 is the floating-point floor
    e = np.array([x for x in grad_norms[1:] if x > 1e-10])
    assert len(e) >= 3
    # quadratic: e_{k+1} <= C e_k^2 with one C; linear convergence would make e_{k+1}/e_k^2 blow up,
    # and the contraction factor itself must shrink by orders of magnitude
    C = e[1:] / e[:-1] ** 2
    assert C.max() < 10.0
    ratios = e[1:] / e[:-1]
    assert np.all(ratios[1:] < 0.1 * ratios[:-1])


def test_eigen_gap_guard_is_reported():
    problem, T, points = random_problem(9, n_scans=3, n_planes=4)
    # add a line-like "plane": lambda_min == lambda_mid, the eigenvector term would blow up
    rng = np.random.default_rng(0)
    clusters = list(problem.clusters)
    plane_index, scan_index = list(problem.plane_index), list(problem.scan_index)
    for j in range(3):
        q_world = np.outer(rng.uniform(-3, 3, 10), [1.0, 0.5, 0.2]) + [1.0, 2.0, 3.0]
        clusters.append(points_to_cluster((q_world - T[j, :3, 3]) @ T[j, :3, :3]))
        plane_index.append(4)
        scan_index.append(j)
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=3)
    result = solve(problem, T, SolverConfig())  # the line is exactly degenerate at T
    assert any("eigen-gap guard" in w for w in result.report["warnings"])
    assert np.isfinite(result.report["cost_final_m2"])
    assert result.report["cost_final_m2"] <= result.report["cost_initial_m2"]
