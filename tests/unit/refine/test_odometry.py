"""KISS-ICP initial poses: config adapter, time normalisation, and ATE on real data."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pa_cli.config import KissIcpConfig, SensorConfig
from pa_cli.refine.odometry import kiss_config, normalized_point_times, run_kiss_icp
from pa_cli.sources.memory import ArraySource


def _ate_se3_m(T_ref: np.ndarray, T_est: np.ndarray) -> float:
    """ATE RMSE (m) of positions after a least-squares rigid (Umeyama, no scale) alignment."""
    a, b = T_est[:, :3, 3], T_ref[:, :3, 3]
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((b - cb).T @ (a - ca))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    aligned = (R @ (a - ca).T).T + cb
    return float(np.sqrt(np.mean(np.sum((aligned - b) ** 2, axis=1))))


def _read_pcd_xyz(path) -> np.ndarray:
    from pypcd4 import PointCloud

    return PointCloud.from_path(path).numpy(("x", "y", "z")).astype(np.float64)


def test_kiss_config_maps_our_keys():
    cfg = kiss_config(SensorConfig(max_range_m=50.0, min_range_m=1.0), KissIcpConfig(voxel_size_m=None, deskew=False))
    assert cfg.data.max_range == 50.0 and cfg.data.min_range == 1.0
    assert cfg.mapping.voxel_size == pytest.approx(0.5)  # KISS default: max_range / 100
    assert cfg.data.deskew is False
    cfg = kiss_config(SensorConfig(), KissIcpConfig(voxel_size_m=0.3, deskew=True))
    assert cfg.mapping.voxel_size == pytest.approx(0.3) and cfg.data.deskew is True


def test_normalized_point_times():
    t = np.array([0.05, 0.0, 0.1, 0.075])
    assert np.allclose(normalized_point_times(t), [0.5, 0.0, 1.0, 0.75])
    assert normalized_point_times(None).size == 0
    assert normalized_point_times(np.zeros(5)).size == 0


def _box_room_scan(rng, n=6000) -> np.ndarray:
    """Points on the walls, floor and ceiling of an asymmetric 12 x 8 x 3 m room (room frame)."""
    faces = rng.integers(0, 6, n)
    u, v = rng.random(n), rng.random(n)
    size = np.array([12.0, 8.0, 3.0])
    p = np.empty((n, 3))
    axis = faces // 2
    for ax in range(3):
        sel = axis == ax
        others = [i for i in range(3) if i != ax]
        p[sel, ax] = np.where(faces[sel] % 2 == 0, 0.0, size[ax])
        p[sel, others[0]] = u[sel] * size[others[0]]
        p[sel, others[1]] = v[sel] * size[others[1]]
    # a pillar breaks the symmetry along the walls
    m = n // 10
    ang = rng.random(m) * 2 * np.pi
    pillar = np.column_stack([3 + 0.3 * np.cos(ang), 5 + 0.3 * np.sin(ang), rng.random(m) * 3])
    return np.vstack([p, pillar])


def test_kiss_icp_recovers_synthetic_motion(caplog):
    """A sensor moving 10 cm per scan through a room: poses match ground truth (world = scan 0)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    n = 12
    T_world_scan_gt = np.tile(np.eye(4), (n, 1, 1))
    T_world_scan_gt[:, :3, 3] = np.column_stack([2 + 0.1 * np.arange(n), 3 + 0.02 * np.arange(n), 1.5 * np.ones(n)])
    T_world_scan_gt[:, :3, :3] = Rotation.from_euler("z", 0.01 * np.arange(n)[:, None]).as_matrix()
    scans = []
    for k in range(n):
        pts_world = _box_room_scan(rng)
        T_scan_world = np.linalg.inv(T_world_scan_gt[k])
        scans.append(pts_world @ T_scan_world[:3, :3].T + T_scan_world[:3, 3])
    sensor, config = SensorConfig(max_range_m=30.0, min_range_m=0.1), KissIcpConfig(voxel_size_m=0.1, deskew=True)
    calls = []
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        T_est = run_kiss_icp(ArraySource(scans), sensor, config, progress=lambda d, t: calls.append((d, t)))
    assert "no per-point time" in caplog.text  # deskew asked for, these arrays have no times
    assert calls[-1] == (n, n) and len(calls) == n
    assert np.allclose(T_est[0], np.eye(4))
    T_gt_rel = np.linalg.inv(T_world_scan_gt[0]) @ T_world_scan_gt
    assert np.abs(T_est[:, :3, 3] - T_gt_rel[:, :3, 3]).max() < 0.02
    # distinct arrays (last_pose copied, not aliased)
    assert not np.allclose(T_est[1], T_est[-1])


def test_kiss_icp_on_balm_campus(shared_data):
    folder = shared_data / "balm-campus-30"
    files = sorted((folder / "scans").glob("*.pcd"))
    scans = [_read_pcd_xyz(f) for f in files]
    T_est = run_kiss_icp(ArraySource(scans), SensorConfig(), KissIcpConfig())
    ref = np.loadtxt(folder / "poses_kitti.txt").reshape(-1, 3, 4)
    T_ref = np.tile(np.eye(4), (len(ref), 1, 1))
    T_ref[:, :3, :] = ref
    ate = _ate_se3_m(T_ref, T_est)
    assert ate < 0.05, ate
