"""The calibration cost: base poses and extrinsics, each (scan, LiDAR) cluster at a composite pose.

Unknowns: base poses T_world_base(t) (t = 0..N-1) and extrinsics T_base_lidar(k) (k = 1..K-1;
lidar0 is the base, T_base_lidar(0) = I). A point p of LiDAR k in scan t lies at the world point
T_world_base(t) T_base_lidar(k) p, so the observation (feature i, scan t, LiDAR k) is a plane
cluster of the "virtual scan" v = (t, k) with the composite pose T_v = T_world_base(t) T_base_lidar(k),
and the cost is the plane cost of `pa_cli.adjust.newton` (`FeatureCost`) at the composite poses.

State: one (N + K - 1, 4, 4) array, the N base poses then the K - 1 extrinsics. A base pose is
stepped on the left (`pa_cli.core.geometry.retract_left`) by delta_t = (omega, rho) in the world frame;
an extrinsic X = [[R_X, t_X], [0, 1]] by eps = (omega, rho) in the base frame about the LiDAR's own
origin: R_X <- Exp(omega) R_X, t_X <- t_X + rho (`RigLayout.retract`), so rho is the displacement
of the LiDAR in the base frame and "translation along base x" is exactly a change of t_X's x.

Chain rule (derivation in docs/math.md, "Multi-LiDAR calibration"). With the composite
C = T_t X (translation t_C) and E(omega, rho) = [[Exp(omega), rho], [0, 1]], the composite after
the steps is E(delta_t) T_t X' = E(d) C with d(delta_t, eps) the composite's own left step:

    d_omega = Log(Exp(delta_omega) Exp(a)),                 a = R_t eps_omega
    d_rho   = delta_rho + Exp(delta_omega) (R_t eps_rho + (I - Exp(a)) t_C)

(R_t the base rotation). To second order d = J x + q(x), x = (delta_t, eps_k) (12,):

    J = [I_6 | [[R_t, 0], [[t_C]x R_t, R_t]]]
    q_omega = 1/2 delta_omega x a
    q_rho   = -1/2 a x (a x t_C) + delta_omega x (R_t eps_rho) - delta_omega x (a x t_C)

so with g, H the composite's plane-cost gradient and Hessian, the cost's derivatives in x are
J^T g and J^T H J + sum_i g_i d^2 q_i (the second term, linear in g, vanishes at a stationary point
only where g does; it is kept, so the Hessian is exact). Its blocks (u = delta_omega, e = eps):

    H[u, e_omega] = -1/2 [g_omega]x R_t - [g_rho]x [t_C]x R_t,     H[u, e_rho] = -[g_rho]x R_t
    H[e_omega, e_omega] = R_t^T ((g_rho . t_C) I - 1/2 (g_rho t_C^T + t_C g_rho^T)) R_t

and their transposes. The plane couplings of `FeatureLinearization.Bt` become Bt J (rank 3 per
feature, now across base poses and extrinsics); the Hessian is assembled dense: the extrinsic
columns couple with every base pose, and a calibration drive has hundreds of scans, not thousands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust.newton import FeatureCost
from pa_cli.adjust.terms import PoseTerm
from pa_cli.core.geometry import retract_left, skew
from pa_cli.core.problem import FeatureProblem

BLOCK = 6
DIAG_FLOOR = 1e-6  # damping diagonal D = max(|diag H|, DIAG_FLOOR * max|diag H|), as the pose solver clamps


@dataclass
class RigLayout:
    """Which base pose and LiDAR each virtual scan v of a calibration problem belongs to."""

    base_of_virtual: np.ndarray  # (V,) int64, 0..N-1
    lidar_of_virtual: np.ndarray  # (V,) int64, 0..K-1
    n_base: int
    n_lidars: int

    @property
    def n_state(self) -> int:
        """Rows of the state array: N base poses then K - 1 extrinsics."""
        return self.n_base + self.n_lidars - 1

    def split(self, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 4, 4) T_world_base and (K, 4, 4) T_base_lidar (lidar0 the identity) of a state."""
        T_base_lidar = np.concatenate([np.eye(4)[None], state[self.n_base:]])
        return state[:self.n_base], T_base_lidar

    def join(self, T_world_base: np.ndarray, T_base_lidar: np.ndarray) -> np.ndarray:
        """The state array of base poses (N, 4, 4) and extrinsics (K, 4, 4) (lidar0's is dropped)."""
        return np.concatenate([np.asarray(T_world_base, dtype=np.float64),
                               np.asarray(T_base_lidar, dtype=np.float64)[1:]])

    def composite(self, state: np.ndarray) -> np.ndarray:
        """(V, 4, 4) T_world_lidar of every virtual scan: T_world_base(t) T_base_lidar(k)."""
        T_world_base, T_base_lidar = self.split(state)
        return T_world_base[self.base_of_virtual] @ T_base_lidar[self.lidar_of_virtual]

    def retract(self, state: np.ndarray, step: np.ndarray) -> np.ndarray:
        """Step (N + K - 1, 6): base poses on the left (world frame), extrinsics about their own
        origin in the base frame (R <- Exp(omega) R, t <- t + rho)."""
        out = retract_left(state, step)
        n = self.n_base
        out[n:, :3, 3] = state[n:, :3, 3] + step[n:, 3:]
        return out

    def columns(self) -> np.ndarray:
        """(V, 12) unknown indices of (delta_t, eps_k) per virtual scan in the full vector
        (6 N base dofs, then 6 (K - 1) extrinsic dofs); lidar0's eps columns point at the dummy
        index 6 (N + K - 1), which is dropped."""
        cols = np.empty((len(self.base_of_virtual), 2 * BLOCK), dtype=np.int64)
        cols[:, :BLOCK] = BLOCK * self.base_of_virtual[:, None] + np.arange(BLOCK)
        ext = BLOCK * (self.n_base + self.lidar_of_virtual - 1)
        cols[:, BLOCK:] = np.where(self.lidar_of_virtual[:, None] > 0, ext[:, None] + np.arange(BLOCK),
                                   BLOCK * self.n_state)
        return cols


def composite_jacobian(T_world_base: np.ndarray, T_world_lidar: np.ndarray, is_base_lidar: np.ndarray
                       ) -> np.ndarray:
    """(V, 6, 12) J of the composite step d with respect to (delta_t, eps_k) from the base and
    composite poses; zero eps columns where the LiDAR is the base (`is_base_lidar`)."""
    R, t = T_world_base[:, :3, :3], T_world_lidar[:, :3, 3]
    J = np.zeros((len(R), BLOCK, 2 * BLOCK))
    J[:, :, :BLOCK] = np.eye(BLOCK)
    J[:, :3, 6:9] = R
    J[:, 3:, 6:9] = skew(t) @ R
    J[:, 3:, 9:] = R
    J[is_base_lidar, :, BLOCK:] = 0.0
    return J


def composite_second_order(T_world_base: np.ndarray, T_world_lidar: np.ndarray, g: np.ndarray,
                           is_base_lidar: np.ndarray) -> np.ndarray:
    """(V, 12, 12) sum_i g_i d^2 q_i, the second-order chain-rule term (module docstring)."""
    R, t = T_world_base[:, :3, :3], T_world_lidar[:, :3, 3]
    g_w, g_r = g[:, :3], g[:, 3:]
    S = np.zeros((len(R), 2 * BLOCK, 2 * BLOCK))
    u_ew = -0.5 * skew(g_w) @ R - skew(g_r) @ skew(t) @ R
    u_er = -skew(g_r) @ R
    gt = np.einsum("vi,vi->v", g_r, t)
    outer = g_r[:, :, None] * t[:, None, :]
    M = gt[:, None, None] * np.eye(3) - 0.5 * (outer + outer.transpose(0, 2, 1))
    S[:, 0:3, 6:9] = u_ew
    S[:, 6:9, 0:3] = u_ew.transpose(0, 2, 1)
    S[:, 0:3, 9:12] = u_er
    S[:, 9:12, 0:3] = u_er.transpose(0, 2, 1)
    S[:, 6:9, 6:9] = R.transpose(0, 2, 1) @ M @ R
    S[is_base_lidar] = 0.0
    return S


class CalibrationCost:
    """The plane cost of a rig problem at composite poses, plus pose terms on the base poses.

    `problem` is a feature problem over the virtual scans of `layout` (its `scan_index` is v);
    `terms` are pose terms (`pa_cli.adjust.terms`) over the N base poses (the odometry factors).
    """

    def __init__(self, problem: FeatureProblem, layout: RigLayout, terms: list[PoseTerm] | tuple = (),
                 eigen_gap_tolerance: float = 1e-6) -> None:
        self.problem = problem
        self.layout = layout
        self.terms = list(terms)
        self.features = FeatureCost(problem, eigen_gap_tolerance)
        self.cols = layout.columns()
        self.is_base_lidar = layout.lidar_of_virtual == 0
        self.n_full = BLOCK * layout.n_state

    def cost(self, state: np.ndarray) -> float:
        """Plane cost at the composite poses plus the pose terms at the base poses (m^2)."""
        T_world_base, _ = self.layout.split(state)
        return self.features.cost(self.layout.composite(state)) + sum(term.cost(T_world_base) for term in self.terms)

    def derivatives(self, state: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, int]:
        """Cost (m^2), full gradient (6 (N + K - 1),), exact Hessian, Gauss-Newton Hessian (both dense,
        same size) and the number of features whose eigen gap was clamped."""
        lay = self.layout
        T_world_base, _ = lay.split(state)
        composite = lay.composite(state)
        lin = self.features.linearize(composite)
        T_base_of_v = T_world_base[lay.base_of_virtual]
        J = composite_jacobian(T_base_of_v, composite, self.is_base_lidar)
        size = self.n_full + 1  # + the dummy column of lidar0's eps
        gradient = np.zeros(size)
        np.add.at(gradient, self.cols, np.einsum("vij,vi->vj", J, lin.gradient))
        second = composite_second_order(T_base_of_v, composite, lin.gradient, self.is_base_lidar)
        H = self._hessian(J, lin.A, lin.Bt, second)
        H_gn = self._hessian(J, lin.A_gn, lin.Bt_gn, None)
        cost = lin.cost
        for term in self.terms:
            t_lin = term.linearize(T_world_base)
            cost += t_lin.cost
            gradient[:BLOCK * lay.n_base] += t_lin.gradient.ravel()
            for M in (H, H_gn):
                _add_pose_term(M, t_lin.pose_blocks, term.pose_pairs(), t_lin.pair_blocks)
        keep = slice(0, self.n_full)
        return float(cost), gradient[keep], H[keep, keep], H_gn[keep, keep], lin.n_guarded

    def _hessian(self, J: np.ndarray, A: np.ndarray, Bt: np.ndarray,
                 second: np.ndarray | None) -> np.ndarray:
        """Dense Hessian: sum over observations of J^T A J, the second-order term, minus the
        feature couplings U^T U with U (r F, 6 (N + K - 1) + 1) the rows (Bt J) of every feature."""
        p = self.problem
        v = p.scan_index
        size = self.n_full + 1
        H = np.zeros((size, size))
        _scatter_blocks(H, self.cols[v], np.einsum("oai,oab,obj->oij", J[v], A, J[v], optimize=True))
        if second is not None:
            _scatter_blocks(H, self.cols, second)
        BJ = np.einsum("ori,oij->orj", Bt, J[v], optimize=True)  # (O, r, 12)
        r = Bt.shape[1]
        u_rows = np.repeat((r * p.plane_index[:, None] + np.arange(r))[:, :, None], 2 * BLOCK, axis=2)
        u_cols = np.repeat(self.cols[v][:, None, :], r, axis=1)
        U = sp.csr_matrix((BJ.ravel(), (u_rows.ravel(), u_cols.ravel())), shape=(r * p.n_planes, size))
        H -= (U.T @ U).toarray()
        return H


def _scatter_blocks(H: np.ndarray, cols: np.ndarray, blocks: np.ndarray) -> None:
    """H[cols[m], cols[m]] += blocks[m] for (M, c) indices and (M, c, c) blocks."""
    np.add.at(H, (cols[:, :, None], cols[:, None, :]), blocks)


def _add_pose_term(H: np.ndarray, pose_blocks: np.ndarray, pairs: np.ndarray, pair_blocks: np.ndarray) -> None:
    """Add a pose term's diagonal blocks (N, 6, 6) and pair blocks H_jk (K, 6, 6) to H (base dofs first)."""
    idx = BLOCK * np.arange(len(pose_blocks))[:, None] + np.arange(BLOCK)
    np.add.at(H, (idx[:, :, None], idx[:, None, :]), pose_blocks)
    if len(pairs):
        a = BLOCK * np.asarray(pairs)[:, 0][:, None] + np.arange(BLOCK)
        b = BLOCK * np.asarray(pairs)[:, 1][:, None] + np.arange(BLOCK)
        np.add.at(H, (a[:, :, None], b[:, None, :]), pair_blocks)
        np.add.at(H, (b[:, :, None], a[:, None, :]), pair_blocks.transpose(0, 2, 1))

