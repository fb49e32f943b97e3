"""The quality verdict: each doubt is reported, and only a clean refinement is `improved`."""

import numpy as np

from pa_cli.clusters import points_to_cluster
from pa_cli.problem import make_problem
from pa_cli.quality import assess, pair_ties, verdict_warning

GOOD_RMS = {"planes_at_initial_poses": {"initial": 0.03, "refined": 0.01},
            "planes_at_refined_poses": {"initial": 0.05, "refined": 0.01}}
ARGS = {"outlier_sigma": 5.0, "min_tie": 0.5, "rms_tolerance": 0.01}


def _assess(rms=GOOD_RMS, sigmas=None, ties=None, settled=True):
    sigmas = np.full((9, 2), 0.5) if sigmas is None else sigmas
    ties = np.full(9, 2.0) if ties is None else ties
    return assess(rms, sigmas, ties, settled, **ARGS)


def test_clean_refinement_is_improved():
    q = _assess()
    assert q["verdict"] == "improved" and verdict_warning(q) is None
    assert q["pairs_beyond_odometry_sigma"] == [] and q["pairs_not_tied_by_planes"] == []


def test_worse_on_either_association_is_degraded():
    for association in GOOD_RMS:
        rms = {a: dict(r) for a, r in GOOD_RMS.items()}
        rms[association]["refined"] = rms[association]["initial"] * 1.05
        q = _assess(rms=rms)
        assert q["verdict"] == "degraded"
        assert association.replace("_", " ") in q["reasons"][0]
        assert "DEGRADED" in verdict_warning(q)


def test_each_doubt_makes_it_uncertain():
    sigmas = np.full((9, 2), 0.5)
    sigmas[4] = [30.0, 1.0]  # a broken step: the refinement turned pair 4-5 by 30 sigmas
    q = _assess(sigmas=sigmas)
    assert q["verdict"] == "uncertain" and q["pairs_beyond_odometry_sigma"] == [[4, 5]]
    assert q["n_scans_beyond_odometry_sigma"] == 2
    ties = np.full(9, 2.0)
    ties[6] = 0.0
    q = _assess(ties=ties)
    assert q["verdict"] == "uncertain" and q["pairs_not_tied_by_planes"] == [[6, 7]]
    q = _assess(settled=False)
    assert q["verdict"] == "uncertain" and "settle" in q["reasons"][0]
    rms = {a: dict(r) for a, r in GOOD_RMS.items()}
    rms["planes_at_initial_poses"]["refined"] = 0.03  # equal: not sharper, not worse beyond tolerance
    assert _assess(rms=rms)["verdict"] == "uncertain"


def test_pair_ties_see_the_orientations_of_shared_planes():
    """Scans 0-1 share a floor and a wall, scans 1-2 only the floor."""
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (3, 1, 1))
    planes = {0: (np.array([0, 0, 1.0]), [0, 1, 2]), 1: (np.array([1.0, 0, 0]), [0, 1]),
              2: (np.array([0, 1.0, 0]), [2])}
    plane_index, scan_index, clusters = [], [], []
    for i, (n, scans) in planes.items():
        for j in scans:
            q = rng.uniform(-5, 5, (100, 3))
            q -= np.outer(q @ n, n)
            plane_index.append(i)
            scan_index.append(j)
            clusters.append(points_to_cluster(q))
    problem = make_problem(np.array(plane_index), np.array(scan_index), np.array(clusters), n_scans=3)
    ties = pair_ties(problem, T)
    np.testing.assert_allclose(ties, [1.0, 0.0], atol=1e-9)
