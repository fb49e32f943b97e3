"""Pose covariance with edge features: the pieces against the solver's, the sandwich against dense
algebra on per-point Jacobians, and the NEES by Monte Carlo on a scene the edges hold."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import covariance, solve
from pa_cli.adjust.covariance import nees, pose_covariance, tangent_error
from pa_cli.adjust.covariance_edges import edge_gauss_newton_pieces, edge_noise, feature_directions
from pa_cli.adjust.newton import NewtonModel
from pa_cli.adjust.noise_model import EdgeObservations
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import plane_eigen, points_to_cluster
from pa_cli.core.geometry import exp_so3
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from pa_cli.errors import SolverError
from pa_testing.synthetic_problems import projected_information

TIGHT = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _planes_and_poles(rng: np.random.Generator, T: np.ndarray, normals: np.ndarray, centres: np.ndarray,
                      directions: np.ndarray, bases: np.ndarray, noise_m: float, shared_m: float, m: int = 25,
                      growth: float = 1.0):
    """Every scan observes every plane (`normals`, `centres`) and every pole (unit `directions` through
    `bases`): m points each, with white noise (along the normal; across the line) of noise_m (1 + growth j) in
    scan j and an offset of sigma `shared_m` all the observation's points share. Returns the merged problem
    (planes first, observations by feature then scan) and each observation's world points."""
    plane_index, scan_index, clusters, points_world, kinds = [], [], [], [], []
    n_scans = len(T)
    for i, (n, c) in enumerate(zip(normals, centres, strict=True)):
        basis = np.linalg.svd(n[None, :])[2][1:]
        for j in range(n_scans):
            q = (c + rng.uniform(-3, 3, (m, 2)) @ basis + rng.normal(0, noise_m * (1 + growth * j), (m, 1)) * n
                 + rng.normal(0, shared_m) * n)
            plane_index.append(i)
            scan_index.append(j)
            points_world.append(q)
        kinds.append(FEATURE_PLANE)
    for i, (d, b) in enumerate(zip(directions, bases, strict=True)):
        across = np.linalg.svd(d[None, :])[2][1:]  # two unit directions across the line
        for j in range(n_scans):
            q = (b + rng.uniform(-2, 2, (m, 1)) * d + rng.normal(0, noise_m * (1 + growth * j), (m, 2)) @ across
                 + rng.normal(0, shared_m, 2) @ across)
            plane_index.append(len(normals) + i)
            scan_index.append(j)
            points_world.append(q)
        kinds.append(FEATURE_EDGE)
    for q, j in zip(points_world, scan_index, strict=True):
        clusters.append(points_to_cluster((q - T[j, :3, 3]) @ T[j, :3, :3]))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=n_scans,
                           T_world_scan=T, feature_kind=np.array(kinds, np.uint8))
    return problem, points_world


def _scene(seed: int):
    rng = np.random.default_rng(seed)
    n_scans = 4
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.2, (n_scans, 3)))
    T[:, :3, 3] = rng.normal(0, 2.0, (n_scans, 3))
    normals = _unit(rng.normal(size=(5, 3)))
    directions = _unit(rng.normal(size=(3, 3)))
    problem, points = _planes_and_poles(rng, T, normals, rng.normal(0, 5.0, (5, 3)), directions,
                                        rng.normal(0, 4.0, (3, 3)), 0.01, 0.02)
    return problem, T, points


def test_the_edge_pieces_are_the_solvers_gauss_newton_pieces():
    problem, T, _ = _scene(3)
    model = NewtonModel(problem)
    (_, planes), (edge_obs, edges) = model.feature_cost.parts
    assert planes.problem.feature_kind[0] == FEATURE_PLANE and edges.problem.feature_kind[0] == FEATURE_EDGE
    lin = edges.linearize(T)
    eig = plane_eigen(T, *edges.moments, edges.problem.scan_index, edges.starts)
    A, Bt = edge_gauss_newton_pieces(eig, edges.problem.plane_index, eig[0], eig[1], edges.moments[3])
    scale = np.abs(lin.A_gn).max()
    assert np.abs(A - lin.A_gn).max() < 1e-12 * scale
    assert np.abs(Bt - lin.Bt_gn).max() < 1e-12 * np.abs(lin.Bt_gn).max()


def test_feature_directions_split_every_edge_in_two():
    problem, _, _ = _scene(4)
    d = feature_directions(problem)
    n_planes, n_edges = 5, 3
    assert d.problem.n_planes == n_planes + 2 * n_edges and not d.identity
    assert np.array_equal(d.feature_of, np.r_[np.arange(n_planes), np.repeat(n_planes + np.arange(n_edges), 2)])
    assert np.all(np.diff(d.problem.plane_index) >= 0)  # observations by feature
    # each direction holds every observation of its edge, at the original scans
    for f in range(d.problem.n_planes):
        obs = d.source_obs[d.problem.plane_index == f]
        assert np.array_equal(np.sort(obs), np.flatnonzero(problem.plane_index == d.feature_of[f]))
        assert np.array_equal(d.problem.scan_index[d.problem.plane_index == f], problem.scan_index[obs])
    Bt = np.random.default_rng(0).normal(size=(problem.n_observations, 4, 6))
    rows = d.rows(Bt)
    edge_obs = d.is_edge[d.problem.plane_index]
    assert np.array_equal(rows[~edge_obs], Bt[d.source_obs[~edge_obs], :3])
    second = d.first_row == 2
    assert np.array_equal(rows[edge_obs & ~second, :2], Bt[d.source_obs[edge_obs & ~second], :2])
    assert np.array_equal(rows[edge_obs & second, :2], Bt[d.source_obs[edge_obs & second], 2:])
    assert np.all(rows[edge_obs, 2] == 0.0)
    planes_only = make_problem(problem.plane_index[problem.plane_index < n_planes],
                               problem.scan_index[problem.plane_index < n_planes],
                               problem.clusters[problem.plane_index < n_planes], n_scans=problem.n_scans)
    same = feature_directions(planes_only)
    assert same.identity and same.problem is planes_only and same.rows(Bt) is Bt


def test_sandwich_with_edges_against_brute_force_jacobians():
    """2 H^-1 W H^-1 of planes and edges against dense algebra on per-point Jacobians: a plane's residual
    n . (q - c) (its normal and offset projected out), an edge's two residuals across the line u_a . (q - c)
    (each direction's turn towards u_a and offset projected out), W = 2 J^T P V P J, H = 2 J^T P J, with the
    variances the covariance estimated: planes white per observation, plus the offset and tilt its points share;
    edges white per observation and direction, plus the offset its points share."""
    problem, T, points_world = _scene(7)
    model = NewtonModel(problem)
    (plane_obs, planes), (edge_obs, edges) = model.feature_cost.parts
    eig = plane_eigen(T, *planes.moments, planes.problem.scan_index, planes.starts)
    edge_eig = plane_eigen(T, *edges.moments, edges.problem.scan_index, edges.starts)
    A_planes, _ = covariance.gauss_newton_pieces(eig, planes.problem.plane_index, eig[0], eig[1], planes.moments[3],
                                                 planes.problem.scan_index, problem.n_scans)
    A_edges, _ = edge_gauss_newton_pieces(edge_eig, edges.problem.plane_index, edge_eig[0], edge_eig[1],
                                          edges.moments[3])
    A = A_planes + covariance._sum_per_scan(A_edges, edges.problem.scan_index, problem.n_scans)
    edge_observations = EdgeObservations(edge_eig, edges.problem.plane_index, edges.problem.scan_index,
                                         edges.moments[3])
    _, noise, leverage = covariance.observation_noise(eig, planes.problem, planes.moments,
                                                      covariance._LocalSystem(model, T, []), A, edge_observations)
    white_e, shared_e = edge_noise(edge_eig, edges.problem.plane_index, edges.moments[3], leverage)
    assert np.all(shared_e > 0.1 * white_e / edges.moments[3])  # a shared offset that matters
    cov = pose_covariance(problem, T, noise_model="observation")

    n_dof = 6 * problem.n_scans
    W, H = np.zeros((n_dof, n_dof)), np.zeros((n_dof, n_dof))

    def pose_rows(q, j, n):
        jx = np.zeros((len(q), n_dof))
        jx[:, 6 * j:6 * j + 3] = np.cross(q, n)
        jx[:, 6 * j + 3:6 * j + 6] = n
        return jx

    _, _, _, vec, centroid, _ = eig
    for i in range(planes.problem.n_planes):
        n, c = vec[i, :, 0], centroid[i]
        rows_x, rows_pi, var = [], [], []
        for k in np.flatnonzero(planes.problem.plane_index == i):
            o, j = plane_obs[k], problem.scan_index[plane_obs[k]]
            q = points_world[o]
            rows_x.append(pose_rows(q, j, n))
            qa = [np.r_[vec[i, :, a], -vec[i, :, a] @ c] for a in (1, 2)] + [np.r_[0.0, 0.0, 0.0, 1.0]]
            rows_pi.append(np.column_stack([np.hstack([q, np.ones((len(q), 1))]) @ qq for qq in qa]))
            in_plane = (q - q.mean(axis=0)) @ (np.eye(3) - np.outer(n, n))
            var.append(noise.white_m2[k] * np.eye(len(q)) + noise.shared_m2[k] * np.ones((len(q), len(q)))
                       + noise.tilt_rad2[k] * in_plane @ in_plane.T)
        w, h = projected_information(rows_x, rows_pi, var)
        W, H = W + w, H + h
    _, _, _, vec_e, centroid_e, _ = edge_eig
    for i in range(edges.problem.n_planes):
        line, c = vec_e[i, :, 2], centroid_e[i]
        for a in (0, 1):  # each direction across the line on its own
            u = vec_e[i, :, a]
            rows_x, rows_pi, var = [], [], []
            for k in np.flatnonzero(edges.problem.plane_index == i):
                o, j = edge_obs[k], problem.scan_index[edge_obs[k]]
                q = points_world[o]
                rows_x.append(pose_rows(q, j, u))
                rows_pi.append(np.column_stack([(q - c) @ line, np.ones(len(q))]))
                var.append(white_e[k] * np.eye(len(q)) + shared_e[k] * np.ones((len(q), len(q))))
            w, h = projected_information(rows_x, rows_pi, var)
            W, H = W + w, H + h
    H_inv = np.linalg.inv(H[6:, 6:])  # gauge pose 0 removed
    M = H_inv @ W[6:, 6:] @ H_inv
    expected = 2.0 * np.array([M[6 * s:6 * s + 6, 6 * s:6 * s + 6] for s in range(problem.n_scans - 1)])
    d = np.sqrt(np.einsum("nii->ni", expected))
    assert cov.hessian == "gauss-newton" and np.all(cov.covariance[0] == 0.0)
    assert np.max(np.abs(cov.covariance[1:] - expected) / (d[:, :, None] * d[:, None, :])) < 1e-6
    # given sigma: 2 sigma^2 H^-1 with the exact Hessian of planes and edges (the Gauss-Newton one at the truth)
    given = pose_covariance(problem, T, point_sigma_m=0.01)
    assert given.hessian in ("exact", "gauss-newton") and np.all(np.linalg.eigvalsh(given.covariance[1:]) > 0)


def test_an_edges_only_problem_is_refused():
    problem, T, _ = _scene(5)
    edges = problem.feature_kind[problem.plane_index] == FEATURE_EDGE
    only = make_problem(problem.plane_index[edges] - 5, problem.scan_index[edges], problem.clusters[edges],
                        n_scans=problem.n_scans, feature_kind=problem.feature_kind[5:])
    with pytest.raises(SolverError, match="needs plane features"):
        pose_covariance(only, T)


@pytest.mark.slow
def test_monte_carlo_nees_where_the_edges_hold_the_poses(monkeypatch):
    """Walls facing x and the ground leave every scan free along y; three vertical poles hold it. White
    noise of 1 cm (along the planes' normals, across the poles) and an offset of 1 cm each observation's
    points share, new noise per draw, each draw solved from the true poses: the mean NEES / 6 of the default
    covariance lies in [0.5, 2] and the averaged covariance matches the spread of the errors along its
    principal axes; the edges' shared offset is estimated without bias, and without it the NEES is far
    above 2."""
    rng = np.random.default_rng(11)
    n_scans = 8
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, :3, :3] = exp_so3(np.column_stack([np.zeros((n_scans, 2)), rng.normal(0, 0.1, n_scans)]))
    T[:, :3, 3] = np.column_stack([rng.normal(0, 0.5, n_scans), np.arange(n_scans) * 1.0, np.zeros(n_scans)])
    normals = _unit(np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.3]]))
    centres = np.array([[8.0, 3.0, 1.0], [-8.0, 2.0, 1.0], [0.0, 3.0, -1.5], [9.0, 0.0, 4.0]])
    directions = _unit(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]))
    bases = np.array([[3.0, -2.0, 0.0], [-4.0, 8.0, 0.0], [5.0, 5.0, 0.0]])
    estimate = covariance.edge_noise
    shared_m2: list[float] = []

    def recorded(*args):
        white, shared = estimate(*args)
        shared_m2.append(float(shared.mean()))
        return white, shared

    monkeypatch.setattr(covariance, "edge_noise", recorded)
    errors, covariances, white_only = [], [], []
    for _ in range(40):
        problem, _ = _planes_and_poles(rng, T, normals, centres, directions, bases, 0.01, 0.01, m=40, growth=0.0)
        T_est = solve(problem, T, TIGHT).T_world_scan
        errors.append(tangent_error(T_est, T)[1:])
        covariances.append(pose_covariance(problem, T_est).covariance[1:])
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(covariance, "edge_noise", lambda *args: (estimate(*args)[0], np.zeros(len(args[1]))))
            white_only.append(pose_covariance(problem, T_est).covariance[1:])
    errors, covariances = np.array(errors), np.array(covariances)
    assert 0.5 < nees(errors, covariances).mean() / 6 < 2.0
    assert nees(errors, np.array(white_only)).mean() / 6 > 3.0
    assert 0.8 < np.sqrt(np.mean(shared_m2)) / 0.01 < 1.2
    for scan in range(n_scans - 1):  # the spread of the errors along the averaged covariance's axes
        variance, axes = np.linalg.eigh(covariances[:, scan].mean(axis=0))
        ratio = (errors[:, scan] @ axes).std(axis=0) / np.sqrt(variance)
        assert np.all((ratio > 0.6) & (ratio < 1.5)), (scan, ratio)
