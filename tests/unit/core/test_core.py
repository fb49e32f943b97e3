"""The core modules: geometry against closed forms and brute force, clusters against explicit
points, voxel keys, feature kinds in the problem and its file, and the solver backend registry."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import register_backend, solve
from pa_cli.adjust.backend import BackendResult
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import fit_planes, points_to_cluster, sum_by_feature, transform_clusters
from pa_cli.core.geometry import (
    exp_so3,
    left_jacobian_inverse_so3,
    log_so3,
    orthonormalize,
    retract_left,
    rigid_inverse,
    rotation_angles,
    skew,
    tangent_basis,
    transform_points,
)
from pa_cli.core.point_moments import clusters_by_label
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, make_problem
from pa_cli.core.voxels import KEY_OFFSET, decode_keys, encode_keys, voxel_keys
from pa_cli.errors import FormatError, InputError, SolverError
from pa_cli.io.problem import load_problem, save_problem
from pa_testing.synthetic_problems import RelativeTranslations, fd_pose_gradient, make_scene, random_poses


def test_exp_log_skew_and_angles():
    rng = np.random.default_rng(0)
    omega = rng.normal(0, 1.0, (20, 3))
    omega[0] = 0.0
    omega[1] = [1e-9, -2e-9, 0.0]
    R = exp_so3(omega)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (20, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    small = np.linalg.norm(omega, axis=1) < np.pi
    np.testing.assert_allclose(log_so3(R)[small], omega[small], atol=1e-9)
    np.testing.assert_allclose(rotation_angles(R)[small], np.linalg.norm(omega, axis=1)[small], atol=1e-9)
    a, b = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-14)


def test_left_jacobian_inverse_against_finite_differences():
    """Log(Exp(d) Exp(phi)) = phi + J_l^{-1}(phi) d + O(d^2)."""
    rng = np.random.default_rng(1)
    phi = rng.normal(0, 0.8, (4, 3))
    J = left_jacobian_inverse_so3(phi)
    h = 1e-6
    for k in range(3):
        d = np.zeros((4, 3))
        d[:, k] = h
        fd = (log_so3(exp_so3(d) @ exp_so3(phi)) - log_so3(exp_so3(-d) @ exp_so3(phi))) / (2 * h)
        np.testing.assert_allclose(fd, J[:, :, k], atol=1e-7)


def test_retraction_inverse_and_transform():
    rng = np.random.default_rng(2)
    T = random_poses(6, rng, 1.0)
    delta = rng.normal(0, 0.3, (6, 6))
    T_new = retract_left(T, delta)
    p = rng.normal(size=(10, 3))
    for j in range(6):  # a world point q of scan j moves to Exp(omega) q + rho
        q = transform_points(T[j], p)
        expected = q @ exp_so3(delta[j:j + 1, :3])[0].T + delta[j, 3:]
        np.testing.assert_allclose(transform_points(T_new[j], p), expected, atol=1e-12)
    np.testing.assert_allclose(rigid_inverse(T) @ T, np.tile(np.eye(4), (6, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(rigid_inverse(T), np.linalg.inv(T), atol=1e-12)


def test_orthonormalize_and_tangent_basis():
    rng = np.random.default_rng(3)
    R = exp_so3(rng.normal(size=(5, 3)))
    noisy = R + rng.normal(0, 1e-4, R.shape)
    R_ortho, deviation = orthonormalize(noisy)
    np.testing.assert_allclose(R_ortho @ R_ortho.transpose(0, 2, 1), np.tile(np.eye(3), (5, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(deviation, np.linalg.norm(noisy - R_ortho, axis=(1, 2)))
    assert np.abs(R_ortho - R).max() < 1e-3
    normals = rng.normal(size=(50, 3))
    normals[0] = [1.0, 0.0, 0.0]  # the helper axis switches near x
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    B = tangent_basis(normals)
    full = np.concatenate([normals[:, :, None], B], axis=2)
    np.testing.assert_allclose(full.transpose(0, 2, 1) @ full, np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    np.testing.assert_array_equal(tangent_basis(normals), B)  # deterministic


def test_clusters_by_label_transform_and_fit_match_points():
    rng = np.random.default_rng(4)
    points = rng.normal(size=(300, 3)) * [3.0, 2.0, 0.01] + [10.0, -4.0, 2.0]
    labels = rng.integers(-1, 5, 300)
    labels[labels == 3] = -1  # label 3 absent
    labels[:2] = 4
    labels[2:] = np.where(labels[2:] == 4, 0, labels[2:])  # label 4 has 2 points
    lab, clusters = clusters_by_label(points, labels, min_points=3)
    np.testing.assert_array_equal(lab, [0, 1, 2])
    for k, label in enumerate(lab):
        np.testing.assert_allclose(clusters[k], points_to_cluster(points[labels == label]), rtol=1e-12)
    T = random_poses(3, rng, 1.0)
    world = transform_clusters(clusters, T)
    for k, label in enumerate(lab):
        np.testing.assert_allclose(world[k], points_to_cluster(transform_points(T[k], points[labels == label])),
                                   rtol=1e-10, atol=1e-8)
    per_plane = sum_by_feature(clusters, np.array([1, 0, 1]), 2)
    np.testing.assert_allclose(per_plane[1], clusters[0] + clusters[2])
    evals, normal, centroid, count = fit_planes(points_to_cluster(points)[None])
    centred = points - points.mean(axis=0)
    np.testing.assert_allclose(centroid[0], points.mean(axis=0), atol=1e-12)
    assert count[0] == 300
    assert abs(abs(normal[0] @ np.linalg.svd(centred)[2][-1]) - 1.0) < 1e-12
    np.testing.assert_allclose(evals[0, 0], np.sum((centred @ normal[0]) ** 2), rtol=1e-8)


def test_voxel_keys_round_trip_and_grid_limit():
    rng = np.random.default_rng(5)
    coords = rng.integers(-KEY_OFFSET, KEY_OFFSET, (100, 3))
    keys = encode_keys(coords)
    assert keys.min() >= 0
    np.testing.assert_array_equal(decode_keys(keys), coords)
    points = rng.uniform(-50, 50, (200, 3))
    np.testing.assert_array_equal(decode_keys(voxel_keys(points, 0.5, "map.voxel_m")),
                                  np.floor(points / 0.5))
    with pytest.raises(InputError, match="map.voxel_m"):
        voxel_keys(np.array([[KEY_OFFSET * 0.5 + 1.0, 0.0, 0.0]]), 0.5, "map.voxel_m")


def _problem_arrays():
    rng = np.random.default_rng(6)
    plane_index = np.array([0, 2, 0, 2, 1])
    scan_index = np.array([0, 0, 1, 1, 0])
    clusters = np.stack([points_to_cluster(rng.normal(size=(10, 3))) for _ in range(5)])
    return plane_index, scan_index, clusters


def test_feature_kind_defaults_renumbers_and_round_trips(tmp_path):
    plane_index, scan_index, clusters = _problem_arrays()
    assert list(make_problem(plane_index, scan_index, clusters).feature_kind) == [FEATURE_PLANE] * 2
    kinds = np.array([FEATURE_EDGE, FEATURE_PLANE, FEATURE_PLANE], dtype=np.uint8)
    problem = make_problem(plane_index, scan_index, clusters, feature_kind=kinds)  # feature 1: one scan
    assert problem.feature_kind.dtype == np.uint8 and list(problem.feature_kind) == [FEATURE_EDGE, FEATURE_PLANE]
    save_problem(tmp_path / "p.npz", problem)
    np.testing.assert_array_equal(load_problem(tmp_path / "p.npz").feature_kind, problem.feature_kind)
    np.savez(tmp_path / "old.npz", plane_index=plane_index, scan_index=scan_index, clusters=clusters)
    assert list(load_problem(tmp_path / "old.npz").feature_kind) == [FEATURE_PLANE] * 2


@pytest.mark.parametrize(("kinds", "message"), [
    (np.array([0, 0]), "has 2 entries but 'plane_index' refers to feature 2"),
    (np.array([0, 7, 0]), "holds 7"),
    (np.array([0.0, 0.0, 0.0]), "1-D integer array"),
])
def test_feature_kind_validation(tmp_path, kinds, message):
    plane_index, scan_index, clusters = _problem_arrays()
    np.savez(tmp_path / "bad.npz", plane_index=plane_index, scan_index=scan_index, clusters=clusters,
             feature_kind=kinds)
    with pytest.raises(FormatError, match=message):
        load_problem(tmp_path / "bad.npz")


def test_edge_problem_round_trips_and_solves(tmp_path):
    problem, T = make_scene(n_scans=4, n_planes=6, window=3, seed=0)
    problem.feature_kind[2] = FEATURE_EDGE
    save_problem(tmp_path / "edges.npz", problem)
    loaded = load_problem(tmp_path / "edges.npz")
    np.testing.assert_array_equal(loaded.feature_kind, problem.feature_kind)
    result = solve(loaded, T)
    assert result.report["n_planes"] == 6 and np.all(np.isfinite(result.T_world_scan))


def test_backend_registry_runs_the_named_backend():
    problem, T = make_scene(n_scans=4, n_planes=6, window=3, seed=0)
    calls = []

    def identity_backend(problem, T_world_scan_init, config, terms=(), progress=None):
        calls.append(config.max_iterations)
        fields = {"iterations": 0, "cost_initial_m2": 1.0, "cost_final_m2": 1.0, "converged": True,
                  "stop_reason": "none", "history": []}
        return BackendResult(T_world_scan_init.copy(), fields, ["identity"])

    register_backend("test-identity", identity_backend)
    config = SolverConfig.model_construct(**{**SolverConfig().model_dump(), "solver": "test-identity",
                                             "max_iterations": 7})
    result = solve(problem, T, config)
    assert calls == [7] and result.report["solver"] == "test-identity"
    assert result.report["warnings"] == ["identity"]
    np.testing.assert_array_equal(result.T_world_scan, T)
    bad = SolverConfig.model_construct(**{**SolverConfig().model_dump(), "solver": "nope"})
    with pytest.raises(SolverError, match="unknown solver 'nope'"):
        solve(problem, T, bad)


def test_pose_pair_term_gradient_and_both_backends_agree():
    rng = np.random.default_rng(8)
    problem, T_gt = make_scene(n_scans=10, n_planes=40, window=4, noise_m=0.01, seed=8)
    term = RelativeTranslations(T_gt, weight=0.5, rng=rng)
    T = retract_left(T_gt, rng.normal(0, 0.02, (10, 6)))
    fd = fd_pose_gradient(term.cost, T)
    np.testing.assert_allclose(term.linearize(T).gradient, fd, atol=1e-6 * np.abs(fd).max())
    newton = solve(problem, T, SolverConfig(solver="newton"), terms=[term])
    lm = solve(problem, T, SolverConfig(solver="lm", max_iterations=500), terms=[term])
    assert newton.report["converged"] and lm.report["converged"]
    assert lm.report["relative_cost_final_m2"] == pytest.approx(newton.report["relative_cost_final_m2"], rel=1e-5)
    assert np.abs(lm.T_world_scan - newton.T_world_scan).max() < 1e-5
    # the term pulls: the optimum differs from the one without it
    alone = solve(problem, T, SolverConfig(solver="newton"))
    assert np.abs(alone.T_world_scan - newton.T_world_scan).max() > 1e-4
