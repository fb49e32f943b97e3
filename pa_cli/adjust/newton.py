"""The `newton` backend: second-order plane adjustment with the planes eliminated.

`PlaneCost` is the plane feature cost (cost, exact gradient and Hessian pieces); `NewtonModel`
adds the pose terms (`pa_cli.adjust.terms`) and the sparse Hessian pattern; `solve_newton` runs the
damped loop of `pa_cli.adjust.damped` on it.

Cost (m^2): tau = sum_i lambda_min(S_i), S_i the world-frame scatter of plane i's points about
their centroid = the sum of squared point-to-plane distances with every plane at its optimum.

Derivatives are taken for the left retraction of `pa_cli.geometry.retract_left`: pose j gets
delta_j = (omega_j rad, rho_j m) and its world points move q -> Exp(omega_j) q + rho_j.

Derivation (equivalent to Zhou's Theorem 1 and BALM2 eq. 159). With the homogeneous plane
pi = [n; d] (|n| = 1) and the plane's world cluster C(x) = sum_j E_j W_j E_j^T (E_j = the
perturbation, W_j = T_j C_ij T_j^T), lambda(x) = min_pi pi^T C(x) pi / |n|^2. At the optimal
pi* = [u; -u.c] (u the lambda_min eigenvector of S, c the centroid) the implicit function theorem
gives, in the plane coordinates q_1 = [e_1; -e_1.c], q_2 = [e_2; -e_2.c], q_3 = [0; 1]
(e_1, e_2 the other eigenvectors of S), where the reduced plane Hessian is
M = diag(lambda_2 - lambda_min, lambda_3 - lambda_min, N):

    g   = pi*^T (dC) pi*
    H   = pi*^T (d^2 C) pi* - 2 sum_a b_a b_a^T / M_aa,   b_a = q_a^T (dC) pi*.

Per observation (world cluster [[P, v], [v^T, N]], a = P n + d v, s = n.v + N d):
    g_w = 2 a x n,  g_rho = 2 s n
    A_ww = 2 [n]x P [n]x^T + n a^T + a n^T - 2 (n.a) I,  A_wrho = 2 (v x n) n^T,  A_rhorho = 2 N n n^T
    b_a = [(P m + e v) x n + a x m ; (m.v + N e) n + s m]  for q_a = [m; e].
So each plane's Hessian is block diagonal (A per observing scan) minus a rank-3 coupling
Bt^T Bt with Bt_a = sqrt(2 / M_aa) b_a. Everything is vectorised over all observations.

Eigen-gap guard: when lambda_k - lambda_min < eigen_gap_tolerance * lambda_max, M_aa is clamped
to eigen_gap_tolerance * lambda_max (the coupling term is bounded instead of blowing up; the model
is then approximate, which the damped loop tolerates) and the plane is counted as guarded.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pa_cli.adjust.backend import BackendResult
from pa_cli.adjust.damped import IterationRecord, minimize_damped
from pa_cli.adjust.linalg import HessianPattern, damped_solve
from pa_cli.adjust.terms import PoseTerm
from pa_cli.clusters import central_moments, plane_eigen, plane_starts
from pa_cli.config import SolverConfig
from pa_cli.geometry import retract_left, skew
from pa_cli.problem import FeatureProblem


def plane_cost(problem: FeatureProblem, T_world_scan: np.ndarray) -> float:
    """Sum over planes of lambda_min of the world scatter matrix (m^2)."""
    return PlaneCost(problem).cost(T_world_scan)


@dataclass
class PlaneLinearization:
    """Cost (m^2), per-pose gradient (N, 6) and per-observation Hessian pieces of the plane cost."""

    cost: float
    gradient: np.ndarray  # (N, 6): d cost / d (omega, rho)
    A: np.ndarray  # (O, 6, 6): block-diagonal part, per observation
    Bt: np.ndarray  # (O, 3, 6): H_jk -= Bt_j^T Bt_k within a plane (and the diagonal too)
    n_guarded: int  # planes whose eigen gap was clamped
    A_gn: np.ndarray  # (O, 6, 6): Gauss-Newton (PSD) block-diagonal part
    Bt_gn: np.ndarray  # (O, 3, 6): Gauss-Newton plane coupling


class PlaneCost:
    """The plane feature cost: sum over planes of lambda_min(S_plane) (m^2), planes eliminated.

    Precomputes the scan-frame central moments of the clusters and the plane offsets once per
    problem. `linearize` gives the exact gradient and the Hessian pieces for the sparse system
    (`HessianPattern.assemble`: block diagonal A minus the rank-3 plane couplings Bt^T Bt).
    """

    def __init__(self, problem: FeatureProblem, eigen_gap_tolerance: float = 1e-6):
        self.problem = problem
        self.eigen_gap_tolerance = eigen_gap_tolerance
        self.starts = plane_starts(problem.plane_index, problem.n_planes)
        self.moments = central_moments(problem.clusters)

    def cost(self, T_world_scan: np.ndarray) -> float:
        lam = plane_eigen(T_world_scan, *self.moments, self.problem.scan_index, self.starts)[2]
        return float(np.sum(np.maximum(lam[:, 0], 0.0)))

    def linearize(self, T_world_scan: np.ndarray) -> PlaneLinearization:
        """Cost, exact gradient and the Hessian pieces at T_world_scan (see the module docstring).

        All sums use centred moments, so nothing cancels with large coordinates.
        """
        problem, moments, eigen_gap_tolerance = self.problem, self.moments, self.eigen_gap_tolerance
        S_o, c_o, lam, vec, centroid, N_plane = plane_eigen(T_world_scan, *moments, problem.scan_index,
                                                            self.starts)
        No = moments[3]
        pidx = problem.plane_index
        u = vec[:, :, 0]

        # Reduced plane Hessian diag(lambda_2 - lambda_1, lambda_3 - lambda_1, N), with the guard.
        gaps = lam[:, 1:] - lam[:, :1]
        floor = eigen_gap_tolerance * np.abs(lam[:, 2:3])  # relative to lambda_max, the plane's scale
        guarded = gaps < floor
        gaps = np.where(guarded, floor, gaps)
        with np.errstate(divide="ignore"):
            w_gap = np.where(gaps > 0, np.sqrt(2.0 / np.where(gaps > 0, gaps, 1.0)), 0.0)  # (P, 2)
        w_N = np.sqrt(2.0 / N_plane)

        n = u[pidx]
        dc = c_o - centroid[pidx]  # observation centroid relative to the plane centroid (m)
        r_mean = np.einsum("oi,oi->o", n, dc)  # mean signed distance of the observation's points (m)
        a = np.einsum("oij,oj->oi", S_o, n) + (No * r_mean)[:, None] * c_o  # sum_k r_k q_k
        s = No * r_mean  # sum_k r_k
        v = No[:, None] * c_o
        P = S_o + No[:, None, None] * c_o[:, :, None] * c_o[:, None, :]

        n_obs = len(pidx)
        grad_obs = np.empty((n_obs, 6))
        grad_obs[:, :3] = 2.0 * np.cross(a, n)
        grad_obs[:, 3:] = 2.0 * s[:, None] * n
        gradient = np.zeros((problem.n_scans, 6))
        np.add.at(gradient, problem.scan_index, grad_obs)

        A = np.empty((n_obs, 6, 6))
        K = skew(n)
        na = np.einsum("oi,oi->o", n, a)
        A[:, :3, :3] = (2.0 * K @ P @ K.transpose(0, 2, 1) + n[:, :, None] * a[:, None, :]
                        + a[:, :, None] * n[:, None, :] - 2.0 * na[:, None, None] * np.eye(3))
        A[:, :3, 3:] = 2.0 * np.cross(v, n)[:, :, None] * n[:, None, :]
        A[:, 3:, :3] = A[:, :3, 3:].transpose(0, 2, 1)
        A[:, 3:, 3:] = 2.0 * No[:, None, None] * n[:, :, None] * n[:, None, :]
        A_gn = A.copy()
        A_gn[:, :3, :3] = 2.0 * K @ P @ K.transpose(0, 2, 1)  # without the sum_k r_k d^2 r_k term

        with np.errstate(divide="ignore"):
            w_gn = np.where(lam[:, 1:] > 0, np.sqrt(2.0 / np.where(lam[:, 1:] > 0, lam[:, 1:], 1.0)), 0.0)
        Bt = np.empty((n_obs, 3, 6))
        Bt_gn = np.empty((n_obs, 3, 6))
        for k in range(2):  # the two tangent directions of the normal (fixed count, not a data loop)
            m = vec[pidx, :, k + 1]
            s_m = No * np.einsum("oi,oi->o", m, dc)  # sum_k (m . q_k + e)
            pm = np.einsum("oij,oj->oi", S_o, m) + s_m[:, None] * c_o  # sum_k (m . q_k + e) q_k
            b_w = np.cross(pm, n) + np.cross(a, m)
            b_r = s_m[:, None] * n + s[:, None] * m
            wk = w_gap[pidx, k][:, None]
            Bt[:, k, :3] = wk * b_w
            Bt[:, k, 3:] = wk * b_r
            wk_gn = w_gn[pidx, k][:, None]  # Gauss-Newton: only the s_k dr_k part, plane block lambda_k
            Bt_gn[:, k, :3] = wk_gn * np.cross(pm, n)
            Bt_gn[:, k, 3:] = wk_gn * s_m[:, None] * n
        # offset direction q_3 = [0; 1]: b = [v x n ; N n]
        wN = w_N[pidx][:, None]
        Bt[:, 2, :3] = wN * np.cross(v, n)
        Bt[:, 2, 3:] = wN * No[:, None] * n
        Bt_gn[:, 2] = Bt[:, 2]

        return PlaneLinearization(cost=float(np.sum(np.maximum(lam[:, 0], 0.0))), gradient=gradient, A=A, Bt=Bt,
                           n_guarded=int(np.count_nonzero(guarded.any(axis=1))), A_gn=A_gn, Bt_gn=Bt_gn)


class NewtonLinearization:
    """The Newton model at one state: plane cost plus pose terms, reduced gradient and sparse
    Hessian (gauge pose removed).

    `solve(mu)` uses the exact Hessian when H + mu D is positive definite; otherwise (far from the
    optimum H can be indefinite) it falls back, within the same iteration, to the Gauss-Newton
    Hessian of the plane-eliminated problem (the Schur complement of the joint pose-plane
    Gauss-Newton matrix, positive semi-definite), and reports the prediction of that model.
    """

    def __init__(self, model: NewtonModel, T_world_scan: np.ndarray):
        der = model.plane_cost.linearize(T_world_scan)
        terms = [term.linearize(T_world_scan) for term in model.terms]
        self.cost = der.cost + sum(t.cost for t in terms)
        self.n_guarded = der.n_guarded
        self.gradient = der.gradient + sum(t.gradient for t in terms)
        self._pose_blocks = [t.pose_blocks for t in terms]
        self._pair_blocks = [(term.pose_pairs(), t.pair_blocks) for term, t in zip(model.terms, terms, strict=True)]
        self.g = model.pattern.reduce_vector(self.gradient)
        self.gradient_norm = float(np.abs(self.g).max(initial=0.0))
        self.H = model.pattern.assemble(der.A, der.Bt, self._pose_blocks, self._pair_blocks)
        self._der = der
        self._H_gn = None
        self._pattern = model.pattern
        model.max_guarded = max(model.max_guarded, der.n_guarded)

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]:
        H = self.H
        x = damped_solve(H, self.g, mu, self._pattern.csc_diag_pos)
        if x is None:
            if self._H_gn is None:
                self._H_gn = self._pattern.assemble(self._der.A_gn, self._der.Bt_gn, self._pose_blocks,
                                                    self._pair_blocks)
            H = self._H_gn
            x = damped_solve(H, self.g, mu, self._pattern.csc_diag_pos)
            if x is None:
                return None, 0.0
        predicted = -(self.g @ x + 0.5 * x @ (H @ x))
        return self._pattern.expand_vector(x), float(predicted)


class NewtonModel:
    """Problem-level precomputation of the Newton backend: the plane cost, the pose terms and the
    Hessian pattern (plane pairs and the terms' pose pairs, gauge pose removed)."""

    def __init__(self, problem: FeatureProblem, fixed_pose: int = 0, eigen_gap_tolerance: float = 1e-6,
                 terms: Sequence[PoseTerm] = ()):
        self.problem = problem
        self.plane_cost = PlaneCost(problem, eigen_gap_tolerance)
        self.terms = list(terms)
        extra = [term.pose_pairs() for term in self.terms]
        self.pattern = HessianPattern(problem.plane_index, problem.scan_index, problem.n_scans, fixed_pose,
                                      self.plane_cost.starts, np.concatenate(extra) if extra else None)
        self.max_guarded = 0

    def cost(self, T_world_scan: np.ndarray) -> float:
        """Plane cost plus the pose terms (m^2)."""
        return self.plane_cost.cost(T_world_scan) + sum(term.cost(T_world_scan) for term in self.terms)

    def linearize(self, T_world_scan: np.ndarray) -> NewtonLinearization:
        return NewtonLinearization(self, T_world_scan)


def solve_newton(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
                 terms: Sequence[PoseTerm] = (),
                 progress: Callable[[IterationRecord], None] | None = None) -> BackendResult:
    """The `newton` backend: damped Newton on the poses with the planes eliminated.

    The step norm is the 2-norm of all pose steps (rad and m). Warns when the eigen-gap guard
    clamped the coupling terms of some planes.
    """
    model = NewtonModel(problem, config.fixed_pose, config.eigen_gap_tolerance, terms)
    T, fields = minimize_damped(np.asarray(T_world_scan_init, dtype=np.float64), model.linearize, model.cost,
                                retract_left, lambda step: float(np.linalg.norm(step)), config, progress)
    warnings = []
    if model.max_guarded:
        warnings.append(
            f"eigen-gap guard: up to {model.max_guarded} of {problem.n_planes} planes had lambda_min "
            f"within {config.eigen_gap_tolerance:g} (relative) of another eigenvalue; their coupling "
            "terms were clamped (degenerate, e.g. line-like or point-like, planes).")
    return BackendResult(T, fields, warnings)
