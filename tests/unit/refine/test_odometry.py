"""KISS-ICP initial poses: config adapter, time normalisation, and ATE on real data."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pa_cli.config import KissIcpConfig, SensorConfig
from pa_cli.refine.odometry import (
    ReplayedFrames,
    kiss_config,
    kiss_frame_voxel_m,
    normalized_point_times,
    run_kiss_icp,
)
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


def test_the_frames_handed_on_are_the_scans_one_point_per_voxel():
    """`on_frame` receives each scan once, in order, as KISS-ICP thinned it for its map: points of the range-cropped
    scan, one in each occupied voxel of `kiss_frame_voxel_m` (checked against the voxels counted by hand)."""
    rng = np.random.default_rng(5)
    scans = [_box_room_scan(rng) - [6.0, 4.0, 1.5] for _ in range(4)]
    sensor, config = SensorConfig(max_range_m=6.0, min_range_m=0.5), KissIcpConfig(voxel_size_m=0.4, deskew=False)
    voxel_m = kiss_frame_voxel_m(sensor, config)
    assert voxel_m == pytest.approx(0.2)
    frames = []
    run_kiss_icp(ArraySource(scans), sensor, config, on_frame=lambda k, points: frames.append((k, points.copy())))
    assert [k for k, _ in frames] == list(range(len(scans)))
    for (_, frame), scan in zip(frames, scans, strict=True):
        distance = np.linalg.norm(scan, axis=1)
        cropped = scan[(distance < 6.0) & (distance > 0.5)]
        assert len(cropped) < len(scan)  # the premise: the range crop removed points
        assert {tuple(p) for p in frame} <= {tuple(p) for p in cropped}
        assert len(frame) == len(np.unique(np.floor(cropped / voxel_m), axis=0))
        assert len(np.unique(np.floor(frame / voxel_m), axis=0)) == len(frame)


@pytest.mark.parametrize("deskew", [False, True])
def test_frames_made_again_from_the_scans_and_poses_equal_those_handed_on(deskew):
    """A run resumed after the odometry makes KISS-ICP's frames again (`ReplayedFrames`): bit for bit the frames it
    handed on, deskewed with the motion it predicted each scan with."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    n = 6
    scans, times = [], []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", 0.03 * k).as_matrix()
        T[:3, 3] = [0.15 * k, 0.02 * k, 0.0]
        points = (_box_room_scan(rng) - [6.0, 4.0, 1.5] - T[:3, 3]) @ T[:3, :3]
        scans.append(points)
        times.append(rng.random(len(points)) * 0.1)
    source = ArraySource(scans, times)
    sensor, config = SensorConfig(max_range_m=6.0, min_range_m=0.5), KissIcpConfig(voxel_size_m=0.2, deskew=deskew)
    handed_on = []
    T_world_scan = run_kiss_icp(source, sensor, config, on_frame=lambda k, points: handed_on.append(points.copy()))
    assert np.abs(np.diff(T_world_scan[:, :3, 3], axis=0)).max() > 0.1  # the premise: a motion to deskew with
    replayed = ReplayedFrames(source, T_world_scan, sensor, config)
    assert len(replayed) == n
    for k in range(n):
        assert np.array_equal(replayed[k], handed_on[k]), k
    if deskew:  # the premise: deskewing changed the frames
        assert not np.array_equal(ReplayedFrames(source, T_world_scan, sensor,
                                                 KissIcpConfig(voxel_size_m=0.2, deskew=False))[3], handed_on[3])


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


@pytest.mark.parametrize(("settings", "kept"), [
    ({"loops": {"enabled": True}}, True),
    ({"loops": {"enabled": False}}, False),  # no loop stage to hand them to
    # KISS-ICP's frames thinned to 0.6 m, coarser than the local maps' 0.5 m voxel: the loop stage reads the scans
    ({"loops": {"enabled": True}, "advanced": {"kiss_icp": {"voxel_size_m": 1.2}}}, False),
])
def test_the_odometry_keeps_its_frames_only_for_a_loop_stage_they_are_fine_enough_for(settings, kept):
    from pa_cli.config import PaConfig
    from pa_cli.refine.clock import StageClock
    from pa_cli.refine.stages import initial_poses

    rng = np.random.default_rng(2)
    scans = [_box_room_scan(rng) - [6.0, 4.0, 1.5] for _ in range(3)]
    config = PaConfig.model_validate(settings)
    state = initial_poses(ArraySource(scans), None, None, config, StageClock(False))
    if not kept:
        assert state.odometry_frames is None
        return
    voxel_m = kiss_frame_voxel_m(config.sensor, config.advanced.kiss_icp)
    assert voxel_m <= config.advanced.loops.local_map_voxel_m
    assert len(state.odometry_frames) == len(scans)
    for frame, scan in zip(state.odometry_frames, scans, strict=True):
        assert frame.dtype == np.float32 and 0 < len(frame) < len(scan)
        assert len(np.unique(np.floor(frame / voxel_m), axis=0)) == len(frame)


@pytest.mark.parametrize(("initial_poses_source", "kept", "expected"), [
    ("kiss-icp", True, "kept"),  # the frames the odometry kept
    ("kiss-icp", False, "replayed"),  # a run resumed after the odometry: the same frames made again
    ("poses.txt", False, "scans"),  # --poses: no KISS-ICP frames, the scans themselves
])
def test_the_loop_stage_merges_the_odometry_frames_kept_or_made_again(monkeypatch, initial_poses_source, kept,
                                                                      expected):
    from pa_cli.config import PaConfig
    from pa_cli.loops import LoopResult
    from pa_cli.refine import stages
    from pa_cli.refine.clock import StageClock
    from pa_cli.refine.state import RefineState

    rng = np.random.default_rng(4)
    scans = [_box_room_scan(rng) - [6.0, 4.0, 1.5] for _ in range(3)]
    T = np.tile(np.eye(4), (3, 1, 1))
    frames = [s[:10].astype(np.float32) for s in scans]
    state = RefineState(origin_world_m=np.zeros(3), T_odometry=T, T_initial=T, T_current=T,
                        initial_poses_source=initial_poses_source, odometry_frames=frames if kept else None)
    seen = {}

    def close_loops(points, T_world_scan, cfg, min_separation_m, progress=None, threads=1, thinned=False):
        seen.update(points=points, thinned=thinned)
        return LoopResult(T_world_scan.copy(), [], [], [], {"n_loop_edges": 0})

    monkeypatch.setattr(stages, "close_loops", close_loops)
    stages.loop_closure(ArraySource(scans), state, PaConfig.model_validate({"loops": {"enabled": True}}),
                        StageClock(False))
    points = seen["points"]
    assert seen["thinned"] == (expected != "scans")
    if expected == "kept":
        assert points is frames
    elif expected == "replayed":
        assert isinstance(points, ReplayedFrames) and points.T_world_scan is T
    else:
        assert np.array_equal(points[1], scans[1])
