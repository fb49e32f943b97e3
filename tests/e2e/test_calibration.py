"""`pa calibrate` end to end on simulated rigs: from 5 deg / 0.2 m initial errors (--init) to
within 0.05 deg and 5 mm; the outputs, their formats, and the refusals of bad inputs."""

from __future__ import annotations

import json

import numpy as np

from pa_cli.calibration.outputs import read_rig_map
from pa_cli.io.extrinsics import read_extrinsics
from pa_testing.calibration_cases import THREE_MIXED, BARELY_2x16, OVERLAP_2x16, OVERLAP_2x32, run_case

ROTATION_TOL_DEG = 0.05
TRANSLATION_TOL_M = 0.005
SCANS = 20  # 4 m of walking: the barely overlapping LiDARs see common walls only as the rig moves on
AZIMUTH_STEPS = 360


def _check(result: dict) -> None:
    assert np.all(result["init_rotation_error_deg"] > 4.9) and np.all(result["init_translation_error_m"] > 0.19)
    assert np.all(result["rotation_error_deg"] < ROTATION_TOL_DEG), result
    assert np.all(result["translation_error_m"] < TRANSLATION_TOL_M), result


def test_two_lidars_overlapping_16_beams(run_pa, tmp_path) -> None:
    result = run_case(run_pa, tmp_path, OVERLAP_2x16, seed=1, scans=SCANS, azimuth_steps=AZIMUTH_STEPS)
    _check(result)
    # the outputs: extrinsics, base poses (KITTI, TUM), a map with a LiDAR index per point, the report
    out = tmp_path / "extrinsics.yaml"
    kitti = np.loadtxt(tmp_path / "extrinsics_base_poses_kitti.txt")
    tum = np.loadtxt(tmp_path / "extrinsics_base_poses_tum.txt")
    assert kitti.shape == (SCANS, 12) and tum.shape == (SCANS, 8)
    np.testing.assert_allclose(tum[:, 0], np.arange(SCANS) * 0.1, atol=1e-9)  # times.txt of the rig
    points, scan_index, lidar_index = read_rig_map(tmp_path / "extrinsics_map.ply")
    assert set(np.unique(lidar_index)) == {0, 1} and scan_index.max() == SCANS - 1 and len(points) == len(lidar_index)
    report = json.loads((tmp_path / "extrinsics_report.json").read_text())
    cov = np.array(report["extrinsics"]["lidar1"]["covariance"])
    assert cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert report["extrinsics"]["lidar1"]["unobservable"] == []
    # the written 4x4 and xyz + rpy agree
    X = read_extrinsics(out)
    assert np.allclose(X[1][:3, 3], report["extrinsics"]["lidar1"]["xyz_m"])


def test_two_lidars_barely_overlapping_16_beams(run_pa, tmp_path) -> None:
    _check(run_case(run_pa, tmp_path, BARELY_2x16, seed=2, scans=SCANS, azimuth_steps=AZIMUTH_STEPS))


def test_two_lidars_32_beams(run_pa, tmp_path) -> None:
    _check(run_case(run_pa, tmp_path, OVERLAP_2x32, seed=3, scans=SCANS, azimuth_steps=AZIMUTH_STEPS))


def test_three_lidars(run_pa, tmp_path) -> None:
    _check(run_case(run_pa, tmp_path, THREE_MIXED, seed=4, scans=SCANS, azimuth_steps=AZIMUTH_STEPS))
