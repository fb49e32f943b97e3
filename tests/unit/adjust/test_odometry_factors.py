"""Relative-pose (odometry) factors: exact gradient, Gauss-Newton Hessian, and what they do in a solve.

In a corridor (floor, ceiling, two walls parallel to x) the planes leave every scan free along x.
With the factors, the solvers correct the five observed degrees of freedom exactly and keep the
relative motions along x where the odometry put them.
"""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.odometry_factors import (
    HOLD_FACTOR,
    HeldHorizontal,
    OdometryFactors,
    OdometryModel,
    held_basis,
    held_motions,
    relative_motions,
)
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.geometry import exp_so3, log_so3
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


def test_held_horizontal_gradient_and_hessian_match_finite_differences():
    rng = np.random.default_rng(7)
    T0 = _random_poses(4, rng)
    factors = OdometryFactors(T0, MODEL)
    held = HeldHorizontal(factors, T0, np.tile(np.eye(6) * 3.0, (4, 1, 1)))
    T = retract_poses(T0, rng.normal(0, 0.2, (4, 6)))
    lin = held.linearize(T)
    assert lin.cost == pytest.approx(held.cost(T), rel=1e-12) and lin.cost > 0
    fd = _finite_difference_gradient(held, T)
    np.testing.assert_allclose(lin.gradient, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    # at the initial trajectory the Gauss-Newton Hessian is the exact one
    fd = _finite_difference_hessian(held, T0)
    np.testing.assert_allclose(_assembled_hessian(held, T0), fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())
    # three directions per pair: the horizontal translation and the heading
    assert [np.linalg.matrix_rank(W) for W in held.weights] == [3, 3, 3]


def test_held_horizontal_keeps_the_odometry_horizontal_and_lets_the_planes_fix_the_rest():
    """Corridor with walls (y, heading) and floor and ceiling (z, roll, pitch): held, each pair's
    horizontal motion and heading change stay the odometry's, while z, roll and pitch go to the truth."""
    from pa_cli.evaluation.degeneracy import plane_information

    problem, T_gt = _corridor(seed=2)
    T_odo = perturb(T_gt, np.deg2rad(0.5), 0.05, seed=4, keep_first=True)
    factors = OdometryFactors(T_odo, MODEL)
    config = SolverConfig(max_iterations=100)
    free = solve(problem, T_odo, config, terms=[factors]).T_world_scan
    held = HeldHorizontal(factors, free, plane_information(problem, free))
    T = solve(problem, free, config, terms=[factors, held]).T_world_scan

    def heading(T):
        return np.arctan2(T[:, 1, 0], T[:, 0, 0])

    def tilt(T):  # the world vertical in each scan's frame
        return T[:, 2, :3]

    # unheld, the walls take y and the heading to the truth
    np.testing.assert_allclose(free[:, 1, 3], T_gt[:, 1, 3], atol=1e-3)
    np.testing.assert_allclose(heading(free), heading(T_gt), atol=1e-4)
    # held: each pair's motion orthogonal to the vertical and its turn about it stay the odometry's
    # (to about 1/HOLD_FACTOR of the unheld change)
    up_prev, up_next = free[:-1, 2, :3], free[1:, 2, :3]

    def held_residuals(T):
        e = factors.residuals(T)
        horizontal = e[:, 3:] - np.einsum("ni,ni->n", e[:, 3:], up_prev)[:, None] * up_prev
        return np.abs(horizontal).max(), np.abs(np.einsum("ni,ni->n", e[:, :3], up_next)).max()

    (move_held, turn_held), (move_free, turn_free) = held_residuals(T), held_residuals(free)
    assert move_free > 0.01 and turn_free > 1e-3
    assert move_held < 2.0 / HOLD_FACTOR * move_free and turn_held < 2.0 / HOLD_FACTOR * turn_free
    # so x, y and the heading stay near the odometry's (its error: 5 cm, 0.8 deg): the pairs' horizontal
    # motions are held in the scans' frames, whose tilt the planes corrected by up to 1.1 deg
    # (0.5 m steps: up to 1 cm in the world), the heading to the second order of that tilt
    assert np.abs(T_odo[:, 1, 3] - T_gt[:, 1, 3]).max() > 0.04
    np.testing.assert_allclose(T[:, :2, 3], T_odo[:, :2, 3], atol=0.01)
    np.testing.assert_allclose(heading(T), heading(T_odo), atol=1e-3)
    assert np.abs(heading(T_odo) - heading(T_gt)).max() > 3e-3
    # z, roll and pitch: decided by the floor and the ceiling, which the odometry had 11 cm and 1.1 deg off;
    # the walls, left 5 cm off by the held y, pull the roll a little (rolling a scan moves its wall
    # points sideways): 2 mm and 0.3 deg here
    z_error, tilt_error = np.abs(T[:, 2, 3] - T_gt[:, 2, 3]).max(), np.abs(tilt(T) - tilt(T_gt)).max()
    assert z_error < 0.05 * np.abs(T_odo[:, 2, 3] - T_gt[:, 2, 3]).max()
    assert tilt_error < 0.5 * np.abs(tilt(T_odo) - tilt(T_gt)).max()


def _tilted_pairs(seed: int):
    """Scans 1 m apart turning a little, each tilted a few degrees: initial motions, a registration
    5 cm and 1 deg from them in every direction."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, :3, :3] = exp_so3(rng.normal(0, 0.05, (6, 3)))
    T[:, :3, 3] = np.column_stack([np.arange(6.0), rng.normal(0, 0.1, 6), rng.normal(0, 0.05, 6)])
    factors = OdometryFactors(T, MODEL)
    T_reg = np.tile(np.eye(4), (5, 1, 1))
    T_reg[:, :3, :3] = factors.R_z @ exp_so3(rng.normal(0, np.deg2rad(1.0), (5, 3)))
    T_reg[:, :3, 3] = factors.t_z + rng.normal(0, 0.05, (5, 3))
    return T, factors, T_reg


def _held_and_other_parts(factors: OdometryFactors, R: np.ndarray, t: np.ndarray, T: np.ndarray):
    """The residual of motions (R, t) against the factors' measurement, split into its held part (in
    `held_basis` coordinates: heading rad, two horizontal translations m) and the rest (6-vectors)."""
    e = np.hstack([log_so3(np.einsum("nji,njk->nik", factors.R_z, R)), t - factors.t_z])
    basis = held_basis(T)
    held = np.einsum("nai,na->ni", basis, e)
    return held, e - np.einsum("nai,ni->na", basis, held)


def test_held_basis_is_the_heading_and_the_horizontal_of_each_pair():
    T, _, _ = _tilted_pairs(seed=1)
    basis = held_basis(T)
    np.testing.assert_allclose(np.einsum("nai,naj->nij", basis, basis), np.tile(np.eye(3), (5, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(basis[:, :3, 0], T[1:, 2, :3])  # the world vertical in scan j+1's frame
    np.testing.assert_allclose(np.einsum("ni,nik->nk", T[:-1, 2, :3], basis[:, 3:, 1:]), 0.0, atol=1e-12)


def test_held_motions_follow_the_registration_where_it_sees_and_the_odometry_elsewhere():
    """A registration that sees every direction far better than the odometry decides the pairs'
    heading and horizontal motion; one that sees nothing leaves the initial motions; one blind along
    a horizontal direction (a corridor) leaves that direction's motion the initial one. The height,
    roll and pitch of the result are the initial motions' in every case."""
    T, factors, T_reg = _tilted_pairs(seed=2)
    reg_held, reg_rest = _held_and_other_parts(factors, T_reg[:, :3, :3], T_reg[:, :3, 3], T)
    assert np.abs(reg_held).min() > 1e-4 and np.abs(reg_rest).max() > 1e-3

    sees_all = np.tile(np.eye(6) * 1e6, (5, 1, 1))
    R, t, n_seen = held_motions(factors, T_reg, sees_all, T, lever_arm_m=10.0)
    held, rest = _held_and_other_parts(factors, R, t, T)
    np.testing.assert_array_equal(n_seen, 3)
    np.testing.assert_allclose(held, reg_held, atol=1e-12)
    np.testing.assert_allclose(rest, 0.0, atol=1e-12)

    R, t, n_seen = held_motions(factors, T_reg, np.zeros((5, 6, 6)), T, lever_arm_m=10.0)
    np.testing.assert_array_equal(n_seen, 0)
    np.testing.assert_allclose(R, factors.R_z, atol=1e-15)
    np.testing.assert_allclose(t, factors.t_z, atol=1e-15)

    # blind along the first horizontal direction: points on planes square to the heading and to the
    # second horizontal direction only (information 2 per point, 100 points each)
    basis = held_basis(T)
    blind = np.zeros((5, 6, 6))
    for k in (0, 2):
        a = basis[:, :, k] * np.r_[np.full(3, 10.0), np.ones(3)]  # a point 10 m away sees the heading
        blind += 200.0 * np.einsum("ni,nj->nij", a, a)
    R, t, n_seen = held_motions(factors, T_reg, blind, T, lever_arm_m=10.0)
    held, rest = _held_and_other_parts(factors, R, t, T)
    np.testing.assert_array_equal(n_seen, 2)
    np.testing.assert_allclose(held[:, [0, 2]], reg_held[:, [0, 2]], atol=1e-12)
    np.testing.assert_allclose(held[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(rest, 0.0, atol=1e-12)

    # the same directions seen half as well as the odometry factor sees them (its Hessian 2 W, the heading
    # in metres at the lever arm): the initial motions stay
    odometry_m = 2.0 * min(factors.weights[:, 3].min(), factors.weights[:, 0].min() / 10.0**2)
    weak = blind * (0.5 * odometry_m / 200.0)
    _, _, n_seen = held_motions(factors, T_reg, weak, T, lever_arm_m=10.0)
    np.testing.assert_array_equal(n_seen, 0)
