"""Derivatives of one observation's squared distances along one unit normal of its feature.

Both feature costs are sums of such terms at the feature's optimum: a plane's cost is the sum
of squared distances along its normal u_1 (lambda_min), an edge's the sum along the two normals
u_1, u_2 across its line (lambda_min + lambda_mid). For one normal n of feature i (world frame,
through the feature centroid c) and observation o of scan j with world points q_k
(k = 1..N_o), r_k = n . (q_k - c). With pose j perturbed by the left retraction (omega rad,
rho m), this module gives, per observation (vectorised over observations):

- the gradient of sum_k r_k^2: [2 a x n, 2 s n], a = sum_k r_k q_k, s = sum_k r_k;
- the block A (6x6) of its Hessian with the feature held fixed (and its Gauss-Newton part);
- the coupling rows b = q^T (dC) pi of the eliminated feature directions: a tangent m of the
  normal (the normal turning towards m about the centroid, q = [m; -m.c]) and the offset of the
  normal (q = [0; 1]).

The feature costs (`newton.PlaneCost`, `edges.EdgeCost`) weigh each coupling row by
sqrt(2 / curvature of the feature in that direction) and subtract their outer products (the
derivation is in `newton`'s module docstring).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pa_cli.core.clusters import central_moments, plane_starts
from pa_cli.core.problem import FeatureProblem


class ClusterCost:
    """What a feature cost precomputes once per problem: the scan-frame central moments of the
    clusters, each feature's observation offsets (observations sorted by feature) and the sum of
    per-observation arrays over each scan's observations (`scan_sum`)."""

    def __init__(self, problem: FeatureProblem, eigen_gap_tolerance: float = 1e-6):
        self.problem = problem
        self.eigen_gap_tolerance = eigen_gap_tolerance
        self.starts = plane_starts(problem.plane_index, problem.n_planes)
        self.moments = central_moments(problem.clusters)
        self.scan_sum = ScanSum(problem.scan_index, problem.n_scans)


class ScanSum:
    """Sums (n_scans, ...) of per-observation arrays (O, ...) over each scan's observations, in
    observation order (as `np.add.at` adds them, to the last bit), by one sparse product: a pass
    over the observations instead of one per entry of the arrays."""

    def __init__(self, scan_index: np.ndarray, n_scans: int):
        n_obs = len(scan_index)
        self.matrix = sp.csr_matrix((np.ones(n_obs), (np.asarray(scan_index), np.arange(n_obs))),
                                    shape=(int(n_scans), n_obs))

    def __call__(self, per_observation: np.ndarray) -> np.ndarray:
        flat = per_observation.reshape(len(per_observation), int(np.prod(per_observation.shape[1:])))
        return np.asarray(self.matrix @ flat).reshape(self.matrix.shape[0], *per_observation.shape[1:])


@dataclass
class NormalTerms:
    """Per-observation sums of one normal n (O, 3): a = sum_k r_k q_k (O, 3) m^2, s = sum_k r_k (O,)
    m, with the observation's world scatter S_o (O, 3, 3) m^2, centroid c_o (O, 3) m, offset of
    c_o from the feature centroid dc (O, 3) m and point count N_o (O,)."""

    n: np.ndarray
    a: np.ndarray
    s: np.ndarray
    S_o: np.ndarray
    c_o: np.ndarray
    dc: np.ndarray
    N_o: np.ndarray

    @classmethod
    def build(cls, n: np.ndarray, S_o: np.ndarray, c_o: np.ndarray, dc: np.ndarray, N_o: np.ndarray
              ) -> NormalTerms:
        s = N_o * np.einsum("oi,oi->o", n, dc)  # N_o times the mean signed distance (m)
        a = np.einsum("oij,oj->oi", S_o, n) + s[:, None] * c_o
        return cls(n, a, s, S_o, c_o, dc, N_o)

    def gradient(self) -> np.ndarray:
        """(O, 6) gradient of sum_k r_k^2 with respect to the observing pose (omega, rho)."""
        return np.concatenate([2.0 * _cross(self.a, self.n), 2.0 * self.s[:, None] * self.n], axis=1)

    def blocks(self, out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(O, 6, 6) Hessian blocks with the feature fixed: exact and Gauss-Newton (PSD), in new
        arrays or in `out` (two (O, 6, 6) float64 arrays or views)."""
        n, a = self.n, self.a
        A, A_gn = out if out is not None else (np.empty((len(n), 6, 6)), np.empty((len(n), 6, 6)))
        self.gauss_newton_blocks(A_gn)
        na = np.einsum("oi,oi->o", n, a)
        A[:, :3, :3] = (A_gn[:, :3, :3] + n[:, :, None] * a[:, None, :] + a[:, :, None] * n[:, None, :]
                        - 2.0 * na[:, None, None] * np.eye(3))  # plus the sum_k r_k d^2 r_k term
        A[:, :3, 3:] = A_gn[:, :3, 3:]
        A[:, 3:] = A_gn[:, 3:]
        return A, A_gn

    def gauss_newton_blocks(self, out: np.ndarray | None = None) -> np.ndarray:
        """(O, 6, 6) Gauss-Newton (PSD) Hessian blocks with the feature fixed (in `out` when given)."""
        n, c_o, N_o = self.n, self.c_o, self.N_o
        P = self.S_o + N_o[:, None, None] * c_o[:, :, None] * c_o[:, None, :]  # sum_k q_k q_k^T
        v = N_o[:, None] * c_o
        A_gn = np.empty((len(n), 6, 6)) if out is None else out
        A_gn[:, :3, :3] = 2.0 * _skew_congruence(n, P)
        A_gn[:, :3, 3:] = 2.0 * _cross(v, n)[:, :, None] * n[:, None, :]
        A_gn[:, 3:, :3] = A_gn[:, :3, 3:].transpose(0, 2, 1)
        A_gn[:, 3:, 3:] = 2.0 * N_o[:, None, None] * n[:, :, None] * n[:, None, :]
        return A_gn

    def tangent_row(self, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coupling rows (O, 6) of the normal turning towards the unit tangent m (O, 3): exact,
        and its Gauss-Newton part (only the sum_k (m . (q_k - c)) dr_k term)."""
        s_m = self.N_o * np.einsum("oi,oi->o", m, self.dc)  # sum_k m . (q_k - c)
        pm = np.einsum("oij,oj->oi", self.S_o, m) + s_m[:, None] * self.c_o
        gn = np.concatenate([_cross(pm, self.n), s_m[:, None] * self.n], axis=1)
        exact = gn + np.concatenate([_cross(self.a, m), self.s[:, None] * m], axis=1)
        return exact, gn

    def offset_row(self) -> np.ndarray:
        """Coupling row (O, 6) of the normal's offset: [v x n; N n], v = N_o c_o."""
        return np.concatenate([_cross(self.N_o[:, None] * self.c_o, self.n),
                               self.N_o[:, None] * self.n], axis=1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (O, 3) arrays (`np.cross` without its axis handling, which costs more than
    the products for the few thousand rows of a block of observations)."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=1)


def _skew_congruence(n: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(O, 3, 3) [n]x P [n]x^T of unit normals n (O, 3) and symmetric P (O, 3, 3), entry by entry
    (two stacked 3x3 products cost more): X = [n]x P row by row, then the six distinct entries of
    X [n]x^T (symmetric)."""
    n0, n1, n2 = n[:, 0, None], n[:, 1, None], n[:, 2, None]
    X0 = n1 * P[:, 2] - n2 * P[:, 1]  # rows of [n]x P, (O, 3)
    X1 = n2 * P[:, 0] - n0 * P[:, 2]
    X2 = n0 * P[:, 1] - n1 * P[:, 0]
    n0, n1, n2 = n0[:, 0], n1[:, 0], n2[:, 0]
    M = np.empty((len(n), 3, 3))
    M[:, 0, 0] = n1 * X0[:, 2] - n2 * X0[:, 1]
    M[:, 0, 1] = M[:, 1, 0] = n2 * X0[:, 0] - n0 * X0[:, 2]
    M[:, 0, 2] = M[:, 2, 0] = n0 * X0[:, 1] - n1 * X0[:, 0]
    M[:, 1, 1] = n2 * X1[:, 0] - n0 * X1[:, 2]
    M[:, 1, 2] = M[:, 2, 1] = n0 * X1[:, 1] - n1 * X1[:, 0]
    M[:, 2, 2] = n0 * X2[:, 1] - n1 * X2[:, 0]
    return M


def lever_origins(T_world_scan: np.ndarray, centred: bool) -> np.ndarray:
    """(N, 3) the point each scan turns about (m): its own position for `newton.retract_centred`,
    the world origin for `retract_left`. A feature cost's derivatives for scan j are those of the left
    retraction with the scan's points taken relative to this point (a point q moves by
    omega x (q - t_j) + rho to first order), so they come out in centred coordinates directly,
    with the second-order term of the change of retraction inside."""
    T_world_scan = np.asarray(T_world_scan, dtype=np.float64)
    return T_world_scan[:, :3, 3] if centred else np.zeros((len(T_world_scan), 3))


def coupling_weight(curvature: np.ndarray) -> np.ndarray:
    """sqrt(2 / curvature) where the curvature is positive, 0 elsewhere (no coupling)."""
    positive = curvature > 0
    with np.errstate(divide="ignore"):
        return np.where(positive, np.sqrt(2.0 / np.where(positive, curvature, 1.0)), 0.0)


def scan_sum(per_observation: np.ndarray, scan_index: np.ndarray, n_scans: int) -> np.ndarray:
    """Sums (n_scans, ...) of per-observation arrays (O, ...) over each scan's observations."""
    return ScanSum(scan_index, n_scans)(per_observation)


@dataclass
class FeatureLinearization:
    """Cost (m^2), per-pose gradient (N, 6) and per-observation Hessian pieces of a feature cost."""

    cost: float
    gradient: np.ndarray  # (N, 6): d cost / d (omega, rho)
    A: np.ndarray  # (O, 6, 6): block-diagonal part, per observation
    Bt: np.ndarray  # (O, R, 6): H_jk -= Bt_j^T Bt_k within a feature (and the diagonal too)
    n_guarded: int  # features whose eigen gap was clamped
    A_gn: np.ndarray  # (O, 6, 6): Gauss-Newton (PSD) block-diagonal part
    Bt_gn: np.ndarray  # (O, R, 6): Gauss-Newton feature coupling

    def scan_information(self, scan_index: np.ndarray, n_scans: int) -> np.ndarray:
        """(N, 6, 6) per-scan information: the diagonal blocks of the Gauss-Newton Hessian
        (how fast the cost grows when that scan alone moves, the features re-fitted)."""
        blocks = self.A_gn - np.einsum("oki,okj->oij", self.Bt_gn, self.Bt_gn)
        H = scan_sum(blocks, scan_index, n_scans)
        return 0.5 * (H + H.transpose(0, 2, 1))
