"""The `newton` backend: second-order feature adjustment with the features eliminated.

`PlaneCost` is the plane feature cost (cost, exact gradient and Hessian pieces), `EdgeCost`
(`pa_cli.adjust.edges`) the edge feature cost, `FeatureCost` the sum of both over a problem's
features by `feature_kind`; `NewtonModel` adds the pose terms (`pa_cli.adjust.terms`) and the
sparse Hessian pattern; `solve_newton` runs the damped loop of `pa_cli.adjust.damped` on it.

Cost (m^2): tau = sum_i lambda_min(S_i), S_i the world-frame scatter of plane i's points about
their centroid = the sum of squared point-to-plane distances with every plane at its optimum.

Derivatives are taken for the left retraction of `pa_cli.core.geometry.retract_left`: pose j gets
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

Per observation (world cluster [[P, v], [v^T, N]], a = P n + d v, s = n.v + N d; computed in
`pa_cli.adjust.normal_terms`, shared with the edge cost):
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

import sys
from collections.abc import Callable, Sequence

import numpy as np

from pa_cli.adjust.backend import BackendResult
from pa_cli.adjust.damped import IterationRecord, minimize_damped
from pa_cli.adjust.edges import EDGE_COUPLING_ROWS, EdgeCost
from pa_cli.adjust.linalg import HessianPattern, damped_solve
from pa_cli.adjust.normal_terms import ClusterCost, FeatureLinearization, NormalTerms, coupling_weight, lever_origins
from pa_cli.adjust.terms import PoseTerm
from pa_cli.config import SolverConfig
from pa_cli.core.clusters import plane_eigen, plane_starts
from pa_cli.core.geometry import exp_so3, retract_left, skew
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, FeatureProblem


def plane_cost(problem: FeatureProblem, T_world_scan: np.ndarray) -> float:
    """The feature cost (m^2): over planes lambda_min, over edges lambda_min + lambda_mid of the
    world scatter matrix (the sum of squared point-to-feature distances)."""
    return FeatureCost(problem).cost(T_world_scan)


# Observations per block of the per-observation work (whole planes, about this many): each block's
# temporaries (a few hundred bytes per observation, a dozen of them) stay in the processor's cache
# and are reused, so the work per observation does not grow with the problem.
CHUNK_OBSERVATIONS = 4096
# poses whose plane eigen-decompositions a `PlaneCost` keeps: the current state's (its linearisation)
# and the last trial step's (linearised next when the step is accepted)
EIGEN_KEPT = 2


def _reference_counts(arrays: list[np.ndarray]) -> list[int]:
    return [sys.getrefcount(a) for a in arrays]


_FREE_REFERENCES = _reference_counts([np.empty(0)])[0]  # an array held by its list alone


class ReusedArrays:
    """Output arrays handed out again once nobody else holds them: `get` returns a set of arrays
    of the given shapes (float64, uninitialised), one of its sets whose arrays nothing outside the
    pool refers to (a view refers to its array), else a new set. Fresh arrays of hundreds of MB are
    faulted in page by page by the operating system on first touch, on every call; reused ones
    are not. At most `max_sets` sets are kept."""

    def __init__(self, max_sets: int = 2):
        self.max_sets = max_sets
        self.sets: list[list[np.ndarray]] = []

    def get(self, shapes: list[tuple[int, ...]]) -> list[np.ndarray]:
        for arrays in self.sets:
            if [a.shape for a in arrays] == shapes and max(_reference_counts(arrays)) <= _FREE_REFERENCES:
                return list(arrays)
        arrays = [np.empty(shape) for shape in shapes]
        self.sets = [*self.sets, arrays][-self.max_sets:]
        return list(arrays)


def plane_chunks(starts: np.ndarray, size: int = CHUNK_OBSERVATIONS) -> list[tuple[int, int]]:
    """Consecutive plane ranges [p0, p1) covering all planes, each of about `size` observations
    (at least one plane) given the planes' observation offsets `starts` (P + 1,)."""
    n_planes = len(starts) - 1
    cuts = np.searchsorted(starts, np.arange(size, starts[-1], size))
    bounds = np.unique(np.concatenate([[0], cuts, [n_planes]])).astype(int)
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True))


class PlaneCost(ClusterCost):
    """The plane feature cost: sum over planes of lambda_min(S_plane) (m^2), planes eliminated.

    Precomputes the scan-frame central moments of the clusters and the plane offsets once per
    problem (every feature of `problem` is treated as a plane). `linearize` gives the exact
    gradient and the Hessian pieces for the sparse system (`HessianPattern.assemble`: block
    diagonal A minus the rank-3 plane couplings Bt^T Bt). Both work through the planes in blocks
    of `CHUNK_OBSERVATIONS` observations (`plane_chunks`); every plane is computed whole, so the
    results are those of one vectorised pass.
    """

    def __init__(self, problem: FeatureProblem, eigen_gap_tolerance: float = 1e-6):
        super().__init__(problem, eigen_gap_tolerance)
        self.chunks = plane_chunks(self.starts)
        self.outputs = ReusedArrays()
        self._kept_eigen: list[tuple[np.ndarray, list[tuple]]] = []  # (T_world_scan, `_eigen` per block), newest first

    def _eigen(self, T_world_scan: np.ndarray, p0: int, p1: int) -> tuple[np.ndarray, ...]:
        """`plane_eigen` of planes p0..p1-1 (their observations starts[p0]..starts[p1]-1)."""
        o = slice(int(self.starts[p0]), int(self.starts[p1]))
        return plane_eigen(T_world_scan, *(m[o] for m in self.moments), self.problem.scan_index[o],
                           self.starts[p0:p1 + 1] - self.starts[p0])

    def _eigen_blocks(self, T_world_scan: np.ndarray) -> list[tuple[np.ndarray, ...]]:
        """`_eigen` of every block of `chunks` at T_world_scan, kept for the last `EIGEN_KEPT` poses
        it was asked at: the damped loop evaluates the cost at a trial step and, when it accepts
        the step, linearises there; the pose covariance reuses the solver's last linearisation."""
        for T_kept, blocks in self._kept_eigen:
            if np.array_equal(T_kept, T_world_scan):
                return blocks
        blocks = [self._eigen(T_world_scan, p0, p1) for p0, p1 in self.chunks]
        T_copy = np.array(T_world_scan, dtype=np.float64, copy=True)
        self._kept_eigen = [(T_copy, blocks), *self._kept_eigen][:EIGEN_KEPT]
        return blocks

    def cost(self, T_world_scan: np.ndarray) -> float:
        lam_min = np.concatenate([eig[2][:, 0] for eig in self._eigen_blocks(T_world_scan)])
        return float(np.sum(np.maximum(lam_min, 0.0)))

    def linearize(self, T_world_scan: np.ndarray, centred: bool = False) -> FeatureLinearization:
        """Cost, exact gradient and the Hessian pieces at T_world_scan (see the module docstring),
        for the left retraction or (`centred`) for `retract_centred` (`lever_origins`).

        All sums use centred moments, so nothing cancels with large coordinates.
        """
        problem = self.problem
        origin = lever_origins(T_world_scan, centred)
        n_obs = problem.n_observations
        A, A_gn, Bt, Bt_gn, gradient_obs = self.outputs.get([(n_obs, 6, 6), (n_obs, 6, 6), (n_obs, 3, 6), (n_obs, 3, 6),
                                                             (n_obs, 6)])
        lam_min = np.empty(problem.n_planes)
        n_guarded = 0
        for (p0, p1), eig in zip(self.chunks, self._eigen_blocks(T_world_scan), strict=True):
            o = slice(int(self.starts[p0]), int(self.starts[p1]))
            S_o, c_o, lam, vec, centroid, N_plane = eig
            lam_min[p0:p1] = lam[:, 0]
            pidx = problem.plane_index[o] - p0
            # Reduced plane Hessian diag(lambda_2 - lambda_1, lambda_3 - lambda_1, N), with the guard.
            gaps = lam[:, 1:] - lam[:, :1]
            floor = self.eigen_gap_tolerance * np.abs(lam[:, 2:3])  # relative to lambda_max, the plane's scale
            guarded = gaps < floor
            n_guarded += int(np.count_nonzero(guarded.any(axis=1)))
            w_gap = coupling_weight(np.where(guarded, floor, gaps))  # (P, 2)
            w_gn = coupling_weight(lam[:, 1:])  # Gauss-Newton: plane block lambda_k

            terms = NormalTerms.build(vec[pidx, :, 0], S_o, c_o - origin[problem.scan_index[o]], c_o - centroid[pidx],
                                      self.moments[3][o])
            terms.blocks(out=(A[o], A_gn[o]))
            for k in range(2):  # the two tangent directions of the normal (fixed count, not a data loop)
                exact, gn = terms.tangent_row(vec[pidx, :, k + 1])
                Bt[o, k] = w_gap[pidx, k][:, None] * exact
                Bt_gn[o, k] = w_gn[pidx, k][:, None] * gn
            Bt[o, 2] = Bt_gn[o, 2] = np.sqrt(2.0 / N_plane)[pidx, None] * terms.offset_row()
            gradient_obs[o] = terms.gradient()
        return FeatureLinearization(cost=float(np.sum(np.maximum(lam_min, 0.0))),
                                    gradient=self.scan_sum(gradient_obs),
                                    A=A, Bt=Bt, n_guarded=n_guarded, A_gn=A_gn, Bt_gn=Bt_gn)


    def eigen_of_last_linearization(self, T_world_scan: np.ndarray) -> tuple[np.ndarray, ...] | None:
        """The `plane_eigen` outputs of every plane at T_world_scan when `linearize` or `cost` kept
        them (`_eigen_blocks`; the pose covariance reuses the solver's last linearisation, which is
        at the solution), else None."""
        parts = next((blocks for T_kept, blocks in self._kept_eigen if np.array_equal(T_kept, T_world_scan)), None)
        if parts is None:
            return None
        return tuple(np.concatenate([part[k] for part in parts]) for k in range(len(parts[0])))


class FeatureCost:
    """The cost of every feature of a problem: `PlaneCost` over its planes plus `EdgeCost` over its
    edges (m^2), each on the sub-problem of its kind; the pieces are put back in the problem's
    observation order, with as many coupling rows as the widest kind (3 for planes, 4 for edges;
    unused rows are zero)."""

    def __init__(self, problem: FeatureProblem, eigen_gap_tolerance: float = 1e-6):
        self.problem = problem
        self.starts = plane_starts(problem.plane_index, problem.n_planes)
        self.parts = []  # (observation indices, cost on the sub-problem)
        for kind, cost_class in ((FEATURE_PLANE, PlaneCost), (FEATURE_EDGE, EdgeCost)):
            observations, sub = feature_subproblem(problem, kind)
            if len(observations):
                self.parts.append((observations, cost_class(sub, eigen_gap_tolerance)))

    def cost(self, T_world_scan: np.ndarray) -> float:
        return float(sum(part.cost(T_world_scan) for _, part in self.parts))

    def linearize(self, T_world_scan: np.ndarray, centred: bool = False) -> FeatureLinearization:
        """The pieces of every part (`PlaneCost.linearize`, `EdgeCost.linearize`) in the problem's
        observation order."""
        lins = [(obs, part.linearize(T_world_scan, centred)) for obs, part in self.parts]
        if len(lins) == 1:
            return lins[0][1]
        n_obs = self.problem.n_observations
        A, A_gn = np.empty((n_obs, 6, 6)), np.empty((n_obs, 6, 6))
        for obs, lin in lins:
            A[obs], A_gn[obs] = lin.A, lin.A_gn
        Bt = rows_in_problem_order(n_obs, [(obs, lin.Bt) for obs, lin in lins])
        Bt_gn = rows_in_problem_order(n_obs, [(obs, lin.Bt_gn) for obs, lin in lins])
        return FeatureLinearization(cost=sum(lin.cost for _, lin in lins),
                                    gradient=sum(lin.gradient for _, lin in lins), A=A, Bt=Bt,
                                    n_guarded=sum(lin.n_guarded for _, lin in lins), A_gn=A_gn, Bt_gn=Bt_gn)

    def scan_information(self, T_world_scan: np.ndarray) -> np.ndarray:
        """(N, 6, 6) per-scan information of all features (see `FeatureLinearization.scan_information`)."""
        return sum(part.linearize(T_world_scan).scan_information(part.problem.scan_index, self.problem.n_scans)
                   for _, part in self.parts)


def rows_in_problem_order(n_observations: int, parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(O, R, 6) coupling rows of a problem from its parts' (observation indices, rows (O_k, R_k, 6)), R the
    widest part's rows (the others' padded with zero rows)."""
    rows = max(part.shape[1] for _, part in parts)
    out = np.zeros((n_observations, rows, 6))
    for obs, part in parts:
        out[obs, :part.shape[1]] = part
    return out


def feature_subproblem(problem: FeatureProblem, kind: int) -> tuple[np.ndarray, FeatureProblem]:
    """Observation indices (ascending) of the features of one kind, and the problem of those
    features alone (renumbered 0..F-1 in their order, observations still sorted by feature)."""
    of_kind = problem.feature_kind == kind
    observations = np.flatnonzero(of_kind[problem.plane_index])
    new_index = np.cumsum(of_kind) - 1
    sub = FeatureProblem(plane_index=new_index[problem.plane_index[observations]],
                         scan_index=problem.scan_index[observations], clusters=problem.clusters[observations],
                         n_scans=problem.n_scans, T_world_scan=problem.T_world_scan,
                         feature_kind=problem.feature_kind[of_kind])
    return observations, sub


def centring(T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3, 3) [t_j]x of the scan positions t_j (m): the change of pose tangent from the left
    retraction's (omega, rho) to the centred one (omega, rho_c), rho = rho_c + t_j x omega
    (`retract_centred`)."""
    return skew(np.asarray(T_world_scan, dtype=np.float64)[:, :3, 3])


def centre_blocks(blocks: np.ndarray, K_row: np.ndarray, K_col: np.ndarray) -> np.ndarray:
    """J_row^T X J_col of 6x6 blocks X (M, 6, 6) in left-retraction coordinates, J = [[I, 0], [K, I]]
    (K = [t]x of the row's / the column's scan, (M, 3, 3)): the blocks in centred coordinates (a new
    array)."""
    out = np.array(blocks, dtype=np.float64, copy=True)
    out[:, :, :3] += out[:, :, 3:] @ K_col
    out[:, :3, :] -= K_row @ out[:, 3:, :]  # K^T = -K
    return out


def centre_gradient(gradient: np.ndarray, K: np.ndarray) -> np.ndarray:
    """J^T g of per-pose gradients (N, 6) in left-retraction coordinates: g_omega + K^T g_rho."""
    out = np.array(gradient, dtype=np.float64, copy=True)
    out[:, :3] -= np.einsum("nij,nj->ni", K, gradient[:, 3:])
    return out


def retract_centred(T_world_scan: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply steps delta (N, 6) = (omega rad, rho m) turning each scan about its own position:
    R <- Exp(omega) R, t <- t + rho (a world point q moves to Exp(omega) (q - t) + t + rho).

    The same poses as `retract_left` reaches, but its derivatives do not grow with the distance
    of the scan from the world origin: with the left retraction a turn of a scan 20 km away also
    moves it by turn x 20 km, the Hessian couples omega and rho by that lever arm and its
    diagonal (the damping) no longer scales the problem.
    """
    delta = np.asarray(delta, dtype=np.float64)
    T_new = np.array(T_world_scan, dtype=np.float64, copy=True)
    T_new[:, :3, :3] = exp_so3(delta[:, :3]) @ T_world_scan[:, :3, :3]
    T_new[:, :3, 3] += delta[:, 3:]
    return T_new


class NewtonLinearization:
    """The Newton model at one state: feature cost plus pose terms, reduced gradient and sparse
    Hessian (gauge pose removed).

    With `model.centred` the pose tangent is the centred one of `retract_centred`. The feature
    cost's pieces come in it directly: each scan's points enter its derivatives relative to the
    scan's position (`normal_terms.lever_origins`), which also carries the second-order term of
    the change of retraction. The pose terms' blocks and gradient are moved from the left-retraction
    coordinates x by x = J x_c per scan, J = [[I, 0], [[t]x, I]], and the exact Hessian gains their
    second-order term of that change, rho = rho_c - (Exp(omega) - I) t: in the (omega, omega) block
    -(g_rho t^T + t g_rho^T - 2 (g_rho . t) I) / 2, g_rho the terms' gradient.

    `solve(mu)` uses the exact Hessian when H + mu D is positive definite; otherwise (far from the
    optimum H can be indefinite) it falls back, within the same iteration, to the Gauss-Newton
    Hessian of the plane-eliminated problem (the Schur complement of the joint pose-plane
    Gauss-Newton matrix, positive semi-definite), and reports the prediction of that model.
    """

    def __init__(self, model: NewtonModel, T_world_scan: np.ndarray):
        der = model.feature_cost.linearize(T_world_scan, model.centred)
        terms = [term.linearize(T_world_scan) for term in model.terms]
        self.cost = der.cost + sum(t.cost for t in terms)
        self.n_guarded = der.n_guarded
        terms_gradient = sum(t.gradient for t in terms)
        self._pose_blocks = [t.pose_blocks for t in terms]
        self._pair_blocks = [(term.pose_pairs(), t.pair_blocks) for term, t in zip(model.terms, terms, strict=True)]
        self._exact_pose_blocks = self._pose_blocks
        if model.centred and terms:
            terms_gradient = self._centre_terms(T_world_scan, terms_gradient)
        self.gradient = der.gradient + terms_gradient
        self.g = model.pattern.reduce_vector(self.gradient)
        self.gradient_norm = float(np.abs(self.g).max(initial=0.0))
        self.H = model.pattern.assemble(der.A, der.Bt, self._exact_pose_blocks, self._pair_blocks)
        self._der = der
        # the feature cost's pieces in left-retraction coordinates (the pose covariance's), when not centred
        self.left_der = None if model.centred else der
        self._H_gn = None
        self._pattern = model.pattern
        model.max_guarded = max(model.max_guarded, der.n_guarded)

    def _centre_terms(self, T_world_scan: np.ndarray, terms_gradient: np.ndarray) -> np.ndarray:
        """The pose terms' blocks in centred coordinates (see the class docstring) and their
        gradient (returned); the second-order term of their change of retraction is a pose block
        of the exact Hessian only (the Gauss-Newton fallback stays PSD). The feature cost's pieces
        come centred from `FeatureCost.linearize` (`lever_origins`)."""
        K = centring(T_world_scan)
        t, g_rho = T_world_scan[:, :3, 3], terms_gradient[:, 3:]
        second = np.zeros((len(t), 6, 6))
        second[:, :3, :3] = -0.5 * (g_rho[:, :, None] * t[:, None, :] + t[:, :, None] * g_rho[:, None, :]
                                    - 2.0 * np.einsum("ni,ni->n", g_rho, t)[:, None, None] * np.eye(3))
        self._pose_blocks = [centre_blocks(b, K, K) for b in self._pose_blocks]
        self._exact_pose_blocks = [*self._pose_blocks, second]
        self._pair_blocks = [(pairs, centre_blocks(b, K[pairs[:, 0]], K[pairs[:, 1]]) if len(pairs) else b)
                             for pairs, b in self._pair_blocks]
        return centre_gradient(terms_gradient, K)

    def solve(self, mu: float) -> tuple[np.ndarray | None, float]:
        system = self.H
        x = damped_solve(system, self.g, mu)
        if x is None:
            if self._H_gn is None:
                self._H_gn = self._pattern.assemble(self._der.A_gn, self._der.Bt_gn, self._pose_blocks,
                                                    self._pair_blocks)
            system = self._H_gn
            x = damped_solve(system, self.g, mu)
            if x is None:
                return None, 0.0
        # (H + mu D) x = -g gives x^T H x = -g.x - mu x^T D x, so the model decrease
        # -(g.x + x^T H x / 2) = (-g.x + mu x^T D x) / 2
        predicted = 0.5 * (-(self.g @ x) + mu * (x @ (system.damping() * x)))
        return self._pattern.expand_vector(x), float(predicted)


class NewtonModel:
    """Problem-level precomputation of the Newton backend: the feature cost, the pose terms and the
    Hessian pattern (pose pairs sharing a feature and the terms' pose pairs, gauge pose removed).

    `centred`: linearise for `retract_centred` (the solver's steps) instead of the left retraction
    of `pa_cli.core.geometry.retract_left` (the covariance's and the tests' coordinates)."""

    def __init__(self, problem: FeatureProblem, fixed_pose: int = 0, eigen_gap_tolerance: float = 1e-6,
                 terms: Sequence[PoseTerm] = (), centred: bool = False):
        self.problem = problem
        self.centred = centred
        self.feature_cost = FeatureCost(problem, eigen_gap_tolerance)
        self.terms = list(terms)
        extra = [term.pose_pairs() for term in self.terms]
        rows = EDGE_COUPLING_ROWS if np.any(problem.feature_kind == FEATURE_EDGE) else 3  # Bt rows (linearize)
        self.pattern = HessianPattern(problem.plane_index, problem.scan_index, problem.n_scans, fixed_pose,
                                      self.feature_cost.starts, np.concatenate(extra) if extra else None, rank=rows)
        self.max_guarded = 0
        self.last: tuple[np.ndarray, NewtonLinearization] | None = None

    def cost(self, T_world_scan: np.ndarray) -> float:
        """Feature cost plus the pose terms (m^2)."""
        return self.feature_cost.cost(T_world_scan) + sum(term.cost(T_world_scan) for term in self.terms)

    def linearize(self, T_world_scan: np.ndarray) -> NewtonLinearization:
        """The linearisation at T_world_scan, kept as `last` (the damped loop's last one is at the solution)."""
        self.last = None  # the previous one's arrays go back to the feature cost's pool first
        lin = NewtonLinearization(self, T_world_scan)
        self.last = (T_world_scan, lin)
        return lin


def solve_newton(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig,
                 terms: Sequence[PoseTerm] = (),
                 progress: Callable[[IterationRecord], None] | None = None, centred: bool = True) -> BackendResult:
    """The `newton` backend: damped Newton on the poses with the planes eliminated.

    Steps turn each scan about its own position (`retract_centred`), so the system's scaling does
    not depend on where the scans lie in the world frame; with `centred` False they are the left
    retraction's (`retract_left`, turns about the world origin: for poses expressed relative to
    one of them and lying near it, see `hierarchical.refine_window`). The step norm is the 2-norm of all pose
    steps (rad and m). Warns when the eigen-gap guard clamped the coupling terms of some planes.
    """
    model = NewtonModel(problem, config.fixed_pose, config.eigen_gap_tolerance, terms, centred=centred)
    retract = retract_centred if centred else retract_left
    T, fields = minimize_damped(np.asarray(T_world_scan_init, dtype=np.float64), model.linearize, model.cost,
                                retract, lambda step: float(np.linalg.norm(step)), config, progress)
    warnings = []
    if model.max_guarded:
        warnings.append(
            f"eigen-gap guard: up to {model.max_guarded} of {problem.n_planes} features had an eliminated "
            f"eigenvalue within {config.eigen_gap_tolerance:g} (relative) of another (planes: lambda_min, "
            "edges: lambda_max); their coupling terms were clamped (degenerate features: line-like "
            "planes, blob-like edges).")
    return BackendResult(T, fields, warnings, model)
