"""`pa adjust` end to end: outputs, report keys, clean errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.adjust import REPORT_KEYS, REPORT_VERSION
from pa_cli.io.problem import save_problem
from pa_cli.io.trajectory import read_trajectory, write_kitti
from pa_testing.synthetic_problems import make_scene, perturb

HISTORY_KEYS = {"iteration", "cost_m2", "gradient_norm", "mu", "step_norm", "accepted", "time_s"}


@pytest.fixture
def scene(tmp_path):
    problem, T_gt = make_scene(20, 80, 6, points_per_observation=12, seed=3)
    problem.T_world_scan = perturb(T_gt, np.deg2rad(1.0), 0.1, seed=4)
    path = tmp_path / "problem.npz"
    save_problem(path, problem)
    return path, problem, T_gt


def test_adjust_writes_poses_and_report(run_pa, scene, tmp_path):
    path, problem, T_gt = scene
    out, report = tmp_path / "refined.txt", tmp_path / "report.json"
    code, _, err = run_pa("adjust", path, "--out", out, "--report", report)
    assert code == 0, err
    assert "cost final" in err
    T = read_trajectory(out).T_world_scan
    assert np.abs(T[:, :3, 3] - T_gt[:, :3, 3]).max() < 1e-6  # pose 0 fixed at ground truth
    rep = json.loads(report.read_text())
    assert set(rep) == set(REPORT_KEYS)
    assert next(iter(rep)) == "report_version" and rep["report_version"] == REPORT_VERSION
    assert rep["solver"] == "newton"
    assert rep["converged"] is True
    assert rep["n_scans"] == 20 and rep["n_planes"] == problem.n_planes
    assert rep["n_observations"] == problem.n_observations
    assert rep["iterations"] == len(rep["history"])
    assert all(set(h) == HISTORY_KEYS for h in rep["history"])
    assert rep["cost_final_m2"] < 1e-6 * rep["cost_initial_m2"]


def test_adjust_with_poses_file_tum_output_and_fix(run_pa, scene, tmp_path):
    path, problem, T_gt = scene
    init = tmp_path / "init.txt"
    write_kitti(init, problem.T_world_scan)
    out = tmp_path / "refined.tum"
    code, _, err = run_pa("adjust", path, "--poses", init, "--out", out, "--format", "tum",
                          "--fix", "5", "--max-iterations", "3")
    assert code == 0, err
    rows = np.loadtxt(out)
    assert rows.shape == (20, 8)
    np.testing.assert_allclose(read_trajectory(out).T_world_scan[5], problem.T_world_scan[5], atol=1e-8)


def test_adjust_refuses_existing_output(run_pa, scene, tmp_path):
    path, _, _ = scene
    out = tmp_path / "refined.txt"
    out.write_text("keep me\n")
    code, _, err = run_pa("adjust", path, "--out", out)
    assert code == 1 and "--force" in err
    assert out.read_text() == "keep me\n"


def test_adjust_pose_count_mismatch(run_pa, scene, tmp_path):
    path, problem, _ = scene
    init = tmp_path / "init.txt"
    write_kitti(init, problem.T_world_scan[:7])
    out = tmp_path / "refined.txt"
    code, _, err = run_pa("adjust", path, "--poses", init, "--out", out)
    assert code == 1
    assert "7 poses" in err and "20 scans" in err
    assert not out.exists()


def test_adjust_without_any_poses(run_pa, scene, tmp_path):
    path, problem, _ = scene
    no_poses = tmp_path / "bare.npz"
    np.savez(no_poses, plane_index=problem.plane_index, scan_index=problem.scan_index, clusters=problem.clusters)
    code, _, err = run_pa("adjust", no_poses, "--out", tmp_path / "o.txt")
    assert code == 1 and "--poses" in err and "Traceback" not in err


@pytest.mark.parametrize("kind", ["garbage", "missing_arrays", "bad_shape", "absent"])
def test_adjust_bad_problem_files(run_pa, tmp_path, kind):
    path = tmp_path / "bad.npz"
    if kind == "garbage":
        path.write_bytes(b"not a zip file at all")
    elif kind == "missing_arrays":
        np.savez(path, plane_index=np.arange(3))
    elif kind == "bad_shape":
        np.savez(path, plane_index=np.zeros(4, int), scan_index=np.arange(4), clusters=np.zeros((4, 3, 3)))
    out = tmp_path / "o.txt"
    code, _, err = run_pa("adjust", path, "--out", out)
    assert code == 1
    assert "bad.npz" in err and "Traceback" not in err
    assert not out.exists()


def test_adjust_usage_errors(run_pa, scene, tmp_path):
    path, _, _ = scene
    code, _, _ = run_pa("adjust", path, "--out", tmp_path / "o.txt", "--max-iterations", "0")
    assert code == 2
    code, _, _ = run_pa("adjust", path, "--out", tmp_path / "o.txt", "--fix", "99")
    assert code == 2
    code, _, _ = run_pa("adjust", path, "--out", tmp_path / "o.txt", "--solver", "nope")
    assert code == 2
