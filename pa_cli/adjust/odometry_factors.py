"""Relative-pose (odometry) factors between consecutive scans.

Planes alone leave some directions unobserved (a scan on a featureless street can slide along
it; one in a corridor along the corridor). The factors keep each consecutive pair's relative
motion near the initial trajectory's (KISS-ICP or --poses), with an uncertainty that grows with
the motion, so directions the planes constrain are decided by the planes and directions they
leave free follow the odometry.

Measurement: Z_j = T0_j^{-1} T0_{j+1}, the initial relative motion (rotation R_z, translation
t_z in scan j's frame). Residual of pair j at poses T (R, t):

    e_rot = Log(R_z^T R_j^T R_{j+1})        (3,) rad
    e_pos = R_j^T (t_{j+1} - t_j) - t_z     (3,) m, in scan j's frame

Noise: a sigma per pair and axis, sigma_j (N-1, 6), the rotation's three (rad, about scan j+1's
axes) then the translation's three (m, along scan j's axes). A motion the scans measured gets the
noise measured for the sequence's registrations (`pa_cli.refine.pair_registration.closure_sigmas`).
Otherwise (the initial trajectory's motion) the odometry model, isotropic within each block (per pair,
d = |t_z| metres travelled, theta = |Log R_z| radians turned):

    sigma_t = translation_sigma_m + translation_sigma_per_m * d                      (m)
    sigma_r = rotation_sigma + rotation_sigma_per_rad * theta + rotation_sigma_per_m * d  (rad)

The factor's cost is in the plane cost's unit (m^2): the plane cost is the sum of squared
point-to-plane distances, i.e. sigma_point^2 times the negative log-likelihood of points with noise
sigma_point, so

    cost = sigma_point^2 * sum_j sum_a e_j,a^2 / sigma_j,a^2,

sigma_point the model's `point_sigma_m`: `pa refine` sets it to the planes' measured point noise where the
motions' noise is measured (`pa_cli.adjust.noise_model.PlaneBalance`).

Derivatives for the solvers' left retraction (`common.retract_poses`: R <- Exp(w) R,
t <- Exp(w) t + rho, world frame), exact at any state:

    d e_rot / d w_{j+1} = J_r^{-1}(e_rot) R_{j+1}^T,   d e_rot / d w_j = -J_r^{-1}(e_rot) R_{j+1}^T
    d e_pos / d rho_{j+1} = R_j^T,  d e_pos / d rho_j = -R_j^T
    d e_pos / d w_{j+1} = -R_j^T [t_{j+1}]x,  d e_pos / d w_j = R_j^T [t_{j+1}]x

The gradient is exact; the Hessian is the Gauss-Newton one, 2 sigma_point^2 J^T W J (positive
semi-definite; it is exact where the residuals vanish, which is the initial trajectory).
It couples only j and j+1: block-tridiagonal. It is a pose term of `pa_cli.adjust.terms`
(name `odometry`, pose pairs (j, j+1)), so both backends add it to their systems.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.adjust.terms import TermLinearization
from pa_cli.config import PaConfig
from pa_cli.core.geometry import left_jacobian_inverse_so3, log_so3, skew

BLOCK = 6


@dataclass(frozen=True)
class OdometryModel:
    """Sigmas of a relative motion (see the module docstring); radians and metres."""

    point_sigma_m: float
    translation_sigma_m: float
    translation_sigma_per_m: float
    rotation_sigma_rad: float
    rotation_sigma_per_rad: float
    rotation_sigma_rad_per_m: float

    @classmethod
    def from_config(cls, config: PaConfig) -> OdometryModel:
        """From `refine.odometry_*` and `advanced.odometry` (degrees there, radians here)."""
        refine, odometry = config.refine, config.advanced.odometry
        return cls(point_sigma_m=odometry.point_sigma_m,
                   translation_sigma_m=refine.odometry_translation_sigma_m,
                   translation_sigma_per_m=odometry.translation_sigma_per_m,
                   rotation_sigma_rad=np.deg2rad(refine.odometry_rotation_sigma_deg),
                   rotation_sigma_per_rad=odometry.rotation_sigma_per_deg,
                   rotation_sigma_rad_per_m=np.deg2rad(odometry.rotation_sigma_deg_per_m))

    def sigmas(self, distance_m: np.ndarray, angle_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sigma_t m, sigma_r rad) per pair."""
        sigma_t = self.translation_sigma_m + self.translation_sigma_per_m * distance_m
        sigma_r = (self.rotation_sigma_rad + self.rotation_sigma_per_rad * angle_rad
                   + self.rotation_sigma_rad_per_m * distance_m)
        return sigma_t, sigma_r


def relative_motions(T_world_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative rotations R_j^T R_{j+1} (N-1, 3, 3) and translations R_j^T (t_{j+1} - t_j) (N-1, 3)."""
    R = T_world_scan[:, :3, :3]
    t = T_world_scan[:, :3, 3]
    R_rel = np.einsum("nji,njk->nik", R[:-1], R[1:])
    t_rel = np.einsum("nji,nj->ni", R[:-1], t[1:] - t[:-1])
    return R_rel, t_rel


class OdometryFactors:
    """Relative-pose factors between scans j and j+1, measured on `T0_world_scan` (N, 4, 4)."""

    name = "odometry"

    def __init__(self, T0_world_scan: np.ndarray, model: OdometryModel) -> None:
        self._measure(*relative_motions(np.asarray(T0_world_scan, dtype=np.float64)), model)

    @classmethod
    def from_motions(cls, R_z: np.ndarray, t_z: np.ndarray, model: OdometryModel,
                     sigmas: np.ndarray | None = None) -> OdometryFactors:
        """Factors measured on the relative motions R_z (N-1, 3, 3), t_z (N-1, 3) (scan j's frame, m), with
        the sigmas (N-1, 6) per pair and axis (rad, m; the module docstring), or the model's."""
        factors = cls.__new__(cls)
        factors._measure(np.asarray(R_z, dtype=np.float64), np.asarray(t_z, dtype=np.float64), model, sigmas)
        return factors

    def _measure(self, R_z: np.ndarray, t_z: np.ndarray, model: OdometryModel, sigmas: np.ndarray | None = None
                 ) -> None:
        self.n_scans = len(t_z) + 1
        self.model = model
        self.R_z, self.t_z = R_z, t_z
        if sigmas is None:
            sigmas = self.model_sigmas()
        self.sigmas = np.asarray(sigmas, dtype=np.float64)  # (N-1, 6): rad (rotation), m (translation)
        self.weights = model.point_sigma_m**2 / self.sigmas**2  # (N-1, 6), m^2 per rad^2 and per m^2

    def model_sigmas(self) -> np.ndarray:
        """(N-1, 6) the odometry model's sigmas of the measured motions (rad, m), isotropic per block."""
        sigma_t, sigma_r = self.model.sigmas(np.linalg.norm(self.t_z, axis=1),
                                             np.linalg.norm(log_so3(self.R_z), axis=1))
        return np.column_stack([np.repeat(sigma_r[:, None], 3, 1), np.repeat(sigma_t[:, None], 3, 1)])

    @property
    def sigma_r_rad(self) -> np.ndarray:
        """(N-1,) each pair's largest rotation sigma (rad)."""
        return self.sigmas[:, :3].max(axis=1)

    @property
    def sigma_t_m(self) -> np.ndarray:
        """(N-1,) each pair's largest translation sigma (m)."""
        return self.sigmas[:, 3:].max(axis=1)

    @property
    def point_sigma_m(self) -> float:
        """The point sigma (m) the weights are expressed in (weights = point_sigma^2 / sigma^2)."""
        return self.model.point_sigma_m

    def residuals(self, T_world_scan: np.ndarray) -> np.ndarray:
        """(N-1, 6): e_rot (rad), e_pos (m) of every pair."""
        R_rel, t_rel = relative_motions(T_world_scan)
        e_rot = log_so3(np.einsum("nji,njk->nik", self.R_z, R_rel))
        return np.hstack([e_rot, t_rel - self.t_z])

    def normalized_residuals(self, T_world_scan: np.ndarray) -> np.ndarray:
        """(N-1, 2): the rotation's and the translation's residual in sigmas, |e_rot / sigma_r| and
        |e_pos / sigma_t| per axis, of every pair (unitless)."""
        z = self.residuals(T_world_scan) / self.sigmas
        return np.column_stack([np.linalg.norm(z[:, :3], axis=1), np.linalg.norm(z[:, 3:], axis=1)])

    def cost(self, T_world_scan: np.ndarray) -> float:
        """sigma_point^2 sum_j e_j^T W_j e_j (m^2)."""
        e = self.residuals(T_world_scan)
        return float(np.sum(self.weights * e**2))

    def jacobians(self, T_world_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals (N-1, 6) and their Jacobians with respect to pose j and pose j+1 (N-1, 6, 6)."""
        e = self.residuals(T_world_scan)
        R = T_world_scan[:, :3, :3]
        t = T_world_scan[:, :3, 3]
        Jr_inv_RT = left_jacobian_inverse_so3(-e[:, :3]) @ R[1:].transpose(0, 2, 1)  # J_r^{-1}(e) R_{j+1}^T
        RjT = R[:-1].transpose(0, 2, 1)
        RjT_t = RjT @ skew(t[1:])
        J_next = np.zeros((len(e), 6, 6))
        J_next[:, :3, :3] = Jr_inv_RT
        J_next[:, 3:, :3] = -RjT_t
        J_next[:, 3:, 3:] = RjT
        J_prev = -J_next  # d/d(pose j) = -d/d(pose j+1) block by block
        return e, J_prev, J_next

    def pose_pairs(self) -> np.ndarray:
        """(N-1, 2): the consecutive pairs (j, j+1) whose off-diagonal blocks the factors fill."""
        j = np.arange(self.n_scans - 1, dtype=np.int64)
        return np.column_stack([j, j + 1])

    def linearize(self, T_world_scan: np.ndarray) -> TermLinearization:
        """Cost (m^2), gradient (N, 6), Gauss-Newton Hessian blocks: diagonal (N, 6, 6) and
        H[j, j+1] (N-1, 6, 6) for `pose_pairs()`."""
        e, J_prev, J_next = self.jacobians(T_world_scan)
        We, WJ_prev, WJ_next = self.weights * e, self.weights[:, :, None] * J_prev, self.weights[:, :, None] * J_next
        n_scans = len(e) + 1
        gradient = np.zeros((n_scans, BLOCK))
        gradient[:-1] += 2.0 * np.einsum("nki,nk->ni", J_prev, We)
        gradient[1:] += 2.0 * np.einsum("nki,nk->ni", J_next, We)
        diag = np.zeros((n_scans, BLOCK, BLOCK))
        diag[:-1] += 2.0 * np.einsum("nki,nkj->nij", J_prev, WJ_prev)
        diag[1:] += 2.0 * np.einsum("nki,nkj->nij", J_next, WJ_next)
        off = 2.0 * np.einsum("nki,nkj->nij", J_prev, WJ_next)
        return TermLinearization(float(np.sum(We * e)), gradient, diag, off)
