"""The edges' part of the pose covariance (`pa_cli.adjust.covariance`): every edge as its two directions
across the line, each a feature with the pieces of a plane.

An edge's cost is the sum of its points' squared distances along the two normals u_1, u_2 across its
line (`pa_cli.adjust.edges`). Its Gauss-Newton Hessian is that of two features, one per normal u_j:
each observation's block with the feature fixed (a plane's with normal u_j) minus two coupling rows, the
line turning towards u_j (curvature lambda_3, weight sqrt(2 / lambda_3)) and its offset along u_j
(curvature N, weight sqrt(2 / N)). A point's errors along u_1 and u_2 are independent with one variance
(noise isotropic across the line), and each direction's line coordinates (its tilt and offset) fit that
direction's residuals alone, so an edge's variance information W is the sum of its two directions' too.
The covariance therefore takes every edge as two features of three coupling rows (the third zero), the
planes' layout (`FeatureDirections`): the selected inversion and its feature nodes work as they are.

Noise, per edge observation o (world scatter S_o about its centroid c_o, N_o points, U = [u_1 u_2]):

- white, per direction: v_o = trace(U^T S_o U) / (2 (N_o - 1)), the scatter of its points across the
  line about their own centroid (a pole's near half spreads r^2 / 3 sideways: the sampling of the pole's
  surface by the beams counts as noise);
- shared by all its points (the view correction's error, a pole that is not round or not straight),
  per direction, per edge from its observations' centroids across the line, d_o,a = u_a . (c_o - c): with
  h_o,a the share of d_o,a the fit takes (the lines, the poses and the pose terms: the leverage of
  `noise_model.residual_leverage`), E[d_o,a^2] = (v_s + v_o / N_o)(1 - h_o,a), so
  v_s = sum_o,a (d_o,a^2 - (1 - h_o,a) v_o / N_o) / sum_o,a (1 - h_o,a), shrunk towards the value pooled over
  all edges as the planes' shared variances are (`SHARED_PRIOR_DOF`), at least 0.

The shared offset enters W as one point at c_o with weight v_s N_o^2 (the planes' `variance_pieces`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.adjust.noise_model import SHARED_PRIOR_DOF
from pa_cli.adjust.normal_terms import NormalTerms, coupling_weight
from pa_cli.core.problem import FEATURE_EDGE, FeatureProblem

COUPLING_ROWS = 3  # coupling rows per feature in the covariance's layout (a plane's; an edge direction uses two)
EDGE_ROWS = 4  # an edge's coupling rows (`pa_cli.adjust.edges`): turn and offset towards u_1, then u_2


@dataclass(frozen=True)
class FeatureDirections:
    """A problem's features as the covariance takes them: each plane once, each edge twice (its two directions
    across the line, in that order), observations sorted by the new features. `problem` gives the pattern (the
    new features' observations, clusters unchanged), `source_obs` (O',) each observation's index in the
    original problem and `first_row` (O',) where its coupling rows start in the original rows (0, or 2 for an
    edge's second direction), `feature_of` (F',) the original feature of each new one."""

    problem: FeatureProblem
    source_obs: np.ndarray
    first_row: np.ndarray
    feature_of: np.ndarray
    is_edge: np.ndarray  # (F',) bool: the new feature is an edge direction

    @property
    def identity(self) -> bool:
        """No edges: the original problem and its rows as they are."""
        return not self.is_edge.any()

    def rows(self, Bt: np.ndarray) -> np.ndarray:
        """(O', 3, 6) coupling rows of the new features from the original problem's (O, R, 6)."""
        if self.identity:
            return Bt
        out = np.zeros((len(self.source_obs), COUPLING_ROWS, Bt.shape[2]))
        plane = ~self.is_edge[self.problem.plane_index]
        out[plane] = Bt[self.source_obs[plane], :COUPLING_ROWS]
        for first in (0, 2):
            edge = ~plane & (self.first_row == first)
            out[edge, :2] = Bt[self.source_obs[edge], first:first + 2]
        return out

    def features(self, Q: np.ndarray) -> np.ndarray:
        """(F', 3, 3) per-feature matrices on the coupling rows from the original features' (F, R, R), an
        edge's (4, 4) block diagonal in its two directions."""
        if self.identity:
            return Q
        out = np.zeros((len(self.feature_of), COUPLING_ROWS, COUPLING_ROWS))
        out[~self.is_edge] = Q[self.feature_of[~self.is_edge], :COUPLING_ROWS, :COUPLING_ROWS]
        edge = np.flatnonzero(self.is_edge)
        second = np.r_[False, self.feature_of[1:] == self.feature_of[:-1]][edge]
        for k, first in ((edge[~second], 0), (edge[second], 2)):
            out[k, :2, :2] = Q[self.feature_of[k], first:first + 2, first:first + 2]
        return out


def feature_directions(problem: FeatureProblem) -> FeatureDirections:
    """The covariance's features of `problem` (`FeatureDirections`; observations sorted by feature)."""
    n_features = problem.n_planes
    edge_feature = problem.feature_kind == FEATURE_EDGE
    if not edge_feature.any():
        return FeatureDirections(problem, np.arange(problem.n_observations), np.zeros(problem.n_observations, np.int64),
                                 np.arange(n_features), np.zeros(n_features, bool))
    copies = np.where(edge_feature, 2, 1)
    feature_of = np.repeat(np.arange(n_features), copies)
    new_first = np.cumsum(copies) - copies  # the first new feature of each original one
    order = np.argsort(problem.plane_index, kind="stable")  # the observations by feature
    source, new_feature, first_row = [], [], []
    for copy in (0, 1):
        take = order[copy < copies[problem.plane_index[order]]]
        source.append(take)
        new_feature.append(new_first[problem.plane_index[take]] + copy)
        first_row.append(np.full(len(take), 2 * copy))
    source, new_feature, first_row = (np.concatenate(a) for a in (source, new_feature, first_row))
    by_feature = np.argsort(new_feature, kind="stable")
    source, new_feature, first_row = source[by_feature], new_feature[by_feature], first_row[by_feature]
    directions = FeatureProblem(plane_index=new_feature, scan_index=problem.scan_index[source],
                                clusters=problem.clusters[source], n_scans=problem.n_scans,
                                T_world_scan=problem.T_world_scan)
    return FeatureDirections(directions, source, first_row, feature_of, edge_feature[feature_of])


def edge_gauss_newton_pieces(eig: tuple, edge_index: np.ndarray, S_o: np.ndarray, c_o: np.ndarray, N_o: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton blocks (O, 6, 6) and coupling rows (O, 4, 6) of edge observations with world scatter S_o,
    centroid c_o and count N_o (points, or points weighted) on the lines of `eig` (`plane_eigen` of the edges:
    normals vec[:, :, :2], direction vec[:, :, 2], centroid, lambda, counts), as `EdgeCost.linearize` gives
    them for the points (world-frame left tangent)."""
    _, _, lam, vec, centroid, N_edge = eig
    line = vec[edge_index, :, 2]
    w_turn = coupling_weight(lam[:, 2])[edge_index, None]
    w_offset = np.sqrt(2.0 / N_edge)[edge_index, None]
    A = np.zeros((len(edge_index), 6, 6))
    Bt = np.empty((len(edge_index), EDGE_ROWS, 6))
    for j in range(2):  # the two normals across the line (fixed count, not a data loop)
        terms = NormalTerms.build(vec[edge_index, :, j], S_o, c_o, c_o - centroid[edge_index], N_o)
        A += terms.gauss_newton_blocks()
        Bt[:, 2 * j] = w_turn * terms.tangent_row(line)[1]
        Bt[:, 2 * j + 1] = w_offset * terms.offset_row()
    return A, Bt


def edge_noise(eig: tuple, edge_index: np.ndarray, N_o: np.ndarray, leverage: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per edge observation (O,): the white variance of its points per direction across the line and the
    variance of the offset they share (m^2; the module docstring), from `eig` (`plane_eigen` of the edges) and
    the leverage (O, 2) of each observation's offset along u_1 and u_2 (`noise_model.residual_leverage`)."""
    S_o, c_o, _, vec, centroid, _ = eig
    n_edges = len(centroid)
    U = vec[edge_index, :, :2]
    across_m2 = np.einsum("oia,oij,oja->o", U, S_o, U)
    white = across_m2 / (2.0 * np.maximum(N_o - 1.0, 1.0))
    d = np.einsum("oia,oi->oa", U, c_o - centroid[edge_index])
    free = 1.0 - leverage
    excess = np.bincount(edge_index, np.sum(d**2 - free * (white / N_o)[:, None], axis=1), n_edges)
    share = np.bincount(edge_index, np.sum(free, axis=1), n_edges)
    own = np.where(share > 0, excess / np.where(share > 0, share, 1.0), 0.0)
    pooled = excess.sum() / share.sum() if share.sum() > 0 else 0.0
    shared = np.maximum((share * own + SHARED_PRIOR_DOF * pooled) / (share + SHARED_PRIOR_DOF), 0.0)
    return white, shared[edge_index]


def edge_variance_pieces(eig: tuple, edge_index: np.ndarray, N_o: np.ndarray, white: np.ndarray,
                         shared: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The edges' pieces of W (`covariance.variance_pieces` for planes): blocks A_v (O, 6, 6) and coupling
    rows Bt_v (O, 4, 6) of the variance-weighted points (white variance `white` per point, and one point at
    the centroid with weight `shared` N_o^2), and per edge Q (E, 4, 4) = G^-1/2 G_v G^-1/2 in each direction
    (G = diag(lambda_3, N) the line's information on its turn and offset, G_v its variance-weighted
    counterpart), block diagonal in the two directions."""
    S_o, c_o, lam, vec, centroid, N_edge = eig
    n_edges = len(centroid)
    N_v = white * N_o + shared * N_o**2
    S_v = white[:, None, None] * S_o  # the shared point lies at c_o: no scatter about it
    A_v, Bt_v = edge_gauss_newton_pieces(eig, edge_index, S_v, c_o, N_v)
    line = vec[edge_index, :, 2]
    along_m = np.einsum("oi,oi->o", line, c_o - centroid[edge_index])
    G_v = np.empty((n_edges, 2, 2))
    G_v[:, 0, 0] = np.bincount(edge_index, np.einsum("oi,oij,oj->o", line, S_v, line) + N_v * along_m**2, n_edges)
    G_v[:, 0, 1] = G_v[:, 1, 0] = np.bincount(edge_index, N_v * along_m, n_edges)
    G_v[:, 1, 1] = np.bincount(edge_index, N_v, n_edges)
    g = np.column_stack([lam[:, 2], N_edge])
    with np.errstate(divide="ignore", invalid="ignore"):
        g_isqrt = np.where(g > 0, 1.0 / np.sqrt(np.where(g > 0, g, 1.0)), 0.0)
    Q_direction = g_isqrt[:, :, None] * G_v * g_isqrt[:, None, :]
    Q = np.zeros((n_edges, EDGE_ROWS, EDGE_ROWS))
    Q[:, :2, :2] = Q[:, 2:, 2:] = Q_direction
    return A_v, Bt_v, Q
