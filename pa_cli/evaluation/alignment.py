"""Alignment of an estimated trajectory onto the ground truth (Umeyama; se3, sim3, origin, none).

The alignment A (4x4, with scale s for sim3) maps the estimate onto the ground truth:
t_est' = s R_A t_est + t_A, R_est' = R_A R_est.

se3 and sim3 fit the positions only (Umeyama), as evo does. On a path that is nearly a straight
line the positions fix the rotation's two axes across the line but not the turn about it: that
turn is fitted to the positions' small sideways deviations, and where those are no larger than
the position errors (noise, drift) it follows the errors, so the estimate's orientations are
rotated about the path by an arbitrary angle (up to 180 deg) and the rotation ATE measures that
angle, not the estimate (`rotation_alignment_note` says when). Translation ATE is hardly
affected (the sideways deviations are small) and RPE not at all (it does not depend on A).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from pa_cli.errors import InputError

AlignMode = Literal["se3", "sim3", "origin", "none"]
ALIGN_MODES = ("se3", "sim3", "origin", "none")
# The turn of a position-only alignment about a nearly straight path is known to about
# atan(position error / sideways spread of the path); above this ratio (tan 10 deg) the rotation
# ATE is not a property of the estimate.
MAX_ERROR_TO_SPREAD = float(np.tan(np.radians(10.0)))


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


def rotation_alignment_note(positions_gt_m: np.ndarray, ate_rmse_m: float, align: AlignMode) -> str | None:
    """Why the rotation ATE after a se3/sim3 alignment is meaningless for this path, or None.

    `positions_gt_m`: (N, 3) paired ground-truth positions; `ate_rmse_m`: the translation ATE. The
    path's spread across its main direction is the second standard deviation of the positions
    (principal axes); when the position error exceeds MAX_ERROR_TO_SPREAD times it, the turn of the
    alignment about the path is set by the errors (see the module docstring).
    """
    if align not in ("se3", "sim3"):
        return None
    centred = np.asarray(positions_gt_m, dtype=np.float64) - np.mean(positions_gt_m, axis=0)
    along_m, across_m = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / len(centred))[::-1][:2], 0.0))
    if ate_rmse_m <= MAX_ERROR_TO_SPREAD * across_m and across_m > 1e-9 * max(along_m, 1.0):
        return None
    return (f"the rotation ATE is meaningless for this path: the ground truth is nearly a straight line "
            f"({along_m:.3g} m spread along it, {across_m:.3g} m across), and the {align} alignment fits positions "
            f"only, so its turn about the line is set by the position errors (ATE {ate_rmse_m:.3g} m), not by the "
            "path. Use --align origin (the first poses aligned, rotation included) or read the RPE rotation.")
