"""`pa perturb` and `pa eval` in-process: outputs, refusals and error exit codes."""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.io.report import REPORT_VERSION
from pa_cli.io.trajectory import read_trajectory, write_kitti, write_tum


@pytest.fixture
def kitti_gt(tmp_path):
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (2000, 1, 1))
    T[:, :3, :3] = Rotation.random(2000, random_state=0).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(size=(2000, 3)), axis=0)
    write_kitti(tmp_path / "gt.txt", T)
    return tmp_path / "gt.txt"


def test_perturb_statistics_seed_and_level(run_pa, kitti_gt, tmp_path):
    code, _, err = run_pa("perturb", kitti_gt, "--rot-deg", "1", "--trans-m", "0.1", "--seed", "3",
                          "--out", tmp_path / "a.txt")
    assert code == 0, err
    T = read_trajectory(kitti_gt).T_world_scan
    T_a = read_trajectory(tmp_path / "a.txt").T_world_scan
    dt = T_a[:, :3, 3] - T[:, :3, 3]
    w = Rotation.from_matrix(T_a[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1)).as_rotvec()
    np.testing.assert_allclose(dt.std(axis=0), 0.1, rtol=0.05)
    np.testing.assert_allclose(np.rad2deg(w).std(axis=0), 1.0, rtol=0.05)
    assert run_pa("perturb", kitti_gt, "--level", "2", "--seed", "3", "--out", tmp_path / "b.txt")[0] == 0
    assert (tmp_path / "a.txt").read_bytes() == (tmp_path / "b.txt").read_bytes()
    assert run_pa("perturb", kitti_gt, "--level", "2", "--seed", "4", "--out", tmp_path / "c.txt")[0] == 0
    assert (tmp_path / "a.txt").read_bytes() != (tmp_path / "c.txt").read_bytes()


def test_perturb_keep_first_and_tum_timestamps(run_pa, tmp_path):
    T = np.tile(np.eye(4), (5, 1, 1))
    T[:, 0, 3] = np.arange(5)
    stamps = 1630577768.5 + 0.5 * np.arange(5)
    write_tum(tmp_path / "p.tum", T, stamps)
    code, _, err = run_pa("perturb", tmp_path / "p.tum", "--level", "3", "--keep-first", "--out", tmp_path / "o.tum")
    assert code == 0, err
    out = read_trajectory(tmp_path / "o.tum")
    np.testing.assert_allclose(out.timestamps, stamps, atol=1e-9)
    np.testing.assert_allclose(out.T_world_scan[0], T[0], atol=1e-9)
    assert not np.allclose(out.T_world_scan[1], T[1], atol=1e-3)
    code, _, _ = run_pa("perturb", tmp_path / "p.tum", "--level", "1", "--format", "tum",
                        "--out", tmp_path / "o2.txt")
    assert code == 0 and len((tmp_path / "o2.txt").read_text().split("\n")[0].split()) == 8


def test_perturb_usage_errors_exit_2(run_pa, kitti_gt, tmp_path):
    out = tmp_path / "o.txt"
    for args in (["--rot-deg", "-1", "--trans-m", "0.1"], ["--rot-deg", "1", "--trans-m", "-0.1"],
                 ["--rot-deg", "1"], [], ["--level", "2", "--rot-deg", "1"], ["--level", "5"]):
        code, _, err = run_pa("perturb", kitti_gt, *args, "--out", out)
        assert code == 2, (args, err)
        assert "Traceback" not in err and "Invalid value" in err
    assert not out.exists()


def test_perturb_refuses_overwrite_and_input(run_pa, kitti_gt, tmp_path):
    out = tmp_path / "o.txt"
    out.write_text("keep me\n")
    code, _, err = run_pa("perturb", kitti_gt, "--level", "1", "--out", out)
    assert code == 1 and "--force" in err and "Traceback" not in err
    assert out.read_text() == "keep me\n"
    assert run_pa("perturb", kitti_gt, "--level", "1", "--out", out, "--force")[0] == 0
    assert len(read_trajectory(out)) == 2000
    before = kitti_gt.read_bytes()
    code, _, err = run_pa("perturb", kitti_gt, "--level", "1", "--out", kitti_gt, "--force")
    assert code == 1 and "input" in err and kitti_gt.read_bytes() == before
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    code, _, err = run_pa("perturb", tmp_path / "bad.txt", "--level", "1", "--out", tmp_path / "x.txt")
    assert code == 1 and "3 columns" in err and "Traceback" not in err and not (tmp_path / "x.txt").exists()


def _pair(tmp_path, n=40, seed=1):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    E = T.copy()
    E[:, :3, 3] += rng.normal(size=(n, 3)) * 0.1
    E[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.02).as_matrix() @ E[:, :3, :3]
    write_kitti(tmp_path / "gt.txt", T)
    write_kitti(tmp_path / "est.txt", E)
    return tmp_path / "gt.txt", tmp_path / "est.txt"


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_eval_json_equals_evo_ape_cli(run_pa, tmp_path, align):
    """`pa eval` vs evo's own command line `evo_ape kitti GT EST -a [-s]` (full-precision stats)."""
    evo_ape = shutil.which("evo_ape") or str(Path(__import__("sys").executable).parent / "evo_ape")
    if not Path(evo_ape).exists():
        pytest.skip("evo_ape not installed")
    gt, est = _pair(tmp_path)
    code, out, err = run_pa("eval", gt, est, "--align", align, "--json", tmp_path / "e.json",
                            "--plot", tmp_path / "top.png")
    assert code == 0, err
    assert "ATE translation" in out and "RPE rotation" in out
    result = json.loads((tmp_path / "e.json").read_text())
    assert next(iter(result)) == "report_version" and result["report_version"] == REPORT_VERSION
    flags = ["-a"] + (["-s"] if align == "sim3" else [])
    subprocess.run([evo_ape, "kitti", str(gt), str(est), *flags, "--save_results", str(tmp_path / "r.zip"),
                    "--no_warnings"], check=True, capture_output=True)
    with zipfile.ZipFile(tmp_path / "r.zip") as z:
        stats = json.loads(z.read("stats.json"))
    for key in ("rmse", "mean", "median", "max"):
        assert result[f"ate_{key}_m"] == pytest.approx(stats[key], rel=1e-9)
    assert (tmp_path / "top.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert np.asarray(result["alignment"]).shape == (4, 4) and result["n_poses"] == 40
    code, _, err = run_pa("eval", gt, est, "--json", tmp_path / "e.json")
    assert code == 1 and "--force" in err


def test_eval_errors(run_pa, tmp_path):
    gt, est = _pair(tmp_path)
    T = read_trajectory(est).T_world_scan[:25]
    write_kitti(tmp_path / "short.txt", T)
    code, _, err = run_pa("eval", gt, tmp_path / "short.txt")
    assert code == 1 and "40" in err and "25" in err and "Traceback" not in err
    code, _, err = run_pa("eval", gt, tmp_path / "missing.txt")
    assert code == 1 and "not found" in err
    code, _, err = run_pa("eval", gt, est, "--align", "affine")
    assert code == 2
    code, _, err = run_pa("eval", gt, est, "--max-diff", "-1")
    assert code == 2
    write_tum(tmp_path / "a.tum", T, np.arange(25.0))
    write_tum(tmp_path / "b.tum", T, np.arange(25.0) + 50)
    code, _, err = run_pa("eval", tmp_path / "a.tum", tmp_path / "b.tum", "--json", tmp_path / "x.json")
    assert code == 1 and "--max-diff" in err and not (tmp_path / "x.json").exists()


def test_eval_two_estimates_in_one_table_json_and_plot(run_pa, tmp_path):
    from matplotlib.image import imread

    gt, est = _pair(tmp_path)
    worse = read_trajectory(est).T_world_scan.copy()
    worse[:, :3, 3] += np.random.default_rng(2).normal(size=(40, 3)) * 0.5
    write_kitti(tmp_path / "worse.txt", worse)
    code, out, err = run_pa("eval", gt, est, tmp_path / "worse.txt", "--json", tmp_path / "e.json",
                            "--plot", tmp_path / "eval.png")
    assert code == 0, err
    assert "est.txt" in out and "worse.txt" in out and "ATE translation rmse" in out and "RPE rotation" in out
    report = json.loads((tmp_path / "e.json").read_text())
    first, second = report["estimates"]
    assert first["est"] == str(est) and second["est"] == str(tmp_path / "worse.txt")
    assert second["ate_rmse_m"] > 3 * first["ate_rmse_m"] and first["ate_rot_note"] is None
    single = run_pa("eval", gt, est, "--json", tmp_path / "one.json")
    assert single[0] == 0 and json.loads((tmp_path / "one.json").read_text())["ate_rmse_m"] == first["ate_rmse_m"]
    png = tmp_path / "eval.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    pixels = imread(png)
    assert min(pixels.shape[:2]) >= 800 and pixels[..., :3].std() > 0.05


def test_eval_warns_that_the_rotation_ate_is_meaningless_on_a_straight_path(run_pa, tmp_path):
    """A straight path fixes no turn of a position-only (se3) alignment about it: the rotation ATE
    then follows the position errors (here a drift sideways and up), whatever the rotations are."""
    n = 30
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.linspace(0.0, 25.0, n)
    T[:, 1, 3] = 0.01 * np.sin(np.arange(n))  # 1 cm of sideways wander
    E = T.copy()
    E[:, 2, 3] += 0.2 * np.linspace(0.0, 1.0, n) ** 2  # the estimate drifts upwards
    write_kitti(tmp_path / "gt.txt", T)
    write_kitti(tmp_path / "est.txt", E)  # rotations exact
    code, out, err = run_pa("eval", tmp_path / "gt.txt", tmp_path / "est.txt", "--json", tmp_path / "e.json")
    assert code == 0, err
    result = json.loads((tmp_path / "e.json").read_text())
    assert result["ate_rot_rmse_deg"] > 10.0  # rotations are exact: the figure measures the alignment
    assert "(!)" in out and "meaningless" in err and "straight line" in err and "--align origin" in err
    assert "meaningless" in result["ate_rot_note"]
    code, out, err = run_pa("eval", tmp_path / "gt.txt", tmp_path / "est.txt", "--align", "origin")
    assert code == 0 and "meaningless" not in err and "(!)" not in out
