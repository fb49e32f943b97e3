"""`pa refine`: error paths (nothing written), outputs, report, and an end-to-end run on a
small synthetic scan folder with ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.core.geometry import pose_change
from pa_cli.io.report import REPORT_VERSION
from pa_cli.io.trajectory import read_trajectory, write_kitti
from pa_cli.refine.outputs import RefineOutputs
from pa_testing.room_scene import N_SCANS, ground_truth_poses, write_room_folder


@pytest.fixture(scope="module")
def scan_folder(tmp_path_factory):
    return write_room_folder(tmp_path_factory.mktemp("room"))


def _config(tmp_path, text: str):
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


INDOOR = """
sensor: {max_range_m: 30.0, min_range_m: 0.2}
scene: {plane_voxel_m: 1.0}
refine: {max_rounds: 2}
map: {voxel_m: 0.1}
advanced: {kiss_icp: {voxel_size_m: 0.1}}
"""


def test_pose_change_against_known_motion():
    from scipy.spatial.transform import Rotation

    T0 = np.tile(np.eye(4), (3, 1, 1))
    T1 = T0.copy()
    T1[1, :3, 3] = [0.3, 0.4, 0.0]
    T1[2, :3, :3] = Rotation.from_rotvec([0, 0, np.radians(2.5)]).as_matrix()
    moved_m, turned_deg = pose_change(T0, T1)
    assert moved_m == pytest.approx(0.5)
    assert turned_deg == pytest.approx(2.5)


def test_output_names_follow_the_map_stem(tmp_path):
    out = RefineOutputs.from_map_path(tmp_path / "office.ply", tmp_path / "p.npz")
    assert [p.name for p in out.all()] == [
        "office.ply", "office_poses_kitti.txt", "office_poses_tum.txt", "office_initial_poses_kitti.txt",
        "office_report.json", "office_config.yaml", "office_covariance.npz",
            "office_overview.png", "p.npz"]


def test_missing_folder_exit_1(run_pa, tmp_path):
    code, _, err = run_pa("refine", tmp_path / "nope", "--out", tmp_path / "m.ply")
    assert code == 1 and "nope: scans not found" in err
    assert list(tmp_path.iterdir()) == []


def test_bad_config_key_names_the_key(run_pa, tmp_path, scan_folder):
    cfg = _config(tmp_path, "planes:\n  voxel_size: 1.0\n")
    code, _, err = run_pa("refine", scan_folder / "scans", "--out", tmp_path / "m.ply", "--config", cfg)
    assert code == 1 and "planes.voxel_size" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.yaml"]


def test_poses_length_mismatch_names_both_counts(run_pa, tmp_path, scan_folder):
    poses = tmp_path / "short.txt"
    write_kitti(poses, ground_truth_poses()[:7])
    code, _, err = run_pa("refine", scan_folder / "scans", "--out", tmp_path / "m.ply", "--poses", poses, "-q")
    assert code == 1 and "7 poses" in err and f"{N_SCANS} scans" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["short.txt"]


def test_existing_output_refused_nothing_written(run_pa, tmp_path, scan_folder):
    (tmp_path / "m_report.json").write_text("old")
    code, _, err = run_pa("refine", scan_folder / "scans", "--out", tmp_path / "m.ply", "-q")
    assert code == 1 and "--force" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m_report.json"]
    assert (tmp_path / "m_report.json").read_text() == "old"


def test_usage_errors_exit_2(run_pa, tmp_path, scan_folder):
    assert run_pa("refine", scan_folder / "scans")[0] == 2  # no --out
    assert run_pa("refine", scan_folder / "scans", "--out", tmp_path / "m.txt")[0] == 2
    assert run_pa("refine", scan_folder / "scans", "--out", tmp_path / "m.ply", "--solver", "gd")[0] == 2
    assert list(tmp_path.iterdir()) == []


def test_print_config_shows_effective_values(run_pa, tmp_path):
    import yaml

    cfg = _config(tmp_path, "map: {voxel_m: 0.25}\n")
    code, out, _ = run_pa("refine", "--print-config", "--config", cfg, "--rounds", "7", "--solver", "lm")
    assert code == 0
    data = yaml.safe_load(out)
    assert data["map"]["voxel_m"] == 0.25 and data["refine"]["max_rounds"] == 7
    assert data["advanced"]["solver"]["solver"] == "lm"


def test_refine_end_to_end(run_pa, tmp_path, scan_folder):
    pytest.importorskip("pa_cli.planes.associate")
    import pa_cli.adjust

    if not hasattr(pa_cli.adjust, "solve"):
        pytest.skip("pa_cli.adjust.solve not landed yet")
    from pa_cli.adjust.covariance import LEAST_CERTAIN_SCANS, load_covariance
    from pa_cli.io.maps import read_map_ply
    from pa_cli.io.problem import load_problem

    out = tmp_path / "room.ply"
    cfg = _config(tmp_path, INDOOR)
    code, _, err = run_pa("refine", scan_folder / "scans", "--out", out, "--config", cfg, "--loops",
                          "--gt", scan_folder / "gt_kitti.txt", "--save-problem", tmp_path / "room.npz", "-q")
    assert code == 0, err
    outputs = RefineOutputs.from_map_path(out, tmp_path / "room.npz")
    for path in outputs.all():
        assert path.is_file(), path
    cloud = read_map_ply(out)
    assert len(cloud.points_world) > 1000 and set(np.unique(cloud.scan_index)) <= set(range(N_SCANS))
    refined = read_trajectory(outputs.poses_kitti)
    assert len(refined) == N_SCANS
    tum = read_trajectory(outputs.poses_tum)
    assert np.allclose(tum.timestamps, 100.0 + 0.1 * np.arange(N_SCANS))  # from times.txt
    assert np.allclose(tum.T_world_scan, refined.T_world_scan, atol=1e-6)
    report = json.loads(outputs.report_json.read_text())
    assert next(iter(report)) == "report_version" and report["report_version"] == REPORT_VERSION
    for key in ("stage_times_s", "input", "rounds", "summary", "poorly_constrained_scans", "gt", "map"):
        assert key in report, key
    assert {"load", "odometry", "loops", "planes 1", "adjust 1", "write"} <= set(report["stage_times_s"])
    assert set(report["stage_cpu_s"]) == set(report["stage_times_s"])
    assert all(v >= 0 for v in report["stage_cpu_s"].values()) and sum(report["stage_cpu_s"].values()) > 0
    # a short sequence has no place visited twice: no candidate, the odometry goes on unchanged
    assert report["loops"]["enabled"] and report["loops"]["n_candidates"] == 0
    assert report["gt"]["odometry"]["ate_rmse_m"] == pytest.approx(report["gt"]["initial"]["ate_rmse_m"])
    assert report["summary"]["cost_final_m2"] <= report["summary"]["cost_initial_m2"]
    assert report["gt"]["refined"]["ate_rmse_m"] <= report["gt"]["initial"]["ate_rmse_m"]
    problem = load_problem(tmp_path / "room.npz")
    assert problem.n_scans == N_SCANS and np.allclose(problem.T_world_scan, refined.T_world_scan, atol=1e-9)
    cov = load_covariance(outputs.covariance_npz)
    assert np.allclose(cov.T_world_scan, refined.T_world_scan, atol=1e-9)
    assert np.allclose(report["covariance"]["position_sigma_m"], cov.position_sigma_m())
    assert problem.range_clusters is not None and cov.noise_model == report["covariance"]["noise_model"] == "range"
    assert len(report["covariance"]["least_certain_scans"]) == min(LEAST_CERTAIN_SCANS, N_SCANS - 1)
    # a second run refuses to overwrite; with --force it succeeds
    assert run_pa("refine", scan_folder / "scans", "--out", out, "--config", cfg, "-q")[0] == 1
    init = tmp_path / "init.txt"
    init.write_text(outputs.initial_poses_kitti.read_text())
    code, _, err = run_pa("refine", scan_folder / "scans", "--out", out, "--config", cfg, "-q", "--force",
                          "--poses", init, "--solver", "newton", "--no-loops")
    assert code == 0, err
    report = json.loads(outputs.report_json.read_text())
    assert "odometry" not in report["stage_times_s"] and "loops" not in report["stage_times_s"]
    assert report["loops"] == {"enabled": False}
