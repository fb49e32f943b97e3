"""A frozen per-point association reproduces the plane problem it was taken from."""

import numpy as np

from pa_cli.config import PlanesConfig
from pa_cli.core.geometry import transform_points
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.labels import PointLabels
from pa_cli.simulate import SimOptions, simulate_sequence


def _office(seed: int) -> tuple[list[np.ndarray], np.ndarray, PlanesConfig]:
    seq = simulate_sequence(SimOptions(scene="office", scans=6, beams=16, azimuth_steps=256, seed=seed))
    return [s.points_scan for s in seq.scans], seq.T_world_scan, PlanesConfig(voxel_size_m=0.5,
                                                                              max_normal_uncertainty_deg=0.25)


def _labels_by_assign(scans, T_world_scan, found, problem, config) -> list[np.ndarray]:
    """Brute force: each point's landmark looked up again, then its plane and observation found by search."""
    observation = {(int(s), int(p)): o
                   for o, (s, p) in enumerate(zip(problem.scan_index, problem.plane_index, strict=True))}
    plane = {int(lm): p for p, lm in enumerate(found["kept"])}
    out = []
    for k, points in enumerate(scans):
        finite = np.isfinite(points).all(axis=1)
        lm = np.full(len(points), -1)
        lm[finite], _ = found["landmarks"].assign(transform_points(T_world_scan[k], points[finite]),
                                                  config.outlier_sigma, config.outlier_sigma_floor_m)
        out.append(np.array([observation.get((k, plane.get(int(m), -1)), -1) for m in lm]))
    return out


def _clusters_by_bincount(labels: PointLabels, scans) -> np.ndarray:
    """Reference sums: one weighted bincount per entry of [p;1][p;1]^T, scan after scan."""
    n_obs = len(labels.plane_index)
    C = np.zeros((n_obs, 4, 4))
    for k, obs in enumerate(labels.observation_of_point):
        on = obs >= 0
        ph = np.hstack([np.asarray(scans[k], dtype=np.float64)[on], np.ones((on.sum(), 1))])
        for r in range(4):
            for c in range(r, 4):
                C[:, r, c] += np.bincount(obs[on], weights=ph[:, r] * ph[:, c], minlength=n_obs)
    return np.triu(C) + np.triu(C, 1).transpose(0, 2, 1)


def test_labels_reproduce_the_association_and_follow_moved_points():
    scans, T, config = _office(4)
    found: dict = {}
    problem, _ = build_plane_problem(scans, T, config, landmarks_out=found)
    assert problem.n_planes > 5
    labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks,
                                          found["kept"], problem)
    np.testing.assert_allclose(labels.clusters(scans), problem.clusters, rtol=1e-9, atol=1e-6)
    # the same points moved rigidly in their scan frame: clusters transform as T C T^T
    rng = np.random.default_rng(0)
    shift = rng.normal(0, 0.05, 3)
    moved = labels.problem([p + shift for p in scans])
    M = np.eye(4)
    M[:3, 3] = shift
    np.testing.assert_allclose(moved.clusters, M @ problem.clusters @ M.T, rtol=1e-9, atol=1e-6)
    assert np.array_equal(moved.plane_index, problem.plane_index)


def test_labels_from_the_association_pass_equal_a_second_lookup_with_non_finite_rows():
    scans, T, config = _office(9)
    scans[2] = scans[2].copy()
    scans[2][::50] = np.nan  # rows the association skips: labelled -1 in their place
    found: dict = {}
    problem, _ = build_plane_problem(scans, T, config, landmarks_out=found)
    assert problem.n_planes > 5
    labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks,
                                          found["kept"], problem)
    expected = _labels_by_assign(scans, T, found, problem, config)
    for k in range(len(scans)):
        assert labels.observation_of_point[k].shape == (len(scans[k]),)
        assert np.array_equal(labels.observation_of_point[k], expected[k]), k
    assert (labels.observation_of_point[2][::50] == -1).all()
    assert (labels.observation_of_point[2] >= 0).sum() > 0.3 * len(scans[2])


def test_clusters_equal_per_entry_bincount_sums_bit_for_bit():
    rng = np.random.default_rng(11)
    n_obs, n_scans = 40, 5
    scans = [rng.normal(0, 30, (int(rng.integers(1000, 5000)), 3)) + rng.normal(0, 500, 3) for _ in range(n_scans)]
    observation = [rng.integers(-1, n_obs, len(p)).astype(np.int32) for p in scans]
    observation[3][:] = -1  # a scan observing nothing
    labels = PointLabels(np.arange(n_obs) % 7, np.arange(n_obs) % n_scans, n_scans, observation)
    C = labels.clusters(scans)
    assert np.array_equal(C, _clusters_by_bincount(labels, scans))
    assert np.array_equal(C, C.transpose(0, 2, 1))
    assert C[:, 3, 3].sum() == sum((o >= 0).sum() for o in observation)
