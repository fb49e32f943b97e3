"""The leverage of the noise model against dense algebra on per-point Jacobians, and the positive definite
factor its solves use."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from pa_cli.adjust import noise_model
from pa_cli.adjust._ldl_solve import PositiveDefiniteFactor
from pa_cli.adjust.covariance import gauss_newton_pieces
from pa_cli.adjust.newton import NewtonModel
from pa_cli.adjust.noise_model import residual_components, residual_leverage
from pa_cli.core.clusters import plane_eigen
from pa_cli.errors import SolverError
from pa_testing.synthetic_problems import planes_seen_by_every_scan


def _points_problem(seed: int, n_scans: int = 5, n_planes: int = 7, m: int = 20):
    """Every plane seen by every scan, the points kept (world frame, in observation order)."""
    rng = np.random.default_rng(seed)

    def observe(i, j, centre, basis, normal):
        return centre + rng.uniform(-3, 3, (m, 2)) @ basis + rng.normal(0, 0.01, (m, 1)) * normal

    return planes_seen_by_every_scan(rng, n_scans, n_planes, observe)


@pytest.mark.parametrize("seed", [1, 2])
def test_leverage_is_the_hutchinson_estimate_of_the_dense_projection(seed):
    """With the same probes, the leverage equals mean_z z (D^T Jbar F^-1 Jbar^T D z) / |d|^2 formed densely:
    Jbar the per-point rows of the free poses ([q x n, n]), of each plane's tilts and offset about its centroid
    (e_a . (q - c), 1) and of an odometry-like pose term coupling scans 1 and 2 (F = Jbar^T Jbar plus half the
    term's Hessian), d per observation its offset (1 on its points) and tilts (t_a . (q_k - c_o))."""
    problem, T, points_world = _points_problem(seed)
    plane_cost = NewtonModel(problem).feature_cost.parts[0][1]
    moments = plane_cost.moments
    eig = plane_eigen(T, *moments, problem.scan_index, plane_cost.starts)
    _, c_o, _, vec, centroid, _ = eig
    A, _ = gauss_newton_pieces(eig, problem.plane_index, eig[0], eig[1], moments[3], problem.scan_index,
                               problem.n_scans)
    components = residual_components(eig, problem, moments)
    rng = np.random.default_rng(100 + seed)
    J_term = rng.normal(size=(12, 12))  # a term on poses 1 and 2 (free indices 0 and 1), H_term = 2 J^T J
    H_term = 2.0 * J_term.T @ J_term
    free = np.arange(1, problem.n_scans)  # pose 0 is the gauge
    pose_hessian = A[free].copy()
    pose_hessian[0] += H_term[:6, :6]
    pose_hessian[1] += H_term[6:, 6:]
    leverage, _ = residual_leverage(eig, problem, moments, components, pose_hessian, free, np.array([[0, 1]]),
                                    H_term[None, :6, 6:])

    n_free, n_planes, n_obs = len(free), problem.n_planes, problem.n_observations
    size = 6 * n_free + 3 * n_planes
    rows, directions = [], []
    for o, q in enumerate(points_world):
        i, j = problem.plane_index[o], problem.scan_index[o]
        n = vec[i, :, 0]
        jbar = np.zeros((len(q), size))
        if j > 0:
            jbar[:, 6 * (j - 1):6 * j] = np.column_stack([np.cross(q, n), np.tile(n, (len(q), 1))])
        plane = 6 * n_free + 3 * i
        jbar[:, plane:plane + 2] = (q - centroid[i]) @ vec[i, :, 1:]
        jbar[:, plane + 2] = 1.0
        rows.append(jbar)
        d = np.zeros((len(q), 3 * n_obs))
        d[:, 3 * o] = 1.0
        d[:, 3 * o + 1:3 * o + 3] = (q - c_o[o]) @ components.directions[o]
        directions.append(d)
    jbar, d = np.vstack(rows), np.vstack(directions)
    F = jbar.T @ jbar
    F[:12, :12] += 0.5 * H_term
    U = jbar.T @ d
    projection = U.T @ np.linalg.solve(F, U)  # (3 O, 3 O)
    draws = np.random.default_rng(noise_model.LEVERAGE_SEED)
    total = np.zeros(3 * n_obs)
    for first in range(0, noise_model.LEVERAGE_PROBES, noise_model.PROBES_PER_DRAW):
        count = min(noise_model.PROBES_PER_DRAW, noise_model.LEVERAGE_PROBES - first)
        z = draws.choice([-1.0, 1.0], size=(n_obs, 3, count)).reshape(3 * n_obs, count)
        total += np.sum(z * (projection @ z), axis=1)
    norm2 = np.column_stack([moments[3], components.spread_m2])
    expected = total.reshape(n_obs, 3) / noise_model.LEVERAGE_PROBES / norm2
    assert np.allclose(norm2, np.sum(d**2, axis=0).reshape(n_obs, 3), rtol=1e-12)
    assert np.max(np.abs(leverage - expected)) < 1e-8 * np.max(np.abs(expected))
    assert np.max(np.abs(leverage - expected) / np.abs(expected)) < 1e-6


def _random_spd(n: int, seed: int) -> sp.csc_matrix:
    rng = np.random.default_rng(seed)
    B = sp.random(n, n, density=0.05, random_state=rng)
    return (B @ B.T + sp.eye(n)).tocsc()


@pytest.mark.parametrize("probes", [1, 5])
def test_probe_sums_are_the_dense_quadratic_forms(probes):
    """probe_sums against dense algebra: sum_p z_p * (U^T M^-1 U z_p) per column of U, the columns grouped by
    observation (sharing their rows of M, some left out with -1)."""
    rng = np.random.default_rng(5)
    n, n_obs, n_columns, n_rows = 80, 12, 3, 5
    M = _random_spd(n, 4)
    rows = np.array([rng.choice(n, n_rows, replace=False) for _ in range(n_obs)])
    rows[rng.random(rows.shape) < 0.2] = -1
    values = rng.normal(size=(n_obs, n_columns, n_rows))
    bits = rng.integers(0, 2, size=(n_obs, n_columns, probes))
    U = np.zeros((n, n_obs * n_columns))
    for o in range(n_obs):
        for m in np.flatnonzero(rows[o] >= 0):
            U[rows[o, m], n_columns * o:n_columns * (o + 1)] = values[o, :, m]
    z = (2.0 * bits - 1.0).reshape(n_obs * n_columns, probes)
    expected = np.sum(z * (U.T @ np.linalg.solve(M.toarray(), U @ z)), axis=1).reshape(n_obs, n_columns)
    sums = PositiveDefiniteFactor(sp.triu(M, format="csc")).probe_sums(rows, values, bits)
    assert np.allclose(sums, expected, rtol=0.0, atol=1e-12 * np.abs(expected).max())


def test_factor_refuses_a_matrix_that_is_not_positive_definite():
    M = _random_spd(40, 6).tolil()
    M[7, 7] = -1.0
    with pytest.raises(ValueError):
        PositiveDefiniteFactor(sp.triu(M.tocsc(), format="csc"))


def test_leverage_of_an_unconstrained_pose_is_refused():
    """A free pose without any information: the leverage raises SolverError instead of dividing by zero."""
    problem, T, _ = _points_problem(3, n_scans=3, n_planes=4)
    plane_cost = NewtonModel(problem).feature_cost.parts[0][1]
    eig = plane_eigen(T, *plane_cost.moments, problem.scan_index, plane_cost.starts)
    components = residual_components(eig, problem, plane_cost.moments)
    with pytest.raises(SolverError):
        residual_leverage(eig, problem, plane_cost.moments, components, np.zeros((2, 6, 6)), np.arange(1, 3),
                          np.empty((0, 2), np.int64), np.empty((0, 6, 6)))


def _offsets(rng: np.random.Generator, shared_m: float, white_m: float, n_planes: int = 400, k: int = 4,
             n: int = 50):
    """Observations' offsets from their plane's centroid: k observations of n points per plane, each with an
    offset of sigma shared_m its points share and white noise white_m per point."""
    means = rng.normal(0, shared_m, (n_planes, k)) + rng.normal(0, white_m, (n_planes, k, n)).mean(axis=2)
    offset = (means - means.mean(axis=1, keepdims=True)).ravel()
    return offset, np.full(offset.size, white_m**2), np.full(offset.size, float(n)), np.repeat(np.arange(n_planes), k)


@pytest.mark.parametrize("shared_m", [0.0, 0.005])
def test_shared_offset_variance_is_the_shared_variance_monte_carlo(shared_m):
    """Over 200 draws of 1,600 observations (400 planes of 4, 50 points of 2 cm white noise each: a white
    variance of 8e-6 m^2 per observation mean), the mean estimate is the shared variance within 3 standard errors:
    0 without a shared offset (counted only where significant),
    2.5e-5 m^2 with 5 mm. Without the plane's degree of freedom (1 - 1/K) it would be 25 % low."""
    rng = np.random.default_rng(5)
    estimates = np.array([noise_model.shared_offset_variance(*_offsets(rng, shared_m, 0.02)) for _ in range(200)])
    standard_error = estimates.std(ddof=1) / np.sqrt(len(estimates))
    if shared_m:
        assert abs(estimates.mean() - shared_m**2) < 3.0 * standard_error
        assert 3.0 * standard_error < 0.1 * shared_m**2  # the test tells the estimate from 3/4 of it
    else:
        assert estimates.mean() < 0.05 * 0.02**2 / 50  # a twentieth of the white variance of a mean


@pytest.mark.parametrize("shared_m", [0.01, 0.0])
def test_plane_balance_gives_the_offsets_information(shared_m):
    """Planes seen by every scan, every observation's points sharing an offset of 1 cm besides 2 cm of white noise,
    at the true poses: the balance sigma is that of the offsets' information, sqrt(sum N_o / sum 1 / (v_c + v_w /
    N_o)) with the true variances, within 10 %; without the shared offset it is the white noise within 5 %."""
    rng = np.random.default_rng(11)

    def observe(i, j, centre, basis, normal):
        return (centre + rng.uniform(-3, 3, (200, 2)) @ basis
                + (rng.normal(0, 0.02, (200, 1)) + rng.normal(0, shared_m)) * normal)

    problem, T, _ = planes_seen_by_every_scan(rng, 6, 60, observe)
    expected = np.sqrt(200.0 * (shared_m**2 + 0.02**2 / 200)) if shared_m else 0.02
    assert abs(noise_model.PlaneBalance(problem).point_sigma_m(T) / expected - 1.0) < (0.1 if shared_m else 0.05)


def test_plane_balance_at_the_features_optimum_is_the_noise_not_the_pose_errors():
    """200 planes over 30 scans, 2 cm white noise per point and no shared offset. At poses 0.5 deg / 5 cm off the
    observations' offsets hold the pose errors, and the balance counts them as noise shared by each observation's
    points (several times the 2 cm); at the features' own optimum from those poses (the planes solved alone, as
    `pa refine`'s rounds measure it) it is the 2 cm again, within 10 %, as at the truth."""
    from pa_cli.adjust import solve
    from pa_cli.config import SolverConfig
    from pa_testing.synthetic_problems import make_scene, perturb

    problem, T_true = make_scene(30, 200, 6, points_per_observation=50, noise_m=0.02, seed=3)
    T_off = perturb(T_true, np.deg2rad(0.5), 0.05, seed=4)
    balance = noise_model.PlaneBalance(problem)
    assert abs(balance.point_sigma_m(T_true) / 0.02 - 1.0) < 0.1
    assert balance.point_sigma_m(T_off) > 3.0 * 0.02
    T_features = solve(problem, T_off, SolverConfig()).T_world_scan
    assert abs(balance.point_sigma_m(T_features) / 0.02 - 1.0) < 0.1
