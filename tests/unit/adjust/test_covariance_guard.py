"""The pose covariance refuses factors above its memory and work limits, before any numerical work."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust.covariance import BLOCK_BYTES, BLOCK_PRODUCTS_PER_WORK, GB, _LocalSystem, pose_covariance
from pa_cli.adjust.newton import NewtonModel
from pa_cli.core.problem import make_problem
from pa_cli.errors import SolverError
from pa_testing.synthetic_problems import make_scene


def _laps(n_per_lap: int, laps: int):
    """The same scans driven `laps` times: every plane is seen again on every lap (a revisited place)."""
    lap, T = make_scene(n_per_lap, 8 * n_per_lap, 10, points_per_observation=10, noise_m=0.01, seed=4)
    problem = make_problem(np.tile(lap.plane_index, laps),
                           np.concatenate([lap.scan_index + k * n_per_lap for k in range(laps)]),
                           np.concatenate([lap.clusters] * laps), n_scans=laps * n_per_lap,
                           T_world_scan=np.concatenate([T] * laps))
    return problem, np.concatenate([T] * laps)


def _symbolic(problem, T):
    return _LocalSystem(NewtonModel(problem, 0, 1e-6, ()), T, []).symbolic


def test_limits_are_checked_on_the_symbolic_factor():
    problem, T = _laps(40, 2)
    sym = _symbolic(problem, T)
    products = BLOCK_PRODUCTS_PER_WORK * sym.work  # one system with a given sigma
    factor_gb = len(sym.rows) * BLOCK_BYTES / GB
    given = pose_covariance(problem, T, point_sigma_m=0.01, max_block_products=products,
                            memory_budget_gb=factor_gb)
    assert np.all(np.isfinite(given.covariance))
    with pytest.raises(SolverError, match="advanced.covariance.max_block_products"):
        pose_covariance(problem, T, point_sigma_m=0.01, max_block_products=0.99 * products)
    with pytest.raises(SolverError, match="memory_budget_gb"):
        pose_covariance(problem, T, point_sigma_m=0.01, memory_budget_gb=0.99 * factor_gb)
    # the estimated sigma needs two systems (the sandwich): twice the work of the given one
    with pytest.raises(SolverError, match="advanced.covariance.max_block_products"):
        pose_covariance(problem, T, max_block_products=1.99 * products)
    assert np.all(np.isfinite(pose_covariance(problem, T, max_block_products=2 * products).covariance))


def test_revisits_fill_the_factor():
    """A sequence driven once has a banded factor; the same places revisited couple scans far apart."""
    once = _symbolic(*_laps(120, 1))
    thrice = _symbolic(*_laps(40, 3))  # as many scans, each place seen on three laps
    assert len(thrice.rows) > 1.5 * len(once.rows)
    assert thrice.work > 2 * once.work
