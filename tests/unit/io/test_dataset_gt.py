"""The datasets' own ground-truth files: LiDAR-frame truth written in each dataset's convention
(`pa_testing.dataset_layouts`, from the datasets' documentation) reads back as the truth."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.errors import FormatError
from pa_cli.io.dataset_gt import read_ground_truth
from pa_cli.io.trajectory import write_kitti
from pa_testing import dataset_layouts as layouts

N_POSES = 7


def _truth(seed: int = 0) -> np.ndarray:
    """LiDAR poses T_world_lidar with roll, pitch and yaw and a path of some 10 m (so lever arms and
    tilts both matter), far from the origin as georeferenced truth is."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (N_POSES, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("xyz", rng.uniform(-0.3, 0.3, (N_POSES, 3)) + [0, 0, 1.0]).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.uniform(-2.0, 2.0, (N_POSES, 3)), axis=0) + [3.5e5, 4.1e6, 30.0]
    return T


def _relative(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T[0]) @ T


def test_kitti_camera_poses_are_moved_to_the_lidar_with_calib_tr(tmp_path, caplog):
    truth = _truth()
    path = layouts.write_kitti_gt(tmp_path, truth)
    with caplog.at_level(logging.INFO):
        gt = read_ground_truth(path)
    assert "KITTI camera poses moved to the LiDAR with Tr of" in caplog.text
    assert gt.timestamps is None  # KITTI pairs by index
    np.testing.assert_allclose(gt.T_world_scan, _relative(truth), atol=1e-7)
    # the same file elsewhere (no calib.txt to find) is an ordinary KITTI trajectory: read as it is
    plain = tmp_path / "plain.txt"
    plain.write_text(path.read_text())
    assert not np.allclose(read_ground_truth(plain).T_world_scan, gt.T_world_scan, atol=1e-3)


def test_kitti_poses_txt_beside_calib_txt(tmp_path):
    truth = _truth(1)
    path = layouts.write_kitti_gt(tmp_path, truth)
    seq = tmp_path / "sequences" / "00"
    (seq / "poses.txt").write_text(path.read_text())
    np.testing.assert_allclose(read_ground_truth(seq / "poses.txt").T_world_scan, _relative(truth), atol=1e-7)


def test_kitti_calib_without_tr_is_refused(tmp_path):
    path = layouts.write_kitti_gt(tmp_path, _truth())
    (tmp_path / "sequences" / "00" / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(FormatError, match="no 'Tr:' line with 12 numbers"):
        read_ground_truth(path)


def test_mulran_base_poses_are_moved_to_the_ouster(tmp_path):
    truth, stamps = _truth(2), layouts.stamps_s(N_POSES)
    gt = read_ground_truth(layouts.write_mulran_gt(tmp_path / "KAIST01", truth, stamps))
    # KISS-ICP's copy of the calibration is rounded to 8 digits: about 1e-7 m and rad at 2 m
    np.testing.assert_allclose(gt.T_world_scan, truth, atol=1e-5)
    np.testing.assert_allclose(gt.timestamps, stamps, rtol=0, atol=1e-6)


def test_newer_college_base_poses_are_moved_to_the_ouster(tmp_path):
    truth, stamps = _truth(3), layouts.stamps_s(N_POSES)
    gt = read_ground_truth(layouts.write_ncd_gt(tmp_path / "01_short_experiment", truth, stamps))
    np.testing.assert_allclose(_relative(gt.T_world_scan), _relative(truth), atol=2e-5)
    np.testing.assert_allclose(gt.timestamps, stamps, rtol=0, atol=1e-6)


def test_nclt_z_down_body_poses_are_turned_z_up(tmp_path, caplog):
    truth, stamps = _truth(4), layouts.stamps_s(N_POSES)
    path = layouts.write_nclt_gt(tmp_path / "2012-01-08", truth, stamps)
    gt = read_ground_truth(path)
    np.testing.assert_allclose(gt.T_world_scan, truth, atol=1e-7)
    np.testing.assert_allclose(gt.timestamps, stamps, rtol=0, atol=1e-6)
    # NCLT's files start with rows of NaN: dropped with a warning
    path.write_text("1326030975000000,nan,nan,nan,nan,nan,nan\n" + path.read_text())
    with caplog.at_level(logging.WARNING):
        assert len(read_ground_truth(path)) == N_POSES
    assert "1 rows with NaN dropped" in caplog.text


def test_a_dataset_csv_of_the_wrong_shape_names_the_layout(tmp_path):
    path = tmp_path / "global_pose.csv"
    path.write_text("1,2,3\n")
    with pytest.raises(FormatError, match="13 numbers .MulRan global_pose.csv"):
        read_ground_truth(path)


def test_any_other_file_is_a_kitti_or_tum_trajectory(tmp_path):
    truth = _truth(5)
    write_kitti(tmp_path / "gt.txt", truth)
    np.testing.assert_allclose(read_ground_truth(tmp_path / "gt.txt").T_world_scan, truth, atol=1e-6)


def test_pa_eval_takes_the_datasets_own_ground_truth(run_pa, tmp_path):
    """`pa eval GT EST`: a dataset's file as GT, converted before the comparison (the LiDAR's own poses
    as the estimate give an ATE of zero; the KITTI camera poses read as they are would not)."""
    from pa_cli.io.trajectory import write_tum

    truth, stamps = _truth(6), layouts.stamps_s(N_POSES)
    write_tum(tmp_path / "est_tum.txt", truth, stamps)
    write_kitti(tmp_path / "est_kitti.txt", _relative(truth))
    kitti = layouts.write_kitti_gt(tmp_path / "kitti", truth)
    cases = [(layouts.write_mulran_gt(tmp_path / "mulran", truth, stamps), "est_tum.txt"),
             (layouts.write_nclt_gt(tmp_path / "nclt" / "2012-01-08", truth, stamps), "est_tum.txt"),
             (kitti, "est_kitti.txt")]
    for gt, est in cases:
        code, _, err = run_pa("eval", gt, tmp_path / est, "--json", tmp_path / "eval.json", "--force")
        assert code == 0, err
        result = json.loads((tmp_path / "eval.json").read_text())
        assert result["n_poses"] == N_POSES and result["ate_rmse_m"] < 1e-5, (gt, result["ate_rmse_m"])
    plain = tmp_path / "plain_00.txt"
    plain.write_text(kitti.read_text())
    run_pa("eval", plain, tmp_path / "est_kitti.txt", "--json", tmp_path / "eval.json", "--force")
    assert json.loads((tmp_path / "eval.json").read_text())["ate_rmse_m"] > 0.01
