"""The damped Newton system: sparse assembly with plane auxiliary unknowns, gauge fixing, solve.

Structure. Each feature i with observing scans obs(i) contributes to the pose Hessian
    H = blockdiag_j(sum_o A_o) - sum_i U_i U_i^T,
U_i (6N x r) stacking the feature's couplings Bt_o^T (6 x r, r = 3 for planes) in the rows of the
observing scans: H_jj gets A_o - Bt_o^T Bt_o and H_jk (j != k in obs(i)) gets -Bt_oj^T Bt_ok.
Forming U_i U_i^T costs K_i^2 6x6 blocks (K_i = |obs(i)|): a facade seen by 600 scans gives
180,000 pose-pair blocks. Instead each feature with more than `PAIR_MAX_SCANS` scans gets r
auxiliary unknowns y_i and the system becomes the augmented one
    [ Hp + mu D   U_a ] [x]   [-g]
    [ U_a^T       I   ] [y] = [ 0],
Hp = the block diagonal plus the pair blocks of the features with at most `PAIR_MAX_SCANS` scans
(and the pose terms' blocks), U_a the couplings of the other features. Eliminating y (y = -U_a^T x)
gives exactly (H + mu D) x = -g, so the step is the dense-pair step; the matrix has nnz
proportional to sum_i K_i (6 r per observation) instead of sum_i K_i^2. Rule: a feature uses pair
blocks when they hold no more matrix entries than its auxiliary form, 36 K_i (K_i - 1) / 2 <=
6 r K_i + r, i.e. K_i <= 2 for planes (one block against 3 unknowns with as many entries): the
pair form then adds no unknowns for the same fill.
Per problem: when the scans sharing features are few pairs (a long drive whose planes are each
seen by a short window of scans: H is banded), the whole pair form has fewer entries than the
augmented one (36 per distinct pose pair against 6 r per observation) and every feature takes
pair blocks (summed by the numba kernels of `_pair_kernels`); otherwise (many scans see the same
planes, H nearly dense) the augmented form above. `pair_form_is_smaller` is the rule.

Inertia. The augmented matrix is congruent to diag(I, H + mu D) (Schur complement of the
identity block), so it is positive definite exactly when H + mu D is; then a Cholesky-type
factorisation succeeds in any elimination order, and a non-positive pivot proves H + mu D is not
positive definite (the Newton Hessian can be indefinite far from the optimum: the caller falls
back to Gauss-Newton). D = max(|diag H|, DIAG_FLOOR * max|diag H|) is the diagonal of H itself
(the pose block's diagonal minus the auxiliary features' sum of squared couplings), so the damping
and the step do not depend on how H is split.

Pattern. The block pattern is fixed for a problem and built once (`HessianPattern`); each
iteration sums block values per pose and per pose pair (vectorised, linear in observations and
paired observation pairs) and gathers them, with couplings and the identity, into CSC data through a
precomputed index map. The fixed pose's 6 rows and columns are removed (gauge).

Factorisation. Small systems (fewer than `BLOCK_MIN_UNKNOWNS` unknowns): QDLDL (`qdldl`, a scalar
LDL^T with an AMD fill-reducing ordering) on the upper triangle; its D holds the pivots, whose signs
give the inertia (Sylvester). Larger ones: the block LDL^T of `pa_cli.adjust.selected_inverse`
(`BlockLDL`: 6x6 blocks, one per free pose and one per auxiliary feature, its unknowns padded with
identity rows; the block ordering with the least work of natural, reverse Cuthill-McKee and nested
dissection), whose products run as vector code: it refactorises the 200-scan street's system in
less than half of QDLDL's time (docs/benchmarks.md); a pivot block that is not positive definite
proves H + mu D is not. Both orderings and symbolic analyses are made once per pattern.
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust.normal_terms import ScanSum

DIAG_FLOOR = 1e-6  # damping diagonal D = max(|diag(H)|, DIAG_FLOOR * max|diag(H)|), as Ceres clamps
BLOCK = 6
PAIR_MAX_SCANS = 2  # features seen by at most this many scans use pose-pair blocks (module docstring)
# the numba kernels of the pair form, imported by the first pattern that takes it (numba costs a
# `pa adjust` process a quarter of a second to load; problems in the augmented form never need it)
PAIR_KERNELS = "pa_cli.adjust._pair_kernels"
# From this many unknowns the block LDL^T factorises: below it QDLDL refactorises in about a millisecond (the
# 100-scan office: 684 unknowns, 0.7 ms), and the block kernels (numba, about 0.35 s to load in a process
# that has not loaded it) would not pay for themselves. Imported by the first pattern that takes them.
BLOCK_MIN_UNKNOWNS = 1000
BLOCK_LDL = "pa_cli.adjust.selected_inverse"


def _feature_pairs(starts: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observation pairs (a, b), a < b, within each feature with `use[i]` (observations sorted by
    feature, then scan)."""
    k = np.diff(starts)
    firsts, seconds = [np.empty(0, np.int64)], [np.empty(0, np.int64)]
    for size in np.unique(k[use]):
        first_obs = starts[:-1][use & (k == size)]
        ia, ib = np.triu_indices(int(size), 1)
        firsts.append((first_obs[:, None] + ia).ravel())
        seconds.append((first_obs[:, None] + ib).ravel())
    return np.concatenate(firsts), np.concatenate(seconds)


def pair_form_is_smaller(plane_index: np.ndarray, scan_index: np.ndarray, n_scans: int, n_features: int,
                         rank: int) -> bool:
    """True when the pose-pair form has no more off-diagonal entries (36 per distinct pair of
    scans sharing a feature) than the augmented form's couplings (6 rank per observation).

    The distinct pairs number at least the pairs of the most-seen feature and at most the pairs
    of all features (or of all scans): they are counted (a product of the feature-scan incidence
    with itself, as dense as the scans that share features) only when those bounds do not decide.
    """
    budget = BLOCK * rank * len(plane_index)  # the augmented form's coupling entries
    k = np.bincount(plane_index, minlength=n_features).astype(np.int64)
    pairs_per_feature = k * (k - 1) // 2
    if BLOCK * BLOCK * int(pairs_per_feature.max(initial=0)) > budget:
        return False
    if BLOCK * BLOCK * min(int(pairs_per_feature.sum()), n_scans * (n_scans - 1) // 2) <= budget:
        return True
    ones = np.ones(len(plane_index))
    incidence = sp.csr_matrix((ones, (plane_index, scan_index)), shape=(n_features, n_scans))
    shared = (incidence.T @ incidence).tocoo()
    n_pairs = int(np.count_nonzero(shared.row < shared.col))
    return BLOCK * BLOCK * n_pairs <= budget


class HessianPattern:
    """The sparsity of the augmented damped system for one problem, with the gauge pose removed.

    Unknowns: the free poses' steps (`dim_poses` = 6 (N - 1)), then `rank` auxiliary unknowns per
    feature seen by more than `pair_max_scans` scans (`dim` in all).
    """

    def __init__(self, plane_index: np.ndarray, scan_index: np.ndarray, n_scans: int, fixed_pose: int,
                 starts: np.ndarray, extra_pairs: np.ndarray | None = None, rank: int = 3,
                 pair_max_scans: int | None = None, blocks: bool | None = None):
        """`extra_pairs` (K, 2): pose pairs coupled by pose terms besides those sharing a feature.
        `pair_max_scans`: features seen by at most this many scans take pair blocks; None: the
        problem-level rule of the module docstring (`pair_form_is_smaller`). `blocks`: factorise
        with the block LDL^T (True) or QDLDL (False); None: by size (`BLOCK_MIN_UNKNOWNS`)."""
        self.n_scans = int(n_scans)
        self.fixed_pose = int(fixed_pose)
        self.rank = int(rank)
        self.starts = starts
        self.scan_index = np.ascontiguousarray(scan_index, dtype=np.int64)
        self.plane_of_obs = np.ascontiguousarray(plane_index, dtype=np.int64)
        k = np.diff(starts)
        if pair_max_scans is None:
            pair_max_scans = int(k.max(initial=0)) if pair_form_is_smaller(
                self.plane_of_obs, self.scan_index, self.n_scans, len(k), self.rank) else PAIR_MAX_SCANS
        self.paired = k <= pair_max_scans
        self._kernels = None
        if self.paired.all() and k.max(initial=0) > PAIR_MAX_SCANS:  # the pair form: numba kernels, loaded here
            self._kernels = importlib.import_module(PAIR_KERNELS)
            pair_keys = self._kernels._pair_keys(starts, self.scan_index, self.n_scans, int(np.sum(k * (k - 1) // 2)))
        else:  # few pairs: numpy
            self.pair_a, self.pair_b = _feature_pairs(starts, self.paired)
            pair_keys = self.scan_index[self.pair_a] * self.n_scans + self.scan_index[self.pair_b]
        keys = pair_keys
        if extra_pairs is not None and len(extra_pairs):
            keys = np.concatenate([keys, self.pair_keys(extra_pairs)])
        keys = np.unique(keys)
        self.keys = keys
        if self._kernels is None:
            self.pair_sum = ScanSum(np.searchsorted(keys, pair_keys), len(keys))  # pair blocks by slot
            self.paired_obs = np.flatnonzero(self.paired[self.plane_of_obs])
            self.paired_scan_sum = ScanSum(self.scan_index[self.paired_obs], self.n_scans)
        rows, cols = keys // self.n_scans, keys % self.n_scans
        self.n_blocks = len(keys)
        self.cols = cols.astype(np.int64)
        self.row_ptr = np.zeros(self.n_scans + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=self.n_scans), out=self.row_ptr[1:])
        self.aux_obs = np.flatnonzero(~self.paired[self.plane_of_obs])  # observations with auxiliary unknowns
        self.scan_sum = ScanSum(self.scan_index, self.n_scans)
        aux_features = np.flatnonzero(~self.paired)
        self.n_aux_features = len(aux_features)
        aux_number = np.full(len(self.paired), -1, dtype=np.int64)
        aux_number[aux_features] = np.arange(len(aux_features))
        self._build_csc_map(rows, cols, aux_number[self.plane_of_obs[self.aux_obs]])
        self.blocks = self.dim >= BLOCK_MIN_UNKNOWNS if blocks is None else bool(blocks)
        self._solver: Any = None  # the QDLDL solver or the BlockLDL, kept for refactorisation (`factorise`)

    def _build_csc_map(self, rows: np.ndarray, cols: np.ndarray, aux_of_obs: np.ndarray) -> None:
        """Index map from the flat values [diag blocks, off blocks, couplings, ones] to the CSC data
        of the upper triangle of the augmented matrix."""
        N, f, r = self.n_scans, self.fixed_pose, self.rank
        reduced = np.arange(N) - (np.arange(N) > f)
        reduced[f] = -1
        rr, cc = np.meshgrid(np.arange(BLOCK), np.arange(BLOCK), indexing="ij")
        rr, cc = rr.ravel(), cc.ravel()
        self.dim_poses = BLOCK * (N - 1)
        self.dim = self.dim_poses + r * self.n_aux_features
        n_diag, n_off = N * 36, self.n_blocks * 36
        diag_src = np.arange(n_diag).reshape(N, 36)
        off_src = n_diag + np.arange(n_off).reshape(self.n_blocks, 36)
        n_aux = len(self.aux_obs)
        coupling_src = n_diag + n_off + np.arange(n_aux * r * BLOCK).reshape(n_aux, r * BLOCK)
        ones_src = n_diag + n_off + n_aux * r * BLOCK + np.arange(r * self.n_aux_features)
        self.n_values = int(ones_src[-1] + 1) if len(ones_src) else n_diag + n_off
        keep_d = reduced >= 0
        keep_o = (reduced[rows] >= 0) & (reduced[cols] >= 0)
        rj, ck = reduced[rows[keep_o]], reduced[cols[keep_o]]
        obs_pose = reduced[self.scan_index[self.aux_obs]]
        keep_c = obs_pose >= 0
        tt, c6 = np.meshgrid(np.arange(r), np.arange(BLOCK), indexing="ij")  # coupling Bt[o, t, c]
        tt, c6 = tt.ravel(), c6.ravel()
        aux_col = self.dim_poses + r * aux_of_obs[keep_c]
        r_all = np.concatenate([
            ((BLOCK * reduced[keep_d])[:, None] + rr).ravel(),
            ((BLOCK * rj)[:, None] + rr).ravel(),  # upper block (j, k), j < k
            ((BLOCK * obs_pose[keep_c])[:, None] + c6).ravel(),  # coupling rows: pose dofs
            self.dim_poses + np.arange(r * self.n_aux_features),
        ])
        c_all = np.concatenate([
            ((BLOCK * reduced[keep_d])[:, None] + cc).ravel(),
            ((BLOCK * ck)[:, None] + cc).ravel(),
            (aux_col[:, None] + tt).ravel(),
            self.dim_poses + np.arange(r * self.n_aux_features),
        ])
        src = np.concatenate([diag_src[keep_d].ravel(), off_src[keep_o].ravel(), coupling_src[keep_c].ravel(),
                              ones_src])
        upper = r_all <= c_all
        r_all, c_all, src = r_all[upper], c_all[upper], src[upper]
        order = np.lexsort((r_all, c_all))
        self.csc_src = src[order]
        self.csc_indices = r_all[order].astype(np.int32)
        self.csc_indptr = np.zeros(self.dim + 1, dtype=np.int32)
        np.cumsum(np.bincount(c_all, minlength=self.dim), out=self.csc_indptr[1:])
        diag_mask = (r_all[order] == c_all[order]) & (r_all[order] < self.dim_poses)
        self.csc_diag_pos = np.flatnonzero(diag_mask)  # pose diagonal entries, in column order
        self.free_poses = np.flatnonzero(keep_d)
        # diag(H) loses the auxiliary observations' squared couplings, summed by their scan
        self.aux_scan_sum = ScanSum(self.scan_index[self.aux_obs], N)

    def factorise(self, upper: sp.csc_matrix) -> Any | None:
        """The LDL^T factorisation of an upper-triangle matrix of this pattern (an object with
        `solve(rhs)`), or None when the matrix is not positive definite or singular. The ordering
        and the symbolic analysis are made on the first call and reused (numeric refactorisation)."""
        if self.blocks:
            if self._solver is None:
                self._solver = importlib.import_module(BLOCK_LDL).BlockLDL(self.csc_indptr, self.csc_indices,
                                                                           *self._blocks_of_unknowns())
            return self._solver if self._solver.factorise(upper.data) else None
        import qdldl

        try:
            if self._solver is None:
                self._solver = qdldl.Solver(upper, upper=True)
            else:
                self._solver.update(upper, upper=True)
        except (ValueError, RuntimeError):  # a zero pivot: singular
            self._solver = None
            return None
        if np.any(self._solver.factors()[1] <= 0.0):  # LDL^T pivots: some non-positive -> not PD
            return None
        return self._solver

    def _blocks_of_unknowns(self) -> tuple[np.ndarray, np.ndarray, int]:
        """The block LDL^T's grouping of the unknowns: (node, offset) per unknown and the node count; a free
        pose's 6 unknowns are a node, an auxiliary feature's `rank` unknowns the first entries of one."""
        n_free = self.dim_poses // BLOCK
        pose = np.arange(self.dim_poses)
        aux = np.arange(self.dim - self.dim_poses)
        return (np.concatenate([pose // BLOCK, n_free + aux // self.rank]),
                np.concatenate([pose % BLOCK, aux % self.rank]), n_free + self.n_aux_features)

    def pair_keys(self, pairs: np.ndarray) -> np.ndarray:
        """Keys j * N + k (j < k) of pose pairs (K, 2)."""
        pairs = np.asarray(pairs, dtype=np.int64)
        return np.minimum(pairs[:, 0], pairs[:, 1]) * self.n_scans + np.maximum(pairs[:, 0], pairs[:, 1])

    def assemble(self, A: np.ndarray, Bt: np.ndarray, pose_blocks: list[np.ndarray] = (),
                 pair_blocks: list[tuple[np.ndarray, np.ndarray]] = ()) -> AugmentedSystem:
        """The undamped augmented system from per-observation blocks A (O,6,6) and feature
        couplings Bt (O,r,6), plus per-pose blocks (N,6,6) and (pose pairs (K,2), H_jk blocks
        (K,6,6)) of pose terms (the pairs must be among the pattern's `extra_pairs`)."""
        diag = np.zeros((self.n_scans, BLOCK, BLOCK))
        for blocks in pose_blocks:
            diag += blocks
        off = np.zeros((self.n_blocks, BLOCK, BLOCK))
        for pairs, blocks in pair_blocks:
            if len(pairs):
                upper = (np.asarray(pairs)[:, 0] < np.asarray(pairs)[:, 1])[:, None, None]
                np.add.at(off, np.searchsorted(self.keys, self.pair_keys(pairs)),
                          np.where(upper, blocks, blocks.transpose(0, 2, 1)))
        if self._kernels is not None:
            self._kernels._accumulate(self.plane_of_obs, self.starts, self.scan_index,
                                       np.ascontiguousarray(A), np.ascontiguousarray(Bt), self.row_ptr, self.cols,
                                       diag, off)
        else:
            diag += self.scan_sum(A)
            if len(self.paired_obs):  # minus Bt_o^T Bt_o where the feature takes pair blocks
                diag -= self.paired_scan_sum(np.einsum("oti,otj->oij", Bt[self.paired_obs], Bt[self.paired_obs]))
        if self._kernels is None and len(self.pair_a):
            off -= self.pair_sum(np.einsum("pti,ptj->pij", Bt[self.pair_a], Bt[self.pair_b]))
        coupling = Bt[self.aux_obs]
        flat = np.concatenate([diag.ravel(), off.ravel(), coupling.ravel(), np.ones(self.rank * self.n_aux_features)])
        data = flat[self.csc_src]
        # diag(H): the pose block's diagonal minus the auxiliary features' squared couplings
        h_diag = np.einsum("nii->ni", diag) - self.aux_scan_sum(np.einsum("oti,oti->oi", coupling, coupling))
        return AugmentedSystem(self, data, h_diag[self.free_poses].ravel())

    def reduce_vector(self, g: np.ndarray) -> np.ndarray:
        """(N, 6) per-pose vector -> reduced (6(N-1),) without the fixed pose."""
        return g[self.free_poses].ravel()

    def expand_vector(self, x: np.ndarray) -> np.ndarray:
        """Reduced vector -> (N, 6) with zeros at the fixed pose."""
        out = np.zeros((self.n_scans, BLOCK))
        out[self.free_poses] = x.reshape(-1, BLOCK)
        return out


class AugmentedSystem:
    """The undamped augmented matrix of one linearisation (CSC upper-triangle data) and diag(H)."""

    def __init__(self, pattern: HessianPattern, data: np.ndarray, h_diag: np.ndarray):
        self.pattern = pattern
        self.data = data
        self.h_diag = h_diag  # (6(N-1),) diagonal of the pose Hessian H

    def upper(self, data: np.ndarray | None = None) -> sp.csc_matrix:
        """The upper triangle (CSC) of the augmented matrix (undamped unless `data` is given)."""
        p = self.pattern
        return sp.csc_matrix((self.data if data is None else data, p.csc_indices, p.csc_indptr),
                             shape=(p.dim, p.dim))

    def pose_hessian(self) -> sp.csc_matrix:
        """The pose Hessian H = Hp - U_a U_a^T (reduced, CSC; dense where features are seen by many
        scans): for covariances and tests, never for the Newton step."""
        M = self.upper()
        M = (M + sp.triu(M, 1).T).tocsc()
        n = self.pattern.dim_poses
        return (M[:n, :n] - M[:n, n:] @ M[n:, :n]).tocsc()

    def hessian(self) -> np.ndarray:
        """The pose Hessian as a dense array (for tests and references)."""
        return self.pose_hessian().toarray()

    def damping(self) -> np.ndarray:
        """The damping diagonal D = max(|diag H|, DIAG_FLOOR * max|diag H|) over the free pose dofs."""
        d = np.abs(self.h_diag)
        return np.maximum(d, DIAG_FLOOR * max(float(d.max(initial=0.0)), 1e-300))


def damped_solve(system: AugmentedSystem, g: np.ndarray, mu: float) -> np.ndarray | None:
    """Solve (H + mu D) x = -g through the augmented system; None when H + mu D is not positive
    definite (a pivot that is not) or the factorisation fails."""
    p = system.pattern
    data = system.data.copy()
    data[p.csc_diag_pos] += mu * system.damping()
    upper = system.upper(data)
    solver = p.factorise(upper)
    if solver is None:
        return None
    rhs = np.zeros(p.dim)
    rhs[:p.dim_poses] = -g
    z = solver.solve(rhs)
    # one step of iterative refinement: H = Hp - U_a U_a^T is formed by cancellation inside the
    # factorisation, so the residual is recomputed with the augmented matrix and corrected once
    residual = rhs - (upper @ z + upper.T @ z - upper.diagonal() * z)
    z += solver.solve(residual)
    x = z[:p.dim_poses]
    if not np.all(np.isfinite(x)):
        return None
    return x
