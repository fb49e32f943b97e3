"""ATE and RPE of an estimated trajectory against the ground truth, after alignment.

Poses are T_world_scan (N, 4, 4): they map scan-frame points into the world, metres.
Angles are radians inside; only the metric names ending in `_deg` are in degrees.

Metric definitions (the same as evo's `evo_ape` / `evo_rpe`, so the numbers can be compared):

- ATE translation error of pose k: ||t_gt(k) - t_est'(k)|| with t_est' the aligned estimate
  (see `alignment`); rotation error: the angle of R_gt(k)^T R_est'(k).
- RPE between consecutive paired poses k, k+1 (in time order): E = (T_gt(k)^-1
  T_gt(k+1))^-1 (T_est'(k)^-1 T_est'(k+1)); translation error ||t_E||, rotation error angle(R_E).
"""

from __future__ import annotations

import numpy as np

from pa_cli.core.geometry import rigid_inverse, rotation_angles
from pa_cli.evaluation.alignment import ALIGN_MODES, AlignMode, alignment_transform, apply_alignment
from pa_cli.evaluation.association import pair_trajectories
from pa_cli.io.trajectory import Trajectory


def _stats(errors: np.ndarray) -> dict[str, float]:
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "mean": float(np.mean(errors)),
        "median": float(np.median(errors)),
        "max": float(np.max(errors)),
        "min": float(np.min(errors)),
        "std": float(np.std(errors)),
    }


def evaluate(gt: Trajectory, est: Trajectory, align: AlignMode = "se3", max_diff_s: float = 0.01
             ) -> dict:
    """ATE and RPE of `est` against `gt` after alignment; see the module docstring for definitions.

    Pairing: `association.pair_trajectories` (by timestamp within `max_diff_s` seconds when both
    trajectories have timestamps, in time order; otherwise by index). Returns a dict with
    `ate_rmse_m`, `ate_mean_m`, `ate_median_m`, `ate_max_m`, `ate_std_m`, `ate_rot_rmse_deg`,
    `ate_rot_mean_deg`, `rpe_trans_rmse_m`, `rpe_trans_mean_m`, `rpe_rot_rmse_deg`,
    `rpe_rot_mean_deg`, `alignment` (4x4 nested list), `scale`, `align`, `pairing`, `n_poses`,
    `n_gt`, `n_est`.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGN_MODES}")
    n_gt, n_est = len(gt), len(est)
    min_pairs = 3 if align in ("se3", "sim3") else 2
    i_gt, i_est, pairing = pair_trajectories(gt, est, max_diff_s, min_pairs)
    T_gt = gt.T_world_scan[i_gt]
    T_est = est.T_world_scan[i_est]
    A, s = alignment_transform(T_gt, T_est, align)
    T_al = apply_alignment(T_est, A, s)

    ate_trans = np.linalg.norm(T_gt[:, :3, 3] - T_al[:, :3, 3], axis=1)
    ate_rot_deg = np.rad2deg(rotation_angles(T_gt[:, :3, :3].transpose(0, 2, 1) @ T_al[:, :3, :3]))
    rel_gt = rigid_inverse(T_gt[:-1]) @ T_gt[1:]
    rel_est = rigid_inverse(T_al[:-1]) @ T_al[1:]
    E = rigid_inverse(rel_gt) @ rel_est
    rpe_trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rpe_rot_deg = np.rad2deg(rotation_angles(E[:, :3, :3]))

    ate, ate_r = _stats(ate_trans), _stats(ate_rot_deg)
    rpe_t, rpe_r = _stats(rpe_trans), _stats(rpe_rot_deg)
    return {
        "ate_rmse_m": ate["rmse"],
        "ate_mean_m": ate["mean"],
        "ate_median_m": ate["median"],
        "ate_max_m": ate["max"],
        "ate_std_m": ate["std"],
        "ate_rot_rmse_deg": ate_r["rmse"],
        "ate_rot_mean_deg": ate_r["mean"],
        "ate_rot_max_deg": ate_r["max"],
        "rpe_trans_rmse_m": rpe_t["rmse"],
        "rpe_trans_mean_m": rpe_t["mean"],
        "rpe_trans_max_m": rpe_t["max"],
        "rpe_rot_rmse_deg": rpe_r["rmse"],
        "rpe_rot_mean_deg": rpe_r["mean"],
        "rpe_rot_max_deg": rpe_r["max"],
        "alignment": A.tolist(),
        "scale": float(s),
        "align": align,
        "pairing": pairing,
        "max_diff_s": float(max_diff_s) if pairing == "timestamp" else None,
        "n_poses": int(len(i_gt)),
        "n_gt": int(n_gt),
        "n_est": int(n_est),
    }
