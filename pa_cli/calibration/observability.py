"""Which directions of each extrinsic the data determine, in words, and the extrinsic covariance.

Information. With H the Gauss-Newton Hessian of the calibration cost over the free base poses p
and the extrinsics e, the extrinsics' information with the poses marginalised is the Schur
complement S = H_ee - H_ep H_pp^+ H_pe (H_pp^+ the pseudo-inverse: with the odometry factors H_pp
is positive definite; without them a base-pose direction nothing constrains is dropped). LiDAR k's
own information also marginalises the other extrinsics: S_k = S_kk - S_ko S_oo^+ S_ok.

Units. Rotations are scaled by a lever arm L (`advanced.calibrate.lever_arm_m`): a rotation of x rad counts
as the L x metres it moves a point L metres away, so every direction is in metres and eigenvalues
compare. For a scaled unit direction with eigenvalue lam (the cost is a sum of squared distances,
so H = 2 J^T J), the first-order 1-sigma of the extrinsic along it is sigma_point sqrt(2 / lam)
with sigma_point = `advanced.odometry.point_sigma_m` (the effective point noise). A direction whose 1-sigma
exceeds `advanced.calibrate.unobservable_sigma_m` is unobservable: it is reported in words
("lidar1: translation along base z") and the solver holds it at its initial value. Every round
of `pa calibrate` also holds the directions its own plane association leaves weak (before the
LiDARs' planes are associated with each other, only the motion constrains an extrinsic).

Covariance. Over the observable directions (each extrinsic restricted to its basis B_k), the
covariance is 2 sigma^2 (B^T S B)^-1 mapped back by B (zero along held directions), with sigma^2
the residual variance of the plane cost (cost / (points - 3 planes - free unknowns)), as the pose
covariance of `pa_cli.adjust.covariance` (first order, independent point noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.calibration.composite import BLOCK

AXIS_NAMES = ("x", "y", "z")
AXIS_COS = np.cos(np.deg2rad(20.0))  # a direction within 20 deg of a base axis is named by that axis
MIXED_SHARE = 0.2  # a direction with at least this share (squared) in both rotation and translation names both


def pseudo_inverse(M: np.ndarray) -> np.ndarray:
    """The symmetric pseudo-inverse, eigenvalues below 1e-12 of the largest treated as zero."""
    if M.size == 0:
        return M.copy()
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    keep = lam > 1e-12 * max(float(lam.max(initial=0.0)), 1e-300)
    return (V[:, keep] / lam[keep]) @ V[:, keep].T


def marginal_information(H: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Schur complement of H onto the indices `keep` (the others marginalised)."""
    other = np.setdiff1d(np.arange(len(H)), keep)
    H_kk, H_ko, H_oo = H[np.ix_(keep, keep)], H[np.ix_(keep, other)], H[np.ix_(other, other)]
    S = H_kk - H_ko @ pseudo_inverse(H_oo) @ H_ko.T
    return 0.5 * (S + S.T)


def extrinsic_columns(n_base: int, n_lidars: int) -> np.ndarray:
    """Indices of the extrinsic unknowns in the full vector (6 N base dofs, then the extrinsics)."""
    return BLOCK * n_base + np.arange(BLOCK * (n_lidars - 1))


def free_information(H_full: np.ndarray, n_base: int) -> np.ndarray:
    """H without the gauge pose (base pose 0)."""
    keep = np.arange(BLOCK, len(H_full))
    return H_full[np.ix_(keep, keep)]


def describe_direction(direction: np.ndarray) -> str:
    """Words for a unit direction (omega scaled by the lever arm, rho) in the base frame."""
    w, r = direction[:3], direction[3:]
    share_w = float(w @ w) / max(float(direction @ direction), 1e-300)

    def axis(v: np.ndarray) -> str:
        v = v / np.linalg.norm(v)
        i = int(np.argmax(np.abs(v)))
        if abs(v[i]) >= AXIS_COS:
            return f"base {AXIS_NAMES[i]}"
        v = v * np.sign(v[i])
        return "base (" + ", ".join(f"{c:.2f}" for c in v) + ")"

    if share_w >= 1.0 - MIXED_SHARE:
        return f"rotation about {axis(w)}"
    if share_w <= MIXED_SHARE:
        return f"translation along {axis(r)}"
    return f"rotation about {axis(w)} with translation along {axis(r)}"


@dataclass
class ExtrinsicObservability:
    """One LiDAR's extrinsic: its marginal information (scaled), weakest 1-sigma, unobservable
    directions (words, each once: two weak directions may read alike) and the basis of the
    directions the solver may move (6, m)."""

    lidar: int
    eigenvalues: np.ndarray  # (6,) ascending, of the scaled information
    sigma_m: np.ndarray  # (6,) predicted 1-sigma along each eigenvector (m; rotations at the lever arm)
    unobservable: list[str]
    basis: np.ndarray  # (6, m) in (omega rad, rho m)

    def as_dict(self) -> dict:
        return {"lidar": self.lidar, "eigenvalues": self.eigenvalues.tolist(),
                "sigma_m": [float(s) for s in self.sigma_m], "unobservable": self.unobservable}


def analyse_extrinsics(H_gn_full: np.ndarray, n_base: int, n_lidars: int, lever_arm_m: float,
                       point_sigma_m: float, unobservable_sigma_m: float,
                       bases: list[np.ndarray] | None = None) -> list[ExtrinsicObservability]:
    """Observability of every extrinsic (lidar1..) from the full Gauss-Newton Hessian. With `bases`
    (per extrinsic, the directions it may still move, 6 x m_k), only those directions are
    analysed and the returned bases are within them."""
    H = free_information(H_gn_full, n_base)
    ext = extrinsic_columns(n_base, n_lidars) - BLOCK
    S = marginal_information(H, ext)
    scale = np.r_[np.full(3, 1.0 / lever_arm_m), np.ones(3)]  # eps = scale * (scaled coordinates)
    out = []
    for k in range(1, n_lidars):
        own = BLOCK * (k - 1) + np.arange(BLOCK)
        S_k = marginal_information(S, own) * np.outer(scale, scale)
        B = np.eye(BLOCK) if bases is None else bases[k - 1]
        Q = np.linalg.qr(B / scale[:, None])[0] if B.shape[1] else np.zeros((BLOCK, 0))  # scaled, orthonormal
        lam, V = np.linalg.eigh(Q.T @ S_k @ Q)
        V = Q @ V
        with np.errstate(divide="ignore"):
            sigma = np.where(lam > 0, point_sigma_m * np.sqrt(2.0 / np.where(lam > 0, lam, 1.0)), np.inf)
        weak = sigma > unobservable_sigma_m
        words = list(dict.fromkeys(f"lidar{k}: {describe_direction(V[:, i])}" for i in np.flatnonzero(weak)))
        out.append(ExtrinsicObservability(k, lam, sigma, words, scale[:, None] * V[:, ~weak]))
    return out


def extrinsic_covariance(H_gn_full: np.ndarray, n_base: int, n_lidars: int, bases: list[np.ndarray],
                         residual_variance_m2: float) -> np.ndarray:
    """(K - 1, 6, 6) covariance of each extrinsic step (omega rad, rho m; base frame) over its
    observable directions (zero along held ones): 2 sigma^2 B (B^T S B)^-1 B^T."""
    H = free_information(H_gn_full, n_base)
    S = marginal_information(H, extrinsic_columns(n_base, n_lidars) - BLOCK)
    m = [B.shape[1] for B in bases]
    B_all = np.zeros((BLOCK * len(bases), sum(m)))
    col = 0
    for k, B in enumerate(bases):
        B_all[BLOCK * k:BLOCK * (k + 1), col:col + B.shape[1]] = B
        col += B.shape[1]
    cov = 2.0 * residual_variance_m2 * B_all @ np.linalg.pinv(B_all.T @ S @ B_all, hermitian=True) @ B_all.T
    return np.stack([cov[BLOCK * k:BLOCK * (k + 1), BLOCK * k:BLOCK * (k + 1)] for k in range(len(bases))]) \
        if bases else np.empty((0, BLOCK, BLOCK))
