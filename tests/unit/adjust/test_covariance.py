"""Pose covariance: selected inversion against dense inverses, the factor 2 of the cost by Monte
Carlo on i.i.d. point-to-plane noise, and the Monte Carlo check on the simulated office."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import scipy.sparse as sp

from pa_cli.adjust import covariance, solve
from pa_cli.adjust.covariance import (
    LEAST_CERTAIN_SCANS,
    covariance_report,
    load_covariance,
    nees,
    origin_jacobian,
    pose_covariance,
    save_covariance,
    tangent_error,
)
from pa_cli.adjust.newton import NewtonModel
from pa_cli.adjust.selected_inverse import diagonal_blocks_of_inverse
from pa_cli.config import SolverConfig
from pa_cli.errors import SolverError
from pa_cli.io.problem import save_problem
from pa_cli.io.trajectory import read_trajectory
from pa_testing.synthetic_problems import make_scene, perturb, projected_information

TIGHT = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)


def _dense_blocks(M: np.ndarray) -> np.ndarray:
    n = M.shape[0] // 6
    return np.array([M[6 * i:6 * i + 6, 6 * i:6 * i + 6] for i in range(n)])


def _random_spd(n_blocks: int, density: float, seed: int) -> sp.csc_matrix:
    A = sp.random(6 * n_blocks, 6 * n_blocks, density=density, random_state=seed)
    return (A @ A.T + 0.1 * sp.eye(6 * n_blocks)).tocsc()


@pytest.mark.parametrize("seed", [1, 2])
def test_selected_inverse_matches_dense_inverse(seed):
    H = _random_spd(50, 0.01, seed)
    expected = _dense_blocks(np.linalg.inv(H.toarray()))
    got = diagonal_blocks_of_inverse(H)
    assert np.max(np.abs(got - expected)) < 1e-9 * np.max(np.abs(expected))


def test_every_candidate_ordering_gives_the_dense_inverse():
    """Natural, reverse Cuthill-McKee and nested dissection (METIS) orderings."""
    from pa_cli.adjust.selected_inverse import BlockSymbolic, _candidate_orders, block_graph, block_matrix

    H = _random_spd(60, 0.01, 4)
    expected = _dense_blocks(np.linalg.inv(H.toarray()))
    Hb = block_matrix(H)
    graph = block_graph(60, np.repeat(np.arange(60), np.diff(Hb.indptr)), Hb.indices)
    orders = _candidate_orders(graph)
    assert set(orders) == {"natural", "rcm", "nd"}
    for order in orders.values():
        assert np.array_equal(np.sort(order), np.arange(60))
        got = diagonal_blocks_of_inverse(H, BlockSymbolic(graph, order))
        assert np.max(np.abs(got - expected)) < 1e-9 * np.max(np.abs(expected))


def test_analysis_keeps_the_cheapest_ordering_with_its_full_pattern():
    """analyse_graph counts the candidates' rows and fills only the winner's: the same pattern as
    the winner analysed on its own, and no candidate needs fewer block products."""
    from pa_cli.adjust.selected_inverse import BlockSymbolic, _candidate_orders, analyse_graph, block_graph

    rng = np.random.default_rng(2)
    n = 80
    band = np.array([(j, j + d) for j in range(n) for d in (1, 2) if j + d < n])
    far = rng.integers(0, n, (25, 2))  # revisits: pairs far apart
    pairs = np.concatenate([band, far])
    graph = block_graph(n, pairs[:, 0], pairs[:, 1])
    sym = analyse_graph(graph)
    candidates = [BlockSymbolic(graph, order) for order in _candidate_orders(graph).values()]
    assert sym.work == min(c.work for c in candidates)
    alone = BlockSymbolic(graph, sym.order)
    for name in ("perm_inv", "colptr", "rows", "keys"):
        assert np.array_equal(getattr(sym, name), getattr(alone, name))


@pytest.fixture(params=["dense", "selected"])
def inversion(request, monkeypatch):
    """Both inversions of `pose_covariance`: dense (few poses, the default here) and selected."""
    if request.param == "selected":
        monkeypatch.setattr(covariance, "DENSE_MAX_POSES", 0)
    return request.param


@pytest.mark.parametrize(("scene", "aux"), [((15, 60, 5), False), ((14, 10, 14), True)])
def test_covariance_matches_dense_inverse_in_both_hessian_forms(scene, aux, inversion):
    """2 sigma^2 H^-1 (assembled into the block factor from the observations' blocks, or into the
    dense matrix) against the dense inverse of the Newton system's pose Hessian, with planes in the
    pair form and with planes seen by many scans (auxiliary unknowns in the Newton system), gauge pose 3."""
    problem, T = make_scene(*scene, points_per_observation=15, noise_m=0.01, seed=6)
    T = solve(problem, T, SolverConfig(fixed_pose=3)).T_world_scan
    model = NewtonModel(problem, fixed_pose=3)
    assert (model.pattern.n_aux_features > 0) == aux
    got = pose_covariance(problem, T, fixed_pose=3, point_sigma_m=0.01, model=model).covariance
    expected = 2e-4 * _dense_blocks(np.linalg.inv(model.linearize(T).H.hessian()))
    assert np.all(got[3] == 0.0)
    free = np.delete(np.arange(problem.n_scans), 3)
    d = np.sqrt(np.einsum("nii->ni", expected))
    assert np.max(np.abs(got[free] - expected) / (d[:, :, None] * d[:, None, :])) < 1e-6


def _dense_feature_matrix(n: int, starts, block_of_obs, U, Y, step: float) -> np.ndarray:
    """-sum over features of (U^T U + step (Y^T U + U^T Y)) as a dense (6n, 6n) matrix, the
    observations of block -1 left out: the straightforward form of `_add_feature_blocks`."""
    H = np.zeros((6 * n, 6 * n))
    for i in range(len(starts) - 1):
        obs = [o for o in range(starts[i], starts[i + 1]) if block_of_obs[o] >= 0]
        for a in obs:
            for b in obs:
                j, k = block_of_obs[a], block_of_obs[b]
                H[6 * j:6 * j + 6, 6 * k:6 * k + 6] -= U[a].T @ U[b] + step * (Y[a].T @ U[b] + U[a].T @ Y[b])
    return H


@pytest.mark.parametrize(("rank", "steps"), [(3, [0.3, -0.3]), (3, [0.0]), (4, [0.0])])
def test_feature_block_assembly_matches_the_dense_sum(rank, steps):
    """`_add_feature_blocks` writes every block of the dense per-feature sum into the factor's
    storage (diagonal blocks in D, each off-diagonal block once, at its slot, as (later, earlier) in
    the factor's order), for the two-matrix form (linear in the step) and one matrix; observations
    of the gauge (block -1) contribute nothing, the same blocks to the bit when the columns are
    assembled in ranges (in parallel), and a pair outside the pattern is reported."""
    from pa_cli.adjust.selected_inverse import (
        _add_feature_blocks,
        _add_feature_blocks_in_parallel,
        _factor_slots,
        _feature_observations,
        analyse_graph,
        block_graph,
    )

    rng = np.random.default_rng(5)
    n, n_features = 12, 9
    sizes = rng.integers(1, 6, n_features)
    starts = np.r_[0, np.cumsum(sizes)]
    block_of_obs = np.concatenate([rng.choice(np.arange(-1, n), size, replace=False) for size in sizes])
    U = rng.normal(size=(starts[-1], rank, 6))
    Y = rng.normal(size=(starts[-1], rank, 6))
    pairs = np.array([(j, k) for i in range(n_features) for j in block_of_obs[starts[i]:starts[i + 1]]
                      for k in block_of_obs[starts[i]:starts[i + 1]] if 0 <= j < k])
    sym = analyse_graph(block_graph(n, pairs[:, 0], pairs[:, 1]))
    steps = np.array(steps)
    D = np.zeros((len(steps), n, 6, 6))
    L = np.zeros((len(steps), len(sym.rows), 6, 6))
    first, obs, new_block = _feature_observations(starts, block_of_obs, sym.perm_inv)
    assert _add_feature_blocks(0, n, first, obs, new_block, sym.colptr, sym.rows, U, Y, steps, D, L)
    D_split, L_split = np.zeros_like(D), np.zeros_like(L)  # column ranges, as the threads take them
    assert _add_feature_blocks_in_parallel(np.array([0, 4, 5, n]), starts, block_of_obs, sym.perm_inv, sym.colptr,
                                           sym.rows, U, Y, steps, D_split, L_split)
    assert np.array_equal(D_split, D) and np.array_equal(L_split, L)
    rows, cols = np.nonzero(~np.eye(n, dtype=bool))
    slots, transposed = _factor_slots(sym, rows, cols)
    in_pattern = np.isin(np.minimum(rows, cols) * n + np.maximum(rows, cols), pairs[:, 0] * n + pairs[:, 1])
    for m, step in enumerate(steps):
        H = _dense_feature_matrix(n, starts, block_of_obs, U, Y, step)
        blocks = H.reshape(n, 6, n, 6).transpose(0, 2, 1, 3)
        scale = np.max(np.abs(H))
        assert np.max(np.abs(D[m][sym.perm_inv] - blocks[np.arange(n), np.arange(n)])) < 1e-13 * scale
        stored = np.where(transposed[:, None, None], L[m][slots].transpose(0, 2, 1), L[m][slots])
        assert np.max(np.abs(stored[in_pattern] - blocks[rows, cols][in_pattern])) < 1e-13 * scale
        assert np.all(blocks[rows, cols][~in_pattern] == 0.0)
    keep = pairs[:, 0] * n + pairs[:, 1] != pairs[0, 0] * n + pairs[0, 1]  # one pair missing
    other = analyse_graph(block_graph(n, pairs[keep, 0], pairs[keep, 1]))
    first, obs, new_block = _feature_observations(starts, block_of_obs, other.perm_inv)
    assert not _add_feature_blocks(0, n, first, obs, new_block, other.colptr, other.rows, U, Y, steps,
                                   np.zeros((len(steps), n, 6, 6)), np.zeros((len(steps), len(other.rows), 6, 6)))


def test_two_matrix_assembly_needs_three_coupling_rows():
    from pa_cli.adjust.selected_inverse import analyse_graph, block_graph, diagonal_blocks_of_feature_inverses

    sym = analyse_graph(block_graph(2, np.array([0]), np.array([1])))
    rows4 = np.zeros((2, 4, 6))
    with pytest.raises(SolverError, match="3 coupling rows"):
        diagonal_blocks_of_feature_inverses(sym, np.array([0, 2]), np.array([0, 1]), rows4, rows4,
                                            np.array([0.1, -0.1]), np.tile(np.eye(6), (2, 2, 1, 1)),
                                            np.empty((0, 2), np.int64), np.empty((2, 0, 6, 6)),
                                            np.tile(np.eye(6), (2, 1, 1)))


def test_indefinite_hessian_is_refused():
    H = _random_spd(10, 0.05, 3).toarray()
    H[6:12, 6:12] -= 1e3 * np.eye(6)
    with pytest.raises(SolverError, match="not positive definite"):
        diagonal_blocks_of_inverse(sp.csc_matrix(H))


def test_iid_noise_nees_is_six_so_covariance_is_two_sigma2_inverse_hessian():
    """Normal noise of 1 cm along the plane normals, the same scene with new noise per draw: NEES
    averages 6 with sigma given and with the per-observation estimate (with H^-1 instead of
    2 H^-1 it would average 12, with 4 H^-1 3)."""
    errors, given, estimated, sigmas = [], [], [], []
    for draw in range(30):
        problem, T_true = make_scene(12, 40, 6, points_per_observation=30, noise_m=0.01, seed=3,
                                     noise_seed=100 + draw)
        T_est = solve(problem, T_true, TIGHT).T_world_scan
        errors.append(tangent_error(T_est, T_true)[1:])
        given.append(pose_covariance(problem, T_est, point_sigma_m=0.01).covariance[1:])
        cov = pose_covariance(problem, T_est)
        estimated.append(cov.covariance[1:])
        sigmas.append(cov.point_sigma_m)
    errors = np.array(errors)
    for covariances in (given, estimated):
        assert 0.85 * 6 < nees(errors, np.array(covariances)).mean() < 1.15 * 6
    assert np.all(np.abs(np.array(sigmas) / 0.01 - 1.0) < 0.05)  # residual estimate, dof = 6 (N-1) + 3 P


def _monte_carlo(scene: str, draws: int, scans: int, first_seed: int, shares: list | None = None,
                 **noise: float) -> tuple[float, np.ndarray, set]:
    """Same poses, new noise (seed; range noise unless `noise` gives other `SimOptions`) per draw, exact
    association, each draw solved from the true poses: mean NEES / 6 of the default covariance, predicted /
    empirical 1-sigma per axis (omega, scan-origin displacement; median over scans) and the noise models
    used; `shares` collects the range model's isotropic shares."""
    from pa_cli.simulate import SimOptions, build_problem_from_labels, simulate_sequence

    errors, covariances, models = [], [], set()
    for draw in range(draws):
        seq = simulate_sequence(SimOptions(scene=scene, scans=scans, azimuth_steps=512, seed=first_seed + draw,
                                           **noise))
        problem = build_problem_from_labels(seq)
        T_est = solve(problem, seq.T_world_scan, TIGHT).T_world_scan
        cov = pose_covariance(problem, T_est)
        models.add(cov.noise_model)
        if shares is not None:
            shares.append(cov.isotropic_share)
        errors.append(tangent_error(T_est, seq.T_world_scan)[1:])
        covariances.append(cov.covariance[1:])
    errors, covariances = np.array(errors), np.array(covariances)
    T = seq.T_world_scan[1:]
    J = np.zeros((len(T), 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:] = origin_jacobian(T)
    predicted = np.sqrt(np.einsum("nii->ni", J @ covariances.mean(0) @ J.transpose(0, 2, 1)))
    empirical = np.einsum("nij,dnj->dni", J, errors).std(axis=0)
    return float(nees(errors, covariances).mean() / 6), np.median(predicted / empirical, axis=0), models


@pytest.mark.slow
def test_simulated_office_monte_carlo():
    """Average NEES and per-axis 1-sigma (median over scans; bench/covariance.py checks the median
    scan with 50 draws) of the default covariance, the range model."""
    nees_6, ratio, models = _monte_carlo("office", 20, 15, 500)
    assert models == {"range"} and 0.7 < nees_6 < 1.4
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


def test_file_round_trip_and_report(tmp_path):
    problem, T = make_scene(30, 90, 8, points_per_observation=15, noise_m=0.01, seed=5)
    T_opt = solve(problem, T, TIGHT).T_world_scan
    cov = pose_covariance(problem, T_opt, fixed_pose=3)
    assert np.all(cov.covariance[3] == 0.0)
    assert np.all(np.linalg.eigvalsh(np.delete(cov.covariance, 3, axis=0)) > 0.0)
    cov = dataclasses.replace(cov, isotropic_share=0.37)  # the range model's (this problem has no range clusters)
    path = tmp_path / "cov.npz"
    save_covariance(path, cov)
    back = load_covariance(path)
    assert np.array_equal(back.covariance, cov.covariance)
    assert (back.point_sigma_m, back.gauge_pose, back.point_sigma_source) == (cov.point_sigma_m, 3, "residual")
    assert (back.shared_sigma_m, back.isotropic_share) == (cov.shared_sigma_m, 0.37)
    report = covariance_report(cov)
    assert (report["shared_sigma_m"], report["isotropic_share"]) == (cov.shared_sigma_m, 0.37)
    worst = report["least_certain_scans"]
    assert len(worst) == LEAST_CERTAIN_SCANS and 3 not in [w["scan"] for w in worst]
    sig = [w["position_sigma_m"] for w in worst]
    assert sig == sorted(sig, reverse=True) and sig[0] == max(report["position_sigma_m"])
    # position sigma = the largest axis of the scan origin's covariance, brute force
    J = origin_jacobian(T_opt)
    j = worst[0]["scan"]
    P = J[j] @ cov.covariance[j] @ J[j].T
    assert np.isclose(sig[0], np.sqrt(np.linalg.eigvalsh(P)[-1]))


def test_cli_adjust_writes_covariance(run_pa, tmp_path):
    problem, T_gt = make_scene(20, 80, 6, points_per_observation=12, noise_m=0.01, seed=3)
    problem.T_world_scan = perturb(T_gt, np.deg2rad(0.5), 0.05, seed=4)
    path = tmp_path / "problem.npz"
    save_problem(path, problem)
    out, report, cov_path = tmp_path / "refined.txt", tmp_path / "report.json", tmp_path / "cov.npz"
    code, _, err = run_pa("adjust", path, "--out", out, "--report", report, "--covariance", cov_path, "--fix", "2")
    assert code == 0, err
    assert "least certain scan" in err
    cov = load_covariance(cov_path)
    rep = json.loads(report.read_text())["covariance"]
    assert cov.gauge_pose == 2 and np.all(cov.covariance[2] == 0.0)
    assert np.allclose(rep["position_sigma_m"], cov.position_sigma_m())
    assert abs(cov.point_sigma_m / 0.01 - 1.0) < 0.1 and rep["point_sigma_source"] == "residual"
    assert cov.noise_model == rep["noise_model"] == "observation"  # the problem has no range clusters
    given = tmp_path / "given.npz"
    code, _, err = run_pa("adjust", path, "--out", tmp_path / "r2.txt", "--covariance", given,
                          "--point-sigma-m", "0.02", "--fix", "2")
    assert code == 0, err
    T = read_trajectory(out).T_world_scan
    direct = pose_covariance(problem, T, fixed_pose=2, point_sigma_m=0.01).covariance
    assert np.allclose(load_covariance(given).covariance, 4.0 * direct, rtol=1e-6, atol=0.0)
    code, _, err = run_pa("adjust", path, "--out", tmp_path / "r3.txt", "--covariance", tmp_path / "c3.npz",
                          "--point-sigma-m", "-1")
    assert code == 2 and "--point-sigma-m" in err


def _linearised(problem, T: np.ndarray):
    """The Newton model of `problem`, its plane cost, the plane eigen-decompositions at poses T and the
    Gauss-Newton pieces A, beta built from them (what the covariance's noise measurement starts from)."""
    from pa_cli.adjust.covariance import gauss_newton_pieces
    from pa_cli.core.clusters import plane_eigen

    model = NewtonModel(problem)
    plane_cost = model.feature_cost.parts[0][1]
    eig = plane_eigen(T, *plane_cost.moments, problem.scan_index, plane_cost.starts)
    A, beta = gauss_newton_pieces(eig, problem.plane_index, eig[0], eig[1], plane_cost.moments[3],
                                  problem.scan_index, problem.n_scans)
    return model, plane_cost, eig, A, beta


def _explicit_points_problem(seed: int = 7):
    """A few planes seen by a few scans, with the points kept (for brute-force Jacobians): white noise growing
    with the scan, and per observation an offset and a tilt all its points share."""
    from pa_testing.synthetic_problems import planes_seen_by_every_scan

    rng = np.random.default_rng(seed)
    m = 25

    def observe(i, j, centre, basis, normal):
        q = (centre + rng.uniform(-3, 3, (m, 2)) @ basis + rng.normal(0, 0.01 * (j + 1), (m, 1)) * normal
             + rng.normal(0, 0.02) * normal)  # an offset all the observation's points share
        q += ((q - q.mean(axis=0)) @ rng.normal(0, 0.01, 3))[:, None] * normal  # and a tilt
        return q

    return planes_seen_by_every_scan(rng, 4, 6, observe)


@pytest.mark.parametrize("noise_model", ["observation", "plane", "range"])
def test_sandwich_against_brute_force_jacobians(noise_model, monkeypatch):
    """The covariance 2 H^-1 W H^-1 against dense algebra on per-point Jacobians:
    W = 2 J^T P V P J (r = pi^T [q; 1], planes projected out by P), H = 2 J^T P J, with the
    variances the covariance estimated: white per observation (per plane; per observation and spread
    over its points in proportion to gamma + cos^2 of the beam's incidence, cos^2 = d^2 / |p|^2 in the
    scan frame, with gamma = 0.3 given) plus the shared variance of each observation's points,
    V_o = diag(v) + v_shared,o 1 1^T."""
    from pa_cli.adjust.covariance import _LocalSystem, observation_noise
    from pa_cli.adjust.noise_model import (
        plane_noise_variances,
    )

    gamma = 0.3
    monkeypatch.setattr(covariance, "isotropic_ratio", lambda *args: (gamma, 0.5))
    problem, T, points_world = _explicit_points_problem()
    model, plane_cost, eig, A, _ = _linearised(problem, T)
    components, noise, _ = observation_noise(eig, problem, plane_cost.moments, _LocalSystem(model, T, []), A)
    v_obs, v_shared, v_tilt = noise.white_m2, noise.shared_m2, noise.tilt_rad2
    points_scan = [(q - T[j, :3, 3]) @ T[j, :3, :3] for q, j in zip(points_world, problem.scan_index, strict=True)]
    inverse_square = [1.0 / np.einsum("ki,ki->k", p, p) for p in points_scan]
    range_clusters = np.array([np.einsum("k,ki,kj->ij", w, np.c_[p, np.ones(len(p))], np.c_[p, np.ones(len(p))])
                               for w, p in zip(inverse_square, points_scan, strict=True)])
    cov = pose_covariance(problem, T, noise_model=noise_model, range_clusters=range_clusters)
    if noise_model == "plane":
        dof = plane_cost.moments[3] - 1.0 - components.counted.sum(axis=1)
        v_obs = plane_noise_variances(v_obs, dof, problem)[problem.plane_index]
    assert len(np.unique(np.round(v_obs, 12))) > problem.n_planes // 2  # unequal variances
    assert np.all(v_shared > 0.1 * v_obs / plane_cost.moments[3])  # a shared offset that matters
    assert np.all(v_tilt > 0.0)

    _, _, _, vec, centroid, _ = eig
    W = np.zeros((6 * problem.n_scans, 6 * problem.n_scans))
    H = np.zeros_like(W)
    for i in range(problem.n_planes):
        obs = np.flatnonzero(problem.plane_index == i)
        n, c = vec[i, :, 0], centroid[i]
        rows_x, rows_pi, var = [], [], []
        for o in obs:
            q = points_world[o]  # this problem keeps the observations in generation order
            jx = np.zeros((len(q), 6 * problem.n_scans))
            j = problem.scan_index[o]
            jx[:, 6 * j:6 * j + 3] = np.cross(q, n)
            jx[:, 6 * j + 3:6 * j + 6] = n
            qa = [np.r_[vec[i, :, a], -vec[i, :, a] @ c] for a in (1, 2)] + [np.r_[0.0, 0.0, 0.0, 1.0]]
            rows_pi.append(np.column_stack([np.hstack([q, np.ones((len(q), 1))]) @ qq for qq in qa]))
            rows_x.append(jx)
            if noise_model == "range":  # d: the plane's distance from the sensor
                cos2 = (n @ (c - T[j, :3, 3])) ** 2 * inverse_square[o]
                white = v_obs[o] * (gamma + cos2) / (gamma + cos2.mean())
            else:
                white = np.full(len(q), v_obs[o])
            in_plane = (q - q.mean(axis=0)) @ (np.eye(3) - np.outer(n, n))  # shared tilt: its residual a . X
            var.append(np.diag(white) + v_shared[o] * np.ones((len(q), len(q))) + v_tilt[o] * in_plane @ in_plane.T)
        w, h = projected_information(rows_x, rows_pi, var)
        W += w
        H += h
    H_inv = np.linalg.inv(H[6:, 6:])  # gauge pose 0 removed
    expected = 2.0 * _dense_blocks(H_inv @ W[6:, 6:] @ H_inv)
    assert cov.hessian == "gauss-newton" and np.all(cov.covariance[0] == 0.0)
    d = np.sqrt(np.einsum("nii->ni", expected))
    assert np.max(np.abs(cov.covariance[1:] - expected) / (d[:, :, None] * d[:, None, :])) < 1e-6


def test_sandwich_of_proportional_variance_is_the_scaled_inverse():
    """W = v H (every point with variance v: A_v = v A, couplings v beta, Q = v I) makes the sandwich
    H^-1 W H^-1 = v H^-1 exactly. A 100-scan sequence drifts, so H is nearly singular along the drift,
    and any term of second order in the central difference's step would show here."""
    from pa_cli.adjust.covariance import _LocalSystem

    problem, T_gt = make_scene(100, 400, 10, points_per_observation=10, noise_m=0.01, seed=1)
    T = solve(problem, T_gt, TIGHT).T_world_scan
    model, _, _, A, beta = _linearised(problem, T)
    system = _LocalSystem(model, T, [])
    v = 1e-4
    expected = v * system.plain_inverse_blocks(A, beta)
    Q = np.tile(v * np.eye(3), (problem.n_planes, 1, 1))
    sandwich = system.sandwich_blocks(A, beta, v * A, v * beta, Q, problem.plane_index, v)
    d = np.sqrt(np.einsum("nii->ni", expected))
    assert np.max(np.abs(sandwich - expected) / (d[:, :, None] * d[:, None, :])) < 1e-6


@pytest.mark.parametrize("point_sigma_m", [None, 0.01])
def test_solver_model_reuse_gives_the_same_covariance(point_sigma_m):
    """`SolveResult.model` (its last linearisation is at the solution) gives the covariance computed
    from scratch."""
    problem, T_gt = make_scene(30, 120, 8, points_per_observation=30, noise_m=0.01, seed=3)
    result = solve(problem, perturb(T_gt, 0.01, 0.01, seed=4), TIGHT)
    assert np.array_equal(result.model.last[0], result.T_world_scan)
    reused = pose_covariance(problem, result.T_world_scan, point_sigma_m=point_sigma_m, model=result.model)
    fresh = pose_covariance(problem, result.T_world_scan, point_sigma_m=point_sigma_m)
    np.testing.assert_allclose(reused.covariance, fresh.covariance, rtol=1e-9, atol=1e-20)
    other_gauge = pose_covariance(problem, result.T_world_scan, fixed_pose=1, point_sigma_m=point_sigma_m,
                                  model=result.model)
    assert other_gauge.gauge_pose == 1 and np.all(other_gauge.covariance[1] == 0.0)


def test_pose_terms_are_part_of_the_information():
    """Odometry factors and another pose-pair term enter H: the covariance is 2 sigma^2 H^-1 of the
    whole objective (dense check) and smaller than without them."""
    from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
    from pa_testing.synthetic_problems import RelativeTranslations

    problem, T = make_scene(15, 60, 5, points_per_observation=15, noise_m=0.01, seed=6)
    model = OdometryModel(point_sigma_m=0.01, translation_sigma_m=0.05, translation_sigma_per_m=0.01,
                          rotation_sigma_rad=np.deg2rad(0.5), rotation_sigma_per_rad=0.02,
                          rotation_sigma_rad_per_m=np.deg2rad(0.01))
    terms = [OdometryFactors(perturb(T, np.deg2rad(0.5), 0.05, seed=1), model),
             RelativeTranslations(T, 0.05, np.random.default_rng(0))]
    T_opt = solve(problem, T, TIGHT, terms=terms).T_world_scan
    got = pose_covariance(problem, T_opt, point_sigma_m=0.01, terms=terms).covariance
    H = NewtonModel(problem, terms=terms).linearize(T_opt).H.hessian()
    expected = 2e-4 * _dense_blocks(np.linalg.inv(H))
    d = np.sqrt(np.einsum("nii->ni", expected))
    assert np.max(np.abs(got[1:] - expected) / (d[:, :, None] * d[:, None, :])) < 1e-6
    without = pose_covariance(problem, T_opt, point_sigma_m=0.01).covariance
    assert np.all(np.trace(got[1:], axis1=1, axis2=2) < np.trace(without[1:], axis1=1, axis2=2))
    residual = pose_covariance(problem, T_opt, terms=terms).covariance
    assert np.all(np.linalg.eigvalsh(residual[1:]) > 0.0)


def test_range_model_needs_range_clusters():
    problem, T = make_scene(6, 12, 3, points_per_observation=10, noise_m=0.01, seed=2)
    with pytest.raises(SolverError, match="range clusters"):
        pose_covariance(problem, T, noise_model="range")
    with pytest.raises(SolverError, match="range clusters"):
        pose_covariance(problem, T, noise_model="range", range_clusters=problem.clusters[1:])


def test_association_accumulates_range_clusters_like_brute_force():
    """The association's range clusters (one per observation) against sums over the observation's
    points of [p; 1][p; 1]^T / |p|^2 (scan frame); the frozen association reproduces them."""
    from pa_cli.config import PlanesConfig
    from pa_cli.planes.associate import build_plane_problem
    from pa_cli.planes.labels import PointLabels
    from pa_cli.simulate import SimOptions, simulate_sequence

    seq = simulate_sequence(SimOptions(scene="office", scans=5, beams=16, azimuth_steps=256, seed=8))
    scans = [s.points_scan for s in seq.scans]
    config = PlanesConfig(voxel_size_m=0.5)
    found: dict = {}
    problem, _ = build_plane_problem(scans, seq.T_world_scan, config, landmarks_out=found)
    assert problem.n_observations > 10 and problem.range_clusters.shape == (problem.n_observations, 4, 4)
    labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks, found["kept"],
                                          problem)
    expected = np.zeros((problem.n_observations, 4, 4))
    for k, points in enumerate(scans):
        obs = labels.observation_of_point[k]
        for o in np.unique(obs[obs >= 0]):
            p = points[obs == o].astype(np.float64)
            ph = np.c_[p, np.ones(len(p))]
            expected[o] = ph.T @ (ph / np.sum(p * p, axis=1)[:, None])
    np.testing.assert_allclose(problem.range_clusters, expected, rtol=1e-9, atol=1e-12)
    frozen = labels.problem(scans, seq.T_world_scan, with_range=True)
    np.testing.assert_allclose(frozen.range_clusters, expected, rtol=1e-9, atol=1e-12)
    assert labels.problem(scans).range_clusters is None


def _range_problem(seed: int = 3):
    """A simulated street problem (exact association), with its range clusters."""
    from pa_cli.simulate import SimOptions, build_problem_from_labels, simulate_sequence

    seq = simulate_sequence(SimOptions(scene="street", scans=6, beams=16, azimuth_steps=256, seed=seed))
    return build_problem_from_labels(seq), seq


def test_problem_file_carries_range_clusters(tmp_path):
    """Round trip of the optional 'range_clusters' (reordered and dropped with the observations by
    make_problem); a file without them loads with none; a wrong shape is refused."""
    from pa_cli.core.problem import make_problem
    from pa_cli.errors import FormatError
    from pa_cli.io.problem import load_problem

    problem, _ = _range_problem()
    path = tmp_path / "p.npz"
    save_problem(path, problem)
    back = load_problem(path)
    assert np.array_equal(back.range_clusters, problem.range_clusters)
    # shuffled input observations plus one plane seen by a single scan: K follows its observation
    rng = np.random.default_rng(0)
    order = rng.permutation(problem.n_observations)
    lone = np.array([problem.n_planes])
    shuffled = make_problem(np.r_[problem.plane_index[order], lone], np.r_[problem.scan_index[order], 0],
                            np.r_[problem.clusters[order], problem.clusters[:1]],
                            range_clusters=np.r_[problem.range_clusters[order], problem.range_clusters[:1]])
    assert np.array_equal(shuffled.range_clusters, problem.range_clusters)
    old = tmp_path / "old.npz"
    np.savez(old, plane_index=problem.plane_index, scan_index=problem.scan_index, clusters=problem.clusters)
    assert load_problem(old).range_clusters is None
    bad = tmp_path / "bad.npz"
    np.savez(bad, plane_index=problem.plane_index, scan_index=problem.scan_index, clusters=problem.clusters,
             range_clusters=problem.range_clusters[1:])
    with pytest.raises(FormatError, match="range_clusters"):
        load_problem(bad)


def test_noise_model_falls_back_without_range_clusters():
    """auto is the range model with range clusters and the per-observation model without them."""
    problem, seq = _range_problem()
    T = solve(problem, seq.T_world_scan, TIGHT).T_world_scan
    with_range = pose_covariance(problem, T)
    without = pose_covariance(dataclasses.replace(problem, range_clusters=None), T)
    assert with_range.noise_model == "range" and without.noise_model == "observation"
    assert np.array_equal(without.covariance, pose_covariance(problem, T, noise_model="observation").covariance)
    explicit = pose_covariance(problem, T, noise_model="range", range_clusters=problem.range_clusters)
    assert np.array_equal(with_range.covariance, explicit.covariance)
    assert not np.allclose(with_range.covariance, without.covariance, rtol=1e-3, atol=0.0)
    assert pose_covariance(problem, T, point_sigma_m=0.01).noise_model == "given"
    assert covariance_report(with_range)["noise_model"] == "range"


@pytest.mark.slow
def test_simulated_street_monte_carlo_range_model():
    """Street (range noise along the beam, grazing ground): the range model's average NEES and its
    per-axis 1-sigma over draws of new noise (40 draws: about 11 % sampling error per sigma). The
    per-observation model fails the per-axis check here (roll and pitch, which the grazing ground
    constrains, 1.4-1.6)."""
    nees_6, ratio, models = _monte_carlo("street", 40, 12, 700)
    assert models == {"range"} and 0.7 < nees_6 < 1.4
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


@pytest.mark.slow
@pytest.mark.parametrize(("point_noise_m", "range_noise_m", "share_range"), [(0.02, 0.0, (0.8, 1.0)),
                                                                           (0.01, 0.01, (0.3, 0.8))])
def test_simulated_street_monte_carlo_isotropic_noise(point_noise_m, range_noise_m, share_range):
    """Street with isotropic point noise (alone, or beside range noise of the same sigma): the range model
    finds the isotropic share and its NEES and per-axis 1-sigma stay covered. The same noise spread as range
    noise alone gives NEES / 6 1.41 and an omega_y 1-sigma 0.75 of the empirical one (20 draws)."""
    shares: list[float] = []
    nees_6, ratio, models = _monte_carlo("street", 20, 12, 700, shares, point_noise_m=point_noise_m,
                                         range_noise_m=range_noise_m)
    assert models == {"range"} and 0.8 < nees_6 < 1.25
    assert np.all((ratio > 0.8) & (ratio < 1.3)), ratio
    assert share_range[0] <= np.mean(shares) <= share_range[1]


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_isotropic_ratio_recovers_the_split_of_the_noise(share):
    """White variances drawn from the model (planes at their own noise level, observations at random
    incidences, chi-square sampling with each one's degrees of freedom, a spread of 20 % between one
    surface's observations): the fitted isotropic share over 30 draws is the true one within 0.1."""
    from pa_cli.adjust.noise_model import isotropic_ratio
    from pa_cli.core.problem import FeatureProblem

    rng = np.random.default_rng(5)
    n_planes, per_plane = 40, 8
    plane_index = np.repeat(np.arange(n_planes), per_plane)
    problem = FeatureProblem(plane_index, np.tile(np.arange(per_plane), n_planes),
                             np.zeros((len(plane_index), 4, 4)), per_plane)
    fitted = []
    for _ in range(30):
        cos2 = rng.uniform(0.05, 1.0, len(plane_index))
        gamma = share / (1.0 - share) * cos2.mean() if share < 1.0 else np.inf
        level = rng.uniform(1e-4, 1e-3, n_planes)[plane_index]
        dof = rng.integers(20, 400, len(plane_index)).astype(float)
        variance = level * (np.minimum(gamma, 1e12) + cos2) * rng.chisquare(dof) / dof \
            * np.exp(rng.normal(0.0, 0.2, len(plane_index)))
        fitted.append(isotropic_ratio(variance, dof, cos2, problem)[1])
    assert abs(np.mean(fitted) - share) < 0.1, np.mean(fitted)


def test_cli_adjust_uses_the_problems_range_clusters(run_pa, tmp_path):
    problem, seq = _range_problem()
    problem.T_world_scan = perturb(seq.T_world_scan, np.deg2rad(0.2), 0.02, seed=4)
    path = tmp_path / "problem.npz"
    save_problem(path, problem)
    for flags, model in (((), "range"), (("--noise-model", "observation"), "observation")):
        cov_path, report = tmp_path / f"{model}.npz", tmp_path / f"{model}.json"
        code, _, err = run_pa("adjust", path, "--out", tmp_path / f"{model}.txt", "--covariance", cov_path,
                              "--report", report, *flags)
        assert code == 0, err
        assert load_covariance(cov_path).noise_model == model
        assert json.loads(report.read_text())["covariance"]["noise_model"] == model
    code, _, err = run_pa("adjust", path, "--out", tmp_path / "x.txt", "--covariance", tmp_path / "x.npz",
                          "--noise-model", "beams")
    assert code == 2 and "--noise-model" in err


@pytest.mark.parametrize("point_sigma_m", [0.01, None])
def test_feature_nodes_give_the_pair_form_covariance(point_sigma_m):
    """Planes many scans share as nodes of the augmented matrix (`selected_inverse`, "Feature
    nodes") give the covariance of the pair blocks: the plain inverse against the dense inverse of
    the Newton system's pose Hessian, and the sandwich (two matrices, couplings linear in the step)
    against the pair form's."""
    from pa_cli.adjust.covariance import _LocalSystem

    problem, T = make_scene(14, 10, 14, points_per_observation=15, noise_m=0.01, seed=6)
    T = solve(problem, T, TIGHT).T_world_scan
    model, _, _, A, beta = _linearised(problem, T)
    assert model.pattern.n_aux_features > 0
    nodes, pairs = (_LocalSystem(model, T, [], feature_nodes=f) for f in (True, False))
    assert nodes.feature_node is not None and pairs.feature_node is None
    assert len(nodes.symbolic.perm_inv) == len(pairs.symbolic.perm_inv) + model.pattern.n_aux_features
    if point_sigma_m is not None:
        got = nodes.to_world(nodes.plain_inverse_blocks(A, beta), problem.n_scans)
        # dense H = blockdiag(A) - sum over planes of U U^T, U the plane's coupling rows
        H = sp.block_diag(list(A)).toarray()
        for i in range(problem.n_planes):
            U = np.zeros((6 * problem.n_scans, 3))
            for o in np.flatnonzero(problem.plane_index == i):
                j = problem.scan_index[o]
                U[6 * j:6 * j + 6] += beta[o].T
            H -= U @ U.T
        expected = np.zeros((problem.n_scans, 6, 6))
        expected[1:] = _dense_blocks(np.linalg.inv(H[6:, 6:]))  # gauge pose 0 removed
    else:
        rng = np.random.default_rng(1)
        A_v = A * rng.uniform(0.5, 2.0, (len(A), 1, 1))
        Bt_v = beta * rng.uniform(0.5, 2.0, (len(beta), 1, 1))
        Q = np.einsum("pij,pkj->pik", *(2 * [rng.normal(size=(problem.n_planes, 3, 3))])) * 1e-2
        got, expected = (s.sandwich_blocks(A, beta, A_v, Bt_v, Q, problem.plane_index, 0.0)
                         for s in (nodes, pairs))
    d = np.sqrt(np.abs(np.einsum("nii->ni", expected[1:])))  # the random W need not be positive
    assert np.max(np.abs(got[1:] - expected[1:]) / (d[:, :, None] * d[:, None, :])) < 1e-6


@pytest.mark.parametrize("point_sigma_m", [0.01, None])
def test_dense_and_selected_inversions_agree(point_sigma_m, monkeypatch):
    """The dense inversion (at most DENSE_MAX_POSES free poses) and the selected inversion give the same
    covariance, plain (given sigma) and sandwich (estimated noise, two matrices), odometry-like pose
    terms included; planes seen by every scan (feature nodes of the selected inversion)."""
    problem, T = make_scene(30, 40, 30, points_per_observation=15, noise_m=0.01, seed=2)
    T = solve(problem, T, TIGHT).T_world_scan
    assert len(T) - 1 <= covariance.DENSE_MAX_POSES
    dense = pose_covariance(problem, T, point_sigma_m=point_sigma_m).covariance
    monkeypatch.setattr(covariance, "DENSE_MAX_POSES", 0)
    selected = pose_covariance(problem, T, point_sigma_m=point_sigma_m).covariance
    d = np.sqrt(np.einsum("nii->ni", selected[1:]))
    assert np.max(np.abs(dense[1:] - selected[1:]) / (d[:, :, None] * d[:, None, :])) < 1e-6


@pytest.mark.parametrize("window", [3, 6])
def test_block_pattern_keeps_the_node_set_with_the_least_work(window, monkeypatch):
    """The pattern `_LocalSystem` analyses (skipping node sets by lower bounds of their work) is the
    cheapest of `node_sets`, each analysed by brute force: local planes seen by `window` scans and
    two grounds every scan sees."""
    from pa_cli.adjust.covariance import _LocalSystem, node_sets
    from pa_cli.adjust.selected_inverse import analyse_graph, block_graph
    from pa_cli.core.problem import make_problem

    local, T = make_scene(40, 80, window, points_per_observation=12, seed=3)
    ground, T_same = make_scene(40, 2, 40, points_per_observation=12, seed=3)
    assert np.array_equal(T, T_same)
    problem = make_problem(np.concatenate([local.plane_index, ground.plane_index + local.n_planes]),
                           np.concatenate([local.scan_index, ground.scan_index]),
                           np.concatenate([local.clusters, ground.clusters]), n_scans=40, T_world_scan=T)
    model = NewtonModel(problem)
    monkeypatch.setattr(covariance, "DENSE_MAX_POSES", 0)  # the selected inversion's pattern
    chosen = _LocalSystem(model, T, [])
    k = np.bincount(problem.plane_index)
    works = []
    for as_node in node_sets(k, ~model.pattern.paired):
        rows, cols = [], []
        nodes = 39 + np.cumsum(as_node) - 1  # block rows after the 39 free poses (gauge pose 0)
        for i in range(problem.n_planes):
            scans = problem.scan_index[(problem.plane_index == i) & (problem.scan_index > 0)] - 1
            if as_node[i]:
                rows += list(scans)
                cols += [nodes[i]] * len(scans)
            else:
                a, b = np.meshgrid(scans, scans)
                rows += list(a.ravel())
                cols += list(b.ravel())
        works.append(analyse_graph(block_graph(39 + int(as_node.sum()), np.array(rows), np.array(cols))).work)
    assert len(set(works)) > 1
    assert chosen.symbolic.work == min(works)
    best = node_sets(k, ~model.pattern.paired)[int(np.argmin(works))]
    assert np.array_equal(chosen.feature_node >= 0, best) if best.any() else chosen.feature_node is None


def _noisy_odometry(T, model, rng):
    """Odometry factors measured on T's relative motions plus noise at the factors' own sigmas."""
    from pa_cli.adjust.odometry_factors import OdometryFactors, relative_motions
    from pa_cli.core.geometry import exp_so3

    R, t = relative_motions(T)
    exact = OdometryFactors.from_motions(R, t, model)
    R = R @ exp_so3(rng.standard_normal((len(t), 3)) * exact.sigma_r_rad[:, None])
    t = t + rng.standard_normal((len(t), 3)) * exact.sigma_t_m[:, None]
    return OdometryFactors.from_motions(R, t, model)


def test_odometry_noise_at_its_sigmas_is_covered_monte_carlo(monkeypatch):
    """Planes that leave the direction of travel free (`corridor_scene`) and odometry factors whose
    measurements carry noise at their stated sigmas, weighted with a point sigma (0.1 m) far above the
    planes' noise (1 cm), as `pa refine` weights them: over noise draws the NEES of the refined poses
    against the truth averages 6 per scan. Taking the factors' noise at the residual point sigma
    instead (the term variance before) claims a covariance far too small."""
    import pa_cli.adjust.covariance as covariance
    from pa_cli.adjust.odometry_factors import OdometryModel
    from pa_testing.synthetic_problems import corridor_scene

    model = OdometryModel(point_sigma_m=0.1, translation_sigma_m=0.02, translation_sigma_per_m=0.0,
                          rotation_sigma_rad=np.deg2rad(0.2), rotation_sigma_per_rad=0.0, rotation_sigma_rad_per_m=0.0)
    per_draw, at_residual = [], []
    for draw in range(24):
        noise_rng = np.random.default_rng(100 + draw)
        problem, T = corridor_scene(12, 0.01, np.random.default_rng(0), noise_rng)
        factors = _noisy_odometry(T, model, noise_rng)
        T_opt = solve(problem, T, TIGHT, terms=[factors]).T_world_scan
        errors = tangent_error(T_opt, T)[1:]
        per_draw.append(nees(errors, pose_covariance(problem, T_opt, terms=[factors]).covariance[1:]))
        with monkeypatch.context() as patch:
            patch.setattr(covariance, "term_variance", lambda terms, sigma: sigma**2)
            at_residual.append(nees(errors, pose_covariance(problem, T_opt, terms=[factors]).covariance[1:]))
    assert 0.7 < np.mean(per_draw) / 6 < 1.4
    assert np.mean(at_residual) / 6 > 10


def test_term_variance_is_the_terms_point_sigma():
    from pa_cli.adjust.covariance import term_variance
    from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
    from pa_testing.synthetic_problems import RelativeTranslations

    T = np.tile(np.eye(4), (4, 1, 1))
    T[:, 0, 3] = np.arange(4.0)
    odometry = OdometryFactors(T, OdometryModel(0.1, 0.05, 0.0, 0.01, 0.0, 0.0))
    assert term_variance([odometry], 0.002) == pytest.approx(0.01)
    assert term_variance([], 0.002) == pytest.approx(4e-6)
    assert term_variance([odometry, RelativeTranslations(T, 1.0, np.random.default_rng(0))], 0.002) == \
        pytest.approx(4e-6)  # a term without a point sigma: the residual one for all


def test_correlated_noise_monte_carlo_nees():
    """Points of one observation share an offset along the normal (1 cm, beside 5 mm of white noise over
    30 points: the offset dominates their mean) and a tilt about their centroid (0.1 deg), the same scene
    with new noise per draw: the NEES of the default covariance averages 6 within [0.5, 2] x, and the
    estimated shared offset is 1 cm within 20 %. Treating the points as independent (the shared
    variances forced to 0, the covariance before the shared errors were modelled) claims far too small
    a covariance."""
    from pa_cli.adjust import covariance

    errors, covariances, independent, shared = [], [], [], []
    estimate = covariance.correlated_noise_variances

    def independent_points(*args):
        noise = estimate(*args)
        return dataclasses.replace(noise, shared_m2=0.0 * noise.shared_m2, tilt_rad2=0.0 * noise.tilt_rad2)

    for draw in range(20):
        problem, T_true = make_scene(12, 40, 6, points_per_observation=30, noise_m=0.005, seed=3,
                                     noise_seed=900 + draw, shared_noise_m=0.01, shared_tilt_rad=np.deg2rad(0.1))
        T_est = solve(problem, T_true, TIGHT).T_world_scan
        errors.append(tangent_error(T_est, T_true)[1:])
        cov = pose_covariance(problem, T_est)
        covariances.append(cov.covariance[1:])
        shared.append(cov.shared_sigma_m)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(covariance, "correlated_noise_variances", independent_points)
            independent.append(pose_covariance(problem, T_est).covariance[1:])
    errors = np.array(errors)
    assert 0.5 < nees(errors, np.array(covariances)).mean() / 6 < 2.0
    assert nees(errors, np.array(independent)).mean() / 6 > 5.0
    assert 0.8 < np.mean(shared) / 0.01 < 1.2


@pytest.mark.parametrize(("shared_noise_m", "shared_tilt_rad"), [(0.0, 0.0), (0.003, 0.0), (0.003, 0.002)])
def test_shared_variances_are_estimated_without_bias(shared_noise_m, shared_tilt_rad):
    """The shared offset and tilt variances over noise draws against the truth (white 5 mm over 30
    points: 0.9 mm on an observation's mean, 0.05 deg on its tilt over 6 m): within 10 % where they are
    not 0; at 0 (floored at 0: biased up) small against the white noise's share of the statistic."""
    from pa_cli.adjust.covariance import _LocalSystem, observation_noise

    shared, tilt, white = [], [], []
    for draw in range(20):
        problem, T_true = make_scene(12, 40, 6, points_per_observation=30, noise_m=0.005, seed=3,
                                     noise_seed=1200 + draw, shared_noise_m=shared_noise_m,
                                     shared_tilt_rad=shared_tilt_rad)
        T = solve(problem, T_true, TIGHT).T_world_scan
        model, plane_cost, eig, A, _ = _linearised(problem, T)
        _, noise, _ = observation_noise(eig, problem, plane_cost.moments, _LocalSystem(model, T, []), A)
        shared.append(noise.shared_m2.mean())
        tilt.append(noise.tilt_rad2.mean())
        white.append(noise.white_m2.mean())
    for estimate, truth, white_share in ((shared, shared_noise_m**2, 0.005**2 / 30), (tilt, shared_tilt_rad**2,
                                                                                     0.005**2 / (30 * 3.0))):
        if truth:
            assert abs(np.mean(estimate) / truth - 1.0) < 0.1
        else:
            assert 0.0 <= np.mean(estimate) < 0.2 * white_share
    assert abs(np.mean(white) / 0.005**2 - 1.0) < 0.05
