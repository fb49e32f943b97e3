"""PA_LM: the Levenberg-Marquardt baseline of seed 000, with the planes kept as unknowns.

Unknowns
--------
- Poses T_j = T_world_scan[j] (N, 4, 4), perturbed with the same 6-dof retraction as the
  Newton engine (`pa_cli.core.geometry.retract_left`); pose `fixed_pose` is held (gauge).
- Planes pi_i = [n_i; d_i] in the world frame: unit normal n_i and offset d_i (metres), so a
  world point q lies on the plane when n_i . q + d_i = 0. Minimal 3-dof update
  (alpha (2,) rad, delta_e m): n_i <- exp_{n_i}(B_i alpha), the exponential map of the unit
  sphere along the tangent vector B_i alpha, where B_i (3, 2) is an orthonormal basis of the
  plane orthogonal to n_i computed deterministically from n_i (`tangent_basis`); the normal
  turns about the plane's anchor a_i (its centroid at the initial poses): the signed distance
  of a_i is kept and shifted by delta_e, d_i <- d_i + (n_i - n_i') . a_i + delta_e. At zero the
  derivative of n is B_i and of d is (-B_i^T a_i, 1). Turning about the centroid rather than
  the world origin decouples rotation and offset (bench/convergence.py compares both; the
  origin-anchored variant runs there as `lm-origin`).
- Edges (features of kind `FEATURE_EDGE`): a line is a frame [n1, n2, d] (two normals, the
  direction) and a point p on it, with a 4-dof update (`retract_lines`): the frame turns about
  alpha_1 n1 + alpha_2 n2 through p, p moves across the line by delta_1 n1 + delta_2 n2. Its
  residuals are those of its two planes [n_k; -n_k . p], whose squares sum to the squared
  point-to-line distances. With edges every feature gets 4 unknowns and 8 residuals per
  observation (a plane's fourth unknown and second residual block are zero and stay zero).
  Initial lines: PCA of all of the edge's points (direction = eigenvector of lambda_max).
- Initial planes: PCA of all of a plane's points at the initial poses (seed 000 eq. 7):
  the eigenvector of the smallest eigenvalue of the world scatter, offset -n . centroid.

Residuals
---------
Observation o = (plane i, scan j) with scan-frame cluster C_o = sum_k [p_k; 1][p_k; 1]^T.
We factor C_o = L_o L_o^T with a fixed-size 4x4 square root (`cluster_sqrt`), so that

    r_o = L_o^T T_j^T pi_i  (4,)   and   ||r_o||^2 = sum_k (n_i . q_k + d_i)^2,  q_k = T_j p_k.

The joint cost F = sum_o ||r_o||^2 (m^2) is the sum of squared point-to-plane distances; at
the optimal planes it equals the Newton engine's sum of lambda_min. Gauss-Newton normal
equations (J^T J + mu D) delta = -J^T r with D = diag(J^T J) (clipped as in Ceres), the plane
blocks (3x3, block diagonal) eliminated by the Schur complement onto the poses, a sparse
solve for the poses and back-substitution for the planes. Everything is vectorised over the
observations; no Python loop over observations, planes or pose pairs.

numpy/scipy rather than pyceres, by measurement (bench/pyceres_compare.py): pyceres needs one
Python cost-function call per observation and evaluation, which dominates Ceres' time.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pa_cli.adjust.backend import BackendResult
from pa_cli.adjust.damped import IterationRecord, minimize_damped
from pa_cli.adjust.terms import PoseTerm
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import fit_planes as fit_cluster_planes
from pa_cli.core.clusters import scatter, sum_by_feature, transform_clusters
from pa_cli.core.geometry import exp_so3, retract_left, skew, tangent_basis
from pa_cli.core.problem import FEATURE_EDGE, FeatureProblem

# Ceres' LevenbergMarquardtStrategy clips the diagonal of J^T J into [1e-6, 1e32] before
# using it as the damping matrix D (so variables with no information still get damped).
MIN_DIAGONAL = 1e-6
MAX_DIAGONAL = 1e32
PLANE_DOF = 3  # two normal angles and the offset
LINE_DOF = 4  # two direction angles and two offsets across the line


def pose_generators(normals_world: np.ndarray) -> np.ndarray:
    """d(T'^T pi)/d delta at delta = 0, before the left factor T^T: (..., 4, 6).

    For the left perturbation T' = [[Exp(omega), rho], [0, 1]] T (first order; any SE(3)
    retraction whose differential at zero is this one gives the same Jacobian):
    T'^T pi = T^T [Exp(omega)^T n; rho . n + d], so the derivative is
    T^T [[skew(n), 0], [0, n^T]] with the 6-vector ordered (omega, rho) as in
    `pa_cli.core.geometry.retract_left`.
    """
    shape = normals_world.shape[:-1]
    G = np.zeros((*shape, 4, 6))
    G[..., :3, :3] = skew(normals_world)
    G[..., 3, 3:] = normals_world
    return G


def retract_planes(normals: np.ndarray, offsets: np.ndarray, delta: np.ndarray,
                   anchors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Apply the 3-dof plane update delta = (alpha1, alpha2, delta_e) (rad, rad, m).

    The normal turns about the plane's anchor point a (world, m; the origin when None): the
    signed distance of a, n . a + d, is kept and then shifted by delta_e, so
    d' = d + n . a - n' . a + delta_e.
    """
    v = np.einsum("pab,pb->pa", tangent_basis(normals), delta[:, :2])
    theta = np.linalg.norm(v, axis=1)
    safe = np.where(theta < 1e-12, 1.0, theta)
    sinc = np.where(theta < 1e-12, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    n_new = np.cos(theta)[:, None] * normals + sinc[:, None] * v
    n_new /= np.linalg.norm(n_new, axis=1, keepdims=True)
    d_new = offsets + delta[:, 2]
    if anchors is not None:
        d_new = d_new + np.einsum("pa,pa->p", normals - n_new, anchors)
    return n_new, d_new


def retract_lines(frames: np.ndarray, points: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply the 4-dof line update delta = (alpha_1, alpha_2, delta_1, delta_2) (rad, rad, m, m).

    A line is a frame R = [n1, n2, d] (columns: two normals and the direction) and a point p on
    it (world, m). The frame turns about the axis alpha_1 n1 + alpha_2 n2 through p,
    R <- Exp(alpha_1 n1 + alpha_2 n2) R, and p moves across the line, p <- p + delta_1 n1 + delta_2 n2.
    """
    axis = frames[:, :, 0] * delta[:, :1] + frames[:, :, 1] * delta[:, 1:2]
    new_points = points + frames[:, :, 0] * delta[:, 2:3] + frames[:, :, 1] * delta[:, 3:4]
    return exp_so3(axis) @ frames, new_points


def line_jacobians(frames: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d pi_k / d delta (E, 4, 4) at delta = 0 of a line's two planes pi_k = [n_k; -n_k . p]
    under `retract_lines`: turning about n1 moves n2 by d, turning about n2 moves n1 by -d, and
    the offsets move by -1 per metre along their normal."""
    d = frames[:, :, 2]
    dp = np.concatenate([d, -np.einsum("pi,pi->p", d, points)[:, None]], axis=1)  # [d; -d . p]
    E1 = np.zeros((len(frames), 4, LINE_DOF))
    E2 = np.zeros((len(frames), 4, LINE_DOF))
    E1[:, :, 1] = -dp
    E1[:, 3, 2] = -1.0
    E2[:, :, 0] = dp
    E2[:, 3, 3] = -1.0
    return E1, E2


def cluster_sqrt(clusters: np.ndarray) -> np.ndarray:
    """Fixed-size square roots L (O, 4, 4) with L L^T = C for point clusters C (O, 4, 4).

    Factored about the centroid for conditioning: with m = centroid and S the 3x3 scatter
    about it, C = M blockdiag(S, N) M^T, M = [[I, m], [0, 1]]; S = U diag(s) U^T with the
    eigenvalues s clipped at 0 (robust to rank-deficient clusters: 1-2 points, lines).
    """
    S, centroid, count = scatter(clusters)
    s, U = np.linalg.eigh(S)
    root = np.zeros_like(clusters)
    root[:, :3, :3] = U * np.sqrt(np.clip(s, 0.0, None))[:, None, :]
    root[:, 3, 3] = np.sqrt(count)
    M = np.zeros_like(clusters)
    M[:, :3, :3] = np.eye(3)
    M[:, :3, 3] = centroid
    M[:, 3, 3] = 1.0
    return M @ root


def pair_matrix(pairs: list[np.ndarray], blocks: list[np.ndarray], free_slot: np.ndarray) -> sp.csr_matrix:
    """Sparse (6 F, 6 F) matrix over the F free poses holding the pose terms' pair blocks: block b at
    (j, k) and its transpose at (k, j) for each pair (j, k); pairs with the fixed pose are left out."""
    n_free = int(np.count_nonzero(free_slot >= 0))
    pairs_all = np.concatenate(pairs).reshape(-1, 2).astype(np.int64)
    blocks_all = np.concatenate(blocks).reshape(-1, 6, 6)
    keep = (free_slot[pairs_all[:, 0]] >= 0) & (free_slot[pairs_all[:, 1]] >= 0)
    a, b = free_slot[pairs_all[keep, 0]], free_slot[pairs_all[keep, 1]]
    blk = blocks_all[keep]
    i6 = np.arange(6)
    upper = np.broadcast_arrays(6 * a[:, None, None] + i6[None, :, None], 6 * b[:, None, None] + i6[None, None, :])
    lower = np.broadcast_arrays(6 * b[:, None, None] + i6[None, :, None], 6 * a[:, None, None] + i6[None, None, :])
    rows = np.concatenate([upper[0], lower[0]])
    cols = np.concatenate([upper[1], lower[1]])
    values = np.concatenate([blk, blk.transpose(0, 2, 1)])
    return sp.csr_matrix((values.ravel(), (rows.ravel(), cols.ravel())), shape=(6 * n_free, 6 * n_free))


def _group_matrix(keys: np.ndarray, n_groups: int) -> sp.csr_matrix:
    """Sparse (n_groups, O) 0/1 matrix: G @ values sums values per key (empty groups -> 0)."""
    n = len(keys)
    return sp.csr_matrix((np.ones(n), (keys, np.arange(n))), shape=(n_groups, n))


@dataclass
class JointState:
    """Poses and planes of the joint problem."""

    T_world_scan: np.ndarray  # (N, 4, 4)
    normals_world: np.ndarray  # (P, 3) unit normals (of the planes; edges: ignored)
    offsets_m: np.ndarray  # (P,) plane offsets d (n . q + d = 0), metres
    anchors_world: np.ndarray | None = None  # (P, 3) points the normals turn about (m); None: origin
    line_frames_world: np.ndarray | None = None  # (P, 3, 3) edges: columns [n1, n2, direction]; None: no edges
    line_points_world: np.ndarray | None = None  # (P, 3) edges: a point on the line (m)


class JointModel:
    """The PA_LM least-squares problem for one `FeatureProblem` (precomputes the square roots)."""

    def __init__(self, problem: FeatureProblem, fixed_pose: int = 0, anchor_at_centroid: bool = True,
                 terms: Sequence[PoseTerm] = ()) -> None:
        self.problem = problem
        self.terms = list(terms)
        self.anchor_at_centroid = anchor_at_centroid
        self.n_scans = problem.n_scans
        self.n_planes = problem.n_planes
        self.is_edge = problem.feature_kind == FEATURE_EDGE  # (P,) edges: 4 dof and two residual blocks
        self.has_edges = bool(np.any(self.is_edge))
        self.dof = LINE_DOF if self.has_edges else PLANE_DOF  # unknowns per feature (planes pad with 0)
        self.fixed_pose = fixed_pose
        self.plane_index = problem.plane_index
        self.scan_index = problem.scan_index
        self.L_T = cluster_sqrt(problem.clusters).transpose(0, 2, 1)  # (O, 4, 4) = L^T
        self.by_plane = _group_matrix(self.plane_index, self.n_planes)
        self.by_scan = _group_matrix(self.scan_index, self.n_scans)
        free = np.ones(self.n_scans, dtype=bool)
        free[fixed_pose] = False
        self.free_scans = np.flatnonzero(free)
        # column of each scan in the reduced (free-pose) system, -1 for the fixed pose
        self.free_slot = np.full(self.n_scans, -1, dtype=np.int64)
        self.free_slot[self.free_scans] = np.arange(len(self.free_scans))

    # -- state ---------------------------------------------------------------------------
    def initial_state(self, T_world_scan: np.ndarray) -> JointState:
        """Planes by PCA of all their points at the given poses (seed 000 eq. 7); each plane's
        anchor (the point its normal turns about) is its centroid at these poses."""
        normals, offsets, centroids = fit_planes(self.problem, T_world_scan)
        anchors = centroids if self.anchor_at_centroid else None
        frames = fit_line_frames(self.problem, T_world_scan) if self.has_edges else None
        return JointState(np.asarray(T_world_scan, dtype=np.float64), normals, offsets, anchors, frames,
                          centroids if self.has_edges else None)

    def feature_planes(self, state: JointState) -> tuple[np.ndarray, np.ndarray]:
        """Two homogeneous planes per feature (P, 4) each: a plane's own and zero; an edge's two
        planes through its line, [n1; -n1 . p] and [n2; -n2 . p]."""
        pi1 = np.concatenate([state.normals_world, state.offsets_m[:, None]], axis=1)
        pi2 = np.zeros_like(pi1)
        if self.has_edges:
            e = self.is_edge
            for pi, k in ((pi1, 0), (pi2, 1)):
                n = state.line_frames_world[e, :, k]
                pi[e] = np.concatenate([n, -np.einsum("pi,pi->p", n, state.line_points_world[e])[:, None]], axis=1)
        return pi1, pi2

    def residuals(self, state: JointState) -> np.ndarray:
        """r_o = L_o^T T_j^T pi_i for every observation: (O, 4), metres; with edges (O, 8), the
        second block for an edge's second plane (zero for planes)."""
        T = state.T_world_scan[self.scan_index]
        blocks = [np.einsum("oab,ob->oa", self.L_T, np.einsum("oba,ob->oa", T, pi[self.plane_index]))
                  for pi in self.feature_planes(state)[:1 + self.has_edges]]
        return np.concatenate(blocks, axis=1)

    def cost(self, state: JointState) -> float:
        """Joint cost sum_o ||r_o||^2 (m^2), plus the pose terms."""
        cost = float(np.sum(self.residuals(state) ** 2))
        return cost + sum(term.cost(state.T_world_scan) for term in self.terms)

    def split_step(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A flat step (6 N + D P,) -> pose deltas (N, 6) (omega rad, rho m; zero at the fixed
        pose) and feature deltas (P, D): planes (alpha rad, alpha rad, delta_d m[, 0]), edges
        (alpha_1 rad, alpha_2 rad, delta_1 m, delta_2 m) (`retract_lines`)."""
        k = 6 * self.n_scans
        return step[:k].reshape(self.n_scans, 6), step[k:].reshape(self.n_planes, self.dof)

    def retract(self, state: JointState, step: np.ndarray) -> JointState:
        """Apply a flat step (see `split_step`)."""
        d_pose, d_plane = self.split_step(step)
        T = retract_left(state.T_world_scan, d_pose)
        n, d = retract_planes(state.normals_world, state.offsets_m, d_plane[:, :3], state.anchors_world)
        frames, points = state.line_frames_world, state.line_points_world
        if self.has_edges:
            frames, points = frames.copy(), points.copy()
            e = self.is_edge
            frames[e], points[e] = retract_lines(frames[e], points[e], d_plane[e])
        return JointState(T, n, d, state.anchors_world, frames, points)

    # -- linearisation -------------------------------------------------------------------
    def jacobians(self, state: JointState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals (O, R), pose Jacobians (O, R, 6) and feature Jacobians (O, R, D): R = 4
        residuals per plane (8 with edges), D = 3 unknowns per feature (4 with edges)."""
        n = state.normals_world
        T = state.T_world_scan[self.scan_index]
        T_T = T.transpose(0, 2, 1)
        LT_TT = self.L_T @ T_T  # (O, 4, 4)
        E = np.zeros((self.n_planes, 4, self.dof))
        B = tangent_basis(n)
        E[:, :3, :2] = B
        if state.anchors_world is not None:  # d' = d - (B alpha) . a to first order
            E[:, 3, :2] = -np.einsum("pab,pa->pb", B, state.anchors_world)
        E[:, 3, 2] = 1.0
        planes = self.feature_planes(state)
        E_all = [E]
        if self.has_edges:
            E[self.is_edge] = 0.0
            E_line = line_jacobians(state.line_frames_world[self.is_edge], state.line_points_world[self.is_edge])
            E2 = np.zeros_like(E)
            E[self.is_edge], E2[self.is_edge] = E_line
            E_all.append(E2)
        r, J_pose, J_plane = [], [], []
        for pi, E_k in zip(planes, E_all, strict=False):
            r.append(np.einsum("oab,ob->oa", LT_TT, pi[self.plane_index]))
            J_pose.append(LT_TT @ pose_generators(pi[:, :3])[self.plane_index])
            J_plane.append(LT_TT @ E_k[self.plane_index])
        return np.concatenate(r, axis=1), np.concatenate(J_pose, axis=1), np.concatenate(J_plane, axis=1)

    def linearize(self, state: JointState) -> JointLinearization:
        return JointLinearization(self, state)


class JointLinearization:
    """Gauss-Newton model of the joint problem at one state (Linearization protocol).

    `.cost` (m^2), `.gradient_norm` (max-norm of the gradient 2 J^T r over the free
    variables) and `.solve(mu) -> (step, predicted_decrease)`.
    """

    def __init__(self, model: JointModel, state: JointState) -> None:
        self.model = model
        r, Jp, Jl = model.jacobians(state)
        self.r, self.Jp, self.Jl = r, Jp, Jl
        self.cost = float(np.sum(r**2))
        O = len(r)
        # half gradients J^T r
        gp = np.asarray(model.by_scan @ np.einsum("oab,oa->ob", Jp, r))  # (N, 6)
        gl = np.asarray(model.by_plane @ np.einsum("oab,oa->ob", Jl, r))  # (P, D)
        self.term_gradient = self.term_hessian = self.term_pairs = None
        if model.terms:  # cost-scale gradient/Hessian; halve them for J^T r and J^T J
            lins = [term.linearize(state.T_world_scan) for term in model.terms]
            self.cost += sum(lin.cost for lin in lins)
            self.term_gradient = sum(lin.gradient for lin in lins)
            self.term_hessian = sum(lin.pose_blocks for lin in lins)
            self.term_pairs = pair_matrix([term.pose_pairs() for term in model.terms],
                                          [lin.pair_blocks for lin in lins], model.free_slot)
            gp = gp + 0.5 * self.term_gradient
        gp[model.fixed_pose] = 0.0
        self.gp, self.gl = gp, gl
        self.gradient_norm = 2.0 * float(max(np.abs(gp).max(initial=0.0), np.abs(gl).max(initial=0.0)))
        # blocks of J^T J
        self.A = np.asarray(model.by_scan @ np.einsum("oai,oaj->oij", Jp, Jp).reshape(O, 36)).reshape(-1, 6, 6)
        if self.term_hessian is not None:
            self.A = self.A + 0.5 * self.term_hessian
        D = model.dof
        self.C = np.asarray(model.by_plane @ np.einsum("oai,oaj->oij", Jl, Jl).reshape(O, D * D)).reshape(-1, D, D)
        self.W = np.einsum("oai,oaj->oij", Jp, Jl)  # (O, 6, D) pose-feature coupling
        free_obs = model.free_slot[model.scan_index] >= 0
        self.free_obs = np.flatnonzero(free_obs)

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]:
        """Damped step: (J^T J + mu D) delta = -J^T r by the Schur complement onto the poses.

        Returns (flat step (6 N + D P,), see `JointModel.split_step`; predicted decrease of
        the cost under the undamped Gauss-Newton model); (None, 0.0) when the solve fails.
        """
        m = self.model
        n_free = len(m.free_scans)
        A = self.A[m.free_scans]
        C = self.C
        dA = np.clip(np.einsum("nii->ni", A), MIN_DIAGONAL, MAX_DIAGONAL)
        dC = np.clip(np.einsum("pii->pi", C), MIN_DIAGONAL, MAX_DIAGONAL)
        A_d = A + mu * np.einsum("ni,ij->nij", dA, np.eye(6))
        D = m.dof
        C_d = C + mu * np.einsum("pi,ij->pij", dC, np.eye(D))
        try:
            C_inv = np.linalg.inv(C_d)
        except np.linalg.LinAlgError:
            return None, 0.0
        bp = -self.gp[m.free_scans]  # (n_free, 6)
        bl = -self.gl  # (P, D)
        obs = self.free_obs
        W = self.W[obs]
        slot = m.free_slot[m.scan_index[obs]]
        plane = m.plane_index[obs]
        WCinv = W @ C_inv[plane]  # (o, 6, D)
        rows6 = (6 * slot[:, None] + np.arange(6)[None, :])  # (o, 6)
        colsD = (D * plane[:, None] + np.arange(D)[None, :])  # (o, D)
        shape = (6 * n_free, D * m.n_planes)
        r_idx = np.broadcast_to(rows6[:, :, None], W.shape).ravel()
        c_idx = np.broadcast_to(colsD[:, None, :], W.shape).ravel()
        B = sp.csr_matrix((W.ravel(), (r_idx, c_idx)), shape=shape)
        BCinv = sp.csr_matrix((WCinv.ravel(), (r_idx, c_idx)), shape=shape)
        blk = np.arange(n_free)
        rr = np.broadcast_to((6 * blk[:, None, None] + np.arange(6)[None, :, None]), (n_free, 6, 6)).ravel()
        cc = np.broadcast_to((6 * blk[:, None, None] + np.arange(6)[None, None, :]), (n_free, 6, 6)).ravel()
        A_sp = sp.csr_matrix((A_d.ravel(), (rr, cc)), shape=(6 * n_free, 6 * n_free))
        S = A_sp - BCinv @ B.T
        if self.term_pairs is not None:
            S = S + 0.5 * self.term_pairs
        S = S.tocsc()
        rhs = bp.ravel() - BCinv @ bl.ravel()
        try:
            with warnings.catch_warnings():  # a singular system is a rejected step, not a warning
                warnings.simplefilter("error", spla.MatrixRankWarning)
                x_p = spla.spsolve(S, rhs) if n_free else np.zeros(0)
        except (RuntimeError, ValueError, spla.MatrixRankWarning):
            return None, 0.0
        if not np.all(np.isfinite(x_p)):
            return None, 0.0
        x_l = np.einsum("pij,pj->pi", C_inv, (bl.ravel() - B.T @ x_p).reshape(-1, D))
        dp = np.zeros((m.n_scans, 6))
        dp[m.free_scans] = x_p.reshape(-1, 6)
        step = np.concatenate([dp.ravel(), x_l.ravel()])
        # predicted decrease of F = ||r||^2 under the undamped model ||r + J delta||^2
        J_delta = (np.einsum("oab,ob->oa", self.Jp, dp[m.scan_index])
                   + np.einsum("oab,ob->oa", self.Jl, x_l[m.plane_index]))
        predicted = -float(2.0 * np.sum(self.r * J_delta) + np.sum(J_delta**2))
        if self.term_gradient is not None:
            predicted -= float(np.sum(self.term_gradient * dp)
                               + 0.5 * np.einsum("ni,nij,nj->", dp, self.term_hessian, dp)
                               + 0.5 * x_p @ (self.term_pairs @ x_p))
        return step, predicted


def fit_planes(problem: FeatureProblem, T_world_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA planes of all points of each plane, world frame: unit normals (P, 3), offsets (P,) m
    (n . q + d = 0) and centroids (P, 3) m."""
    world = transform_clusters(problem.clusters, T_world_scan[problem.scan_index])
    _, normals, centroid, _ = fit_cluster_planes(sum_by_feature(world, problem.plane_index, problem.n_planes))
    offsets = -np.einsum("pa,pa->p", normals, centroid)
    return normals, offsets, centroid


def fit_line_frames(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """PCA line frames (P, 3, 3) of every feature, world frame: columns [u1, u2, u3] (eigenvectors
    of the scatter, ascending; u3 the line direction), right-handed."""
    world = transform_clusters(problem.clusters, T_world_scan[problem.scan_index])
    U = np.linalg.eigh(scatter(sum_by_feature(world, problem.plane_index, problem.n_planes))[0])[1]
    U[:, :, 2] = np.cross(U[:, :, 0], U[:, :, 1])
    return U


def solve_lm(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
             terms: Sequence[PoseTerm] = (), progress: Callable[[IterationRecord], None] | None = None,
             anchor_at_centroid: bool = True) -> BackendResult:
    """The `lm` backend: PA_LM from the given poses (planes initialised by PCA at them).

    The step norm is the 2-norm of the whole flat step (poses and planes, rad and m). Pose terms
    join the pose block of the Schur system (their pair blocks undamped, like the plane coupling).
    `anchor_at_centroid=False` turns plane normals about the world origin instead of each
    plane's centroid (a worse-conditioned parametrisation, kept for the benchmark).
    """
    model = JointModel(problem, config.fixed_pose, anchor_at_centroid, terms)
    state = model.initial_state(T_world_scan_init)
    state, fields = minimize_damped(state, model.linearize, model.cost, model.retract,
                                    lambda step: float(np.linalg.norm(step)), config, progress)
    return BackendResult(state.T_world_scan, fields)
