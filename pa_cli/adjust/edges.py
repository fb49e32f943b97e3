"""The edge feature cost: lambda_min + lambda_mid of each line cluster, the lines eliminated.

Cost (m^2): sum over edges of lambda_1(S_i) + lambda_2(S_i), S_i the world-frame scatter of
edge i's points about their centroid = the sum of squared point-to-line distances with every line
at its optimum (through the centroid, along u_3, the eigenvector of lambda_max). BALM2, Lemma 1,
Lemma 2 and Theorem 4: the derivatives of each eigenvalue follow from those of S.

Derivation, with the notation of `pa_cli.adjust.newton` (homogeneous world cluster C(x), the
eigenvectors u_1, u_2, u_3 of S, pi_j = [u_j; -u_j . c], q_3 = [0; 1]): for a simple eigenvalue,
d^2 lambda_j = pi_j^T (d^2 C) pi_j - 2 (q_3^T dC pi_j)^2 / N + 2 sum_{k != j} (pi_k^T dC pi_j)^2
/ (lambda_j - lambda_k). Summed over j = 1, 2 the terms coupling u_1 and u_2 cancel (the cost does
not depend on how the normals turn about the line), so

    g = sum_{j=1,2} pi_j^T (dC) pi_j,
    H = sum_{j=1,2} [pi_j^T (d^2 C) pi_j - 2 (q_3^T dC pi_j)^2 / N - 2 (pi_3^T dC pi_j)^2 / (lambda_3 - lambda_j)]:

each normal u_j contributes what a plane with normal u_j does (`normal_terms`), with one tangent
(the line direction u_3, curvature lambda_3 - lambda_j) and the offset (curvature N). The four
coupling rows are the line's 4 degrees of freedom (two of direction, two of position).

Eigen-gap guard: the cost is smooth while lambda_3 is simple. When lambda_3 - lambda_j <
eigen_gap_tolerance * lambda_3 (a blob, not a line), that gap is clamped to
eigen_gap_tolerance * lambda_3 and the edge counted as guarded. Gauss-Newton: the curvatures
of the direction rows become lambda_3 (the Schur complement of the joint pose-line problem).
"""

from __future__ import annotations

import numpy as np

from pa_cli.adjust.normal_terms import ClusterCost, FeatureLinearization, NormalTerms, coupling_weight, lever_origins
from pa_cli.core.clusters import plane_eigen, sum_per_plane

EDGE_COUPLING_ROWS = 4  # two direction and two position degrees of freedom of a 3-D line


class EdgeCost(ClusterCost):
    """The edge feature cost: sum over edges of lambda_min + lambda_mid of S_edge (m^2).

    `problem` holds edge features only (any `feature_kind`: every feature is treated as an edge).
    `linearize` gives the exact gradient and the Hessian pieces for the sparse system (block
    diagonal A minus the rank-4 line couplings Bt^T Bt).
    """

    def _eigen(self, T_world_scan: np.ndarray) -> tuple:
        S_o, c_o, lam, vec, centroid, N_edge = plane_eigen(T_world_scan, *self.moments, self.problem.scan_index,
                                                           self.starts)
        dc = c_o - centroid[self.problem.plane_index]
        return S_o, c_o, lam, vec, dc, N_edge

    def _cost(self, S_o: np.ndarray, vec: np.ndarray, dc: np.ndarray) -> float:
        """Sum of squared distances across the lines, as sums of non-negative terms (no cancellation)."""
        U = vec[self.problem.plane_index, :, :2]  # (O, 3, 2): the two normals of each edge
        across = np.einsum("oij,oik,ojk->o", S_o, U, U) + self.moments[3] * np.sum(
            np.einsum("oi,oik->ok", dc, U) ** 2, axis=1)
        return float(np.sum(np.maximum(sum_per_plane(np.maximum(across, 0.0), self.starts), 0.0)))

    def cost(self, T_world_scan: np.ndarray) -> float:
        S_o, _, _, vec, dc, _ = self._eigen(T_world_scan)
        return self._cost(S_o, vec, dc)

    def linearize(self, T_world_scan: np.ndarray, centred: bool = False) -> FeatureLinearization:
        """Cost, exact gradient and the Hessian pieces at T_world_scan (see the module docstring),
        for the left retraction or (`centred`) for `newton.retract_centred` (`normal_terms.lever_origins`)."""
        problem = self.problem
        S_o, c_o, lam, vec, dc, N_edge = self._eigen(T_world_scan)
        c_lever = c_o - lever_origins(T_world_scan, centred)[problem.scan_index]
        eidx = problem.plane_index
        N_o = self.moments[3]
        gaps = lam[:, 2:3] - lam[:, :2]  # (E, 2): lambda_3 - lambda_j
        floor = self.eigen_gap_tolerance * np.abs(lam[:, 2:3])
        guarded = gaps < floor
        w_gap = coupling_weight(np.where(guarded, floor, gaps))
        w_gn = coupling_weight(lam[:, 2])
        w_N = np.sqrt(2.0 / N_edge)[eidx, None]
        line = vec[eidx, :, 2]

        n_obs = len(eidx)
        grad_obs = np.zeros((n_obs, 6))
        A = np.zeros((n_obs, 6, 6))
        A_gn = np.zeros((n_obs, 6, 6))
        Bt = np.empty((n_obs, EDGE_COUPLING_ROWS, 6))
        Bt_gn = np.empty((n_obs, EDGE_COUPLING_ROWS, 6))
        for j in range(2):  # the two normals across the line (fixed count, not a data loop)
            terms = NormalTerms.build(vec[eidx, :, j], S_o, c_lever, dc, N_o)
            grad_obs += terms.gradient()
            A_j, A_gn_j = terms.blocks()
            A += A_j
            A_gn += A_gn_j
            exact, gn = terms.tangent_row(line)
            Bt[:, 2 * j] = w_gap[eidx, j][:, None] * exact
            Bt_gn[:, 2 * j] = w_gn[eidx][:, None] * gn
            Bt[:, 2 * j + 1] = Bt_gn[:, 2 * j + 1] = w_N * terms.offset_row()
        return FeatureLinearization(cost=self._cost(S_o, vec, dc),
                                    gradient=self.scan_sum(grad_obs),
                                    A=A, Bt=Bt, n_guarded=int(np.count_nonzero(guarded.any(axis=1))),
                                    A_gn=A_gn, Bt_gn=Bt_gn)
