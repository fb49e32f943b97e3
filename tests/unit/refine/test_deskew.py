"""Motion compensation: unit detection, interpolation and deskew against the simulator's truth."""

import numpy as np
import pytest

from pa_cli.refine.deskew import (
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



def _affine_fixed_point_map(T_star, J, lever_arm_m):
    """F(T) = T* (+) J (T (-) T*) in the chart of `retract_left` (rotation scaled by the lever arm)."""
    from pa_cli.core.geometry import retract_left
    from pa_cli.refine.deskew import _chart

    scale = np.array([lever_arm_m] * 3 + [1.0] * 3)

    def F(T):
        x = _chart(T_star, T, lever_arm_m)
        return retract_left(T_star, (J @ x).reshape(-1, 6) / scale)
    return F


def _fixed_point_case(seed, n=6):
    from pa_cli.core.geometry import exp_so3, retract_left

    rng = np.random.default_rng(seed)
    T_star = np.tile(np.eye(4), (n, 1, 1))
    T_star[:, :3, :3] = exp_so3(rng.normal(scale=0.3, size=(n, 3)))
    T_star[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    # one slow mode (contraction 0.6, the deskew's velocity error) and fast ones (0.05)
    u = rng.normal(size=6 * n)
    u /= np.linalg.norm(u)
    J = 0.05 * np.eye(6 * n) + 0.55 * np.outer(u, u)
    x0 = rng.normal(scale=0.0005, size=6 * n) + 0.05 * u  # chart coordinates: mostly the slow mode
    start = retract_left(T_star, x0.reshape(n, 6) / np.array([10.0] * 3 + [1.0] * 3))
    return T_star, J, start


def _distance(T_a, T_b):
    from pa_cli.refine.deskew import _chart

    return float(np.abs(_chart(T_a, T_b, 10.0)).max())


def test_fixed_point_acceleration_removes_the_slow_mode():
    from pa_cli.refine.deskew import DeskewFixedPoint

    T_star, J, start = _fixed_point_case(0)
    F = _affine_fixed_point_map(T_star, J, 10.0)

    def rounds(max_contraction, n_rounds):
        accel, T = DeskewFixedPoint(10.0, max_contraction), start
        records = []
        for _ in range(n_rounds):
            T, record = accel.next_start(T, F(T))
            records.append(record)
        return T, records

    plain, _ = rounds(0.0, 4)
    fast, records = rounds(0.9, 4)
    assert records[0]["contraction"] is None
    assert records[1]["extrapolated"] and records[1]["contraction"] == pytest.approx(0.6, abs=0.05)
    assert not any(r.get("extrapolation_failed") for r in records)
    # plain: the slow mode keeps 0.6^4 of the start; accelerated: removed, what is left contracts by 0.05
    assert _distance(T_star, plain) > 0.1 * _distance(T_star, start)
    assert _distance(T_star, fast) < 1e-3 * _distance(T_star, plain)


def test_fixed_point_acceleration_safeguards():
    from pa_cli.refine.deskew import DeskewFixedPoint

    T_star, J, start = _fixed_point_case(1)
    F = _affine_fixed_point_map(T_star, J, 10.0)
    accel = DeskewFixedPoint(10.0, 0.9)
    T1 = F(start)
    accel.next_start(start, T1)
    T2 = F(T1)
    x, record = accel.next_start(T1, T2)
    assert record["extrapolated"]
    # the round from the extrapolated start moves the poses more than the round before: failed,
    # the next start is that round's plain result, and the secant restarts (no step next round)
    bad = _affine_fixed_point_map(T_star, np.eye(len(J)), 10.0)(start)  # back at the start, far from x
    T_next, record = accel.next_start(x, bad)
    assert record["extrapolation_failed"] and not record["extrapolated"]
    np.testing.assert_array_equal(T_next, bad)
    T_after, record = accel.next_start(bad, F(bad))
    assert record["contraction"] is not None  # measured again, from the pair (x, F(x)) and this round
    # a contraction above the cap (a nearly free mode) is not extrapolated
    F_slow = _affine_fixed_point_map(T_star, 0.95 * np.eye(len(J)), 10.0)
    accel = DeskewFixedPoint(10.0, 0.9)
    T1 = F_slow(start)
    accel.next_start(start, T1)
    T2 = F_slow(T1)
    T_next, record = accel.next_start(T1, T2)
    assert record["contraction"] == pytest.approx(0.95, abs=1e-3) and not record["extrapolated"]
    np.testing.assert_array_equal(T_next, T2)
