"""Start-consistency: the second start's result against the first, judged by the pose covariance."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import solve
from pa_cli.adjust.covariance import pose_covariance
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel, relative_motions
from pa_cli.config import SolverConfig
from pa_cli.core.geometry import log_so3
from pa_cli.refine.consistency import chained, perturbed_measurements, start_consistency
from pa_testing.synthetic_problems import corridor_scene

TIGHT = SolverConfig(cost_tolerance=1e-14, gradient_tolerance=1e-12, step_tolerance=1e-12)
MODEL = OdometryModel(point_sigma_m=0.1, translation_sigma_m=0.02, translation_sigma_per_m=0.0,
                      rotation_sigma_rad=np.deg2rad(0.2), rotation_sigma_per_rad=0.0, rotation_sigma_rad_per_m=0.0)


@pytest.fixture(scope="module")
def corridor():
    problem, T = corridor_scene(12, 0.01, np.random.default_rng(0), np.random.default_rng(1))
    factors = OdometryFactors(T, MODEL)
    T_refined = solve(problem, T, TIGHT, terms=[factors]).T_world_scan
    covariance = pose_covariance(problem, T_refined, terms=[factors])
    return problem, T, factors, T_refined, covariance


def test_the_measurements_are_drawn_within_their_sigmas_and_chained():
    T = np.tile(np.eye(4), (400, 1, 1))
    T[:, 0, 3] = np.arange(400.0)
    factors = OdometryFactors(T, MODEL)
    R, t = perturbed_measurements(factors, np.random.default_rng(5))
    R0, t0 = relative_motions(T)
    assert np.std(t - t0) == pytest.approx(0.02, rel=0.1)
    assert np.std(log_so3(np.einsum("nji,njk->nik", R0, R))) == pytest.approx(np.deg2rad(0.2), rel=0.1)
    first = np.eye(4)
    first[:3, 3] = [1.0, 2.0, 3.0]
    chain = chained(R, t, first)
    assert np.array_equal(chain[0], first)  # the gauge stays
    R1, t1 = relative_motions(chain)
    np.testing.assert_allclose(t1, t, atol=1e-12)
    np.testing.assert_allclose(R1, R, atol=1e-12)


def test_a_covariance_that_covers_the_odometry_passes(corridor):
    problem, T, factors, T_refined, covariance = corridor
    check = start_consistency(problem, T_refined, factors, TIGHT, covariance.position_covariance_m2())
    assert check.consistent and check.beyond == []
    assert check.moved_m.max() > 0.005  # the corridor's free direction follows the start's motions
    assert np.sqrt(check.mahalanobis.max()) < 3.8


def test_a_covariance_too_small_for_the_start_dependence_is_named(corridor):
    problem, T, factors, T_refined, covariance = corridor
    too_small = covariance.position_covariance_m2() / 400.0  # claims 20x less than it knows
    check = start_consistency(problem, T_refined, factors, TIGHT, too_small)
    assert not check.consistent
    assert all(b["sigmas"] > 3.76 for b in check.beyond)  # sqrt(14.16): beyond 3 sigma in 3-D
    assert [b["scan"] for b in check.beyond] == sorted((b["scan"] for b in check.beyond),
                                                       key=lambda j: -check.mahalanobis[j])
    along = ["direction of travel" in b["direction"] for b in check.beyond]  # the corridor's free axis
    assert sum(along) >= 0.75 * len(along)
    assert "more than 3 sigma" in check.reason() and str(check.beyond[0]["scan"]) in check.reason()
    assert check.report()["consistent"] is False


def test_without_a_covariance_the_moves_are_reported_not_judged(corridor):
    problem, T, factors, T_refined, _ = corridor
    check = start_consistency(problem, T_refined, factors, TIGHT, None)
    assert check.consistent and check.mahalanobis is None and check.report()["max_sigmas"] is None


def test_the_second_start_keeps_the_refined_gauge(corridor):
    """Rounds that moved the first scan (a relocalised scan 0) leave every pose rigidly moved: the
    second start begins at the refined first pose, so the comparison sees no gauge offset."""
    problem, T, factors, T_refined, covariance = corridor
    moved = np.eye(4)
    moved[:3, 3] = [0.7, -0.2, 0.05]
    check = start_consistency(problem, moved @ T_refined, factors, TIGHT, covariance.position_covariance_m2())
    assert check.consistent and check.moved_m.max() < 0.2  # as without the offset, not 0.7 m everywhere
