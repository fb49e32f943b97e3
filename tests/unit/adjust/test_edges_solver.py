"""The edge feature cost (lambda_min + lambda_mid): derivatives, cost, mixed problems, recovery."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.edges import EdgeCost
from pa_cli.adjust.newton import FeatureCost, NewtonModel
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from pa_testing.synthetic_problems import perturb, random_poses
from tests.unit.adjust.test_adjust_newton import dense_hessian, fd_gradient, fd_hessian


def random_feature_problem(seed: int, n_scans: int = 4, n_edges: int = 4, n_planes: int = 0,
                           thickness_m: tuple[float, float] = (0.1, 0.05), points: int = 15):
    """Random poses, thick random lines (and planes): (problem, T_world_scan, points[feature, scan]).

    Edge points spread 2 m along a random direction and `thickness_m` across it; plane points
    2 m x 1 m in a random plane, 0.1 m thick. Features 0..n_edges-1 are edges, the rest planes."""
    rng = np.random.default_rng(seed)
    T = random_poses(n_scans, rng, 0.4, 2.0)
    plane_index, scan_index, clusters, pts = [], [], [], {}
    kinds = [FEATURE_EDGE] * n_edges + [FEATURE_PLANE] * n_planes
    for i, kind in enumerate(kinds):
        R = exp_so3(rng.normal(0, 1, (1, 3)))[0]
        centre = rng.normal(0, 3, 3)
        scale = [2.0, *thickness_m] if kind == FEATURE_EDGE else [2.0, 1.0, 0.1]
        for j in range(n_scans):
            q_world = (rng.normal(0, 1, (points, 3)) * scale) @ R.T + centre
            p_scan = (q_world - T[j, :3, 3]) @ T[j, :3, :3]
            pts[i, j] = p_scan
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster(p_scan))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans,
                           feature_kind=np.array(kinds, dtype=np.uint8))
    return problem, T, pts


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("n_planes", [0, 3])
def test_gradient_matches_central_differences(seed, n_planes):
    problem, T, _ = random_feature_problem(seed, n_planes=n_planes)
    _, g, _ = dense_hessian(problem, T)
    g_fd = fd_gradient(problem, T)
    assert np.linalg.norm(g - g_fd) / np.linalg.norm(g_fd) < 1e-6


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("n_planes", [0, 3])
def test_hessian_matches_central_differences_of_cost(seed, n_planes):
    problem, T, _ = random_feature_problem(seed, n_scans=3, n_planes=n_planes)
    _, _, H = dense_hessian(problem, T)
    H_fd = fd_hessian(problem, T)
    assert np.linalg.norm(H - H_fd) / np.linalg.norm(H_fd) < 1e-6


def test_cost_equals_brute_force_point_to_line_distances():
    problem, T, pts = random_feature_problem(5, n_edges=5)
    brute = 0.0
    for i in range(5):
        q = np.vstack([pts[i, j] @ T[j, :3, :3].T + T[j, :3, 3] for j in range(problem.n_scans)])
        centred = q - q.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        brute += np.sum(centred**2) - np.sum((centred @ direction) ** 2)
    assert EdgeCost(problem).cost(T) == pytest.approx(brute, rel=1e-10)
    assert plane_cost(problem, T) == pytest.approx(brute, rel=1e-10)


def test_mixed_cost_is_the_sum_of_the_kinds():
    problem, T, _ = random_feature_problem(6, n_edges=3, n_planes=4)
    edges = np.isin(problem.plane_index, np.flatnonzero(problem.feature_kind == FEATURE_EDGE))
    as_edges = make_problem(problem.plane_index[edges], problem.scan_index[edges], problem.clusters[edges])
    as_planes = make_problem(problem.plane_index[~edges], problem.scan_index[~edges], problem.clusters[~edges])
    assert FeatureCost(problem).cost(T) == pytest.approx(EdgeCost(as_edges).cost(T) + plane_cost(as_planes, T),
                                                         rel=1e-12)
    # the same clusters as planes cost less (one normal instead of two)
    assert plane_cost(as_edges, T) < EdgeCost(as_edges).cost(T)


def test_sparse_assembly_equals_dense_hessian_with_edges():
    problem, T, _ = random_feature_problem(4, n_scans=5, n_edges=4, n_planes=3)
    _, g, H = dense_hessian(problem, T, eigen_gap_tolerance=1e-6)
    lin = NewtonModel(problem, fixed_pose=1).linearize(T)
    keep = np.array([a for a in range(6 * problem.n_scans) if a // 6 != 1])
    np.testing.assert_allclose(lin.H.hessian(), H[np.ix_(keep, keep)], rtol=0, atol=1e-10 * np.abs(H).max())
    np.testing.assert_allclose(lin.g, g[keep], rtol=0, atol=1e-12 * np.abs(g).max())


def test_eigen_gap_guard_counts_blob_edges():
    """A disc (lambda_mid = lambda_max) has no line direction: the guard bounds its coupling."""
    rng = np.random.default_rng(7)
    T = random_poses(3, rng, 0.4, 2.0)
    disc = np.array([[2.0, 0, 0], [-2.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]])
    line = np.array([[2.0, 0, 0], [-2.0, 0, 0], [0, 0.1, 0], [0, -0.1, 0]])
    clusters = [points_to_cluster((q - T[j, :3, 3]) @ T[j, :3, :3]) for q in (disc, line) for j in range(3)]
    problem = make_problem(np.repeat([0, 1], 3), np.tile(np.arange(3), 2), np.array(clusters),
                           feature_kind=np.array([FEATURE_EDGE, FEATURE_EDGE], np.uint8))
    lin = EdgeCost(problem, eigen_gap_tolerance=1e-6).linearize(T)
    assert lin.n_guarded == 1
    assert np.all(np.isfinite(lin.Bt)) and np.all(np.isfinite(lin.gradient))
    assert np.abs(lin.Bt).max() < 1e6 * np.abs(lin.A).max()


def edge_scene(seed: int, n_scans: int = 6, n_edges: int = 5):
    """Noise-free lines with random directions, each seen by every scan: (problem, T_gt)."""
    rng = np.random.default_rng(seed)
    T_gt = random_poses(n_scans, rng, 0.3, 2.0)
    directions = rng.normal(size=(n_edges, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    centres = rng.normal(0, 4, (n_edges, 3))
    plane_index, scan_index, clusters = [], [], []
    for i in range(n_edges):
        for j in range(n_scans):
            q_world = centres[i] + rng.uniform(-3, 3, (12, 1)) * directions[i]
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster((q_world - T_gt[j, :3, 3]) @ T_gt[j, :3, :3]))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans,
                           feature_kind=np.full(n_edges, FEATURE_EDGE, np.uint8))
    return problem, T_gt


@pytest.mark.parametrize("solver", ["newton", "lm"])
@pytest.mark.parametrize("n_edges", [3, 6])
def test_edge_only_problem_recovers_exact_poses(solver, n_edges):
    problem, T_gt = edge_scene(10 + n_edges, n_edges=n_edges)
    T0 = perturb(T_gt, np.deg2rad(2.0), 0.2, seed=3)
    result = solve(problem, T0, SolverConfig(solver=solver, max_iterations=200))
    T = result.T_world_scan
    assert result.report["converged"], result.report["stop_reason"]
    assert np.abs(T[:, :3, 3] - T_gt[:, :3, 3]).max() < 1e-6
    assert np.abs(T[:, :3, :3] - T_gt[:, :3, :3]).max() < 1e-6


def test_parallel_edges_leave_the_shared_direction_free():
    """Lines along one direction cannot fix a translation along it: the information has a null direction."""
    problem, T_gt = edge_scene(20, n_edges=4)
    rng = np.random.default_rng(0)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    pts_problem = []  # the same observations with every edge along d
    for o in range(problem.n_observations):
        j = problem.scan_index[o]
        i = problem.plane_index[o]
        q_world = np.array([3.0 * i, -i, 2.0]) + np.linspace(-2, 2, 10)[:, None] * d
        pts_problem.append(points_to_cluster((q_world - T_gt[j, :3, 3]) @ T_gt[j, :3, :3]))
    world = np.array(pts_problem)
    parallel = make_problem(problem.plane_index, problem.scan_index, world, feature_kind=problem.feature_kind)
    info = FeatureCost(parallel).scan_information(T_gt)
    along = np.concatenate([np.zeros(3), d])
    assert np.abs(info[1] @ along).max() < 1e-9 * np.abs(info[1]).max()
    info_skew = FeatureCost(problem).scan_information(T_gt)
    assert np.linalg.eigvalsh(info_skew[1])[0] > 1e-3 * np.abs(info_skew[1]).max()


def test_lm_joint_cost_at_pca_lines_equals_the_eliminated_cost():
    from pa_cli.adjust.joint_lm import JointModel

    problem, T, _ = random_feature_problem(8, n_edges=3, n_planes=3)
    model = JointModel(problem)
    assert model.cost(model.initial_state(T)) == pytest.approx(plane_cost(problem, T), rel=1e-9)


def test_newton_and_lm_reach_the_same_minimum_on_a_mixed_problem():
    problem, T, _ = random_feature_problem(9, n_scans=5, n_edges=4, n_planes=4)
    config = dict(max_iterations=300, cost_tolerance=1e-14, gradient_tolerance=1e-12)
    T0 = perturb(T, np.deg2rad(3.0), 0.3, seed=4)
    newton = solve(problem, T0, SolverConfig(solver="newton", **config))
    lm = solve(problem, T0, SolverConfig(solver="lm", **config))
    assert newton.report["converged"] and lm.report["converged"]
    assert newton.report["cost_final_m2"] < 0.5 * newton.report["cost_initial_m2"]
    assert lm.report["cost_final_m2"] == pytest.approx(newton.report["cost_final_m2"], rel=1e-6)


def test_lm_line_jacobian_matches_central_differences():
    from pa_cli.adjust.joint_lm import JointModel

    problem, T, _ = random_feature_problem(11, n_edges=2, n_planes=2)
    model = JointModel(problem)
    state = model.initial_state(T)
    _, J_pose, J_feature = model.jacobians(state)
    n_pose = 6 * problem.n_scans
    h = 1e-6
    for column in range(model.dof * problem.n_planes):
        step = np.zeros(n_pose + model.dof * problem.n_planes)
        step[n_pose + column] = h
        fd = (model.residuals(model.retract(state, step)) - model.residuals(model.retract(state, -step))) / (2 * h)
        feature, k = divmod(column, model.dof)
        analytic = np.where((problem.plane_index == feature)[:, None], J_feature[:, :, k], 0.0)
        np.testing.assert_allclose(fd, analytic, atol=1e-6 * np.abs(J_feature).max())
    for column in range(6, n_pose):  # pose 0 is the gauge in the solver, but its Jacobian is exact too
        step = np.zeros(n_pose + model.dof * problem.n_planes)
        step[column] = h
        fd = (model.residuals(model.retract(state, step)) - model.residuals(model.retract(state, -step))) / (2 * h)
        scan, k = divmod(column, 6)
        analytic = np.where((problem.scan_index == scan)[:, None], J_pose[:, :, k], 0.0)
        np.testing.assert_allclose(fd, analytic, atol=1e-6 * np.abs(J_pose).max())
