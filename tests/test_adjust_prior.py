"""The odometry pose prior: exact gradient, Gauss-Newton Hessian, and what it does in a solve.

A corridor (floor, ceiling, two walls, all parallel to x) leaves every scan free to slide along
x: the planes constrain the other five degrees of freedom only. With the prior the solver must
correct those five exactly and keep each scan's x where the initial poses put it.
"""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import PosePrior, plane_cost, solve
from pa_cli.clusters import points_to_cluster
from pa_cli.config import SolverConfig
from pa_cli.geometry import exp_so3, retract_left
from pa_cli.problem import make_problem
from tests.synthetic_problems import fd_pose_gradient, perturb, random_poses


def test_prior_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    T0 = random_poses(4, rng)
    T = retract_left(T0, rng.normal(0, 0.3, (4, 6)))
    prior = PosePrior.from_sigmas(T0, sigma_point_m=0.01, sigma_translation_m=0.5, sigma_rotation_rad=np.deg2rad(3.0))
    gradient = prior.linearize(T).gradient
    fd = fd_pose_gradient(prior.cost, T)
    np.testing.assert_allclose(gradient, fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_prior_hessian_is_exact_at_the_prior_poses():
    rng = np.random.default_rng(1)
    T0 = random_poses(2, rng)
    prior = PosePrior.from_sigmas(T0, 0.01, 0.5, np.deg2rad(3.0))
    lin = prior.linearize(T0)
    cost, gradient, hessian = lin.cost, lin.gradient, lin.pose_blocks
    assert cost == 0.0 and np.all(gradient == 0.0)
    h = 1e-4
    for j in range(2):
        fd = np.zeros((6, 6))
        for a in range(6):
            for b in range(6):
                def f(sa, sb, a=a, b=b, j=j):
                    d = np.zeros((2, 6))
                    d[j, a] += sa * h
                    d[j, b] += sb * h
                    return prior.cost(retract_left(T0, d))
                fd[a, b] = (f(1, 1) - f(1, -1) - f(-1, 1) + f(-1, -1)) / (4 * h * h)
        np.testing.assert_allclose(hessian[j], fd, rtol=1e-5, atol=1e-8 * np.abs(fd).max())


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
def test_prior_holds_the_unobserved_direction_and_frees_the_rest(solver):
    problem, T_gt = _corridor()
    T_init = perturb(T_gt, np.deg2rad(1.0), 0.1, seed=3, keep_first=True)
    prior = PosePrior.from_sigmas(T_init, 0.01, 1.0, np.deg2rad(5.0))
    result = solve(problem, T_init, SolverConfig(max_iterations=100, solver=solver), terms=[prior])
    T = result.T_world_scan
    assert result.report["converged"]
    # the planes' five degrees of freedom are corrected exactly (the prior is ~1e-4 of a point)
    assert plane_cost(problem, T) < 1e-8
    np.testing.assert_allclose(T[:, 1:3, 3], T_gt[:, 1:3, 3], atol=1e-5)
    R_err = np.einsum("nji,njk->nik", T_gt[:, :3, :3], T[:, :3, :3])
    assert np.max(np.abs(R_err - np.eye(3))) < 1e-5
    # ... and the free one (x along the corridor) stays where the initial poses put it
    np.testing.assert_allclose(T[:, 0, 3], T_init[:, 0, 3], atol=1e-4)
    assert result.report["cost_final_m2"] == pytest.approx(plane_cost(problem, T))
    assert result.report["prior_cost_final_m2"] == pytest.approx(prior.cost(T))
    assert result.report["prior_cost_initial_m2"] == 0.0  # the prior is centred on the initial poses
