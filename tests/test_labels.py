"""A frozen per-point association reproduces the plane problem it was taken from."""

import numpy as np

from pa_cli.config import PlanesConfig
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.labels import PointLabels
from pa_cli.simulate import SimOptions, simulate_sequence


def test_labels_reproduce_the_association_and_follow_moved_points():
    seq = simulate_sequence(SimOptions(scene="office", scans=6, beams=16, azimuth_steps=256, seed=4))
    scans = [s.points_scan for s in seq.scans]
    config = PlanesConfig(voxel_size_m=0.5, max_normal_uncertainty_deg=0.25)
    found: dict = {}
    problem, _ = build_plane_problem(scans, seq.T_world_scan, config, landmarks_out=found)
    assert problem.n_planes > 5
    labels = PointLabels.from_landmarks(scans, seq.T_world_scan, found["landmarks"], found["kept"], problem, config)
    np.testing.assert_allclose(labels.clusters(scans), problem.clusters, rtol=1e-9, atol=1e-6)
    # the same points moved rigidly in their scan frame: clusters transform as T C T^T
    rng = np.random.default_rng(0)
    shift = rng.normal(0, 0.05, 3)
    moved = labels.problem([p + shift for p in scans])
    M = np.eye(4)
    M[:3, 3] = shift
    np.testing.assert_allclose(moved.clusters, M @ problem.clusters @ M.T, rtol=1e-9, atol=1e-6)
    assert np.array_equal(moved.plane_index, problem.plane_index)
