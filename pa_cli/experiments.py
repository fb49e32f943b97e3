"""Experiments: the pose perturbation model, trajectory alignment (Umeyama) and ATE / RPE.

Poses are T_world_scan (N, 4, 4): they map scan-frame points into the world, metres.
Angles are radians inside; only the metric names ending in `_deg` are in degrees.

Metric definitions (the same as evo's `evo_ape` / `evo_rpe`, so the numbers can be compared):

- alignment A (4x4, with scale s for sim3) maps the estimate onto the ground truth:
  t_est' = s R_A t_est + t_A, R_est' = R_A R_est.
- ATE translation error of pose k: ||t_gt(k) - t_est'(k)||; rotation error: the angle of
  R_gt(k)^T R_est'(k).
- RPE between consecutive frames k, k+1: E = (T_gt(k)^-1 T_gt(k+1))^-1 (T_est'(k)^-1 T_est'(k+1));
  translation error ||t_E||, rotation error angle(R_E).
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from pa_cli.errors import InputError
from pa_cli.geometry import rigid_inverse, rotation_angles
from pa_cli.io.trajectory import Trajectory

log = logging.getLogger(__name__)

AlignMode = Literal["se3", "sim3", "origin", "none"]
ALIGN_MODES = ("se3", "sim3", "origin", "none")

# The four perturbation levels of Zhou, "Efficient Second-Order Plane Adjustment", section 5.2:
# level -> (sigma_rot_deg, sigma_trans_m).
PERTURBATION_LEVELS: dict[int, tuple[float, float]] = {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


# --------------------------------------------------------------------------------------------
# perturbation
# --------------------------------------------------------------------------------------------


def perturb_poses(T_world_scan: np.ndarray, sigma_rot_rad: float, sigma_trans_m: float,
                  rng: np.random.Generator, keep_first: bool = False) -> np.ndarray:
    """Perturb poses with the model of seed 000, section 5.2; returns new (N, 4, 4) poses.

    t <- t + N(0, sigma_trans_m^2 I) and R <- Exp(w) R with w ~ N(0, sigma_rot_rad^2 I) (a left,
    world-frame rotation perturbation). Noise is drawn for every pose (rotations first, then
    translations) so the noise of pose k does not depend on `keep_first`; with `keep_first`
    pose 0 is then restored unchanged.
    """
    if sigma_rot_rad < 0 or sigma_trans_m < 0:
        raise ValueError("perturbation sigmas must be non-negative")
    T = np.array(T_world_scan, dtype=np.float64, copy=True)
    n = len(T)
    w = rng.normal(0.0, 1.0, size=(n, 3)) * sigma_rot_rad
    dt = rng.normal(0.0, 1.0, size=(n, 3)) * sigma_trans_m
    T_out = T.copy()
    T_out[:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ T[:, :3, :3]
    T_out[:, :3, 3] = T[:, :3, 3] + dt
    if keep_first and n:
        T_out[0] = T[0]
    return T_out


# --------------------------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------------------------


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (R, t, s) with dst ~ s R src + t (Umeyama 1991, eqs. 34-42).

    `src`, `dst`: (N, 3) corresponding points. Returns R (3, 3), t (3,), s (1.0 unless
    `with_scale`). Raises `InputError` when the points are degenerate.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    n = len(src)
    mu_src = src.mean(axis=0)
    mu_dst = dst.mean(axis=0)
    src_c = src - mu_src
    dst_c = dst - mu_dst
    var_src = float((src_c**2).sum() / n)
    cov = dst_c.T @ src_c / n  # Sigma_xy of the paper, x = dst, y = src
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    if with_scale:
        if var_src <= np.finfo(float).tiny:
            raise InputError("sim3 alignment: the estimated trajectory has no spatial extent, so its "
                             "scale is undefined; use --align se3, origin or none.")
        s = float(np.trace(np.diag(d) @ S) / var_src)
    else:
        s = 1.0
    t = mu_dst - s * R @ mu_src
    return R, t, s


def alignment_transform(T_gt: np.ndarray, T_est: np.ndarray, align: AlignMode
                        ) -> tuple[np.ndarray, float]:
    """The 4x4 transform A (rotation + translation) and scale s that map the estimate onto gt."""
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGN_MODES}")
    A = np.eye(4)
    s = 1.0
    if align in ("se3", "sim3"):
        R, t, s = umeyama_alignment(T_est[:, :3, 3], T_gt[:, :3, 3], with_scale=align == "sim3")
        A[:3, :3] = R
        A[:3, 3] = t
    elif align == "origin":
        A = T_gt[0] @ np.linalg.inv(T_est[0])
    return A, s


def apply_alignment(T_est: np.ndarray, A: np.ndarray, s: float = 1.0) -> np.ndarray:
    """Poses A * (scaled T_est): t' = s R_A t + t_A, R' = R_A R."""
    T = np.array(T_est, dtype=np.float64, copy=True)
    T[:, :3, 3] *= s
    return A @ T


# --------------------------------------------------------------------------------------------
# association and metrics
# --------------------------------------------------------------------------------------------


def match_timestamps(stamps_a: np.ndarray, stamps_b: np.ndarray, max_diff_s: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Pair each stamp of the shorter list with its nearest stamp in the other, within max_diff_s.

    Returns index arrays (ia, ib) into `stamps_a` and `stamps_b`.
    """
    a = np.asarray(stamps_a, dtype=np.float64)
    b = np.asarray(stamps_b, dtype=np.float64)
    swap = len(b) < len(a)
    short, long_ = (b, a) if swap else (a, b)
    order = np.argsort(long_, kind="stable")
    sorted_long = long_[order]
    pos = np.searchsorted(sorted_long, short)
    lo = np.clip(pos - 1, 0, len(long_) - 1)
    hi = np.clip(pos, 0, len(long_) - 1)
    d_lo = np.abs(sorted_long[lo] - short)
    d_hi = np.abs(sorted_long[hi] - short)
    best = np.where(d_hi < d_lo, hi, lo)
    diff = np.minimum(d_lo, d_hi)
    ok = diff <= max_diff_s
    i_short = np.flatnonzero(ok)
    i_long = order[best[ok]]
    return (i_long, i_short) if swap else (i_short, i_long)


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

    Pairing: by timestamp (nearest within `max_diff_s` seconds) when both trajectories have
    timestamps, otherwise by index (then both must have the same length). Returns a dict with
    `ate_rmse_m`, `ate_mean_m`, `ate_median_m`, `ate_max_m`, `ate_std_m`, `ate_rot_rmse_deg`,
    `ate_rot_mean_deg`, `rpe_trans_rmse_m`, `rpe_trans_mean_m`, `rpe_rot_rmse_deg`,
    `rpe_rot_mean_deg`, `alignment` (4x4 nested list), `scale`, `align`, `pairing`, `n_poses`,
    `n_gt`, `n_est`.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown alignment {align!r}; expected one of {ALIGN_MODES}")
    n_gt, n_est = len(gt), len(est)
    min_pairs = 3 if align in ("se3", "sim3") else 2
    if gt.timestamps is not None and est.timestamps is not None:
        pairing = "timestamp"
        i_gt, i_est = match_timestamps(gt.timestamps, est.timestamps, max_diff_s)
        if len(i_gt) < min_pairs:
            raise InputError(
                f"only {len(i_gt)} poses of the ground truth ({n_gt} poses) and the estimate ({n_est} "
                f"poses) have timestamps within {max_diff_s} s of each other; at least {min_pairs} "
                "are needed. Check that both use the same clock, or raise --max-diff."
            )
    else:
        pairing = "index"
        if n_gt != n_est:
            raise InputError(
                f"the ground truth has {n_gt} poses but the estimate has {n_est}; without timestamps "
                "on both (TUM files) poses are paired by index, so the lengths must be equal."
            )
        if n_gt < min_pairs:
            raise InputError(f"trajectories have {n_gt} poses; at least {min_pairs} are needed "
                             f"for --align {align}.")
        i_gt = i_est = np.arange(n_gt)
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
