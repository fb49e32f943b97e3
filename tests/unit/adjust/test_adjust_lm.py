"""PA_LM (planes as unknowns): residuals, derivatives, Schur step and convergence.

References are independent of the code under test: explicit points (brute force), central
finite differences, dense linear algebra, and ground-truth poses of noise-free scenes.
"""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust.joint_lm import (
    JointModel,
    JointState,
    cluster_sqrt,
    fit_planes,
    retract_planes,
    solve_lm,
)
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import retract_left
from pa_cli.core.problem import make_problem
from pa_testing.synthetic_problems import RelativeTranslations, make_scene


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    delta = np.hstack([rng.normal(scale=0.5, size=(n, 3)), rng.normal(scale=3.0, size=(n, 3))])
    return retract_left(np.tile(np.eye(4), (n, 1, 1)), delta)


def _points_problem(seed: int = 0, n_scans: int = 5, n_planes: int = 6, n_points: int = 15):
    """A problem with explicit scan-frame points per observation (every plane seen by every scan)."""
    rng = np.random.default_rng(seed)
    T = _random_poses(rng, n_scans)
    plane_index = np.repeat(np.arange(n_planes), n_scans)
    scan_index = np.tile(np.arange(n_scans), n_planes)
    # points near (not on) random planes so that the cost is not zero
    points_scan = rng.normal(scale=2.0, size=(len(plane_index), n_points, 3))
    points_scan[..., 2] *= 0.05
    points_scan += rng.normal(scale=5.0, size=(len(plane_index), 1, 3))
    clusters = np.stack([points_to_cluster(p) for p in points_scan])
    problem = make_problem(plane_index, scan_index, clusters, T_world_scan=T)
    return problem, points_scan, T


def _world_points(points_scan, T, scan_index):
    Tj = T[scan_index]
    return np.einsum("oab,okb->oka", Tj[:, :3, :3], points_scan) + Tj[:, None, :3, 3]


def test_cluster_sqrt_reproduces_clusters_including_rank_deficient():
    rng = np.random.default_rng(1)
    point_sets = [
        rng.normal(size=(50, 3)) * [3.0, 2.0, 0.01] + [40.0, -20.0, 5.0],  # thin plane far away
        rng.normal(size=(1, 3)),  # one point: rank 1
        rng.normal(size=(2, 3)),  # two points
        np.outer(rng.normal(size=20), [1.0, 2.0, -1.0]) + 3.0,  # collinear points
    ]
    C = np.stack([points_to_cluster(p) for p in point_sets])
    L = cluster_sqrt(C)
    assert np.all(np.isfinite(L))
    np.testing.assert_allclose(L @ L.transpose(0, 2, 1), C, rtol=0, atol=1e-9 * np.abs(C).max())


def test_residual_norm_is_sum_of_squared_point_to_plane_distances():
    problem, points_scan, T = _points_problem(seed=2)
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(problem.n_planes, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.normal(scale=3.0, size=problem.n_planes)
    model = JointModel(problem)
    r = model.residuals(JointState(T, normals, offsets))
    q = _world_points(points_scan, T, problem.scan_index)
    dist = np.einsum("oka,oa->ok", q, normals[problem.plane_index]) + offsets[problem.plane_index][:, None]
    np.testing.assert_allclose(np.sum(r**2, axis=1), np.sum(dist**2, axis=1), rtol=1e-10)


def test_joint_cost_at_pca_planes_equals_sum_of_smallest_eigenvalues():
    problem, points_scan, T = _points_problem(seed=4)
    model = JointModel(problem)
    state = model.initial_state(T)
    q = _world_points(points_scan, T, problem.scan_index)
    expected = 0.0
    for i in range(problem.n_planes):  # brute force over explicit points, one plane at a time
        pts = q[problem.plane_index == i].reshape(-1, 3)
        centred = pts - pts.mean(axis=0)
        expected += np.linalg.eigvalsh(centred.T @ centred)[0]
    assert model.cost(state) == pytest.approx(expected, rel=1e-9)
    try:
        from pa_cli.adjust import plane_cost
    except ImportError:
        return
    assert model.cost(state) == pytest.approx(plane_cost(problem, T), rel=1e-9)


def test_pca_planes_are_stationary_in_the_planes():
    problem, _, T = _points_problem(seed=5)
    model = JointModel(problem)
    lin = model.linearize(model.initial_state(T))
    assert np.abs(lin.gl).max() < 1e-8 * max(1.0, np.abs(lin.gp).max())


def _flat_fd(model: JointModel, state: JointState, fun, eps: float = 1e-6) -> np.ndarray:
    """Central differences of fun(state) over every variable of the flat step."""
    n_var = 6 * model.n_scans + 3 * model.n_planes
    cols = []
    for k in range(n_var):
        e = np.zeros(n_var)
        e[k] = eps
        cols.append((fun(model.retract(state, e)) - fun(model.retract(state, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def _perturbed_state(model: JointModel, T: np.ndarray, seed: int) -> JointState:
    """Poses and planes (and, if the model uses them, anchors) away from any optimum."""
    rng = np.random.default_rng(seed)
    state = model.initial_state(T)
    T_pert = retract_left(T, rng.normal(scale=0.02, size=(len(T), 6)))
    n, d = retract_planes(state.normals_world, state.offsets_m, rng.normal(scale=0.02, size=(model.n_planes, 3)),
                          state.anchors_world)
    return JointState(T_pert, n, d, state.anchors_world)


@pytest.mark.parametrize("anchor_at_centroid", [True, False])
def test_gradient_matches_central_finite_differences(anchor_at_centroid):
    problem, _, T = _points_problem(seed=6)
    model = JointModel(problem, fixed_pose=0, anchor_at_centroid=anchor_at_centroid)
    state = _perturbed_state(model, T, seed=7)
    lin = model.linearize(state)
    gradient = 2.0 * np.concatenate([lin.gp.ravel(), lin.gl.ravel()])
    fd = _flat_fd(model, state, model.cost)
    fd[:6] = 0.0  # the fixed pose is not a variable
    assert np.abs(gradient - fd).max() < 1e-6 * np.abs(fd).max()
    assert lin.gradient_norm == pytest.approx(np.abs(fd).max(), rel=1e-6)


@pytest.mark.parametrize("with_pair_term", [False, True])
def test_schur_step_equals_dense_damped_gauss_newton_step(with_pair_term):
    problem, _, T = _points_problem(seed=8)
    terms = [RelativeTranslations(T, weight=0.3, rng=np.random.default_rng(3))] if with_pair_term else []
    model = JointModel(problem, fixed_pose=2, terms=terms)
    state = _perturbed_state(model, T, seed=9)
    lin = model.linearize(state)

    def residuals(s):  # the plane residuals and the terms' whitened residuals
        return np.concatenate([model.residuals(s).ravel()] + [t.residuals(s.T_world_scan) for t in terms])

    # dense Jacobian of the residuals by finite differences, without the fixed pose's columns
    J = _flat_fd(model, state, residuals)
    keep = np.ones(J.shape[1], dtype=bool)
    keep[12:18] = False
    J = J[:, keep]
    r = residuals(state)
    H = J.T @ J
    mu = 1e-3
    dense = np.linalg.solve(H + mu * np.diag(np.clip(np.diag(H), 1e-6, 1e32)), -J.T @ r)
    step, predicted = lin.solve(mu)
    np.testing.assert_allclose(step[keep], dense, rtol=0, atol=1e-6 * np.abs(dense).max())
    assert np.all(step[12:18] == 0.0)
    assert predicted == pytest.approx(r @ r - np.sum((r + J @ step[keep]) ** 2), rel=1e-6)


LEVELS = {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


def _perturb(T: np.ndarray, level: int, seed: int) -> np.ndarray:
    sigma_rot_deg, sigma_trans_m = LEVELS[level]
    rng = np.random.default_rng(seed)
    delta = np.hstack([rng.normal(scale=np.deg2rad(sigma_rot_deg), size=(len(T), 3)),
                       rng.normal(scale=sigma_trans_m, size=(len(T), 3))])
    delta[0] = 0.0
    return retract_left(T, delta)


@pytest.mark.parametrize("level", [1, 4])
def test_noise_free_scene_recovers_ground_truth(level):
    problem = make_scene(n_scans=15, n_planes=40, window=5, noise_m=0.0, seed=level)[0]
    T_gt = problem.T_world_scan
    result = solve_lm(problem, _perturb(T_gt, level, seed=10 + level), SolverConfig(max_iterations=500))
    T_final, fields = result.T_world_scan, result.fields
    # the floor is the rounding of the clusters, not zero: compare with the cost at the truth
    model = JointModel(problem)
    cost_truth = model.cost(model.initial_state(T_gt))
    assert fields["cost_final_m2"] <= cost_truth + 1e-12 * fields["cost_initial_m2"]
    assert np.abs(T_final[:, :3, 3] - T_gt[:, :3, 3]).max() < 1e-6
    assert np.abs(T_final[:, :3, :3] - T_gt[:, :3, :3]).max() < 1e-6
    history = fields["history"]
    assert all(h2["cost_m2"] <= h1["cost_m2"] for h1, h2 in zip(history[:-1], history[1:], strict=True))


def test_fit_planes_matches_points():
    problem, points_scan, T = _points_problem(seed=11)
    normals, offsets, centroids = fit_planes(problem, T)
    q = _world_points(points_scan, T, problem.scan_index)
    for i in (0, problem.n_planes - 1):
        pts = q[problem.plane_index == i].reshape(-1, 3)
        _, vecs = np.linalg.eigh(np.cov(pts.T))
        assert abs(abs(normals[i] @ vecs[:, 0]) - 1.0) < 1e-9
        assert normals[i] @ pts.mean(axis=0) + offsets[i] == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(centroids[i], pts.mean(axis=0), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("level", [1, 2, 3, 4])
def test_lm_and_newton_reach_the_same_optimum(level):
    pytest.importorskip("pa_cli.adjust.newton")
    from pa_cli.adjust import REPORT_KEYS, solve

    problem = make_scene(n_scans=12, n_planes=36, window=5, noise_m=0.01, seed=20 + level)[0]
    T_init = _perturb(problem.T_world_scan, level, seed=30 + level)
    newton = solve(problem, T_init, SolverConfig(max_iterations=100, solver="newton"))
    lm = solve(problem, T_init, SolverConfig(max_iterations=500, solver="lm"))
    assert lm.report["solver"] == "lm"
    assert set(lm.report) == set(REPORT_KEYS) == set(newton.report)
    assert lm.report["cost_initial_m2"] == pytest.approx(newton.report["cost_initial_m2"], rel=1e-9)
    assert lm.report["cost_final_m2"] == pytest.approx(newton.report["cost_final_m2"], rel=1e-6)
    assert np.abs(lm.T_world_scan - newton.T_world_scan).max() < 1e-5
    assert np.all(lm.T_world_scan[0] == T_init[0])  # the gauge pose is held


def test_cli_adjust_solver_lm_matches_newton(tmp_path, run_pa):
    import json

    from pa_cli.io.problem import save_problem
    from pa_cli.io.trajectory import read_trajectory

    problem = make_scene(n_scans=10, n_planes=60, window=5, noise_m=0.01, seed=40)[0]
    problem.T_world_scan = _perturb(problem.T_world_scan, 3, seed=41)
    path = tmp_path / "problem.npz"
    save_problem(path, problem)
    outputs = {}
    for solver in ("newton", "lm"):
        out, rep = tmp_path / f"{solver}_kitti.txt", tmp_path / f"{solver}.json"
        code, _, err = run_pa("adjust", path, "--out", out, "--report", rep, "--solver", solver,
                              "--max-iterations", "500")
        assert code == 0, err
        outputs[solver] = (read_trajectory(out).T_world_scan, json.loads(rep.read_text()))
    (T_n, rep_n), (T_l, rep_l) = outputs["newton"], outputs["lm"]
    assert rep_l["solver"] == "lm" and rep_l["converged"]
    assert set(rep_l) == set(rep_n)
    assert rep_l["cost_final_m2"] == pytest.approx(rep_n["cost_final_m2"], rel=1e-6)
    assert np.abs(T_l - T_n).max() < 1e-5
    # refused without --force, and the existing output is left alone
    before = (tmp_path / "lm_kitti.txt").read_text()
    code, _, err = run_pa("adjust", path, "--out", tmp_path / "lm_kitti.txt", "--solver", "lm")
    assert code == 1 and "--force" in err
    assert (tmp_path / "lm_kitti.txt").read_text() == before


def test_unobserved_scan_stays_put_and_singular_solves_are_rejected():
    problem, _ = make_scene(n_scans=8, n_planes=30, window=4, noise_m=0.01, seed=1)
    T = np.concatenate([_perturb(problem.T_world_scan, 2, seed=50), np.eye(4)[None]])
    extended = make_problem(problem.plane_index, problem.scan_index, problem.clusters, n_scans=9, T_world_scan=T)
    result = solve_lm(extended, T, SolverConfig(max_iterations=200))
    T_final, fields = result.T_world_scan, result.fields
    assert fields["converged"]
    assert np.array_equal(T_final[8], np.eye(4))  # no observation: no information, no motion
    ref = solve_lm(problem, T[:8], SolverConfig(max_iterations=200)).fields
    assert fields["cost_final_m2"] == pytest.approx(ref["cost_final_m2"], rel=1e-9)
    # a system with no information at all cannot be solved: the step is rejected, not NaN
    model = JointModel(extended)
    lin = model.linearize(model.initial_state(T))
    lin.A[:] = 0.0
    lin.C[:] = 0.0
    lin.W[:] = 0.0
    step, predicted = lin.solve(0.0)
    assert step is None and predicted == 0.0
