"""Start-consistency: the second start's result against the first, judged by the pose covariance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pa_cli.adjust import solve
from pa_cli.adjust.covariance import pose_covariance
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel, relative_motions
from pa_cli.config import SolverConfig
from pa_cli.core.geometry import log_so3, retract_left
from pa_cli.refine.consistency import (
    CHI2_3DOF_3SIGMA,
    START_SEED,
    association_spread,
    association_within,
    perturbed_measurements,
    start_consistency,
)
from pa_cli.refine.rounds import registration_chain
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


def test_the_measurements_are_drawn_within_their_sigmas():
    T = np.tile(np.eye(4), (400, 1, 1))
    T[:, 0, 3] = np.arange(400.0)
    factors = OdometryFactors(T, MODEL)
    R, t = perturbed_measurements(factors, np.random.default_rng(5))
    R0, t0 = relative_motions(T)
    assert np.std(t - t0) == pytest.approx(0.02, rel=0.1)
    assert np.std(log_so3(np.einsum("nji,njk->nik", R0, R))) == pytest.approx(np.deg2rad(0.2), rel=0.1)


def test_the_measurements_are_drawn_within_their_sigmas_per_axis():
    """Measured sigmas differ per axis (a registration resolves the heading ten times better than the roll): each
    axis is drawn with its own."""
    T = np.tile(np.eye(4), (2000, 1, 1))
    T[:, 0, 3] = np.arange(2000.0)
    R0, t0 = relative_motions(T)
    sigmas = np.r_[np.deg2rad([0.2, 0.1, 0.01]), 0.02, 0.005, 0.001]
    factors = OdometryFactors.from_motions(R0, t0, MODEL, np.tile(sigmas, (len(t0), 1)))
    R, t = perturbed_measurements(factors, np.random.default_rng(6))
    drawn = np.hstack([log_so3(np.einsum("nji,njk->nik", R0, R)), t - t0])
    np.testing.assert_allclose(np.std(drawn, axis=0), sigmas, rtol=0.05)


def test_the_warm_start_reaches_the_answer_of_the_perturbed_chain(corridor):
    """The check starts from the refined poses; solved from the chain of the perturbed motions instead
    (a start that follows them exactly), the perturbed problem reaches the same poses."""
    problem, T, factors, T_refined, covariance = corridor
    check = start_consistency(problem, T_refined, factors, TIGHT, covariance.position_covariance_m2())
    second = OdometryFactors.from_motions(*perturbed_measurements(factors, np.random.default_rng(START_SEED)),
                                          factors.model)
    T_chain = registration_chain(second, T_refined, 0)
    assert np.abs(T_chain[:, :3, 3] - T_refined[:, :3, 3]).max() > 0.01  # a start of its own
    from_chain = solve(problem, T_chain, TIGHT, terms=[second]).T_world_scan
    np.testing.assert_allclose(np.linalg.norm(from_chain[:, :3, 3] - T_refined[:, :3, 3], axis=1), check.moved_m,
                               atol=1e-6)


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
    """Rounds that moved the first scan leave every pose rigidly moved: the
    second start begins at the refined first pose, so the comparison sees no gauge offset."""
    problem, T, factors, T_refined, covariance = corridor
    moved = np.eye(4)
    moved[:3, 3] = [0.7, -0.2, 0.05]
    check = start_consistency(problem, moved @ T_refined, factors, TIGHT, covariance.position_covariance_m2())
    assert check.consistent and check.moved_m.max() < 0.2  # as without the offset, not 0.7 m everywhere


def _unsettled(change_m: np.ndarray) -> dict:
    """An `unsettled_association` record of every scan moved by `change_m` (N, 3)."""
    return {"round": 4, "max_pose_change_m": float(np.linalg.norm(change_m, axis=1).max()), "settle_m": 0.0,
            "scans": [{"scan": j, "moved_m": float(np.linalg.norm(c)), "change_m": c.tolist()}
                      for j, c in enumerate(change_m)]}


def test_an_association_move_is_judged_by_its_mahalanobis_distance(corridor):
    """Each scan's distance in sigmas is sqrt(d^T C^-1 d) (brute force, scan by scan), and a move is beyond
    3 sigma exactly when its square exceeds the chi-square 99.73 % quantile."""
    covariance = corridor[4].position_covariance_m2()
    rng = np.random.default_rng(3)
    change = rng.standard_normal((len(covariance), 3)) * 0.01
    judged = association_within(_unsettled(change), covariance)
    sigmas = np.array([np.sqrt(d @ np.linalg.pinv(C) @ d) for d, C in zip(change, covariance, strict=True)])
    assert judged["max_sigmas"] == pytest.approx(sigmas.max(), rel=1e-9)
    assert judged["scans_beyond_3_sigma"] == [int(j) for j in np.flatnonzero(sigmas**2 > CHI2_3DOF_3SIGMA)]
    assert judged["within_3_sigma"] is (not judged["scans_beyond_3_sigma"])


def test_moves_the_covariance_predicts_are_within_and_larger_ones_beyond(corridor):
    """Monte Carlo: moves drawn from the covariance itself fall within 3 sigma at the chi-square rate (99.73 %);
    the same moves 3x larger mostly do not, and without a covariance nothing is judged within."""
    covariance = corridor[4].position_covariance_m2()
    rng = np.random.default_rng(4)
    roots = np.linalg.cholesky(covariance + 1e-18 * np.eye(3))
    draws = [np.einsum("nij,nj->ni", roots, rng.standard_normal((len(covariance), 3))) for _ in range(400)]
    within = [len(association_within(_unsettled(d), covariance)["scans_beyond_3_sigma"]) for d in draws]
    assert 1.0 - np.sum(within) / (400 * len(covariance)) == pytest.approx(0.9973, abs=0.002)
    beyond = [len(association_within(_unsettled(3.0 * d), covariance)["scans_beyond_3_sigma"]) for d in draws]
    assert np.sum(beyond) / (400 * len(covariance)) > 0.5
    assert association_within(_unsettled(draws[0]), None)["within_3_sigma"] is False


def test_half_the_outer_product_of_two_draws_averages_to_their_covariance(corridor):
    """Monte Carlo: answers e_1, e_2 drawn independently from the corridor's pose covariance C (6x6 per
    pose); `with_spread(e_1 - e_2)` of a zero covariance, averaged over 4,000 pairs, is C: whitened by
    C's Cholesky factor it is the identity within 0.1 (about 4-6 standard errors of an entry)."""
    covariance = corridor[4]
    free = np.arange(len(covariance.covariance)) != covariance.gauge_pose
    roots = np.linalg.cholesky(covariance.covariance[free])
    zero = dataclasses.replace(covariance, covariance=np.zeros_like(covariance.covariance))
    rng = np.random.default_rng(6)
    pairs = 4000
    total = np.zeros_like(covariance.covariance)
    for _ in range(pairs):
        e_1, e_2 = (np.einsum("nij,nj->ni", roots, rng.standard_normal((int(free.sum()), 6))) for _ in range(2))
        difference = np.zeros((len(free), 6))
        difference[free] = e_1 - e_2
        total += zero.with_spread(difference).covariance
    mean = total / pairs
    whitened = np.linalg.solve(roots, np.linalg.solve(roots, mean[free]).transpose(0, 2, 1))
    np.testing.assert_allclose(whitened, np.broadcast_to(np.eye(6), whitened.shape), atol=0.1)
    assert np.array_equal(mean[~free], np.zeros((1, 6, 6)))  # the gauge pose stays exact


def test_the_spread_adds_half_the_outer_product_and_reports_the_position_sigma_it_adds(corridor):
    """The spread of one change adds change change^T / 2 to each pose's block; the position 1-sigma it adds
    is |d p| / sqrt(2), d p the position change of the poses retracted by the change (finite differences)."""
    _, _, _, T_refined, covariance = corridor
    rng = np.random.default_rng(7)
    change = rng.standard_normal((len(T_refined), 6)) * np.r_[np.full(3, 1e-3), np.full(3, 0.01)]
    change[covariance.gauge_pose] = 0.0
    spread, record = association_spread(covariance, change, 3)
    np.testing.assert_allclose(spread.covariance - covariance.covariance,
                               np.einsum("ni,nj->nij", change, change) / 2, rtol=0, atol=1e-15)
    step = 1e-6
    moved_m = (retract_left(T_refined, step * change)[:, :3, 3] - T_refined[:, :3, 3]) / step
    added_m = np.linalg.norm(moved_m, axis=1) / np.sqrt(2.0)
    assert record["round"] == 3
    assert record["median_added_position_sigma_m"] == pytest.approx(np.median(added_m), rel=1e-5)
    assert record["max_added_position_sigma_m"] == pytest.approx(added_m.max(), rel=1e-5)
    assert [x["scan"] for x in record["largest"]] == list(np.argsort(-added_m, kind="stable")[:len(record["largest"])])
    for x in record["largest"]:
        assert x["added_position_sigma_m"] == pytest.approx(added_m[x["scan"]], rel=1e-5)
