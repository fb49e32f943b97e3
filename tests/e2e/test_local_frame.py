"""Poses far from the world origin (georeferenced, UTM): `pa refine` and `pa adjust` compute in the
local frame of `pa_cli.core.local_frame` and return, in the world frame, the result they return for the
same poses near the origin."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.core.geometry import retract_left
from pa_cli.core.local_frame import local_origin_m, to_local, to_world
from pa_cli.evaluation.perturbation import perturb_poses
from pa_cli.io.trajectory import read_trajectory, write_kitti
from pa_cli.refine.outputs import RefineOutputs
from pa_testing.room_scene import ground_truth_poses, write_room_folder

# UTM-like: hundreds of km east, thousands north; whole kilometres, so the voxel grids stay in place
OFFSET_M = np.array([512_000.0, 4_012_000.0, 0.0])
CONFIG = """
scene: {plane_voxel_m: 1.0}
refine: {max_rounds: 3}
map: {voxel_m: 0.1}
"""


@pytest.fixture(scope="module")
def scan_folder(tmp_path_factory):
    return write_room_folder(tmp_path_factory.mktemp("room"))


def _moved(T: np.ndarray, offset_m: np.ndarray) -> np.ndarray:
    T = T.copy()
    T[:, :3, 3] += offset_m
    return T


def test_local_origin_is_the_first_position_in_whole_kilometres():
    T = np.tile(np.eye(4), (2, 1, 1))
    T[0, :3, 3] = [499.9, -499.9, 3.0]
    assert local_origin_m(T).tolist() == [0.0, 0.0, 0.0]
    T[0, :3, 3] = [512_345.6, 4_012_499.0, -1_600.0]
    assert local_origin_m(T).tolist() == [512_000.0, 4_012_000.0, -2_000.0]
    T[1, :3, 3] = [7e6, 0.0, 0.0]  # only the first pose counts
    assert local_origin_m(T).tolist() == [512_000.0, 4_012_000.0, -2_000.0]


def test_local_and_world_poses_round_trip():
    T_world = _moved(ground_truth_poses(), OFFSET_M + [345.25, -12.5, 7.0])
    origin = local_origin_m(T_world)
    T_local = to_local(T_world, origin)
    assert np.abs(T_local[:, :3, 3]).max() < 1000.0
    assert np.array_equal(T_local[:, :3, :3], T_world[:, :3, :3])
    assert np.allclose(to_world(T_local, origin), T_world, rtol=0, atol=1e-9)


def test_covariance_in_the_world_keeps_its_tangents_about_the_local_origin(tmp_path):
    """position_covariance_m2 = J C J^T with J the derivative of the scan origin under a step that
    turns about origin_world_m and moves by rho (finite differences), the same in both frames."""
    from pa_cli.adjust.covariance import PoseCovariance, load_covariance, save_covariance

    rng = np.random.default_rng(3)
    A = rng.normal(size=(len(ground_truth_poses()), 6, 6))
    local = PoseCovariance(covariance=A @ A.transpose(0, 2, 1) * 1e-6, T_world_scan=ground_truth_poses(),
                           point_sigma_m=0.01, point_sigma_source="given", gauge_pose=0, n_points=100, dof=10,
                           hessian="gauss-newton", noise_model="given")
    world = local.in_world(OFFSET_M)
    assert np.allclose(world.T_world_scan, _moved(local.T_world_scan, OFFSET_M), rtol=0, atol=1e-9)
    assert np.allclose(world.position_covariance_m2(), local.position_covariance_m2(), rtol=1e-9, atol=0)
    j, eps = 4, 1e-6
    T_local = local.T_world_scan[j:j + 1]
    J = np.zeros((3, 6))
    for i in range(6):
        step = np.zeros((1, 6))
        step[0, i] = eps
        # the world pose after the step is to_world(retract_left(T_local, step)): differentiated
        # before the kilometres are added, which would round the difference
        plus = retract_left(T_local, step)[0, :3, 3]
        minus = retract_left(T_local, -step)[0, :3, 3]
        J[:, i] = (plus - minus) / (2 * eps)
    assert np.allclose(world.position_covariance_m2()[j], J @ world.covariance[j] @ J.T, rtol=1e-6, atol=1e-15)
    save_covariance(tmp_path / "c.npz", world)
    loaded = load_covariance(tmp_path / "c.npz")
    assert loaded.origin_world_m.tolist() == OFFSET_M.tolist()
    assert np.allclose(loaded.position_covariance_m2(), local.position_covariance_m2(), rtol=1e-9, atol=0)


def test_voxel_filter_in_a_local_frame_keeps_the_same_points():
    from pa_cli.io.map_filter import MapVoxelFilter

    rng = np.random.default_rng(5)
    scans = [rng.uniform(-5, 5, size=(2000, 3)) for _ in range(3)]
    T_local = ground_truth_poses()[:3]
    near, far = MapVoxelFilter(0.2), MapVoxelFilter(0.2, OFFSET_M)
    for k, points in enumerate(scans):
        a, b = near.add(points, T_local[k], k), far.add(points, T_local[k], k)
        assert b.points_world.dtype == np.float64
        assert np.array_equal(a.scan_index, b.scan_index)
        assert np.allclose(b.points_world - OFFSET_M, a.points_world, rtol=0, atol=1e-9)


def test_ply_map_with_double_coordinates_keeps_millimetres_far_from_the_origin(tmp_path):
    from pa_cli.io.maps import MapCloud, read_map, write_map

    points = OFFSET_M + np.random.default_rng(2).uniform(-50, 50, size=(100, 3))
    cloud = MapCloud(points, np.arange(100, dtype=np.int32))
    write_map(tmp_path / "far.ply", cloud, float64_coordinates=True)
    write_map(tmp_path / "near.ply", cloud)
    assert b"property double x" in (tmp_path / "far.ply").read_bytes()[:200]
    assert np.abs(read_map(tmp_path / "far.ply").points_world - points).max() < 1e-6
    assert np.abs(read_map(tmp_path / "near.ply").points_world - points).max() > 0.01  # float32: decimetres


def test_refine_and_adjust_with_georeferenced_poses_equal_the_run_near_the_origin(run_pa, tmp_path, scan_folder):
    from pa_cli.adjust.covariance import load_covariance
    from pa_cli.io.maps import read_map

    T_gt = ground_truth_poses()
    T_start = perturb_poses(T_gt, np.radians(0.3), 0.05, np.random.default_rng(11), keep_first=True)
    config = tmp_path / "cfg.yaml"
    config.write_text(CONFIG)
    runs = {}
    for name, offset in (("near", np.zeros(3)), ("far", OFFSET_M)):
        poses, gt = tmp_path / f"{name}_start.txt", tmp_path / f"{name}_gt.txt"
        write_kitti(poses, _moved(T_start, offset))
        write_kitti(gt, _moved(T_gt, offset))
        out = tmp_path / f"{name}.ply"
        code, _, err = run_pa("refine", scan_folder / "scans", "--out", out, "--config", config, "--poses", poses,
                              "--gt", gt, "--save-problem", tmp_path / f"{name}.npz", "-q")
        assert code == 0, err
        outputs = RefineOutputs.from_map_path(out, tmp_path / f"{name}.npz")
        runs[name] = {"report": json.loads(outputs.report_json.read_text()),
                      "poses": read_trajectory(outputs.poses_kitti).T_world_scan,
                      "initial": read_trajectory(outputs.initial_poses_kitti).T_world_scan,
                      "map": read_map(out).points_world, "covariance": load_covariance(outputs.covariance_npz)}
        adjusted = tmp_path / f"{name}_adjusted.txt"
        code, _, err = run_pa("adjust", tmp_path / f"{name}.npz", "--poses", poses, "--out", adjusted,
                              "--covariance", tmp_path / f"{name}_cov.npz")
        assert code == 0, err
        runs[name]["adjusted"] = read_trajectory(adjusted).T_world_scan
        runs[name]["adjusted_covariance"] = load_covariance(tmp_path / f"{name}_cov.npz")
    near, far = runs["near"], runs["far"]
    assert near["report"]["local_frame_origin_m"] == [0.0, 0.0, 0.0]
    assert far["report"]["local_frame_origin_m"] == OFFSET_M.tolist()
    assert near["report"]["gt"]["refined"]["ate_rmse_m"] < 0.5 * near["report"]["gt"]["initial"]["ate_rmse_m"]
    for key in ("poses", "initial", "adjusted"):
        assert np.allclose(far[key] - _moved(near[key], OFFSET_M), 0.0, rtol=0, atol=1e-6), key
    for which in ("initial", "refined"):
        assert far["report"]["gt"][which]["ate_rmse_m"] == pytest.approx(
            near["report"]["gt"][which]["ate_rmse_m"], abs=1e-7)
    assert far["report"]["gt"]["rms_point_to_plane_at_gt_m"] == pytest.approx(
        near["report"]["gt"]["rms_point_to_plane_at_gt_m"], rel=1e-6)
    assert far["report"]["quality"]["verdict"] == near["report"]["quality"]["verdict"]
    assert len(far["map"]) == len(near["map"])
    assert np.abs(far["map"] - OFFSET_M - near["map"]).max() < 1e-5  # float32 of the near map
    for key in ("covariance", "adjusted_covariance"):
        assert np.allclose(far[key].position_covariance_m2(), near[key].position_covariance_m2(), rtol=1e-6,
                           atol=1e-15), key
        assert np.allclose(far[key].T_world_scan, _moved(near[key].T_world_scan, OFFSET_M), rtol=0, atol=1e-6)


def test_calibrate_with_georeferenced_base_poses_equals_the_run_near_the_origin(run_pa, tmp_path):
    import yaml

    from pa_cli.calibration.outputs import read_rig_map
    from pa_cli.io.extrinsics import read_extrinsics, write_extrinsics
    from pa_testing.calibration_cases import OVERLAP_2x16, perturbed_extrinsics

    (tmp_path / "rig.yaml").write_text(yaml.safe_dump({"lidars": [dict(lidar) for lidar in OVERLAP_2x16.lidars]}))
    code, _, err = run_pa("simulate", "office", tmp_path / "rig", "--rig", tmp_path / "rig.yaml", "--scans", "8",
                          "--azimuth-steps", "180", "--step-m", "0.2", "--seed", "1")
    assert code == 0, err
    T_true = read_extrinsics(tmp_path / "rig" / "gt_extrinsics.yaml")
    write_extrinsics(tmp_path / "init.yaml", perturbed_extrinsics(T_true, 2.0, 0.05, 1))
    T_base = read_trajectory(tmp_path / "rig" / "gt_poses_kitti.txt").T_world_scan
    runs = {}
    for name, offset in (("near", np.zeros(3)), ("far", OFFSET_M)):
        write_kitti(tmp_path / f"{name}_poses.txt", _moved(T_base, offset))
        out = tmp_path / name / "extrinsics.yaml"
        out.parent.mkdir()
        code, _, err = run_pa("calibrate", tmp_path / "rig", "--out", out, "--init", tmp_path / "init.yaml",
                              "--poses", tmp_path / f"{name}_poses.txt", "--config", "indoor", "--quiet")
        assert code == 0, err
        runs[name] = {"extrinsics": read_extrinsics(out),
                      "poses": read_trajectory(out.parent / "extrinsics_base_poses_kitti.txt").T_world_scan,
                      "map": read_rig_map(out.parent / "extrinsics_map.ply")[0]}
    near, far = runs["near"], runs["far"]
    # the calibration did its work: the extrinsics moved from the initial guess to the truth
    init_error_m = np.abs(read_extrinsics(tmp_path / "init.yaml")[1][:3, 3] - T_true[1][:3, 3]).max()
    assert np.abs(near["extrinsics"][1][:3, 3] - T_true[1][:3, 3]).max() < 0.2 * init_error_m
    assert np.allclose(far["extrinsics"], near["extrinsics"], rtol=0, atol=1e-6)
    assert np.allclose(far["poses"], _moved(near["poses"], OFFSET_M), rtol=0, atol=1e-6)
    assert len(far["map"]) == len(near["map"])
    assert np.abs(far["map"] - OFFSET_M - near["map"]).max() < 1e-5
