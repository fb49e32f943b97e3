"""Motion compensation: unit detection, interpolation and deskew against the simulator's truth."""

import numpy as np
import pytest

from pa_cli.deskew import (
    DeskewedPoints,
    deskew_scan,
    detect_time_unit,
    pose_at_times,
    relative_times_s,
    stamps_from_sweeps,
)
from pa_cli.simulate import SimOptions, simulate_sequence


@pytest.mark.parametrize("name,scale", [("s", 1.0), ("ms", 1e3), ("us", 1e6), ("ns", 1e9)])
@pytest.mark.parametrize("sweep_s", [0.05, 0.1, 0.2])
def test_time_unit_relative_and_absolute(name, scale, sweep_s):
    starts = np.arange(5) * sweep_s
    unit = detect_time_unit(np.zeros(5), np.full(5, sweep_s * 0.999 * scale), max_sweep_s=2.0)
    assert unit.name == name and not unit.absolute
    epoch = 1.7e9
    unit = detect_time_unit((epoch + starts) * scale, (epoch + starts + sweep_s) * scale, max_sweep_s=2.0)
    assert unit.name == name and unit.absolute


def test_time_unit_none_without_a_sweep():
    assert detect_time_unit(np.zeros(3), np.zeros(3), 2.0) is None


def test_relative_times_absolute_nanoseconds_keep_precision():
    raw = np.array([1_700_000_000_123_456_789, 1_700_000_000_173_456_789], dtype=np.int64)
    unit = detect_time_unit(raw[:1], raw[1:], 2.0)
    rel, start = relative_times_s(raw, unit)
    assert unit.name == "ns" and unit.absolute
    np.testing.assert_allclose(rel, [0.0, 0.05], atol=1e-12)
    assert start == pytest.approx(1_700_000_000.123456789, abs=1e-6)


def _random_poses(n, rng):
    from scipy.spatial.transform import Rotation
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.5, (n, 3))).as_matrix()
    T[:, :3, 3] = rng.normal(0, 3, (n, 3))
    return T


def test_pose_at_times_hits_the_poses():
    rng = np.random.default_rng(1)
    T = _random_poses(5, rng)
    stamps = np.array([0.0, 0.1, 0.25, 0.3, 0.5])
    np.testing.assert_allclose(pose_at_times(stamps, T, stamps), T, atol=1e-12)


def test_pose_at_times_is_exact_for_constant_velocity():
    """Constant angular velocity about a fixed axis and constant linear velocity: every time,
    inside and past both ends, is reproduced exactly (uneven scan times)."""
    from scipy.spatial.transform import Rotation

    omega = np.array([0.1, -0.3, 0.8])  # rad/s
    velocity = np.array([10.0, 1.0, -0.5])  # m/s
    R0 = Rotation.from_rotvec([0.3, 0.2, -1.0]).as_matrix()

    def truth(t):
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, :3] = Rotation.from_rotvec(t[:, None] * omega).as_matrix() @ R0
        T[:, :3, 3] = np.array([5.0, -2.0, 1.0]) + t[:, None] * velocity
        return T

    stamps = np.array([0.0, 0.1, 0.22, 0.3, 0.41])
    t = np.linspace(-0.1, 0.55, 27)
    np.testing.assert_allclose(pose_at_times(stamps, truth(stamps), t), truth(t), atol=1e-9)


@pytest.mark.parametrize("scene", ["street", "office"])
def test_deskew_with_true_trajectory_recovers_the_world_points(scene):
    seq = simulate_sequence(SimOptions(scene=scene, scans=4, beams=16, azimuth_steps=256, seed=5,
                                       motion_distortion=True, range_noise_m=0.0))
    points = DeskewedPoints([s.points_scan for s in seq.scans], [s.time for s in seq.scans],
                            seq.timestamps, seq.T_world_scan)
    n_points = 0
    for j in range(4):  # first, interior and last (extrapolated past the last pose) scans
        truth, raw, offsets = [], [], []
        for k, index in points.sources(j):
            scan = seq.scans[k]
            T_point = scan.T_world_sensor[index]
            truth.append(np.einsum("mij,mj->mi", T_point[:, :3, :3], scan.points_scan[index]) + T_point[:, :3, 3])
            raw.append(scan.points_scan[index])
            times_to_j = seq.timestamps[k] + scan.time[index] - seq.timestamps[j]
            offsets.append(times_to_j)
            # attached to the nearest instant (the last scan keeps its late part)
            assert np.all(np.abs(times_to_j) <= 0.05 + 1e-9) or j == 3
        truth, raw = np.vstack(truth), np.vstack(raw)
        parts = points.parts(j)
        assert [k for k, _, _ in parts] == [k for k, _ in points.sources(j)]
        np.testing.assert_allclose(np.concatenate([seq.timestamps[k] + own - seq.timestamps[j] for k, _, own in parts]),
                                   np.concatenate(offsets), atol=1e-12)
        n_points += len(truth)
        T = seq.T_world_scan[j]
        raw_err = np.linalg.norm(raw @ T[:3, :3].T + T[:3, 3] - truth, axis=1)
        err = np.linalg.norm(points[j] @ T[:3, :3].T + T[:3, 3] - truth, axis=1)
        assert raw_err.max() > 0.05  # the distortion is real ...
        # ... and deskewing removes it, up to the interpolation of the trajectory
        assert np.sqrt(np.mean(err**2)) < 0.05 * np.sqrt(np.mean(raw_err**2))
    assert n_points == sum(len(s.points_scan) for s in seq.scans)  # every point once


def test_deskew_is_identity_at_the_reference_instant():
    rng = np.random.default_rng(2)
    T = _random_poses(3, rng)
    p = rng.normal(0, 10, (50, 3))
    np.testing.assert_allclose(deskew_scan(p, np.zeros(50), 1, np.array([0.0, 0.1, 0.2]), T), p, atol=1e-9)


def test_stamps_from_sweeps():
    np.testing.assert_allclose(stamps_from_sweeps(3, np.array([0.099, 0.1, 0.101])), [0.0, 0.1, 0.2])

