"""Per-scan pose covariance from the Hessian of the feature cost (planes and edges) at the optimum.

Model. Each point's signed distance to its true plane is r_k = e_k with e_k i.i.d. N(0, sigma^2)
(sigma = the point-to-plane noise, m; noise within the plane does not move a flat plane's fit).
The cost tau = sum_k r_k^2 (m^2, planes at their optimum, NO factor 1/2) has, at the optimum,
the Gauss-Newton Hessian H = 2 J^T J (J = dr/dx over the pose parameters x, with the planes
profiled out: the Schur complement of the joint pose-plane normal matrix). The maximum
likelihood estimate then has, to first order (Gauss-Newton / Laplace approximation),

    Cov(x) = sigma^2 (J^T J)^-1 = 2 sigma^2 H^-1.

With a given sigma `pose_covariance` uses the exact Hessian of the solver (equal to the
Gauss-Newton one up to terms proportional to the residuals, which vanish on average at the
optimum); where it is not positive definite (poses not at a minimum) the Gauss-Newton Hessian is
used and reported. The sandwich below uses the Gauss-Newton Hessian (the expected Hessian).
Pose priors or odometry factors that the solver adds to the cost enter H with their weights,
which are expressed in the same m^2 as the plane cost: weights point_sigma^2 / sigma_measurement^2.
In the sandwich (below) a term's measurement noise at its stated sigmas then contributes
point_sigma^2 times the term's Hessian to W (`term_variance`): the covariance of the poses the
solver returns, whatever the balance of planes and terms it minimised; with a given sigma (i.i.d.)
the terms are taken at that sigma.

Parameters x: per pose the world-frame left tangent of `pa_cli.core.geometry.retract_left`,
delta = (omega rad, rho m), T <- [[Exp(omega), rho], [0, 1]] T. The gauge pose is held fixed,
so every covariance is relative to it (the gauge pose's own covariance is zero).

Variance. Given (`point_sigma_m`): i.i.d., Cov = 2 sigma^2 H^-1. Otherwise estimated from the
residuals: the global sigma^2 = tau / (points - dof) with dof = 6 (scans - 1) + 3 planes (the
free poses and each plane's normal (2) and offset (1)) is reported, and the covariance uses per
observation (scan j on plane i) a white variance (the scatter of its points about their own
centroid along the plane normal), because a LiDAR's noise is along the ray and the point-to-plane
noise of a surface seen at grazing incidence is a fraction of that of one seen head-on, plus the
variance of the errors all its points share (their offset and tilt from the plane in that scan:
roughness, beam footprint, deskew, calibration; `pa_cli.adjust.noise_model`): the observation's
residuals have the covariance v_w I + v_c 1 1^T + v_t X X^T (X its points' in-plane offsets from
their centroid). With such a covariance V the covariance of the (unweighted) estimate is the sandwich

    Cov(x) = (J^T P J)^-1 J^T P V P J (J^T P J)^-1 = 2 H^-1 W H^-1,   W = 2 J^T P V P J,

P projecting out each plane's parameters (`variance_pieces`); for V = sigma^2 I it is
2 sigma^2 H^-1 again. `noise_model="plane"` pools the white variance per plane instead.

Within one observation the noise is not uniform either: range noise along the beam gives point k
the point-to-plane variance sigma_range^2 cos^2(incidence_k) = sigma_range^2 d^2 / |p_k|^2
(d the plane's distance from the sensor), so far points, which have the longest lever arms, are
the least noisy. A point cluster (sum of [p; 1][p; 1]^T) cannot resolve this; with the range
clusters K_o = sum_k [p_k; 1][p_k; 1]^T / |p_k|^2 of the observations (scan frame, sensor at the
origin; `FeatureProblem.range_clusters`, accumulated by the plane association), `noise_model="range"`
spreads each observation's estimated variance over its points in proportion to gamma + d^2 / |p_k|^2:
a part along the beam and an isotropic part (surface roughness, a sensor or a simulation whose noise is
not along the ray), gamma estimated from how the observations' white variances change with their mean
incidence across the observations of each plane (`isotropic_ratio`; gamma = 0 is range noise alone, where
the far points are the least noisy). It is the default (`"auto"`) when the problem carries range clusters,
else the per-observation model is. The model needs the scan frame's origin at the sensor: for scans given
in another frame (a vehicle frame with the sensor mounted elsewhere, or points already in a world
frame) 1/|p|^2 is not the incidence and the per-observation model should be chosen; deskewed
points were measured from where the sensor was at their firing time, up to half a scan period's
travel from the scan's origin, which changes their weights by about twice that travel over the range.

Edges (`scene.edges`) enter H and W as two features each, one per direction across the line, with
their own white and shared noise per observation (`pa_cli.adjust.covariance_edges`); the global
sigma, the odometry terms' variance and the reported counts are the planes'.

Computation. Only the 6x6 diagonal blocks of H^-1 are computed, by selected inversion
(`selected_inverse.py`), or for at most `DENSE_MAX_POSES` free poses on the dense matrix in numpy
(no numba kernel to compile for a short run). H is first
re-expressed per pose in (omega, delta p) with delta p = rho + omega x t the displacement of the
scan origin (a block-diagonal congruence that keeps the sparsity): this removes the lever arm of
world-frame rotations about the origin, which otherwise makes H ill-conditioned for scans far from
it. The world-tangent covariance is transformed back exactly. The blocks are assembled from the
observations' Hessian pieces straight into the block factor's storage (no sparse matrix is formed).
The sandwich is the derivative of
(H - sW)^-1 at s = 0 by a central difference; H - sW is block diagonal minus per-plane couplings
exactly linear in s, so both matrices are assembled in one pass and inverted in parallel
(`_LocalSystem.sandwich_blocks`). With the solver's `NewtonModel` (`SolveResult.model`) its setup,
and its last linearisation when that is at the given poses (the damped loop's is at the solution),
are reused.

File (`.npz`, `save_covariance` / `load_covariance`):

| array | shape | meaning |
|---|---|---|
| `covariance` | (N, 6, 6) | per scan, [omega rad, rho m] left tangent (below), relative to the gauge pose |
| `origin_world_m` | (3,) | the point the tangents' omega turns about (m, world frame) |
| `position_covariance_m2` | (N, 3, 3) | per scan, of the scan origin (world frame, m^2) |
| `position_sigma_m`, `rotation_sigma_rad` | (N,) | 1-sigma along the largest axis |
| `T_world_scan` | (N, 4, 4) | the poses the covariance belongs to |
| `point_sigma_m` | () | the given sigma, or the global residual sigma (m) |
| `point_sigma_source` | () str | `residual` or `given` |
| `gauge_pose` | () int | the fixed pose (its covariance is zero) |
| `n_points`, `dof` | () int | points on planes, parameters counted in the residual variance |
| `hessian` | () str | `exact` or `gauss-newton` |
| `noise_model` | () str | `given` (i.i.d., `point_sigma_m`), `observation`, `plane` or `range` |
| `shared_sigma_m` | () | median over observations of the estimated offset their points share (m) |
| `shared_tilt_sigma_rad` | () | the same of their shared tilt (rad, per in-plane axis) |
| `isotropic_share` | () | the range model's isotropic share of the point variance at the mean incidence (0-1) |

The tangents are those of the local frame the poses were computed in (`pa_cli.core.local_frame`): rho
moves the scan in the world frame and omega turns it about `origin_world_m`, which is zero unless
the poses lie far from the world origin (georeferenced).

Files written before `noise_model` existed load with `given` or `observation` (from `point_sigma_source`);
files without `origin_world_m` load with the world origin, without `isotropic_share` with 0.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust.covariance_edges import (
    edge_gauss_newton_pieces,
    edge_noise,
    edge_variance_pieces,
    feature_directions,
)
from pa_cli.adjust.newton import NewtonModel, rows_in_problem_order
from pa_cli.adjust.noise_model import (
    EdgeObservations,
    NoiseComponents,
    ResidualComponents,
    correlated_noise_variances,
    isotropic_ratio,
    plane_noise_variances,
    residual_components,
    residual_leverage,
)
from pa_cli.adjust.normal_terms import NormalTerms, coupling_weight
from pa_cli.adjust.selected_inverse import (
    BlockSymbolic,
    analyse_graph,
    block_graph,
    dense_diagonal_blocks_of_feature_inverses,
    diagonal_blocks_of_feature_inverses,
)
from pa_cli.adjust.terms import PoseTerm
from pa_cli.core.clusters import plane_eigen, plane_starts, scatter, sum_per_plane
from pa_cli.core.geometry import log_so3, skew
from pa_cli.core.local_frame import to_local, to_world
from pa_cli.core.problem import FEATURE_EDGE, FEATURE_PLANE, FeatureProblem
from pa_cli.errors import FormatError, InputError, SolverError
from pa_cli.io.atomic import atomic_path

PLANE_DOF = 3  # a plane's normal (2) and offset (1), fitted from the same residuals
POSE_DOF = 6
# relative step of the sandwich's central difference: truncation ~ step^2 (times the spread of the
# eigenvalues of H^-1 W), round-off ~ (selected-inversion accuracy, about 1e-16 cond(H)) / (2 step):
# below 1e-6 on small problems; on 1,000 scans of a drifting sequence (inversion accuracy 5e-8) the
# round-off leaves about 1e-4
SANDWICH_STEP = 1e-4
LEAST_CERTAIN_SCANS = 10  # scans listed in the report, least certain first
BLOCK_BYTES = POSE_DOF * POSE_DOF * 8  # one 6x6 float64 block of the factor
GB = 1e9
# a feature seen by more scans than this times the median feature's is a node candidate on its own
# (`_block_pattern`): a ground or a long facade among the local planes of a sequence
LARGE_FEATURE_FACTOR = 4.0
BLOCK_PRODUCTS_PER_WORK = 1.5  # block products of factorisation + selected inversion per BlockSymbolic.work
# at most this many free poses: dense inversion (`dense_diagonal_blocks_of_feature_inverses`, numpy only), about
# 0.03 s slower than the selected inversion at 40 scans and 0.1 s at 64 (its work grows with n^3), but with no
# numba kernel to compile (the selected inversion's take about 7 s of one core the first time)
DENSE_MAX_POSES = 48


@dataclass
class PoseCovariance:
    """Per-scan pose covariances (see the module docstring for the frame and the file)."""

    covariance: np.ndarray  # (N, 6, 6): [omega rad, rho m], left tangent about origin_world_m
    T_world_scan: np.ndarray  # (N, 4, 4)
    point_sigma_m: float
    point_sigma_source: str  # "residual" or "given"
    gauge_pose: int
    n_points: int
    dof: int
    hessian: str  # "exact" or "gauss-newton"
    noise_model: str  # "given", "observation", "plane" or "range"
    # medians over observations of the estimated errors their points share (0 with a given sigma):
    # the offset's sigma (m) and the tilt's per in-plane axis (rad)
    shared_sigma_m: float = 0.0
    shared_tilt_sigma_rad: float = 0.0
    # the range model's isotropic share of the point variance at the mean incidence (`isotropic_ratio`; 0: all
    # along the beam, 1: all isotropic; 0 for the other models)
    isotropic_share: float = 0.0
    # (3,) m: the tangents' rotations turn about this world point (pa_cli.core.local_frame)
    origin_world_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def in_world(self, origin_world_m: np.ndarray) -> PoseCovariance:
        """The covariances of poses computed in the local frame at origin_world_m
        (`pa_cli.core.local_frame`), with their world poses: the tangents stay about that origin."""
        return dataclasses.replace(self, T_world_scan=to_world(self.T_world_scan, origin_world_m),
                                   origin_world_m=np.asarray(origin_world_m, dtype=np.float64))

    def with_spread(self, difference: np.ndarray) -> PoseCovariance:
        """These covariances plus that of an error of which `difference` (N, 6; omega rad, rho m, as
        `tangent_error`, in this covariance's frame) is one draw of the difference of two independent
        copies: Cov(e_1 - e_2) = 2 Cov(e), so each pose's block gains difference difference^T / 2."""
        difference = np.asarray(difference, dtype=np.float64)
        return dataclasses.replace(self, covariance=self.covariance
                                   + np.einsum("ni,nj->nij", difference, difference) / 2.0)

    def position_covariance_m2(self) -> np.ndarray:
        """(N, 3, 3) covariance of each scan origin (world frame, m^2): d p = -[t]x omega + rho,
        t the scan's position relative to `origin_world_m`."""
        J = origin_jacobian(to_local(self.T_world_scan, self.origin_world_m))
        return J @ self.covariance @ J.transpose(0, 2, 1)

    def position_sigma_m(self) -> np.ndarray:
        """(N,) 1-sigma of each scan origin along its least certain axis (m)."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.position_covariance_m2())[:, -1], 0.0))

    def rotation_sigma_rad(self) -> np.ndarray:
        """(N,) 1-sigma of each rotation about its least certain axis (rad)."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.covariance[:, :3, :3])[:, -1], 0.0))


def origin_jacobian(T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3, 6) derivative of the scan origin t with respect to (omega, rho): [-[t]x, I]."""
    J = np.zeros((len(T_world_scan), 3, POSE_DOF))
    J[:, :, :3] = -skew(T_world_scan[:, :3, 3])
    J[:, :, 3:] = np.eye(3)
    return J


def residual_dof(n_scans: int, n_planes: int) -> int:
    """Parameters fitted from the residuals: 6 per free pose (one is the gauge) and 3 per plane."""
    return POSE_DOF * (n_scans - 1) + PLANE_DOF * n_planes


def residual_point_sigma(cost_m2: float, n_points: int, dof: int) -> float:
    """sigma (m) = sqrt(cost / (points - dof))."""
    if n_points <= dof:
        raise SolverError(f"{n_points} points on planes cannot estimate the point noise of {dof} parameters; "
                          "give it with --point-sigma-m.")
    return float(np.sqrt(max(cost_m2, 0.0) / (n_points - dof)))


def tangent_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(N, 6) error (omega rad, rho m) with T_est = [[Exp(omega), rho], [0, 1]] T_true."""
    R_err = T_est[:, :3, :3] @ T_true[:, :3, :3].transpose(0, 2, 1)
    omega = log_so3(R_err)
    rho = T_est[:, :3, 3] - np.einsum("nij,nj->ni", R_err, T_true[:, :3, 3])
    return np.hstack([omega, rho])


def nees(errors: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared e^T Sigma^-1 e per row of errors (..., 6); about 6 on average
    when the errors follow the covariance."""
    return np.einsum("...i,...i->...", errors, np.linalg.solve(covariance, errors[..., None])[..., 0])


def node_sets(scans_per_feature: np.ndarray, node_candidates: np.ndarray) -> list[np.ndarray]:
    """The sets of features the covariance may take as nodes (boolean per feature), in this order:
    every candidate, the candidates seen by more than LARGE_FEATURE_FACTOR times the median
    feature's scans (a ground or a long facade among a sequence's local planes), none."""
    large = node_candidates & (scans_per_feature > LARGE_FEATURE_FACTOR * np.median(scans_per_feature))
    return [node_candidates, large, np.zeros(len(scans_per_feature), bool)]


def _block_pattern(problem: FeatureProblem, reduced: np.ndarray, n_free: int, term_pairs: np.ndarray,
                   node_candidates: np.ndarray, feature_nodes: bool | None = None
                   ) -> tuple[BlockSymbolic, np.ndarray | None]:
    """The analysed block pattern of the free poses (`reduced`: old scan -> free index or -1) and
    the feature nodes it uses (feature -> block row n_free.., -1 for pair blocks; None: none).

    Pair blocks couple the scans sharing a feature, the pose terms' pairs (`term_pairs`) theirs.
    When some features are `node_candidates` (the solver's augmented features: many scans share
    them), the patterns of `node_sets` are compared and the one needing the fewest block products
    is kept (nodes: `selected_inverse`, "Feature nodes"; a ground among local planes alone as a
    node leaves the pair blocks a sequence's band already holds).
    `feature_nodes` True or False forces the first or the last. The patterns are taken in the order
    of `node_sets` (most nodes first: usually the cheapest) and one is skipped, without analysis,
    when a lower bound of its work already exceeds the best work so far. The factor holds at least
    the E distinct off-diagonal blocks of the matrix in its n block columns, so its work (the sum of
    squared column counts) is at least E^2 / n (Cauchy-Schwarz). E is first bounded from the feature
    sizes alone (a paired feature seen by K free scans gives K (K - 1) / 2 blocks, a node one per
    observation in a free scan), then, when that does not decide, counted (the pose pairs sharing a paired
    feature, from the scan-feature incidence): a ground every scan sees, paired, is skipped before
    its dense product is formed.
    """
    scan_index = problem.scan_index
    k = np.bincount(problem.plane_index, minlength=problem.n_planes).astype(np.float64)
    free_obs = reduced[scan_index] >= 0
    k_free = np.bincount(problem.plane_index[free_obs], minlength=problem.n_planes).astype(np.float64)

    def work_bound(blocks: float, as_node: np.ndarray) -> float:  # E^2 / n
        return blocks**2 / max(n_free + int(as_node.sum()), 1)

    def pairs_and_bound(as_node: np.ndarray) -> tuple[sp.coo_matrix, float]:
        paired = ~as_node[problem.plane_index] & free_obs
        incidence = sp.csr_matrix((np.ones(int(paired.sum())), (problem.plane_index[paired],
                                                                reduced[scan_index[paired]])),
                                  shape=(problem.n_planes, n_free))
        shared = (incidence.T @ incidence).tocoo()
        off = (shared.nnz - np.count_nonzero(shared.row == shared.col)) / 2
        off += np.count_nonzero(as_node[problem.plane_index] & free_obs)
        return shared, work_bound(off, as_node)

    def analysed(as_node: np.ndarray, shared: sp.coo_matrix) -> BlockSymbolic:
        node_obs = as_node[problem.plane_index] & free_obs
        node = n_free + np.cumsum(as_node) - 1  # block row of each node feature
        rows = np.concatenate([shared.row, reduced[term_pairs[:, 0]], reduced[scan_index[node_obs]]])
        cols = np.concatenate([shared.col, reduced[term_pairs[:, 1]], node[problem.plane_index[node_obs]]])
        keep = (rows >= 0) & (cols >= 0)
        return analyse_graph(block_graph(n_free + int(as_node.sum()), rows[keep], cols[keep]))

    if not node_candidates.any() or feature_nodes is False:
        as_node = np.zeros(problem.n_planes, bool)
        return analysed(as_node, pairs_and_bound(as_node)[0]), None
    candidates = [node_candidates] if feature_nodes else node_sets(k, node_candidates)

    def size_bound(as_node: np.ndarray) -> float:
        k_paired = float(k_free[~as_node].max(initial=0.0))
        blocks = max(k_paired * (k_paired - 1) / 2, float(k_free[as_node].sum()))
        return work_bound(blocks, as_node)

    best: tuple[BlockSymbolic, np.ndarray] | None = None
    for i, as_node in enumerate(candidates):
        if any(np.array_equal(as_node, other) for other in candidates[:i]):
            continue
        if best is not None and size_bound(as_node) > best[0].work:
            continue
        shared, bound = pairs_and_bound(as_node)
        if best is not None and bound > best[0].work:
            continue
        sym = analysed(as_node, shared)
        if best is None or sym.work < best[0].work:
            best = (sym, as_node)
    sym, as_node = best
    return sym, (np.where(as_node, n_free + np.cumsum(as_node) - 1, -1) if as_node.any() else None)


class _LocalSystem:
    """The reduced pose Hessians of one problem at one state, in the scan-origin tangent.

    Per pose x_world = M x_local with x_local = (omega, delta p), delta p = rho + omega x t the
    displacement of the scan origin: M = [[I, 0], [[t]x, I]], so H_local = M^T H M block by
    block (applied to the assembled blocks, `diagonal_blocks_of_feature_inverses`). The block
    pattern (pose pairs sharing a feature or a pose term, gauge removed; features many scans share
    as nodes when that needs fewer block products, `_block_pattern`) is analysed once. The features
    are those of `feature_directions` (every edge as its two directions across the line); the coupling
    rows passed in are in that layout (`FeatureDirections.rows`).
    """

    def __init__(self, model: NewtonModel, T_world_scan: np.ndarray, term_lins: list,
                 feature_nodes: bool | None = None):
        pattern = model.pattern
        self.directions = directions = feature_directions(model.problem)
        n_scans = pattern.n_scans
        self.free = pattern.free_poses
        reduced = np.full(n_scans, -1, np.int64)
        reduced[self.free] = np.arange(len(self.free))
        self.M = np.tile(np.eye(POSE_DOF), (n_scans, 1, 1))
        self.M[:, 3:, :3] = skew(T_world_scan[:, :3, 3])
        features = directions.problem  # each edge as its two directions (`covariance_edges`)
        self.block_of_obs = reduced[features.scan_index]
        self.starts = model.feature_cost.starts if directions.identity else plane_starts(features.plane_index,
                                                                                         features.n_planes)
        self.term_blocks = sum((t.pose_blocks for t in term_lins), np.zeros_like(self.M))[self.free]
        pairs = [np.asarray(term.pose_pairs(), np.int64).reshape(-1, 2) for term in model.terms]
        pairs = np.concatenate(pairs) if pairs else np.empty((0, 2), np.int64)
        blocks = np.concatenate([t.pair_blocks for t in term_lins]) if len(pairs) else np.empty((0, 6, 6))
        keep = (reduced[pairs[:, 0]] >= 0) & (reduced[pairs[:, 1]] >= 0)
        self.pairs, self.pair_blocks = reduced[pairs[keep]], blocks[keep]
        self.symbolic: BlockSymbolic | None = None  # None: dense inversion
        self.feature_node: np.ndarray | None = None
        if len(self.free) > DENSE_MAX_POSES or feature_nodes is not None:
            self.symbolic, self.feature_node = _block_pattern(features, reduced, len(self.free), pairs,
                                                              ~pattern.paired[directions.feature_of], feature_nodes)

    def factor_size(self) -> tuple[int, float]:
        """Off-diagonal blocks of the factor and its `BlockSymbolic.work`; the dense inversion's are
        those of a full block factor (n (n - 1) / 2 blocks, column j holding n - 1 - j of them)."""
        if self.symbolic is not None:
            return len(self.symbolic.rows), self.symbolic.work
        below = np.arange(len(self.free), dtype=np.float64)
        return int(below.sum()), float(np.sum(below**2))

    def inverse_blocks(self, A: np.ndarray, A_extra: np.ndarray, Bt: np.ndarray, Bt_extra: np.ndarray,
                       steps: np.ndarray, term_scale: np.ndarray) -> np.ndarray:
        """Diagonal blocks (m, free, 6, 6) of H_m^-1 in the local tangent, H_m from the world-tangent
        blocks per scan A + steps[m] A_extra (N, 6, 6), per feature minus U U^T + steps[m] (Y U^T + U Y^T)
        (U, Y the couplings Bt, Bt_extra) and the pose terms times term_scale[m]
        (`diagonal_blocks_of_feature_inverses`)."""
        scale = term_scale[:, None, None, None]
        diagonal = scale * self.term_blocks + A[self.free] + steps[:, None, None, None] * A_extra[self.free]
        if self.symbolic is None:
            return dense_diagonal_blocks_of_feature_inverses(self.starts, self.block_of_obs, Bt, Bt_extra, steps,
                                                             diagonal, self.pairs, scale * self.pair_blocks,
                                                             self.M[self.free])
        return diagonal_blocks_of_feature_inverses(self.symbolic, self.starts, self.block_of_obs, Bt, Bt_extra, steps,
                                                   diagonal, self.pairs, scale * self.pair_blocks, self.M[self.free],
                                                   self.feature_node)

    def plain_inverse_blocks(self, A: np.ndarray, Bt: np.ndarray) -> np.ndarray:
        """Diagonal blocks (free, 6, 6) of H^-1 in the local tangent, H from the blocks per scan A,
        couplings Bt and the pose terms."""
        return self.inverse_blocks(A, A, Bt, Bt, np.zeros(1), np.ones(1))[0]

    def sandwich_blocks(self, A_gn: np.ndarray, Bt_gn: np.ndarray, A_v: np.ndarray, Bt_v: np.ndarray,
                        Q: np.ndarray, plane_index: np.ndarray, term_variance: float) -> np.ndarray:
        """Diagonal blocks (free, 6, 6) of H^-1 W H^-1 in the local tangent from the world-tangent
        pieces (A_gn, A_v summed per scan), H the Gauss-Newton Hessian and W the variance information
        (`variance_pieces`): per plane, with beta = Bt_gn,

            W_jk = A_v,j [j = k] + beta_j^T Q beta_k - Bt_v,j^T beta_k - beta_j^T Bt_v,k
                 = A_v,j [j = k] + Y_j^T beta_k + beta_j^T Y_k,   Y_j = Q beta_j / 2 - Bt_v,j,

        plus term_variance times the pose terms. H^-1 W H^-1 = d/ds (H - s W)^-1 at s = 0, by a
        central difference at s = +-h of the matrices

            H - s W = blockdiag(A_j - s A_v,j) - sum_planes (beta^T beta + s (Y^T beta + beta^T Y)),

        exactly linear in s (no terms of higher order: H is nearly singular along the poses' drift,
        where any s^2 term, however small against H's blocks, would change (H - s W)^-1), assembled
        in one pass (every block product formed once for both) and inverted in parallel. With
        h = SANDWICH_STEP trace(H) / trace(W) the truncation error is of order SANDWICH_STEP^2 times
        the spread of H^-1 W's eigenvalues, the round-off that of the inversions over 2 SANDWICH_STEP.
        """
        beta = Bt_gn
        trace_terms = float(np.einsum("nii->", self.term_blocks))
        trace_H = np.einsum("oii->", A_gn) - np.einsum("oti,oti->", beta, beta) + trace_terms
        Y = 0.5 * (Q[plane_index] @ beta) - Bt_v  # Y_o = Q_i beta_o / 2 - Bt_v,o, o on plane i
        trace_W = np.einsum("oii->", A_v) + 2.0 * np.einsum("oti,oti->", Y, beta) + term_variance * trace_terms
        if trace_W <= 0.0:  # no noise: W = 0
            return np.zeros((len(self.free), POSE_DOF, POSE_DOF))
        h = SANDWICH_STEP * abs(trace_H) / trace_W
        steps = np.array([h, -h])
        Z = self.inverse_blocks(A_gn, -A_v, beta, Y, steps, 1.0 - steps * term_variance)  # (H -+ h W)^-1
        return (Z[0] - Z[1]) / (2.0 * h)

    def to_world(self, blocks_local: np.ndarray, n_scans: int) -> np.ndarray:
        """(N, 6, 6) world-tangent blocks M B M^T of the free poses' local blocks, zero at the gauge."""
        out = np.zeros((n_scans, POSE_DOF, POSE_DOF))
        M = self.M[self.free]
        out[self.free] = M @ blocks_local @ M.transpose(0, 2, 1)
        return out


def observation_noise(eig: tuple, problem: FeatureProblem, moments: tuple, system: _LocalSystem,
                      A_gn: np.ndarray, edges: EdgeObservations | None = None
                      ) -> tuple[ResidualComponents, NoiseComponents, np.ndarray | None]:
    """Every observation's residual components at the planes of `eig` (`plane_eigen` at the
    optimum) and its white, shared-offset and shared-tilt variances (`pa_cli.adjust.noise_model`),
    with the leverage of the pose system `system` whose Gauss-Newton blocks per scan are `A_gn`
    (N, 6, 6, of every feature) plus the pose terms' blocks; with `edges` (the problem's edge features) the
    lines are fitted parameters too, and the third result is the leverage (O_e, 2) of each edge observation's
    offset across its line (None without edges)."""
    components = residual_components(eig, problem, moments)
    leverage, edge_leverage = residual_leverage(eig, problem, moments, components,
                                                A_gn[system.free] + system.term_blocks, system.free, system.pairs,
                                                system.pair_blocks, edges=edges)
    return components, correlated_noise_variances(components, leverage, problem, moments[3]), edge_leverage


def gauss_newton_pieces(eig: tuple, plane_index: np.ndarray, S_o: np.ndarray, c_o: np.ndarray, N_o: np.ndarray,
                        scan_index: np.ndarray | None = None, n_scans: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton blocks A_gn (O, 6, 6), or with `scan_index` their sums per scan (n_scans, 6, 6), and
    plane couplings Bt_gn (O, 3, 6) of observations with
    world scatter S_o, centroid c_o and count N_o (points, or points weighted) on the planes of
    `eig` (`plane_eigen` outputs), as `PlaneCost.linearize` gives them for the points (formulas in
    `pa_cli.adjust.newton`: A = [[2 [n]x P [n]x^T, 2 (v x n) n^T], [., 2 N n n^T]] with
    P = sum q q^T, v = sum q; tangent rows [(P m + e v) x n; (m.v + N e) n] about the plane
    centroid, offset row [v x n; N n], weighted by sqrt(2 / lambda_k) and sqrt(2 / N_plane))."""
    _, _, lam, vec, centroid, N_plane = eig
    terms = NormalTerms.build(vec[plane_index, :, 0], S_o, c_o, c_o - centroid[plane_index], N_o)
    w_gn = coupling_weight(lam[:, 1:])
    Bt = np.empty((len(plane_index), 3, POSE_DOF))
    for k in range(2):  # the two tangent directions of the normal (fixed count, not a data loop)
        Bt[:, k] = w_gn[plane_index, k][:, None] * terms.tangent_row(vec[plane_index, :, k + 1])[1]
    Bt[:, 2] = np.sqrt(2.0 / N_plane)[plane_index, None] * terms.offset_row()
    A = terms.gauss_newton_blocks()
    return (A if scan_index is None else _sum_per_scan(A, scan_index, n_scans)), Bt


def _plane_coordinate_information(vec: np.ndarray, centroid: np.ndarray, starts: np.ndarray, S_o: np.ndarray,
                                  c_o: np.ndarray, N_o: np.ndarray) -> np.ndarray:
    """(P, 3, 3) information of each plane's observations (world scatter S_o, centroid c_o, count
    N_o, points or points weighted) on the plane's coordinates q_1, q_2 (the in-plane eigenvectors of
    `vec`, about the plane centroid) and q_3 (offset): per plane, from the weighted scatter, first
    moment and count of its points about its centroid."""
    plane = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    d = c_o - centroid[plane]
    scatter_about = sum_per_plane(S_o + N_o[:, None, None] * d[:, :, None] * d[:, None, :], starts)
    first = sum_per_plane(N_o[:, None] * d, starts)
    E = vec[:, :, 1:]
    G = np.empty((len(E), 3, 3))
    G[:, :2, :2] = E.transpose(0, 2, 1) @ scatter_about @ E
    G[:, :2, 2] = G[:, 2, :2] = np.einsum("pia,pi->pa", E, first)
    G[:, 2, 2] = sum_per_plane(N_o, starts)
    return G


def variance_pieces(T_world_scan: np.ndarray, eig: tuple, problem: FeatureProblem, moments: tuple,
                    v_obs: np.ndarray, range_clusters: np.ndarray | None = None, v_shared: np.ndarray | None = None,
                    v_tilt: np.ndarray | None = None, isotropic: np.ndarray | float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pieces of W = 2 J^T P V P J (P projecting out each plane's 3 parameters) when the
    points of observation o have point-to-plane variances summing to v_obs[o] N_o (m^2):
    A_v (N, 6, 6) summed per scan and Bt_v (O, 3, 6), the Gauss-Newton blocks and coupling rows of
    the variance-weighted points, and per plane Q (P, 3, 3) = G^-1/2 (sum_j G_v,j) G^-1/2 (G the
    plane's information diag(lambda_2, lambda_3, N) on its coordinates, G_v,j observation j's
    variance-weighted share). Then W_jk = A_v,j [j = k] + beta_j^T Q beta_k - Bt_v,j^T beta_k
    - beta_j^T Bt_v,k with beta = Bt_gn (`_LocalSystem.sandwich_blocks`).

    Without `range_clusters` every point of observation o has variance v_obs[o] (the pieces of the
    observation's cluster times v_obs[o]: they are linear in the cluster). `range_clusters`
    (O, 4, 4), K_o = sum_k [p_k; 1][p_k; 1]^T / |p_k|^2 over the observation's points in the scan frame
    (sensor at the origin), model range noise along the beam: the point-to-plane variance of point k
    is sigma_range^2 cos^2(incidence) = sigma_range^2 (n . p_k)^2 / |p_k|^2, and n . p_k (the
    plane's distance from the sensor) is the same for all the observation's points, so its variance
    is proportional to 1/|p_k|^2: the variance-weighted cluster is v_obs[o] N_o K_o / K_o[3, 3]. With
    `isotropic` (O,) or scalar, the share a_o of observation o's variance that is isotropic (the same for
    every point; `isotropic_shares`), it is v_obs[o] N_o (a_o C_o / N_o + (1 - a_o) K_o / K_o[3, 3]) with C_o
    the observation's cluster.

    `v_shared` (O,) adds an error shared by all points of observation o (variance v_shared[o], m^2:
    the covariance of its residuals becomes V_o + v_shared[o] 1 1^T). Its share of W is
    2 v_shared J^T P 1 1^T P J, and since a point's rows of J and of the plane Jacobian are affine in
    its position, 1^T J is N_o times the rows of one point at the observation's centroid c_o: the
    shared error is the variance-weighted cluster of one point at c_o with weight v_shared N_o^2,
    added to the cluster of the white noise. `v_tilt` (O,) adds a tilt shared by its points, residual
    a . (q_k - c_o) with a in the plane of variance v_tilt[o] per axis (rad^2): its rows sum to the
    moments [S_o t; 0] of the in-plane directions t, a second moment with zero first moment, so it adds
    v_tilt S_o (I - n n^T) S_o to the variance-weighted scatter (S_o the observation's world scatter).
    """
    S_o, c_o, lam, vec, centroid, N_plane = eig
    pidx = problem.plane_index
    N_o = moments[3]
    starts = np.r_[0, np.cumsum(np.bincount(pidx, minlength=problem.n_planes))]
    if range_clusters is None:
        S_v, c_v, N_v = v_obs[:, None, None] * S_o, c_o, v_obs * N_o
    else:
        a = np.broadcast_to(np.asarray(isotropic, dtype=np.float64), v_obs.shape)
        weighted = ((v_obs * N_o * (1.0 - a) / range_clusters[:, 3, 3])[:, None, None] * range_clusters
                    + (v_obs * a)[:, None, None] * problem.clusters)
        S_scan, c_scan, N_v = scatter(weighted)
        T = T_world_scan[problem.scan_index]  # the scatter rotated to the world, the centroid moved
        S_v = T[:, :3, :3] @ S_scan @ T[:, :3, :3].transpose(0, 2, 1)
        c_v = np.einsum("oij,oj->oi", T[:, :3, :3], c_scan) + T[:, :3, 3]
    if v_tilt is not None:
        n = vec[pidx, :, 0]
        in_plane = np.eye(3) - n[:, :, None] * n[:, None, :]
        S_v = S_v + v_tilt[:, None, None] * (S_o @ in_plane @ S_o)
    if v_shared is not None:  # one point at the centroid c_o with weight v_shared N_o^2
        w = v_shared * N_o**2
        N_sum = N_v + w
        with np.errstate(divide="ignore", invalid="ignore"):
            c_sum = np.where((N_sum != 0)[:, None], (N_v[:, None] * c_v + w[:, None] * c_o)
                             / np.where(N_sum != 0, N_sum, 1.0)[:, None], c_o)
        d_v, d_c = c_v - c_sum, c_o - c_sum
        S_v = (S_v + N_v[:, None, None] * d_v[:, :, None] * d_v[:, None, :]
               + w[:, None, None] * d_c[:, :, None] * d_c[:, None, :])
        c_v, N_v = c_sum, N_sum
    G_v = _plane_coordinate_information(vec, centroid, starts, S_v, c_v, N_v)
    A_v, Bt_v = gauss_newton_pieces(eig, pidx, S_v, c_v, N_v, problem.scan_index, problem.n_scans)
    g = np.column_stack([lam[:, 1], lam[:, 2], N_plane])
    with np.errstate(divide="ignore", invalid="ignore"):
        g_isqrt = np.where(g > 0, 1.0 / np.sqrt(np.where(g > 0, g, 1.0)), 0.0)
    Q = g_isqrt[:, :, None] * G_v * g_isqrt[:, None, :]
    return A_v, Bt_v, 0.5 * (Q + Q.transpose(0, 2, 1))


def incidence(T_world_scan: np.ndarray, eig: tuple, problem: FeatureProblem, range_clusters: np.ndarray) -> np.ndarray:
    """(O,) each observation's mean cos^2 between the beam and its plane's normal over its points: d_o^2
    K_o[3, 3] / N_o, with d_o the distance of the scan's origin (the sensor) from the plane and K_o the range
    cluster (sum of [p; 1][p; 1]^T / |p|^2: cos^2 = d_o^2 / |p_k|^2 for a point on the plane)."""
    _, _, _, vec, centroid, _ = eig
    pidx, sidx = problem.plane_index, problem.scan_index
    d = np.einsum("oi,oi->o", vec[pidx, :, 0], T_world_scan[sidx, :3, 3] - centroid[pidx])
    return np.clip(d**2 * range_clusters[:, 3, 3] / problem.clusters[:, 3, 3], 0.0, 1.0)


def isotropic_shares(gamma: float, cos2: np.ndarray) -> np.ndarray:
    """(O,) the share of each observation's variance that is isotropic when a point at cos^2 c has the variance
    s (gamma + c) (`isotropic_ratio`): gamma / (gamma + m_o), m_o the observation's mean cos^2 `cos2`."""
    if np.isinf(gamma):
        return np.ones_like(cos2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(gamma + cos2 > 0, gamma / (gamma + cos2), 1.0)


def term_variance(terms: Sequence[PoseTerm], residual_sigma_m: float) -> float:
    """The variance (m^2) the pose terms' measurements enter the sandwich with: a term whose weights
    are point_sigma^2 / measurement sigma^2 (it has `point_sigma_m`, as `OdometryFactors`) brings
    its measurement noise at its stated sigmas, which is point_sigma^2 in the plane cost's units;
    terms without one (or disagreeing) are taken at the residual point sigma."""
    sigmas = {getattr(term, "point_sigma_m", None) for term in terms}
    if len(sigmas) == 1 and None not in sigmas:
        return float(sigmas.pop()) ** 2
    return residual_sigma_m**2


def _sum_per_scan(blocks: np.ndarray, scan_index: np.ndarray, n_scans: int) -> np.ndarray:
    """(n_scans, 6, 6) sums per scan of per-observation blocks (O, 6, 6) in scans `scan_index` (O,)."""
    n_obs = len(scan_index)
    incidence = sp.csr_matrix((np.ones(n_obs), (scan_index, np.arange(n_obs))), shape=(n_scans, n_obs))
    return np.asarray(incidence @ blocks.reshape(n_obs, -1)).reshape(n_scans, POSE_DOF, POSE_DOF)


def _per_scan(blocks: np.ndarray, problem: FeatureProblem) -> np.ndarray:
    """(N, 6, 6) sums per scan of per-observation blocks (O, 6, 6)."""
    return _sum_per_scan(blocks, problem.scan_index, problem.n_scans)


NOISE_MODELS = ("auto", "observation", "plane", "range")


def resolve_noise_model(noise_model: str, range_clusters: np.ndarray | None) -> str:
    """The estimated-noise model to use: `auto` is `range` with range clusters, else `observation`."""
    if noise_model not in NOISE_MODELS:
        raise SolverError(f"unknown noise model '{noise_model}'; expected one of {', '.join(NOISE_MODELS)}.")
    if noise_model == "auto":
        return "observation" if range_clusters is None else "range"
    return noise_model


def check_factor_size(factor_blocks: int, work: float, n_systems: int, memory_budget_gb: float,
                      max_block_products: float) -> None:
    """Raise `SolverError` when `n_systems` block factors of `factor_blocks` blocks and `work`
    (`BlockSymbolic.work`, `_LocalSystem.factor_size`) exceed `memory_budget_gb` or their factorisations
    and inversions `max_block_products` block products. A sequential pose graph has a banded factor
    (memory and work linear in scans); revisits (loop closures, a room scanned for thousands of scans)
    couple scans far apart and fill the factor towards dense (memory quadratic, work cubic in scans)."""
    factor_gb = n_systems * factor_blocks * BLOCK_BYTES / GB
    products = n_systems * BLOCK_PRODUCTS_PER_WORK * work
    if factor_gb > memory_budget_gb:
        raise SolverError(f"the pose covariance's block factor needs {factor_gb:.1f} GB, above "
                          f"execution.memory_budget_gb = {memory_budget_gb:g} (revisited places couple scans far "
                          "apart).")
    if products > max_block_products:
        raise SolverError(f"the pose covariance needs {products:.2g} 6x6 block products, above "
                          f"advanced.covariance.max_block_products = {max_block_products:.2g} (revisited places couple "
                          "scans far apart and fill its factor); raise it to compute it anyway.")


def _model_of(model: NewtonModel | None, problem: FeatureProblem, fixed_pose: int, eigen_gap_tolerance: float,
              terms: Sequence[PoseTerm]) -> bool:
    """True when `model` was built for this problem object, gauge, eigen-gap tolerance and pose terms."""
    return (model is not None and model.problem is problem and model.pattern.fixed_pose == fixed_pose
            and model.feature_cost.parts[0][1].eigen_gap_tolerance == eigen_gap_tolerance
            and len(model.terms) == len(terms) and all(a is b for a, b in zip(model.terms, terms, strict=True)))


def pose_covariance(problem: FeatureProblem, T_world_scan: np.ndarray, fixed_pose: int = 0,
                    point_sigma_m: float | None = None, eigen_gap_tolerance: float = 1e-6,
                    terms: Sequence[PoseTerm] = (), noise_model: str = "auto",
                    model: NewtonModel | None = None, range_clusters: np.ndarray | None = None,
                    memory_budget_gb: float = math.inf, max_block_products: float = math.inf) -> PoseCovariance:
    """Covariance of every pose at (converged) poses T_world_scan; see the module docstring.

    With `point_sigma_m` the noise is i.i.d. with that sigma (2 sigma^2 H^-1). Otherwise the
    variances are estimated from the residuals (`pa_cli.adjust.noise_model`): a white variance per
    observation (`noise_model="observation"`) or per plane (`"plane"`), or per observation and spread
    over its points as range noise along the beam (`"range"`, with `range_clusters`, default the
    problem's, see `variance_pieces`; `"auto"`: `"range"` when there are range clusters, else
    `"observation"`), plus the offset and tilt each observation's points share, and the sandwich
    2 H^-1 W H^-1 (`variance_pieces`, `_LocalSystem.sandwich_blocks`) is used, with the Gauss-Newton
    Hessian H. `terms` are the pose terms the solver minimised with the planes (such as the odometry
    factors): their Hessian blocks are part of H, and sigma^2 times them part of W. `model` reuses the
    solver's `NewtonModel` (`SolveResult.model`; ignored unless built for this problem object, gauge,
    eigen-gap tolerance and terms): its setup is then skipped, and where its last linearisation is at
    T_world_scan (the damped loop's is at the solution) so are the plane eigen-decompositions and, with
    a given sigma, the Hessian pieces. Raises `SolverError` before any numerical work when the block
    factor would exceed `memory_budget_gb` or its factorisation and selected inversion
    `max_block_products` 6x6 block products (`check_factor_size`).
    """
    if range_clusters is None:
        range_clusters = problem.range_clusters
    noise_model = resolve_noise_model(noise_model, range_clusters)
    expected_shape = (problem.n_observations, 4, 4)
    if noise_model == "range" and (range_clusters is None or np.shape(range_clusters) != expected_shape):
        found = None if range_clusters is None else np.shape(range_clusters)
        raise SolverError(f"the range noise model needs range clusters of shape {expected_shape} (one per "
                          f"observation: sum of [p; 1][p; 1]^T / |p|^2 in the scan frame); got {found}.")
    T = np.asarray(T_world_scan, dtype=np.float64)
    if not _model_of(model, problem, fixed_pose, eigen_gap_tolerance, terms):
        model = NewtonModel(problem, fixed_pose, eigen_gap_tolerance, terms)
    parts = {int(part.problem.feature_kind[0]): (obs, part) for obs, part in model.feature_cost.parts}
    if FEATURE_PLANE not in parts:
        raise SolverError("the pose covariance needs plane features (their residuals give the noise scale); the "
                          "problem has edges only.")
    plane_obs, plane_cost = parts[FEATURE_PLANE]
    planes = plane_cost.problem
    system = _LocalSystem(model, T, [term.linearize(T) for term in model.terms])
    directions = system.directions
    n_systems = 1 if point_sigma_m is not None else 2
    check_factor_size(*system.factor_size(), n_systems, memory_budget_gb, max_block_products)
    dof = residual_dof(problem.n_scans, planes.n_planes)
    eig = plane_cost.eigen_of_last_linearization(T) if directions.identity else None
    if eig is None:  # the solver's last linearisation is at the solution (planes alone: its eigen-decompositions)
        eig = plane_eigen(T, *plane_cost.moments, planes.scan_index, plane_cost.starts)
    sigma_residual = residual_point_sigma(float(np.sum(np.maximum(eig[2][:, 0], 0.0))), planes.n_points, dof)
    if point_sigma_m is None:
        sigma, source, kind, used = sigma_residual, "residual", "gauss-newton", noise_model
        A_gn, Bt_gn_planes = gauss_newton_pieces(eig, planes.plane_index, eig[0], eig[1], plane_cost.moments[3],
                                                 planes.scan_index, planes.n_scans)
        edges = parts.get(FEATURE_EDGE)
        if edges is not None:
            edge_obs, edge_cost = edges
            edge_eig = plane_eigen(T, *edge_cost.moments, edge_cost.problem.scan_index, edge_cost.starts)
            edge_index, N_edge_o = edge_cost.problem.plane_index, edge_cost.moments[3]
            A_edges, Bt_gn_edges = edge_gauss_newton_pieces(edge_eig, edge_index, edge_eig[0], edge_eig[1], N_edge_o)
            A_gn = A_gn + _sum_per_scan(A_edges, edge_cost.problem.scan_index, problem.n_scans)
        components, noise, edge_leverage = observation_noise(
            eig, planes, plane_cost.moments, system, A_gn,
            None if edges is None else EdgeObservations(edge_eig, edge_index, edge_cost.problem.scan_index, N_edge_o))
        v_obs = noise.white_m2
        white_dof = plane_cost.moments[3] - 1.0 - components.counted.sum(axis=1)
        if noise_model == "plane":
            v_obs = plane_noise_variances(v_obs, white_dof, planes)[planes.plane_index]
        shared = (float(np.sqrt(np.median(noise.shared_m2))), float(np.sqrt(np.median(noise.tilt_rad2))))
        isotropic, share = 0.0, 0.0
        plane_range = None if range_clusters is None else range_clusters[plane_obs]
        if noise_model == "range":
            cos2 = incidence(T, eig, planes, plane_range)
            gamma, share = isotropic_ratio(noise.white_m2, white_dof, cos2, planes)
            isotropic = isotropic_shares(gamma, cos2)
        A_v, Bt_v_planes, Q_planes = variance_pieces(T, eig, planes, plane_cost.moments, v_obs,
                                                     plane_range if noise_model == "range" else None,
                                                     noise.shared_m2, noise.tilt_rad2, isotropic)
        Bt_gn, Bt_v, Q = Bt_gn_planes, Bt_v_planes, Q_planes
        if edges is not None:
            white, shared_edges = edge_noise(edge_eig, edge_index, N_edge_o, edge_leverage)
            A_v_edges, Bt_v_edges, Q_edges = edge_variance_pieces(edge_eig, edge_index, N_edge_o, white, shared_edges)
            A_v = A_v + _sum_per_scan(A_v_edges, edge_cost.problem.scan_index, problem.n_scans)
            Bt_gn, Bt_v = (rows_in_problem_order(problem.n_observations, [(plane_obs, a), (edge_obs, b)])
                           for a, b in ((Bt_gn_planes, Bt_gn_edges), (Bt_v_planes, Bt_v_edges)))
            Q = np.zeros((problem.n_planes, Q_edges.shape[1], Q_edges.shape[1]))
            Q[problem.feature_kind == FEATURE_PLANE, :Q_planes.shape[1], :Q_planes.shape[1]] = Q_planes
            Q[problem.feature_kind == FEATURE_EDGE] = Q_edges
        blocks = system.sandwich_blocks(A_gn, directions.rows(Bt_gn), A_v, directions.rows(Bt_v),
                                        directions.features(Q), directions.problem.plane_index,
                                        term_variance(terms, sigma))
    elif np.isfinite(point_sigma_m) and point_sigma_m > 0:
        sigma, source, used, shared, share = float(point_sigma_m), "given", "given", (0.0, 0.0), 0.0
        reuse = model.last is not None and model.last[1].left_der is not None and np.array_equal(model.last[0], T)
        der = model.last[1].left_der if reuse else model.feature_cost.linearize(T)
        try:
            kind = "exact"
            blocks = sigma**2 * system.plain_inverse_blocks(_per_scan(der.A, problem), directions.rows(der.Bt))
        except SolverError:
            kind = "gauss-newton"
            blocks = sigma**2 * system.plain_inverse_blocks(_per_scan(der.A_gn, problem), directions.rows(der.Bt_gn))
    else:
        raise SolverError(f"the point sigma must be a positive number of metres; got {point_sigma_m} "
                          "(--point-sigma-m).")
    cov = 2.0 * system.to_world(blocks, problem.n_scans)
    return PoseCovariance(covariance=cov, T_world_scan=T, point_sigma_m=sigma, point_sigma_source=source,
                          gauge_pose=int(fixed_pose), n_points=int(planes.n_points), dof=int(dof), hessian=kind,
                          noise_model=used, shared_sigma_m=shared[0], shared_tilt_sigma_rad=shared[1],
                          isotropic_share=share)


def covariance_report(cov: PoseCovariance, time_s: float | None = None) -> dict[str, Any]:
    """Report entries: the noise used, per-scan 1-sigma position (m) and rotation (deg) along the
    least certain axis, and the `LEAST_CERTAIN_SCANS` scans with the largest position sigma."""
    pos = cov.position_sigma_m()
    rot_deg = np.rad2deg(cov.rotation_sigma_rad())
    free = np.flatnonzero(np.arange(len(pos)) != cov.gauge_pose)
    worst = free[np.argsort(-pos[free], kind="stable")[:LEAST_CERTAIN_SCANS]]
    report: dict[str, Any] = {
        "point_sigma_m": cov.point_sigma_m,
        "point_sigma_source": cov.point_sigma_source,
        "dof": cov.dof,
        "n_points": cov.n_points,
        "gauge_pose": cov.gauge_pose,
        "hessian": cov.hessian,
        "noise_model": cov.noise_model,
        "shared_sigma_m": cov.shared_sigma_m,
        "shared_tilt_sigma_deg": float(np.rad2deg(cov.shared_tilt_sigma_rad)),
        "isotropic_share": cov.isotropic_share,
        "position_sigma_m": pos.tolist(),
        "rotation_sigma_deg": rot_deg.tolist(),
        "position_sigma_m_median": float(np.median(pos[free])) if len(free) else 0.0,
        "rotation_sigma_deg_median": float(np.median(rot_deg[free])) if len(free) else 0.0,
        "least_certain_scans": [{"scan": int(j), "position_sigma_m": float(pos[j]),
                                 "rotation_sigma_deg": float(rot_deg[j])} for j in worst],
    }
    if time_s is not None:
        report["time_s"] = time_s
    return report


def timed_pose_covariance(problem: FeatureProblem, T_world_scan: np.ndarray, **kwargs: Any
                          ) -> tuple[PoseCovariance, dict[str, Any]]:
    """`pose_covariance` and its `covariance_report` (with the wall time)."""
    t0 = time.perf_counter()
    cov = pose_covariance(problem, T_world_scan, **kwargs)
    return cov, covariance_report(cov, time.perf_counter() - t0)


def save_covariance(path: Path | str, cov: PoseCovariance, force: bool = False) -> None:
    """Write the covariance file (`.npz`, atomically; the arrays of the module docstring)."""
    arrays = {
        "covariance": cov.covariance,
        "position_covariance_m2": cov.position_covariance_m2(),
        "position_sigma_m": cov.position_sigma_m(),
        "rotation_sigma_rad": cov.rotation_sigma_rad(),
        "T_world_scan": cov.T_world_scan,
        "origin_world_m": np.asarray(cov.origin_world_m, dtype=np.float64),
        "point_sigma_m": np.float64(cov.point_sigma_m),
        "point_sigma_source": np.str_(cov.point_sigma_source),
        "gauge_pose": np.int64(cov.gauge_pose),
        "n_points": np.int64(cov.n_points),
        "dof": np.int64(cov.dof),
        "hessian": np.str_(cov.hessian),
        "noise_model": np.str_(cov.noise_model),
        "shared_sigma_m": np.float64(cov.shared_sigma_m),
        "shared_tilt_sigma_rad": np.float64(cov.shared_tilt_sigma_rad),
        "isotropic_share": np.float64(cov.isotropic_share),
    }
    with atomic_path(path, force) as tmp, tmp.open("wb") as f:
        np.savez_compressed(f, **arrays)


def load_covariance(path: Path | str) -> PoseCovariance:
    """Read a covariance file written by `save_covariance`."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: covariance file not found.")
    try:
        with np.load(path, allow_pickle=False) as data:
            source = str(data["point_sigma_source"])
            noise_model = str(data["noise_model"]) if "noise_model" in data.files else \
                ("given" if source == "given" else "observation")
            cov = PoseCovariance(covariance=data["covariance"], T_world_scan=data["T_world_scan"],
                                 point_sigma_m=float(data["point_sigma_m"]),
                                 point_sigma_source=source,
                                 gauge_pose=int(data["gauge_pose"]), n_points=int(data["n_points"]),
                                 dof=int(data["dof"]), hessian=str(data["hessian"]), noise_model=noise_model,
                                 shared_sigma_m=float(data["shared_sigma_m"]) if "shared_sigma_m" in data.files
                                 else 0.0,
                                 shared_tilt_sigma_rad=float(data["shared_tilt_sigma_rad"])
                                 if "shared_tilt_sigma_rad" in data.files else 0.0,
                                 isotropic_share=float(data["isotropic_share"]) if "isotropic_share" in data.files
                                 else 0.0,
                                 origin_world_m=np.asarray(data["origin_world_m"], dtype=np.float64)
                                 if "origin_world_m" in data.files else np.zeros(3))
    except (OSError, ValueError, KeyError) as exc:
        raise FormatError(f"{path}: not a pose-covariance .npz with 'covariance', 'T_world_scan', "
                          f"'point_sigma_m', ... ({exc}).") from None
    n = len(cov.T_world_scan)
    if cov.covariance.shape != (n, POSE_DOF, POSE_DOF) or cov.T_world_scan.shape != (n, 4, 4):
        raise FormatError(f"{path}: 'covariance' has shape {cov.covariance.shape} and 'T_world_scan' "
                          f"{cov.T_world_scan.shape}; expected (N, 6, 6) and (N, 4, 4).")
    return cov
