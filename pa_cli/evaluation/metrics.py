"""ATE and RPE of an estimated trajectory against the ground truth, after alignment.

Poses are T_world_scan (N, 4, 4): they map scan-frame points into the world, metres.
Angles are radians inside; only the metric names ending in `_deg` are in degrees.

Metric definitions (the same as evo's `evo_ape` / `evo_rpe`, so the numbers can be compared):

- ATE translation error of pose k: ||t_gt(k) - t_est'(k)|| with t_est' the aligned estimate
  (see `alignment`); rotation error: the angle of R_gt(k)^T R_est'(k).
- RPE between consecutive paired poses k, k+1 (in time order): E = (T_gt(k)^-1
  T_gt(k+1))^-1 (T_est'(k)^-1 T_est'(k+1)); translation error ||t_E||, rotation error angle(R_E).

`pose_errors` gives the errors of each paired pose (for plots), `evaluate` their statistics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.core.geometry import rigid_inverse, rotation_angles
from pa_cli.evaluation.alignment import (
    ALIGN_MODES,
    AlignMode,
    alignment_transform,
    apply_alignment,
    rotation_alignment_note,
)
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


@dataclass
class PoseErrors:
    """The paired poses of two trajectories after alignment and the ATE of each.

    `i_gt`, `i_est`: (M,) indices of the paired poses (time order); `pairing`: "timestamp" or
    "index"; `alignment` (4, 4) and `scale` (`alignment.alignment_transform`); `T_gt`, `T_aligned`:
    (M, 4, 4) the paired ground-truth poses and aligned estimate; `trans_m`, `rot_deg`: (M,)
    translation and rotation error of each pair.
    """

    i_gt: np.ndarray
    i_est: np.ndarray
    pairing: str
    alignment: np.ndarray
    scale: float
    T_gt: np.ndarray
    T_aligned: np.ndarray
    trans_m: np.ndarray
    rot_deg: np.ndarray


def pose_errors(gt: Trajectory, est: Trajectory, align: AlignMode = "se3", max_diff_s: float = 0.01) -> PoseErrors:
    """Pair `est` with `gt` (`association.pair_trajectories`), align it, and the ATE of each pair."""
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGN_MODES}")
    min_pairs = 3 if align in ("se3", "sim3") else 2
    i_gt, i_est, pairing = pair_trajectories(gt, est, max_diff_s, min_pairs)
    T_gt = gt.T_world_scan[i_gt]
    A, s = alignment_transform(T_gt, est.T_world_scan[i_est], align)
    T_al = apply_alignment(est.T_world_scan[i_est], A, s)
    trans_m = np.linalg.norm(T_gt[:, :3, 3] - T_al[:, :3, 3], axis=1)
    rot_deg = np.rad2deg(rotation_angles(T_gt[:, :3, :3].transpose(0, 2, 1) @ T_al[:, :3, :3]))
    return PoseErrors(i_gt, i_est, pairing, A, float(s), T_gt, T_al, trans_m, rot_deg)


def evaluate(gt: Trajectory, est: Trajectory, align: AlignMode = "se3", max_diff_s: float = 0.01
             ) -> dict:
    """ATE and RPE of `est` against `gt` after alignment; see the module docstring for definitions.

    Pairing: `association.pair_trajectories` (by timestamp within `max_diff_s` seconds when both
    trajectories have timestamps, in time order; otherwise by index). Returns a dict with
    `ate_rmse_m`, `ate_mean_m`, `ate_median_m`, `ate_max_m`, `ate_std_m`, `ate_rot_rmse_deg`,
    `ate_rot_mean_deg`, `rpe_trans_rmse_m`, `rpe_trans_mean_m`, `rpe_rot_rmse_deg`,
    `rpe_rot_mean_deg`, `alignment` (4x4 nested list), `scale`, `align`, `pairing`, `n_poses`,
    `n_gt`, `n_est`, and `ate_rot_note`: why the rotation ATE is meaningless for this path
    (`alignment.rotation_alignment_note`) or None.
    """
    errors = pose_errors(gt, est, align, max_diff_s)
    T_gt, T_al = errors.T_gt, errors.T_aligned
    ate_trans, ate_rot_deg = errors.trans_m, errors.rot_deg
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
        "ate_rot_note": rotation_alignment_note(T_gt[:, :3, 3], ate["rmse"], align),
        "alignment": errors.alignment.tolist(),
        "scale": errors.scale,
        "align": align,
        "pairing": errors.pairing,
        "max_diff_s": float(max_diff_s) if errors.pairing == "timestamp" else None,
        "n_poses": int(len(errors.i_gt)),
        "n_gt": len(gt),
        "n_est": len(est),
    }
