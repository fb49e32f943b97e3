"""The point noise of a plane problem, measured from its residuals at the optimum, with the errors
that the points of one observation share.

An observation o (scan j, plane i, N_o points) has residuals r_k = w_k + c_o + a_o . (q_k - c_o):
white noise w_k of variance v_w,o per point (range noise), and an error of the surface patch the
scan saw, shared by its points (roughness and relief at the patch's scale, the beam footprint,
deskew and calibration errors, a curved surface fitted by a plane): an offset c_o of variance
v_c,i and a tilt a_o (in the plane, 2 components) of variance v_t,i per component, i.e.

    Cov(r_o) = v_w,o I + v_c,i 1 1^T + v_t,i X_o X_o^T,    X_o = (q_k - c_o) projected on the plane (N_o, 3).

Estimates (docs/math.md, "Correlated noise within an observation"): each observation's residuals are
split, along the landmark normal n, into its offset delta_o = n . (c_o - c_i), its slope along the
two principal in-plane directions t_a of its points (statistics z_a = t_a^T S_o n / sqrt(lambda_a),
lambda_a = t_a^T S_o t_a; along directions the points spread over by `MIN_TILT_SPREAD_M` or more) and
the rest (white: n^T S_o n - sum_a z_a^2 over N_o - 1 - (slopes) degrees of freedom). The fit takes a
share h of each component (its leverage: `residual_leverage`), so

    E[delta_o^2] = (v_c + v_w / N_o)(1 - h_0),    E[z_a^2] = (v_t lambda_a + v_w)(1 - h_a),

and per plane the method of moments gives v_c,i and v_t,i, kept where significant, pooled over all
planes and shrunk towards the pool for planes with few observations (`SHARED_PRIOR_DOF`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust._ldl_solve import PositiveDefiniteFactor
from pa_cli.adjust.newton import PlaneCost, feature_subproblem
from pa_cli.adjust.normal_terms import NormalTerms
from pa_cli.core.clusters import plane_eigen
from pa_cli.core.problem import FEATURE_PLANE, FeatureProblem
from pa_cli.errors import SolverError

POSE_DOF = 6
PLANE_DOF = 3  # a plane's two tilts and its offset
EDGE_DOF = 4  # an edge's turn and offset towards each of its two normals
COMPONENTS = 3  # shared components per observation: the offset, then the two tilts
# degrees of freedom of the pooled variance in a plane's own estimate: a plane with few observations (a
# handful of scans) takes mostly the pooled value, one seen by dozens mostly its own
SHARED_PRIOR_DOF = 5.0
# Hutchinson probes of the leverage (`residual_leverage`): used summed over a plane's observations,
# where its noise averages out; a fixed seed. On a 12-scan street (330 observations, 34 planes) a plane's
# sum of offset leverages is within about 3.2 of 2,000 probes' with 16 probes, 1.9 with 64, 0.7 with 128
LEVERAGE_PROBES = 128
# probes drawn at once from the seeded generator (their order fixes the estimate) and solved as one block, in
# one pass over the factor: on 1,000 scans (34,000 observations, 7,600 unknowns) the leverage takes 0.55 s,
# 0.72 s with blocks of 8 (memory: observations x 3 x this many integers)
PROBES_PER_DRAW = 16
LEVERAGE_SEED = 35
# an observation's slope along an in-plane direction counts only where its points spread along it by at
# least this RMS (m): along a single scan line the cross-line spread is the noise itself and its "slope" a
# ratio of noises
MIN_TILT_SPREAD_M = 0.05
# a plane's (or the pool's) shared variance counts only where it exceeds this many standard errors of its
# estimate without shared errors (white noise alone: about 0.1 % of planes in the Gaussian limit, a few
# per cent for planes of few observations), instead of an unbiased estimate floored at 0, which white noise
# alone leaves positive for half the planes: that made the covariance of white-noise scenes up to 1.7x
# conservative along the axes a grazing ground decides (2 standard errors: still 1.67x on the height)
SIGNIFICANT_SE = 3.0
# values of the isotropic share u in [0, 1] the split of the noise is fitted over (`isotropic_ratio`): steps of
# 0.02, finer than the share's sampling spread on a few hundred observations
RATIO_GRID = 51


@dataclass(frozen=True)
class ResidualComponents:
    """Per observation (O,): the components of its residuals at the optimum along its plane normal."""

    offset_m: np.ndarray  # (O,) delta_o, its points' mean signed distance to the plane
    slope: np.ndarray  # (O, 2) z_a = t_a^T S_o n / sqrt(lambda_a) (m) along each tilt direction; 0 where not counted
    counted: np.ndarray  # (O, 2) bool: the points spread along t_a by MIN_TILT_SPREAD_M or more
    spread_m2: np.ndarray  # (O, 2) lambda_a = t_a^T S_o t_a: its points' scatter along t_a
    directions: np.ndarray  # (O, 3, 2) t_a: the principal in-plane directions of its points (world)
    white_m2: np.ndarray  # (O,) v_w,o: the variance per point left after its own offset and tilts


@dataclass(frozen=True)
class NoiseComponents:
    """Per observation (O,): white variance per point (m^2), variance of the offset its points share (m^2)
    and of each component of their shared tilt (rad^2)."""

    white_m2: np.ndarray
    shared_m2: np.ndarray
    tilt_rad2: np.ndarray


class PlaneBalance:
    """The point noise (m) at which independent points would give the planes' observations of `problem` the
    information their offsets carry (docs/math.md, "Both terms at their measured noise"): an observation o of N_o
    points with white variance v_w,o per point and an offset v_c its points share measures its offset with
    variance v_c + v_w,o / N_o, so

        sigma^2 = sum_o N_o / sum_o 1 / (v_c + v_w,o / N_o),

    v_w,o from `residual_components`, v_c pooled over the observations of the problem's planes (at least one)
    (`shared_offset_variance`). Without a shared offset it is the white noise. The observations' central moments
    are built once, for every pose set `point_sigma_m` is asked at."""

    def __init__(self, problem: FeatureProblem):
        planes = problem.feature_kind == FEATURE_PLANE
        self.problem = problem if planes.all() else feature_subproblem(problem, FEATURE_PLANE)[1]
        self.cost = PlaneCost(self.problem)

    def point_sigma_m(self, T_world_scan: np.ndarray) -> float:
        """The balance's point noise (m) at the poses T_world_scan (N, 4, 4)."""
        moments = self.cost.moments
        components = residual_components(plane_eigen(T_world_scan, *moments, self.problem.scan_index,
                                                     self.cost.starts), self.problem, moments)
        n_points = moments[3]
        shared = shared_offset_variance(components.offset_m, components.white_m2, n_points, self.problem.plane_index)
        return float(np.sqrt(n_points.sum() / np.sum(1.0 / (shared + components.white_m2 / n_points))))


def shared_offset_variance(offset_m: np.ndarray, white_m2: np.ndarray, n_points: np.ndarray,
                           plane_index: np.ndarray) -> float:
    """The variance (m^2) of an offset every point of an observation shares, pooled over the observations (O,):
    their offsets from their plane's centroid `offset_m`, white variances per point `white_m2`, point counts
    `n_points`. A plane seen by K observations takes one degree of freedom of their offsets, so
    E[offset_o^2] ~ (v_c + v_w,o / N_o)(1 - 1/K) and the moment estimate is

        v_c = sum_o (offset_o^2 - (1 - 1/K) v_w,o / N_o) / sum_o (1 - 1/K),

    counted where it exceeds `SIGNIFICANT_SE` standard errors of that estimate under white noise alone
    (sqrt(2 sum_o ((1 - 1/K) v_w,o / N_o)^2) / sum_o (1 - 1/K)), else 0: its sampling error times N_o would
    otherwise inflate the balance of white-noise scenes by several per cent."""
    n_observations = np.bincount(plane_index)[plane_index]
    kept = 1.0 - 1.0 / n_observations
    mean_variance = kept * white_m2 / n_points
    total = max(float(np.sum(kept)), 1.0)
    estimate = float(np.sum(offset_m**2 - mean_variance)) / total
    standard_error = float(np.sqrt(2.0 * np.sum(mean_variance**2))) / total
    return estimate if estimate > SIGNIFICANT_SE * standard_error else 0.0


def residual_components(eig: tuple, problem: FeatureProblem, moments: tuple) -> ResidualComponents:
    """The offset, the slopes and the white remainder of every observation at the planes of `eig` (the
    `plane_eigen` outputs at the optimum: world scatter S_o and centroid c_o per observation, the planes)."""
    S_o, c_o, _, vec, centroid, _ = eig
    pidx = problem.plane_index
    n = vec[pidx, :, 0]
    E = vec[pidx, :, 1:]  # (O, 3, 2) the plane's in-plane basis
    spread, U = np.linalg.eigh(E.transpose(0, 2, 1) @ S_o @ E)
    directions = E @ U
    spread = np.maximum(spread, 0.0)
    N_o = moments[3]
    counted = spread >= N_o[:, None] * MIN_TILT_SPREAD_M**2
    along = np.einsum("oia,oij,oj->oa", directions, S_o, n)
    slope = np.where(counted, along / np.sqrt(np.where(counted, spread, 1.0)), 0.0)
    dof = N_o - 1.0 - counted.sum(axis=1)
    rest = np.maximum(np.einsum("oi,oij,oj->o", n, S_o, n) - np.sum(slope**2, axis=1), 0.0)
    white = np.where(dof > 0, rest / np.maximum(dof, 1.0), 0.0)
    # an observation without spare points or residual takes its plane's pooled white variance (else all planes')
    pooled = plane_noise_variances(white, dof, problem)
    fallback = np.where(pooled > 0, pooled, np.sum(np.maximum(dof, 0.0) * white) / max(np.sum(np.maximum(dof, 0.0)),
                                                                                         1e-300))
    white = np.where(white > 0, white, fallback[pidx])
    return ResidualComponents(np.einsum("oi,oi->o", n, c_o - centroid[pidx]), slope, counted, spread, directions,
                              white)


def residual_leverage(eig: tuple, problem: FeatureProblem, moments: tuple, components: ResidualComponents,
                      pose_hessian: np.ndarray, free: np.ndarray, pairs: np.ndarray, pair_blocks: np.ndarray,
                      n_probes: int = LEVERAGE_PROBES, edges: EdgeObservations | None = None
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """(O, 3) leverage of each observation's offset and two tilts: the share h of each that the fitted
    parameters (its plane, the poses and the pose terms) take, h = u^T F^-1 u / |d|^2 for the direction d
    of the points (1_o for the offset, t_a . (q_k - c_o) for a tilt) with u = Jbar^T d; with `edges`, the
    edges are fitted parameters too (per direction u_a across the line its turn towards u_a and its offset,
    information diag(lambda_3, N)), and the second result is (O_e, 2) the leverage of each edge observation's
    offset along u_1 and u_2 (None without edges).

    F = Jbar^T Jbar is the information of all the parameters: the free poses (`free`, their Hessian
    blocks `pose_hessian` (F, 6, 6) and the pose terms' `pairs` (reduced indices) and `pair_blocks`, all
    halved: the cost has no 1/2) and each plane's two tilts and offset about its centroid
    (diag(lambda_2, lambda_3, N), couplings sum_k k(q_k) J(q_k)). A point's rows are affine in its
    position, so u is a sum over the observation's moments: for the offset N_o times the rows of its
    centroid ([c_o x n; n] world tangent; (e_1 . (c_o - c), e_2 . (c_o - c), 1)), for a tilt
    [(S_o t_a) x n; 0] and (e_1^T S_o t_a, e_2^T S_o t_a, 0). F keeps the planes as unknowns, so it stays
    sparse when a plane is seen by every scan; it is symmetric positive definite, factorised once (L D L^T,
    `PositiveDefiniteFactor`), and the diagonal of the projection estimated by Hutchinson's method with
    `n_probes` Rademacher vectors over the (observation, component) pairs, `PROBES_PER_DRAW` solved at
    once: unbiased, and not clipped to [0, 1] (that would bias it: it is used summed over a plane's
    observations, where its noise averages out)."""
    S_o, c_o, lam, vec, centroid, N_plane = eig
    pidx, sidx = problem.plane_index, problem.scan_index
    N_o = moments[3]
    n = vec[pidx, :, 0]
    dc = c_o - centroid[pidx]
    terms = NormalTerms.build(n, S_o, c_o, dc, N_o)
    coupling = np.empty((len(pidx), PLANE_DOF, POSE_DOF))  # pose-plane information per observation
    for k in range(2):  # the two tilts of the plane (fixed count, not a data loop)
        coupling[:, k] = terms.tangent_row(vec[pidx, :, k + 1])[1]
    coupling[:, 2] = terms.offset_row()
    n_free = len(free)
    reduced = np.full(problem.n_scans, -1, np.int64)
    reduced[free] = np.arange(n_free)
    n_edges = 0 if edges is None else len(edges.eig[4])
    size = POSE_DOF * n_free + PLANE_DOF * problem.n_planes + EDGE_DOF * n_edges
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def add(first_row: np.ndarray, first_col: np.ndarray, blocks: np.ndarray) -> None:
        """Blocks (B, r, c) at the first rows and columns (B,) and their transposes at the mirrored places,
        the entries in F's upper triangle (row <= column) only."""
        r = np.broadcast_to(first_row[:, None, None] + np.arange(blocks.shape[1])[None, :, None], blocks.shape)
        c = np.broadcast_to(first_col[:, None, None] + np.arange(blocks.shape[2])[None, None, :], blocks.shape)
        for row, col in ((r.ravel(), c.ravel()), (c.ravel(), r.ravel())):
            upper = row <= col
            rows.append(row[upper])
            cols.append(col[upper])
            vals.append(blocks.ravel()[upper])

    first_pose = POSE_DOF * np.arange(n_free)
    add(first_pose, first_pose, 0.25 * pose_hessian)  # F = H / 2, added with its mirror: a quarter each
    first_plane = POSE_DOF * n_free + PLANE_DOF * np.arange(problem.n_planes)
    plane_info = np.zeros((problem.n_planes, PLANE_DOF, PLANE_DOF))
    plane_info[:, np.arange(PLANE_DOF), np.arange(PLANE_DOF)] = 0.5 * np.column_stack([lam[:, 1], lam[:, 2], N_plane])
    add(first_plane, first_plane, plane_info)
    free_obs = reduced[sidx] >= 0
    add(POSE_DOF * reduced[sidx[free_obs]], first_plane[pidx[free_obs]], coupling[free_obs].transpose(0, 2, 1))
    if len(pairs):
        add(POSE_DOF * pairs[:, 0], POSE_DOF * pairs[:, 1], 0.5 * pair_blocks)
    if edges is not None:
        u_e, index_e = _edge_unknowns(edges, reduced, POSE_DOF * n_free + PLANE_DOF * problem.n_planes, add)
    F_upper = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
    try:
        factor = PositiveDefiniteFactor(F_upper)
    except ValueError as exc:
        raise SolverError("the information of the poses and planes is singular (a pose or a plane is not "
                          "constrained); the covariance needs every pose constrained.") from exc
    # u (O, 3 components, 9 = pose 6 + plane 3) and |d|^2 (O, 3)
    u = np.zeros((len(pidx), COMPONENTS, POSE_DOF + PLANE_DOF))
    u[:, 0, :3] = N_o[:, None] * np.cross(c_o, n)
    u[:, 0, 3:POSE_DOF] = N_o[:, None] * n
    u[:, 0, POSE_DOF:POSE_DOF + 2] = N_o[:, None] * np.einsum("oi,oia->oa", dc, vec[pidx, :, 1:])
    u[:, 0, POSE_DOF + 2] = N_o
    St = S_o @ components.directions  # (O, 3, 2) S_o t_a
    u[:, 1:, :3] = np.cross(St.transpose(0, 2, 1), n[:, None, :])
    u[:, 1:, POSE_DOF:POSE_DOF + 2] = np.einsum("oia,oib->oab", St, vec[pidx, :, 1:])
    norm2 = np.column_stack([N_o, components.spread_m2])
    index = np.concatenate([np.where(free_obs[:, None], POSE_DOF * reduced[sidx][:, None] + np.arange(POSE_DOF), -1),
                            first_plane[pidx][:, None] + np.arange(PLANE_DOF)], axis=1)  # (O, 9), -1: gauge
    n_planes_obs = len(pidx)
    if edges is not None:  # each edge observation's two directions: one component each, 8 unknowns of 9
        u = np.concatenate([u, u_e])
        index = np.concatenate([index, index_e])
        norm2 = np.concatenate([norm2, np.column_stack([np.repeat(edges.N_o, 2), np.zeros((len(u_e), 2))])])
    # Rademacher probes z = 2 b - 1 of the seeded generator's bits b per (observation, component); index: the
    # rows of F of each u's entries
    rng = np.random.default_rng(LEVERAGE_SEED)
    total = np.zeros((len(u), COMPONENTS))
    for first in range(0, n_probes, PROBES_PER_DRAW):
        bits = rng.integers(0, 2, size=(len(u), COMPONENTS, min(PROBES_PER_DRAW, n_probes - first)))
        total += factor.probe_sums(index, u, bits)
    with np.errstate(divide="ignore", invalid="ignore"):
        leverage = np.where(norm2 > 0, total / n_probes / np.where(norm2 > 0, norm2, 1.0), 1.0)
    return leverage[:n_planes_obs], None if edges is None else leverage[n_planes_obs:, 0].reshape(-1, 2)


@dataclass(frozen=True)
class EdgeObservations:
    """The edges of a problem at the optimum, for `residual_leverage`: `eig` (`plane_eigen` of the edge
    features: the lines' normals vec[:, :, :2], directions vec[:, :, 2], centroids, eigenvalues and point
    counts), the edge and the scan of each observation (O_e,) and its point count N_o (O_e,)."""

    eig: tuple
    edge_index: np.ndarray
    scan_index: np.ndarray
    N_o: np.ndarray


def _edge_unknowns(edges: EdgeObservations, reduced: np.ndarray, first_unknown: int,
                   add: Callable[[np.ndarray, np.ndarray, np.ndarray], None]) -> tuple[np.ndarray, np.ndarray]:
    """Add the edges' blocks to F with `add` (per direction a: the turn towards u_a and the offset along u_a,
    information diag(lambda_3, N) / 2 mirrored, and each observation's coupling with its pose: the raw rows of
    `NormalTerms` with normal u_a), the unknowns numbered from `first_unknown`; and per (edge observation,
    direction) the vector u (2 O_e, 3, 9) of its offset (component 0; pose 6, turn, offset) and the F rows of
    its entries (2 O_e, 9; -1: the gauge pose, the unused ninth)."""
    S_o, c_o, lam, vec, centroid, N_edge = edges.eig
    eidx, N_o = edges.edge_index, edges.N_o
    n_edges = len(centroid)
    first_edge = first_unknown + EDGE_DOF * np.arange(n_edges)
    info = np.zeros((n_edges, EDGE_DOF, EDGE_DOF))
    info[:, [0, 2], [0, 2]] = 0.5 * lam[:, 2:3]
    info[:, [1, 3], [1, 3]] = 0.5 * N_edge[:, None]
    add(first_edge, first_edge, info)
    line = vec[eidx, :, 2]
    dc = c_o - centroid[eidx]
    along = N_o * np.einsum("oi,oi->o", line, dc)
    pose = reduced[edges.scan_index]
    free_obs = pose >= 0
    u = np.zeros((len(eidx), 2, COMPONENTS, POSE_DOF + PLANE_DOF))
    index = np.full((len(eidx), 2, POSE_DOF + PLANE_DOF), -1, np.int64)
    for a in range(2):  # the two directions across the line (fixed count, not a data loop)
        n = vec[eidx, :, a]
        terms = NormalTerms.build(n, S_o, c_o, dc, N_o)
        coupling = np.stack([terms.tangent_row(line)[1], terms.offset_row()], axis=1)  # (O_e, 2, 6)
        add(POSE_DOF * pose[free_obs], first_edge[eidx[free_obs]] + 2 * a, coupling[free_obs].transpose(0, 2, 1))
        u[:, a, 0, :3] = N_o[:, None] * np.cross(c_o, n)
        u[:, a, 0, 3:POSE_DOF] = N_o[:, None] * n
        u[:, a, 0, POSE_DOF] = along
        u[:, a, 0, POSE_DOF + 1] = N_o
        index[:, a, :POSE_DOF] = np.where(free_obs[:, None], POSE_DOF * pose[:, None] + np.arange(POSE_DOF), -1)
        index[:, a, POSE_DOF:POSE_DOF + 2] = first_edge[eidx][:, None] + 2 * a + np.arange(2)
    return u.reshape(-1, COMPONENTS, POSE_DOF + PLANE_DOF), index.reshape(-1, POSE_DOF + PLANE_DOF)


def correlated_noise_variances(components: ResidualComponents, leverage: np.ndarray, problem: FeatureProblem,
                               N_o: np.ndarray) -> NoiseComponents:
    """The white, shared-offset and shared-tilt variances of every observation (the module docstring):
    per plane i, with the free shares 1 - h of `leverage` (O, 3),

        v_c,i = sum_o (delta_o^2 - (1 - h_0) v_w,o / N_o) / sum_o (1 - h_0)
        v_t,i = sum_o,a (z_a^2 - (1 - h_a) v_w,o) / sum_o,a (1 - h_a) lambda_a,

    pooled over all planes as their median weighted by the precision of each plane's estimate (its
    standard error without shared errors: its white part per unit scale times sqrt(2 / m_i), m_i the
    plane's free shares, per tilt component half of both; a median, so that one plane whose observations
    disagree far beyond the others' does not give every plane a shared error), each kept only where it
    exceeds `SIGNIFICANT_SE` standard errors (else 0: a pre-test estimator, biased low for shared errors
    near the white noise's level, instead of unbiased estimates floored at 0, which white noise alone
    leaves positive for half the planes), and shrunk towards the pool:
    (m_i v_i + SHARED_PRIOR_DOF v) / (m_i + SHARED_PRIOR_DOF)."""
    pidx = problem.plane_index
    free = 1.0 - leverage
    white = components.white_m2

    def per_plane(excess: np.ndarray, white_part: np.ndarray, scale: np.ndarray, dof: np.ndarray) -> np.ndarray:
        """Per observation: its plane's estimate sum(excess) / sum(scale), shrunk towards the pool."""
        e, w, s, m = (np.bincount(pidx, weights=x, minlength=problem.n_planes)
                      for x in (excess, white_part, scale, dof))
        m = np.maximum(m, 0.0)
        usable = (s > 0) & (w > 0) & (m > 0)
        own = np.where(usable, e / np.where(usable, s, 1.0), 0.0)
        # standard error of a plane's estimate when its points share nothing: its white part per unit scale
        # times sqrt(2 / m) (chi-square with m degrees of freedom)
        se = np.where(usable, w / np.where(usable, s, 1.0) * np.sqrt(2.0 / np.where(usable, m, 1.0)), np.inf)
        precision = np.where(usable, 1.0 / se**2, 0.0)
        pooled = _weighted_median(own, precision)
        pooled = pooled if pooled > SIGNIFICANT_SE * (precision.sum() ** -0.5 if precision.sum() > 0 else np.inf) \
            else 0.0
        own = np.where(own > SIGNIFICANT_SE * se, own, 0.0)
        return np.maximum((m * own + SHARED_PRIOR_DOF * pooled) / (m + SHARED_PRIOR_DOF), 0.0)[pidx]

    offset_white = free[:, 0] * white / N_o
    shared = per_plane(components.offset_m**2 - offset_white, offset_white, free[:, 0], free[:, 0])
    tilt_free = free[:, 1:] * components.counted
    tilt_white = np.sum(tilt_free * white[:, None], axis=1)
    tilt = per_plane(np.sum(components.slope**2, axis=1) - tilt_white, tilt_white,
                     np.sum(tilt_free * components.spread_m2, axis=1), 0.5 * np.sum(tilt_free, axis=1))
    return NoiseComponents(white, shared, tilt)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The median of `values` with `weights` (0 when no weight is positive): robust to a plane whose
    observations disagree far beyond the others'."""
    if not np.any(weights > 0):
        return 0.0
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def isotropic_ratio(white_m2: np.ndarray, dof: np.ndarray, incidence: np.ndarray,
                    problem: FeatureProblem) -> tuple[float, float]:
    """How the point-to-plane noise splits into an isotropic part and a part along the beam (range noise),
    from how the observations' white variances `white_m2` (O,) change with their incidence (O,), the mean
    of cos^2 between the beam and the plane normal over the observation's points. A point at cos^2 c has
    the variance s_i (gamma + c) on plane i (s_i: the surface's own level), so per observation

        log v_w,o = log s_i + log(gamma + m_o) + e_o,

    gamma = 0 pure range noise (a grazing surface's points are the less noisy), gamma -> inf isotropic noise.
    gamma is the least-squares fit over `RATIO_GRID` values of the isotropic share at the mean incidence
    m_bar, u = gamma / (gamma + m_bar) in [0, 1], with s_i profiled out per plane: only planes seen at
    several incidences inform it. Weights 1 / (2 / dof_o + tau^2): the sampling variance of the log of a
    variance with dof_o degrees of freedom `dof` (O,), plus tau^2, the spread of the observations of one
    surface beyond it (estimated from the residuals of a first fit). Returns (gamma, u); (0, 0), the
    range model, where no plane is seen at two incidences."""
    pidx = problem.plane_index
    usable = (dof > 0) & (white_m2 > 0) & (incidence > 0)
    seen = np.bincount(pidx[usable], minlength=problem.n_planes)
    usable &= seen[pidx] >= 2
    if not usable.any():
        return 0.0, 0.0
    pidx, log_v, m, dof = pidx[usable], np.log(white_m2[usable]), incidence[usable], dof[usable]
    m_bar = float(np.mean(m))
    n_planes = int(np.count_nonzero(np.bincount(pidx)))
    shares = np.linspace(0.0, 1.0, RATIO_GRID)

    def residuals(u: float, weights: np.ndarray) -> np.ndarray:
        """log v_w,o - log(gamma + m_o), each plane's weighted mean removed."""
        r = log_v - (np.log(u / (1.0 - u) * m_bar + m) if u < 1.0 else 0.0)
        mean = np.bincount(pidx, weights=weights * r) / np.maximum(np.bincount(pidx, weights=weights), 1e-300)
        return r - mean[pidx]

    tau2 = 0.0
    for _ in range(2):  # the fit, then again with tau^2 from its residuals
        weights = 1.0 / (2.0 / dof + tau2)
        sse = [float(np.sum(weights * residuals(u, weights) ** 2)) for u in shares]
        best = float(shares[int(np.argmin(sse))])
        r = residuals(best, weights)
        tau2 = max(0.0, float(np.sum(r**2 - 2.0 / dof)) / max(len(r) - n_planes, 1))
    gamma = best / (1.0 - best) * m_bar if best < 1.0 else np.inf
    return gamma, best


def plane_noise_variances(white_m2: np.ndarray, dof: np.ndarray, problem: FeatureProblem) -> np.ndarray:
    """Per-plane white point-to-plane variance (P,) in m^2: the observations' white variances pooled over
    each plane's points with their degrees of freedom `dof` (O,) (sum dof v_w,o / sum dof; 0 for a plane
    without any)."""
    dof = np.maximum(dof, 0.0)
    total = np.bincount(problem.plane_index, weights=dof * white_m2, minlength=problem.n_planes)
    count = np.bincount(problem.plane_index, weights=dof, minlength=problem.n_planes)
    return total / np.maximum(count, 1e-300)
