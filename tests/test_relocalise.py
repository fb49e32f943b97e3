"""Scans the planes lost at a wrong initial pose are found again along their weak direction."""

import numpy as np

from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.config import PaConfig
from pa_cli.planes.associate import build_plane_problem
from pa_cli.relocalise import relocalise_lost_scans

N_SCANS = 8


def _corridor(rng):
    """A 40 m corridor along x (floor, two side walls) closed by an end wall at x = 30 m, seen from
    poses 1 m apart along its axis: only the end wall fixes a scan along x. (scans, T_true)."""
    n = 6000
    floor = np.column_stack([rng.uniform(-10, 30, n), rng.uniform(-3, 3, n), np.zeros(n)])
    left = np.column_stack([rng.uniform(-10, 30, n), np.full(n, 3.0), rng.uniform(0, 3, n)])
    right = np.column_stack([rng.uniform(-10, 30, n), np.full(n, -3.0), rng.uniform(0, 3, n)])
    end = np.column_stack([np.full(n, 30.0), rng.uniform(-3, 3, n), rng.uniform(0, 3, n)])
    world = np.vstack([floor, left, right, end])
    T_true = np.tile(np.eye(4), (N_SCANS, 1, 1))
    T_true[:, 0, 3] = np.arange(N_SCANS, dtype=float)
    T_true[:, 2, 3] = 1.5
    scans = []
    for T in T_true:
        p = world[rng.choice(len(world), 8000, replace=False)] + rng.normal(0, 0.005, (8000, 3))
        scans.append((p - T[:3, 3]) @ T[:3, :3])
    return scans, T_true


def _relocalise(scans, T):
    config = PaConfig()
    found = {}
    problem, _ = build_plane_problem(scans, T, config.planes, landmarks_out=found)
    odometry = OdometryFactors(T, OdometryModel.from_config(config.refine)).linearize(T).pose_blocks
    return relocalise_lost_scans(scans, T, found["landmarks"], found["kept"], problem, odometry,
                                 config.refine.degeneracy_lever_arm_m, search_m=3.0, step_m=0.02,
                                 outlier_sigma=config.planes.outlier_sigma,
                                 sigma_floor_m=config.planes.outlier_sigma_floor_m)


def test_a_scan_registered_short_is_moved_back_along_its_weak_direction():
    scans, T_true = _corridor(np.random.default_rng(3))
    T_bad = T_true.copy()
    T_bad[2, 0, 3] -= 0.7  # scan 2 registered 0.7 m short: its end-wall points miss the landmark
    T_out, moved = _relocalise(scans, T_bad)
    assert [m["scan"] for m in moved] == [2]
    assert moved[0]["direction"] == "translation along the direction of travel"
    assert moved[0]["information_after"] > max(moved[0]["information_before"], moved[0]["odometry_information"])
    assert abs(T_out[2, 0, 3] - T_true[2, 0, 3]) <= 0.02  # back within one search step
    np.testing.assert_array_equal(np.delete(T_out, 2, axis=0), np.delete(T_bad, 2, axis=0))


def test_scans_at_their_true_poses_stay():
    scans, T_true = _corridor(np.random.default_rng(4))
    T_out, moved = _relocalise(scans, T_true)
    assert moved == []
    np.testing.assert_array_equal(T_out, T_true)


def test_a_scan_the_planes_hold_is_not_moved_to_a_shallow_maximum():
    """Scan 2 off by 1 cm along x keeps its end-wall points (inside the gate): the planes hold it,
    and no search moves it to another maximum."""
    scans, T_true = _corridor(np.random.default_rng(5))
    T_off = T_true.copy()
    T_off[2, 0, 3] += 0.01
    T_out, moved = _relocalise(scans, T_off)
    assert moved == []
    np.testing.assert_array_equal(T_out, T_off)
