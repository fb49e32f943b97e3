"""Perturbation statistics, Umeyama alignment and ATE/RPE against evo (an outside reference)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.errors import InputError
from pa_cli.evaluation import PERTURBATION_LEVELS, evaluate, match_timestamps, perturb_poses, umeyama_alignment
from pa_cli.io.trajectory import Trajectory, read_trajectory


def _random_poses(n, seed, step_m=1.0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)) * step_m, axis=0)
    return T


def test_levels_are_the_papers():
    assert PERTURBATION_LEVELS == {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


@pytest.mark.parametrize("sigma_rot_deg,sigma_trans_m", [(1.0, 0.1), (3.0, 0.3)])
def test_perturbation_per_axis_std(sigma_rot_deg, sigma_trans_m):
    T = _random_poses(2000, 1)
    T_noisy = perturb_poses(T, np.deg2rad(sigma_rot_deg), sigma_trans_m, np.random.default_rng(5))
    dt = T_noisy[:, :3, 3] - T[:, :3, 3]
    # R_noisy = Exp(w) R  =>  w = Log(R_noisy R^T), the world-frame (left) perturbation
    w = Rotation.from_matrix(T_noisy[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1)).as_rotvec()
    np.testing.assert_allclose(dt.std(axis=0), sigma_trans_m, rtol=0.05)
    np.testing.assert_allclose(np.rad2deg(w).std(axis=0), sigma_rot_deg, rtol=0.05)
    assert np.all(np.abs(dt.mean(axis=0)) < 4 * sigma_trans_m / np.sqrt(2000))
    np.testing.assert_array_equal(T_noisy[:, 3], T[:, 3])


def test_perturbation_seed_and_keep_first():
    T = _random_poses(50, 2)
    a = perturb_poses(T, 0.02, 0.1, np.random.default_rng(7))
    b = perturb_poses(T, 0.02, 0.1, np.random.default_rng(7))
    c = perturb_poses(T, 0.02, 0.1, np.random.default_rng(7), keep_first=True)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(c[0], T[0])
    np.testing.assert_array_equal(c[1:], a[1:])
    assert not np.allclose(a[0], T[0])
    np.testing.assert_array_equal(perturb_poses(T, 0.0, 0.0, np.random.default_rng(0)), T)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_a_known_similarity(with_scale):
    rng = np.random.default_rng(3)
    src = rng.normal(size=(40, 3)) * 5
    R_true = Rotation.random(random_state=4).as_matrix()
    t_true = np.array([3.0, -2.0, 1.5])
    s_true = 1.7 if with_scale else 1.0
    R, t, s = umeyama_alignment(src, s_true * src @ R_true.T + t_true, with_scale=with_scale)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, t_true, atol=1e-12)
    assert s == pytest.approx(s_true, rel=1e-12)


def evo_metrics(T_gt, T_est, align, stamps_gt=None, stamps_est=None, max_diff=0.01):
    """Reference numbers from evo's Python API (evo is GPL: called, never copied)."""
    from evo.core import metrics, sync
    from evo.core.trajectory import PosePath3D, PoseTrajectory3D

    if stamps_gt is not None:
        ref = PoseTrajectory3D(poses_se3=list(T_gt), timestamps=stamps_gt)
        est = PoseTrajectory3D(poses_se3=list(T_est), timestamps=stamps_est)
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    else:
        ref, est = PosePath3D(poses_se3=list(T_gt)), PosePath3D(poses_se3=list(T_est))
    if align in ("se3", "sim3"):
        est.align(ref, correct_scale=align == "sim3")
    elif align == "origin":
        est.align_origin(ref)
    out = {}
    for name, relation in (("trans", metrics.PoseRelation.translation_part),
                           ("rot", metrics.PoseRelation.rotation_angle_deg)):
        ape = metrics.APE(relation)
        ape.process_data((ref, est))
        out[f"ape_{name}"] = ape.get_all_statistics()
        rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((ref, est))
        out[f"rpe_{name}"] = rpe.get_all_statistics()
    out["n"] = ref.num_poses
    return out


def assert_equal_to_evo(result, ref):
    rel = 1e-9
    for key in ("rmse", "mean", "median", "max"):
        assert result[f"ate_{key}_m"] == pytest.approx(ref["ape_trans"][key], rel=rel, abs=1e-14), key
    assert result["ate_std_m"] == pytest.approx(ref["ape_trans"]["std"], rel=rel)
    assert result["ate_rot_rmse_deg"] == pytest.approx(ref["ape_rot"]["rmse"], rel=rel)
    assert result["ate_rot_mean_deg"] == pytest.approx(ref["ape_rot"]["mean"], rel=rel)
    assert result["rpe_trans_rmse_m"] == pytest.approx(ref["rpe_trans"]["rmse"], rel=rel)
    assert result["rpe_trans_mean_m"] == pytest.approx(ref["rpe_trans"]["mean"], rel=rel)
    assert result["rpe_rot_rmse_deg"] == pytest.approx(ref["rpe_rot"]["rmse"], rel=rel)
    assert result["rpe_rot_mean_deg"] == pytest.approx(ref["rpe_rot"]["mean"], rel=rel)
    assert result["n_poses"] == ref["n"]


@pytest.mark.parametrize("align", ["se3", "sim3", "origin", "none"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_evaluate_equals_evo_kitti(align, seed):
    T_gt = _random_poses(60, seed)
    T_est = perturb_poses(T_gt, 0.03, 0.2, np.random.default_rng(seed + 10))
    A = np.eye(4)
    A[:3, :3] = Rotation.random(random_state=seed + 20).as_matrix()
    A[:3, 3] = [5.0, -3.0, 2.0]
    T_est = A @ T_est
    T_est[:, :3, 3] *= 1.3 if align == "sim3" else 1.0
    result = evaluate(Trajectory(T_gt), Trajectory(T_est), align=align)
    assert_equal_to_evo(result, evo_metrics(T_gt, T_est, align))
    assert result["pairing"] == "index" and np.asarray(result["alignment"]).shape == (4, 4)
    if align == "sim3":
        assert result["scale"] == pytest.approx(1 / 1.3, rel=0.05)


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_evaluate_equals_evo_tum_timestamps(align):
    rng = np.random.default_rng(4)
    T_gt = _random_poses(80, 4)
    stamps_gt = 1000.0 + 0.1 * np.arange(80)
    keep = np.sort(rng.choice(80, 50, replace=False))  # the estimate misses poses
    T_est = perturb_poses(T_gt[keep], 0.02, 0.1, rng)
    stamps_est = stamps_gt[keep] + rng.uniform(-0.004, 0.004, 50)
    stamps_est[[3, 17]] += 0.03  # two poses beyond --max-diff: unmatched
    result = evaluate(Trajectory(T_gt, stamps_gt), Trajectory(T_est, stamps_est), align=align, max_diff_s=0.01)
    assert result["pairing"] == "timestamp" and result["n_poses"] == 48
    assert_equal_to_evo(result, evo_metrics(T_gt, T_est, align, stamps_gt, stamps_est, 0.01))


def test_match_timestamps_against_brute_force():
    rng = np.random.default_rng(9)
    a = np.sort(rng.uniform(0, 10, 40))
    b = np.sort(rng.uniform(0, 10, 70))
    ia, ib = match_timestamps(a, b, 0.05)
    expected = [(i, int(np.argmin(np.abs(b - t)))) for i, t in enumerate(a) if np.min(np.abs(b - t)) <= 0.05]
    assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == expected
    ib2, ia2 = match_timestamps(b, a, 0.05)  # the shorter list drives the matching either way
    assert list(zip(ia2.tolist(), ib2.tolist(), strict=True)) == expected


def test_evaluate_perfect_estimate_is_zero():
    T = _random_poses(10, 5)
    result = evaluate(Trajectory(T), Trajectory(T.copy()), align="se3")
    assert result["ate_rmse_m"] < 1e-12 and result["rpe_rot_rmse_deg"] < 1e-5
    np.testing.assert_allclose(result["alignment"], np.eye(4), atol=1e-12)


def test_evaluate_errors():
    T = _random_poses(10, 6)
    with pytest.raises(InputError, match="10 poses but the estimate has 7"):
        evaluate(Trajectory(T), Trajectory(T[:7]))
    with pytest.raises(InputError, match="only 0 of the 10 poses .* --max-diff"):
        evaluate(Trajectory(T, np.arange(10.0)), Trajectory(T, np.arange(10.0) + 100.0))
    T_still = np.tile(np.eye(4), (5, 1, 1))
    with pytest.raises(InputError, match="no spatial extent"):
        evaluate(Trajectory(T_still), Trajectory(T_still), align="sim3")


# ---------------------------------------------------------------------------- pairing in time order


def test_unsorted_shorter_tum_estimate_is_evaluated_in_time_order(run_pa, tmp_path):
    """RPE is taken between poses consecutive in time, whatever the file order (as evo sorts)."""
    from pa_cli.io.trajectory import write_tum

    rng = np.random.default_rng(11)
    T_gt = _random_poses(40, 11)
    stamps = 100.0 + 0.1 * np.arange(40)
    keep = np.arange(3, 37)  # the estimate is shorter than the ground truth
    T_est = perturb_poses(T_gt[keep], 0.01, 0.05, rng)
    shuffle = rng.permutation(len(keep))
    write_tum(tmp_path / "gt.tum", T_gt, stamps)
    write_tum(tmp_path / "sorted.tum", T_est, stamps[keep])
    write_tum(tmp_path / "shuffled.tum", T_est[shuffle], stamps[keep][shuffle])
    reports = {}
    for name in ("sorted", "shuffled"):
        code, _, err = run_pa("eval", tmp_path / "gt.tum", tmp_path / f"{name}.tum", "--json",
                              tmp_path / f"{name}.json")
        assert code == 0, err
        reports[name] = json.loads((tmp_path / f"{name}.json").read_text())
    for key in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg", "n_poses"):
        assert reports["shuffled"][key] == pytest.approx(reports["sorted"][key], rel=1e-12), key
    ref = evo_metrics(T_gt, T_est, "se3", stamps, stamps[keep])
    assert reports["sorted"]["rpe_trans_rmse_m"] == pytest.approx(ref["rpe_trans"]["rmse"], rel=1e-9)


# ---------------------------------------------------------------------------- pairing coverage


def _tum_pair(tmp_path, n_est_paired: int) -> tuple:
    """A 40-pose TUM ground truth and a 40-pose estimate of which `n_est_paired` share its clock."""
    from pa_cli.io.trajectory import write_tum

    folder = tmp_path / f"paired_{n_est_paired}"
    folder.mkdir()
    T = _random_poses(40, 12)
    stamps = 1000.0 + 0.1 * np.arange(40)
    stamps_est = stamps.copy()
    stamps_est[n_est_paired:] += 500.0  # the rest of the estimate lies on another clock
    write_tum(folder / "gt.tum", T, stamps)
    write_tum(folder / "est.tum", perturb_poses(T, 0.01, 0.05, np.random.default_rng(1)), stamps_est)
    return folder / "gt.tum", folder / "est.tum"


def test_eval_refuses_when_fewer_than_half_of_the_poses_pair(run_pa, tmp_path):
    from pa_cli.io.trajectory import write_tum

    gt, _ = _tum_pair(tmp_path, 40)
    # The estimate's timestamps are its indices (a common mistake): 4 of 40 fall near the GT's.
    T = read_trajectory(gt).T_world_scan
    write_tum(tmp_path / "index.tum", T, 1000.0 + np.arange(40.0))
    code, out, err = run_pa("eval", gt, tmp_path / "index.tum", "--json", tmp_path / "e.json")
    assert code == 1
    assert "only 4 of the 40 poses" in err and str(gt) in err and str(tmp_path / "index.tum") in err
    assert "50%" in err and "clock" in err
    assert "Traceback" not in err and out == ""
    assert not (tmp_path / "e.json").exists()
    code, _, err = run_pa("eval", *_tum_pair(tmp_path, 19))
    assert code == 1 and "only 19 of the 40 poses" in err


def test_eval_warns_when_fewer_than_90_percent_of_the_poses_pair(run_pa, tmp_path):
    gt, est = _tum_pair(tmp_path, 30)
    code, _, err = run_pa("eval", gt, est, "--json", tmp_path / "e.json")
    assert code == 0, err
    unwrapped = "".join(err.split())  # the log handler wraps long lines
    assert "only30ofthe40poses" in unwrapped and str(est) in unwrapped and "90%" in err
    assert json.loads((tmp_path / "e.json").read_text())["n_poses"] == 30
    gt, est = _tum_pair(tmp_path, 36)  # 90 %: no warning
    code, _, err = run_pa("eval", gt, est)
    assert code == 0 and "only" not in err
    code, _, err = run_pa("eval", *_tum_pair(tmp_path, 20))  # 50 %: a warning, not an error
    assert code == 0 and "only20ofthe40poses" in "".join(err.split())


# ---------------------------------------------------------------------------- the contract with evo on files


@pytest.mark.parametrize("decimals", [9, 7])
def test_eval_of_files_against_evo_reading_the_same_files(run_pa, tmp_path, decimals):
    """pa projects each rotation block it reads onto the nearest rotation; evo uses it as written.

    Contract (README): on the poses pa evaluates (the projected ones) pa equals evo to 1e-9
    relative; against evo's reading of the same files the ATE translation still agrees to 1e-9
    (the alignment uses positions only) and the RPE translation differs by at most
    3 * deviation * (largest step of gt + est), the deviation being the largest Frobenius
    distance of a file's rotation block to a rotation.
    """
    from evo.tools import file_interface

    from pa_cli.io.trajectory import orthonormalize

    T_gt = _random_poses(60, 13)
    T_est = perturb_poses(T_gt, 0.02, 0.1, np.random.default_rng(14))
    for name, T in (("gt", T_gt), ("est", T_est)):
        np.savetxt(tmp_path / f"{name}.txt", T[:, :3, :4].reshape(-1, 12), fmt=f"%.{decimals}f")
    code, _, err = run_pa("eval", tmp_path / "gt.txt", tmp_path / "est.txt", "--json", tmp_path / "e.json")
    assert code == 0, err
    result = json.loads((tmp_path / "e.json").read_text())
    assert_equal_to_evo(result, evo_metrics(read_trajectory(tmp_path / "gt.txt").T_world_scan,
                                            read_trajectory(tmp_path / "est.txt").T_world_scan, "se3"))
    as_written = [np.array(file_interface.read_kitti_poses_file(str(tmp_path / f"{n}.txt")).poses_se3)
                  for n in ("gt", "est")]
    ref = evo_metrics(*as_written, "se3")
    deviation = max(orthonormalize(T[:, :3, :3])[1].max() for T in as_written)
    largest_steps = sum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).max() for T in as_written)
    for key in ("rmse", "mean"):
        difference = abs(result[f"rpe_trans_{key}_m"] - ref["rpe_trans"][key])
        assert difference <= 3 * deviation * largest_steps, key
    for key in ("rmse", "mean", "median", "max"):
        assert result[f"ate_{key}_m"] == pytest.approx(ref["ape_trans"][key], rel=1e-9), key
    assert deviation > (1e-9 if decimals == 7 else 0.0)  # the files' rounding is what the bound covers
