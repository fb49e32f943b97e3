"""Rigid-body geometry: SO(3)/SE(3) maps, the solvers' pose retraction and small helpers.

Conventions: rotation vectors omega in radians, translations in metres, poses T_world_scan as
(N, 4, 4) homogeneous matrices. Every function is vectorised over a leading axis.

Retraction (used by every solver in `pa_cli.adjust`): a step delta_j = (omega_j, rho_j) of pose j,
both expressed in the WORLD frame, acts on the left:

    T_world_scan_j  <-  [[Exp(omega_j), rho_j], [0, 1]] @ T_world_scan_j
    i.e.  R_j <- Exp(omega_j) R_j,   t_j <- Exp(omega_j) t_j + rho_j,

so a world point q of scan j moves to Exp(omega_j) q + rho_j (`retract_left`). The solvers'
derivatives are derivatives with respect to it at delta = 0.
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE_RAD2 = 1e-12  # theta^2 below this: Taylor series in Exp (no division by ~0)
SMALL_ANGLE_RAD = 1e-5  # theta below this: Taylor series in J_l^{-1} (1/theta^2 cancels badly)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: skew(a) @ b = a x b."""
    v = np.asarray(v, dtype=np.float64)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -v[..., 2], v[..., 1]
    K[..., 1, 0], K[..., 1, 2] = v[..., 2], -v[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -v[..., 1], v[..., 0]
    return K


def exp_so3(omega: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors omega (N, 3) in radians (Rodrigues)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta2 = np.einsum("ni,ni->n", omega, omega)
    theta = np.sqrt(theta2)
    small = theta2 < SMALL_ANGLE_RAD2
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(omega)
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) in radians, |omega| <= pi, of rotation matrices (N, 3, 3)."""
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    return Rotation.from_matrix(R).as_rotvec()


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """Rotation angles |Log(R)| (N,) in radians of (N, 3, 3) rotation matrices."""
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    return Rotation.from_matrix(R).magnitude()


def left_jacobian_inverse_so3(phi: np.ndarray) -> np.ndarray:
    """J_l^{-1}(phi) (N, 3, 3) of rotation vectors phi (N, 3) in radians."""
    theta2 = np.einsum("ni,ni->n", phi, phi)
    theta = np.sqrt(theta2)
    small = theta < SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, theta)
    c = np.where(small, 1.0 / 12.0 + theta2 / 720.0,
                 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    K = skew(phi)
    return np.eye(3) - 0.5 * K + c[:, None, None] * (K @ K)


def retract_left(T_world_scan: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply steps delta (N, 6) = (omega rad, rho m), world frame, on the left of poses (N, 4, 4).

    Returns new T_world_scan with R <- Exp(omega) R and t <- Exp(omega) t + rho.
    """
    delta = np.asarray(delta, dtype=np.float64)
    R_delta = exp_so3(delta[:, :3])
    T_new = np.array(T_world_scan, dtype=np.float64, copy=True)
    T_new[:, :3, :3] = R_delta @ T_world_scan[:, :3, :3]
    T_new[:, :3, 3] = np.einsum("nij,nj->ni", R_delta, T_world_scan[:, :3, 3]) + delta[:, 3:]
    return T_new


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverses (N, 4, 4) of rigid transforms (N, 4, 4): [[R^T, -R^T t], [0, 1]]."""
    inv = np.tile(np.eye(4), (len(T), 1, 1))
    Rt = T[:, :3, :3].transpose(0, 2, 1)
    inv[:, :3, :3] = Rt
    inv[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    return inv


def transform_points(T_target_source: np.ndarray, points_source: np.ndarray) -> np.ndarray:
    """(M, 3) points R p + t in the target frame of (M, 3) points in the source frame (m).

    Written as nine scaled column sums rather than a (M, 3) @ (3, 3) product: BLAS threads add
    overhead without gain for an inner dimension of 3 (measured 10-100x slower for 100k points).
    """
    p = np.asarray(points_source, dtype=np.float64)
    out = np.empty((len(p), 3))
    for i in range(3):  # the three output coordinates (fixed count, not a data loop)
        R_i, t_i = T_target_source[i, :3], T_target_source[i, 3]
        out[:, i] = p[:, 0] * R_i[0] + p[:, 1] * R_i[1] + p[:, 2] * R_i[2] + t_i
    return out


def orthonormalize(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest rotations (SVD projection) of (N, 3, 3) matrices and the Frobenius deviations."""
    U, _, Vt = np.linalg.svd(R)
    D = np.ones(R.shape[:-1])
    D[:, -1] = np.sign(np.linalg.det(U @ Vt))
    R_ortho = (U * D[:, None, :]) @ Vt
    return R_ortho, np.linalg.norm(R - R_ortho, axis=(1, 2))


def tangent_basis(normals: np.ndarray) -> np.ndarray:
    """(P, 3) unit normals -> (P, 3, 2) orthonormal bases [b1, b2] of their tangent planes.

    Deterministic in n (the same n always gives the same basis): b1 = n x h / |n x h| with h the
    x axis (the y axis when |n_x| >= 0.9), b2 = n x b1.
    """
    helper = np.zeros_like(normals)
    use_x = np.abs(normals[:, 0]) < 0.9
    helper[use_x, 0] = 1.0
    helper[~use_x, 1] = 1.0
    b1 = np.cross(normals, helper)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(normals, b1)
    return np.stack([b1, b2], axis=-1)


def pose_change(T_before: np.ndarray, T_after: np.ndarray) -> tuple[float, float]:
    """Largest translation change (m) and rotation change (deg) between two (N, 4, 4) pose sets."""
    dt_m = np.linalg.norm(T_after[:, :3, 3] - T_before[:, :3, 3], axis=1)
    R_rel = np.einsum("nji,njk->nik", T_before[:, :3, :3], T_after[:, :3, :3])
    return float(dt_m.max(initial=0.0)), float(np.degrees(rotation_angles(R_rel)).max(initial=0.0))
