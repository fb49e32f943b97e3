"""A weak prior that holds poses near their initial (odometry) values.

Planes alone leave some directions unobserved: a scan that sees only the walls, floor and ceiling
of a corridor can slide along it at no cost, and the solver would then wander along such
directions with round-off. `pa refine` therefore adds, per free pose j,

    prior_j = sigma_point^2 * ( |t_j - t0_j|^2 / sigma_t^2 + |Log(R_j R0_j^T)|^2 / sigma_rot^2 )

to the plane cost (m^2), with T0 the initial poses. With sigma_t of the order of the odometry
drift (metres) and sigma_point of the point noise (centimetres) its weight is ~1e-4 of one
point's, so it changes nothing the planes do constrain and pins only what they do not.

Derivatives are with respect to the solvers' left retraction (`pa_cli.geometry.retract_left`): for a step
(omega, rho), e_rot <- Log(Exp(omega) R R0^T) and e_pos <- Exp(omega) t + rho - t0, so
d e_rot / d omega = J_l^{-1}(e_rot), d e_pos / d omega = -[t]x, d e_pos / d rho = I. The
gradient is exact; the Hessian is the Gauss-Newton one (positive semi-definite). It is a pose
term of `pa_cli.adjust.terms` with diagonal blocks only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.adjust.terms import TermLinearization, no_pairs
from pa_cli.geometry import left_jacobian_inverse_so3, log_so3, skew


@dataclass
class PosePrior:
    """Weak pull of poses T_world_scan towards T0 (N, 4, 4); weights in m^2 per m^2 and per rad^2."""

    T0_world_scan: np.ndarray
    weight_translation: float
    weight_rotation: float
    name: str = "prior"

    @classmethod
    def from_sigmas(cls, T0_world_scan: np.ndarray, sigma_point_m: float, sigma_translation_m: float,
                    sigma_rotation_rad: float) -> PosePrior:
        """Weights sigma_point^2 / sigma_t^2 and sigma_point^2 / sigma_rot^2 (m, m, rad)."""
        return cls(np.asarray(T0_world_scan, dtype=np.float64), (sigma_point_m / sigma_translation_m) ** 2,
                   (sigma_point_m / sigma_rotation_rad) ** 2)

    def residuals(self, T_world_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation errors Log(R R0^T) (N, 3) in rad and position errors t - t0 (N, 3) in m."""
        R_err = T_world_scan[:, :3, :3] @ self.T0_world_scan[:, :3, :3].transpose(0, 2, 1)
        e_rot = log_so3(R_err)
        e_pos = T_world_scan[:, :3, 3] - self.T0_world_scan[:, :3, 3]
        return e_rot, e_pos

    def pose_pairs(self) -> np.ndarray:
        """No pose pairs: the prior's Hessian is block diagonal."""
        return no_pairs()

    def cost(self, T_world_scan: np.ndarray) -> float:
        """Prior cost (m^2) at poses (N, 4, 4)."""
        e_rot, e_pos = self.residuals(T_world_scan)
        return float(self.weight_rotation * np.sum(e_rot**2) + self.weight_translation * np.sum(e_pos**2))

    def linearize(self, T_world_scan: np.ndarray) -> TermLinearization:
        """Cost, gradient (N, 6) and Gauss-Newton Hessian blocks (N, 6, 6) for steps (omega, rho)."""
        e_rot, e_pos = self.residuals(T_world_scan)
        n = len(e_rot)
        J = np.zeros((n, 6, 6))  # rows: e_rot, e_pos; columns: omega, rho
        J[:, :3, :3] = left_jacobian_inverse_so3(e_rot)
        J[:, 3:, :3] = -skew(T_world_scan[:, :3, 3])
        J[:, 3:, 3:] = np.eye(3)
        w = np.array([self.weight_rotation] * 3 + [self.weight_translation] * 3)
        e = np.hstack([e_rot, e_pos])
        cost = float(np.sum(w * e**2))
        gradient = 2.0 * np.einsum("nki,nk->ni", J, w * e)
        hessian = 2.0 * np.einsum("nki,k,nkj->nij", J, w, J)
        return TermLinearization(cost, gradient, hessian, np.empty((0, 6, 6)))
