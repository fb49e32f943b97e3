"""The quality verdict: each doubt is reported, and only a clean refinement is `improved`."""

import numpy as np
import pytest

from pa_cli.core.clusters import points_to_cluster
from pa_cli.core.problem import make_problem
from pa_cli.evaluation.quality import (
    assess,
    decided_by_planes,
    map_subsample,
    mean_map_entropy,
    neighbourhood_fit,
    observation_information,
    pair_tie_information,
    pair_ties,
    verdict_warning,
)

GOOD_RMS = {"planes_at_initial_poses": {"initial": 0.03, "refined": 0.01},
            "planes_at_refined_poses": {"initial": 0.05, "refined": 0.01}}
ARGS = {"outlier_sigma": 5.0, "rms_tolerance": 0.01}


def _assess(rms=GOOD_RMS, sigmas=None, ties=None, settled=True, **extra):
    sigmas = np.full((9, 2), 0.5) if sigmas is None else sigmas
    ties = np.full(9, 2.0) if ties is None else ties
    return assess(rms, sigmas, ties, settled, **ARGS, **extra)


def test_clean_refinement_is_improved():
    q = _assess()
    assert q.verdict == "improved" and verdict_warning(q.as_report()) is None
    assert q.pairs_beyond_odometry_sigma == [] and q.pairs_not_tied_by_planes == []


def test_worse_on_either_association_is_degraded():
    for association in GOOD_RMS:
        rms = {a: dict(r) for a, r in GOOD_RMS.items()}
        rms[association]["refined"] = rms[association]["initial"] * 1.05
        q = _assess(rms=rms)
        assert q.verdict == "degraded"
        assert association.replace("_", " ") in q.reasons[0]
        assert "DEGRADED" in verdict_warning(q.as_report())


def test_each_doubt_makes_it_uncertain():
    sigmas = np.full((9, 2), 0.5)
    sigmas[4] = [30.0, 1.0]  # a broken step: the refinement turned pair 4-5 by 30 sigmas
    q = _assess(sigmas=sigmas)
    assert q.verdict == "uncertain" and q.pairs_beyond_odometry_sigma == [[4, 5]]
    assert q.n_scans_beyond_odometry_sigma == 2
    ties = np.full(9, 2.0)
    ties[6] = 0.039  # a break of 5 odometry sigmas would raise the shared planes' cost by 0.975 sigma^2
    q = _assess(ties=ties)
    assert q.verdict == "uncertain" and q.pairs_not_tied_by_planes == [[6, 7]]
    ties[6] = 0.041
    assert _assess(ties=ties).verdict == "improved"
    q = _assess(settled=False)
    assert q.verdict == "uncertain" and "settle" in q.reasons[0]
    rms = {a: dict(r) for a, r in GOOD_RMS.items()}
    rms["planes_at_initial_poses"]["refined"] = 0.03  # equal: not sharper, not worse beyond tolerance
    assert _assess(rms=rms).verdict == "uncertain"


def test_changes_the_planes_decided_and_held_directions_are_stated_not_doubted():
    sigmas = np.full((9, 2), 0.5)
    sigmas[0] = [1.0, 40.0]  # the planes moved pair 0-1 by 40 sigmas, with the information to do so
    decide = np.zeros(9, dtype=bool)
    decide[0] = True
    held = [{"scan": 3, "directions": ["translation along the direction of travel"]}]
    q = _assess(sigmas=sigmas, planes_decide=decide, held=held)
    assert q.verdict == "improved" and q.pairs_corrected_by_planes == [[0, 1]]
    assert q.pairs_beyond_odometry_sigma == []
    assert any("corrected the odometry" in r for r in q.reasons[1:])
    assert any("scans 3" in r and "direction of travel" in r for r in q.reasons[1:])
    decide[0] = False
    q = _assess(sigmas=sigmas, planes_decide=decide)
    assert q.verdict == "uncertain" and q.pairs_beyond_odometry_sigma == [[0, 1]]


def _plane_cost(points_scan, T, n, d, xi):
    """Squared distances of the points to the plane n.x + d = 0 with the scan moved by xi = (rotation
    about its origin, world axes; translation, world axes)."""
    from pa_cli.core.geometry import exp_so3

    R = exp_so3(xi[None, :3])[0] @ T[:3, :3]
    world = points_scan @ R.T + T[:3, 3] + xi[3:]
    return float(np.sum((world @ n + d) ** 2))


def test_observation_information_is_the_finite_difference_hessian():
    from pa_cli.core.geometry import exp_so3

    rng = np.random.default_rng(1)
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    T = np.eye(4)
    T[:3, :3] = exp_so3(rng.normal(size=(1, 3)))[0]
    T[:3, 3] = [40.0, -25.0, 3.0]
    basis = np.linalg.svd(n[None, :])[2][1:]
    world = T[:3, 3] + 5.0 + rng.uniform(-4, 4, (50, 2)) @ basis  # on the plane through T[:3, 3] + 5
    d = -float(n @ (T[:3, 3] + 5.0))
    points_scan = (world - T[:3, 3]) @ T[:3, :3]
    problem = make_problem(np.array([0, 0]), np.array([0, 1]), np.array([points_to_cluster(points_scan)] * 2),
                           n_scans=2)
    info = observation_information(problem, np.array([n]), np.stack([T, T]))[0]
    h = 1e-4
    expected = np.empty((6, 6))
    for a in range(6):
        for b in range(6):
            e_a, e_b = np.eye(6)[a] * h, np.eye(6)[b] * h
            cost = [_plane_cost(points_scan, T, n, d, xi) for xi in (e_a + e_b, e_a - e_b, e_b - e_a, -e_a - e_b)]
            expected[a, b] = (cost[0] - cost[1] - cost[2] + cost[3]) / (4 * h * h)
    np.testing.assert_allclose(info, expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())


def test_pair_tie_information_sums_the_weaker_shared_observation_brute_force():
    from pa_cli.planes.associate import world_plane_stats
    from pa_testing.synthetic_problems import make_scene

    problem, T = make_scene(30, 20, 4, seed=5)
    # uneven point counts, so which side is weaker differs between pairs
    scale = np.random.default_rng(2).uniform(0.5, 2.0, problem.n_observations)
    problem = make_problem(problem.plane_index, problem.scan_index, problem.clusters * scale[:, None, None],
                           n_scans=problem.n_scans)
    info = observation_information(problem, world_plane_stats(problem, T)[1], T)
    obs = {(int(j), int(p)): o for o, (j, p) in enumerate(zip(problem.scan_index, problem.plane_index, strict=True))}
    expected = np.zeros((problem.n_scans - 1, 6, 6))
    for j in range(problem.n_scans - 1):
        for p in range(problem.n_planes):
            if (j, p) in obs and (j + 1, p) in obs:
                a, b = obs[(j, p)], obs[(j + 1, p)]
                expected[j] += info[a if problem.clusters[a, 3, 3] <= problem.clusters[b, 3, 3] else b]
    assert np.count_nonzero(expected.reshape(len(expected), -1).any(axis=1)) > 20
    np.testing.assert_allclose(pair_tie_information(problem, T), expected, atol=1e-9)


def test_pair_ties_are_generalised_eigenvalues_and_see_a_free_direction():
    """Scans 0-1 share a floor and two walls, scans 1-2 only the floor: yaw and the horizontal
    translations of pair 1-2 rest on the odometry."""
    from scipy.linalg import eigh

    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, 0, 3] = [0.0, 1.0, 2.0]
    planes = {0: (np.array([0, 0, 1.0]), [0, 1, 2]), 1: (np.array([1.0, 0, 0]), [0, 1]),
              2: (np.array([0, 1.0, 0]), [0, 1])}
    plane_index, scan_index, clusters = [], [], []
    for i, (n, scans) in planes.items():
        for j in scans:
            q = rng.uniform(-5, 5, (100, 3))
            q -= np.outer(q @ n, n) - 3.0 * n
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster(q - T[j, :3, 3]))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=3)
    tie = pair_tie_information(problem, T)
    weights = np.array([[300.0] * 3 + [4.0] * 3, [300.0] * 3 + [4.0] * 3])
    ratio, direction = pair_ties(tie, weights)
    for j in range(2):
        np.testing.assert_allclose(ratio[j], max(eigh(tie[j], np.diag(2 * weights[j]), eigvals_only=True)[0], 0),
                                   atol=1e-9)
    assert ratio[0] > 1.0 and ratio[1] < 1e-9
    # pair 1-2's free direction lies in yaw and the horizontal translations
    assert np.linalg.norm(direction[1][[0, 1, 5]]) < 1e-6


def test_a_change_is_decided_by_planes_where_they_carry_more_information_than_the_odometry():
    T = np.tile(np.eye(4), (2, 1, 1))
    weights = np.array([[100.0] * 3 + [4.0] * 3])
    tie = np.zeros((1, 6, 6))
    tie[0, 3, 3] = 20.0  # the shared planes fix translation along x only
    along_x = np.array([[0, 0, 0, 0.5, 0, 0]])
    along_y = np.array([[0, 0, 0, 0, 0.5, 0]])
    assert decided_by_planes(tie, along_x, weights, T).tolist() == [True]
    assert decided_by_planes(tie, along_y, weights, T).tolist() == [False]
    tie[0, 3, 3] = 7.9  # below the factor's 2 x 4
    assert decided_by_planes(tie, along_x, weights, T).tolist() == [False]


def _entropy(mme_initial, mme_refined):
    return {"radius_m": 0.3, "mme_nats": {"initial": mme_initial, "refined": mme_refined}}


def test_map_entropy_enters_the_verdict():
    q = assess(GOOD_RMS, np.full((9, 2), 0.5), np.full(9, 2.0), True, **ARGS,
               entropy=_entropy(-2.0, -2.5), entropy_tolerance_nats=0.03)
    assert q.verdict == "improved" and "entropy" in q.reasons[0]
    q = assess(GOOD_RMS, np.full((9, 2), 0.5), np.full(9, 2.0), True, **ARGS,
               entropy=_entropy(-2.0, -1.9), entropy_tolerance_nats=0.03)
    assert q.verdict == "degraded" and "mean map entropy" in q.reasons[0]
    q = assess(GOOD_RMS, np.full((9, 2), 0.5), np.full(9, 2.0), True, **ARGS,
               entropy=_entropy(-2.0, -1.99), entropy_tolerance_nats=0.03)
    assert q.verdict == "uncertain" and "mean map entropy" in q.reasons[0]


def test_a_blurrier_class_of_surfaces_is_a_doubt():
    def entropy(rise_nats, standard_error_nats):
        e = _entropy(-2.0, -2.5)
        e["surfaces"] = {"level": {"n_query_points": 900, "mme_nats": {"initial": -3.0, "refined": -3.6},
                                   "change_standard_error_nats": {"refined": 0.01}},
                         "upright": {"n_query_points": 400, "mme_nats": {"initial": -2.7, "refined": -2.7 + rise_nats},
                                     "change_standard_error_nats": {"refined": standard_error_nats}}}
        return e

    def verdict(rise_nats, standard_error_nats):
        return assess(GOOD_RMS, np.full((9, 2), 0.5), np.full(9, 2.0), True, **ARGS, entropy_tolerance_nats=0.03,
                      entropy=entropy(rise_nats, standard_error_nats), entropy_standard_errors=3.0)

    q = verdict(0.05, 0.01)
    assert q.verdict == "uncertain"
    assert "upright surfaces" in q.reasons[0] and "5.0 standard errors" in q.reasons[0]
    assert q.blurrier_surfaces == ["upright"] and verdict(-0.05, 0.01).blurrier_surfaces == []
    assert verdict(0.025, 0.005).verdict == "improved"  # 5 standard errors, but within the 0.03 nats tolerance
    assert verdict(0.04, 0.02).verdict == "improved"  # beyond the tolerance, but within 3 standard errors
    assert verdict(-0.05, 0.01).verdict == "improved"
    # a rise far beyond the overall MME tolerance is still a doubt, not a degradation: the map as a whole is sharper
    assert verdict(0.5, 0.01).verdict == "uncertain"


def _gaussian_entropy(cov):
    return 0.5 * np.log(np.linalg.det(2.0 * np.pi * np.e * cov))


def test_entropy_of_a_gaussian_cloud_is_the_analytic_one():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T * 0.01 + np.diag([0.04, 0.01, 0.0025])
    points = rng.multivariate_normal([3.0, -2.0, 1.0], cov, size=200_000)
    queries = points[:3]
    h, _ = neighbourhood_fit(points, queries, radius_m=100.0, min_neighbours=10, min_sigma_m=1e-6)
    # brute force: the maximum-likelihood covariance of the whole sample
    np.testing.assert_allclose(h, _gaussian_entropy(np.cov(points.T, bias=True)), rtol=0, atol=1e-9)
    # analytic: the sampling error of ln det is sqrt(2 * 3 / n) / 2 ~ 0.003 nats here
    np.testing.assert_allclose(h, _gaussian_entropy(cov), rtol=0, atol=0.012)


@pytest.mark.parametrize("radius_m", [0.5, 0.13])
def test_entropy_neighbourhoods_match_brute_force(radius_m):
    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 1, (20_000, 3)) * [2.0, 2.0, 0.2]
    # queries: map points, points off the map, and one far away (no neighbours)
    queries = np.vstack([points[::1000], rng.uniform(-2.2, 2.2, (20, 3)) * [1.0, 1.0, 0.1], [[50.0, 0.0, 0.0]]])
    h, normal_z = neighbourhood_fit(points, queries, radius_m=radius_m, min_neighbours=10, min_sigma_m=1e-6)
    n_checked = 0
    for q, hq, zq in zip(queries, h, normal_z, strict=True):
        near = points[np.linalg.norm(points - q, axis=1) <= radius_m]
        if len(near) < 10:
            assert np.isnan(hq) and np.isnan(zq)
            continue
        n_checked += 1
        cov = np.cov(near.T, bias=True)
        np.testing.assert_allclose(hq, _gaussian_entropy(cov), atol=1e-9)
        np.testing.assert_allclose(zq, abs(np.linalg.eigh(cov)[1][2, 0]), atol=1e-9)
    assert n_checked >= 20 and np.isnan(h[-1])
    sparse, _ = neighbourhood_fit(points[:20], points[:20], radius_m=0.01, min_neighbours=10, min_sigma_m=1e-6)
    assert np.all(np.isnan(sparse))


def test_entropy_counts_points_on_cell_boundaries():
    """Points exactly radius_m away (on the sphere) count, as do points on a cell's faces."""
    radius_m = 0.25
    grid = np.stack(np.meshgrid(*[np.arange(-4, 5) * radius_m / 2] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    h, _ = neighbourhood_fit(grid, grid, radius_m=radius_m, min_neighbours=10, min_sigma_m=1e-6)
    assert np.all(np.isfinite(h))
    for q, hq in zip(grid, h, strict=True):
        # the grid's coordinates are exact in binary: a point two steps away lies exactly on the sphere
        near = grid[np.sum((grid - q) ** 2, axis=1) <= radius_m**2]
        np.testing.assert_allclose(hq, _gaussian_entropy(np.cov(near.T, bias=True)), atol=1e-9)


def _box_scans(rng, n_scans=6):
    """Scans (scan frame) of a floor and two walls with 5 mm noise, from poses along a line."""
    floor = np.column_stack([rng.uniform(0, 10, 6000), rng.uniform(0, 6, 6000), np.zeros(6000)])
    wall_x = np.column_stack([rng.uniform(0, 10, 4000), np.full(4000, 6.0), rng.uniform(0, 3, 4000)])
    wall_y = np.column_stack([np.full(4000, 10.0), rng.uniform(0, 6, 4000), rng.uniform(0, 3, 4000)])
    world = np.vstack([floor, wall_x, wall_y])
    T_true = np.tile(np.eye(4), (n_scans, 1, 1))
    T_true[:, 0, 3] = np.linspace(1, 5, n_scans)
    T_true[:, 1, 3] = 3.0
    T_true[:, 2, 3] = 1.5
    scans = []
    for T in T_true:
        p = world[rng.choice(len(world), 5000, replace=False)] + rng.normal(0, 0.005, (5000, 3))
        scans.append((p - T[:3, 3]) @ T[:3, :3])
    return scans, T_true


def test_true_poses_give_a_lower_map_entropy_than_perturbed_ones():
    from pa_cli.evaluation import perturb_poses

    rng = np.random.default_rng(6)
    scans, T_true = _box_scans(rng)
    T_perturbed = perturb_poses(T_true, np.deg2rad(0.5), 0.03, rng)
    result = mean_map_entropy({"initial": scans, "refined": scans}, {"initial": T_perturbed, "refined": T_true},
                              [len(s) for s in scans], radius_m=0.3, min_neighbours=10, max_map_points=10_000,
                              n_queries=2000)
    assert result["map_stride"] == 3 and result["n_map_points"] == 10_002 and result["n_query_points"] > 1000
    assert result["mme_nats"]["refined"] < result["mme_nats"]["initial"] - 0.3


def _entropy_of(scans, T_initial, T_refined):
    return mean_map_entropy({"initial": scans, "refined": scans}, {"initial": T_initial, "refined": T_refined},
                            [len(s) for s in scans], radius_m=0.3, min_neighbours=10, max_map_points=30_000,
                            n_queries=3000)


def _rise_in_standard_errors(surface):
    mme = surface["mme_nats"]
    return (mme["refined"] - mme["initial"]) / surface["change_standard_error_nats"]["refined"]


@pytest.mark.parametrize("moved", ["horizontal", "vertical"])
def test_map_entropy_splits_upright_and_level_surfaces(moved):
    """Scans moved sideways blur the walls, not the floor; scans moved up and down blur the floor,
    not the walls: each class sees its own directions."""
    rng = np.random.default_rng(8)
    scans, T_true = _box_scans(rng)
    T_moved = T_true.copy()
    offsets = rng.choice([-1.0, 1.0], len(T_true)) * 0.03
    if moved == "horizontal":
        T_moved[:, 0, 3] += offsets
        T_moved[:, 1, 3] -= offsets
    else:
        T_moved[:, 2, 3] += offsets
    result = _entropy_of(scans, T_true, T_moved)
    upright, level = result["surfaces"]["upright"], result["surfaces"]["level"]
    assert upright["n_query_points"] > 1000 and level["n_query_points"] > 700
    assert upright["n_query_points"] + level["n_query_points"] <= result["n_query_points"]
    blurred, kept = (upright, level) if moved == "horizontal" else (level, upright)
    assert _rise_in_standard_errors(blurred) > 10.0
    assert abs(blurred["mme_nats"]["refined"] - blurred["mme_nats"]["initial"]) > 0.1
    # the other class: only the queries near the walls' foot see both surfaces
    assert abs(kept["mme_nats"]["refined"] - kept["mme_nats"]["initial"]) < 0.25 * abs(
        blurred["mme_nats"]["refined"] - blurred["mme_nats"]["initial"])
    same = _entropy_of(scans, T_true, T_true)["surfaces"]["upright"]
    assert same["mme_nats"]["refined"] == same["mme_nats"]["initial"]
    assert same["change_standard_error_nats"]["refined"] == 0


@pytest.mark.slow
def test_the_standard_error_of_a_class_is_the_spread_over_query_draws():
    """Monte Carlo: the mean change of a class over 100 draws of 1,000 query points spreads as the
    reported standard error says (points and poses fixed)."""
    from pa_cli.evaluation import perturb_poses

    rng = np.random.default_rng(3)
    scans, T_true = _box_scans(rng)
    T_a, T_b = perturb_poses(T_true, np.deg2rad(0.1), 0.01, rng), perturb_poses(T_true, np.deg2rad(0.1), 0.01, rng)
    changes, reported = {"upright": [], "level": []}, {"upright": [], "level": []}
    for seed in range(100):
        result = mean_map_entropy({"initial": scans, "refined": scans}, {"initial": T_a, "refined": T_b},
                                  [len(s) for s in scans], radius_m=0.3, min_neighbours=10, max_map_points=100_000,
                                  n_queries=1000, query_seed=seed)
        assert result["map_stride"] == 1
        for name, surface in result["surfaces"].items():
            changes[name].append(surface["mme_nats"]["refined"] - surface["mme_nats"]["initial"])
            reported[name].append(surface["change_standard_error_nats"]["refined"])
    for name in changes:
        # 100 draws give the spread to about 7 % (one sigma)
        assert 0.8 < np.std(changes[name]) / np.median(reported[name]) < 1.25


def test_map_subsample_rule():
    stride, kept = map_subsample([100, 100], 1000)
    assert stride == 1 and all(np.array_equal(k, np.arange(100)) for k in kept)
    stride, kept = map_subsample([1000, 1001], 500)
    assert stride == 5 and [len(k) for k in kept] == [200, 201]
    assert all(len(np.unique(k)) == len(k) and np.all(np.diff(k) > 0) and k[-1] < n
               for k, n in zip(kept, [1000, 1001], strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(kept, map_subsample([1000, 1001], 500)[1], strict=True))
    # not a regular stride: a ring pattern (16 beams, interleaved) keeps every beam
    beams = np.tile(np.arange(16), 100)
    _, kept = map_subsample([len(beams)], 400)
    assert len(np.unique(beams[kept[0]])) == 16


def test_the_closing_table_shows_the_quality():
    from pa_cli.cli.tables import refine_summary_table

    quality = assess(GOOD_RMS, np.full((9, 2), 0.5), np.full(9, 2.0), True, **ARGS,
                     entropy=_entropy(-2.0, -2.5), entropy_tolerance_nats=0.03)
    summary = {"n_scans": 10, "n_points_on_planes": 100, "n_landmarks": 3, "cost_initial_m2": 1.0,
               "cost_final_m2": 0.5, "rms_point_to_plane_initial_m": 0.1, "rms_point_to_plane_final_m": 0.05,
               "n_rounds": 2, "iterations": 7, "settled": True}
    table = refine_summary_table({"summary": summary, "input": {}, "stage_times_s": {"a": 1.0}, "total_time_s": 1.3,
                                  "quality": quality.as_report()})
    rows = dict(zip(table.columns[0]._cells, zip(table.columns[1]._cells, table.columns[2]._cells, strict=True),
                    strict=True))
    assert rows["mean map entropy, 0.3 m (nats)"] == ("-2.0000", "-2.5000")
    assert rows["point-to-plane RMS (m), planes found at the start"] == ("0.0300", "0.0100")
    assert rows["point-to-plane RMS (m), planes found at the end"] == ("0.0500", "0.0100")
    assert rows["quality verdict"] == ("", "improved")
    assert rows["rounds / iterations"] == ("", "2 / 7, settled")
    assert rows["time (s)"] == ("a 1.0, between stages 0.3", "1.3")  # the run's wall time, the stages' and the rest
    assert not any("RMS point-to-plane" in label for label in rows)  # the summary's RMS repeats a quality row
