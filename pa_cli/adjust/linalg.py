"""Sparse Hessian assembly over pose pairs that share a plane, gauge fixing and the damped solve.

Structure: plane i with observing scans obs(i) contributes to the Hessian
  H_jj += A_ij - B_ij^T B_ij            (6x6, per observation)
  H_jk -= B_ij^T B_ik   for j != k in obs(i)   (B_ij is 3x6: the rank-3 plane coupling)
Pose terms (`pa_cli.adjust.terms`) add blocks to H_jj and to H_jk for the pose pairs they declare.
The pose-pair pattern is fixed for a problem, so it is built once (`HessianPattern`); each
iteration only accumulates block values (numba, parallel over poses, race free because pose j
writes only its own block row) and gathers them into a CSC matrix with a precomputed index map.
The fixed pose's 6 rows and columns are removed (gauge).

Factorisation: SuperLU (`scipy.sparse.linalg.splu`) with a symmetric minimum-degree ordering and
no off-diagonal pivoting (`diag_pivot_thresh=0`, SymmetricMode): then U's diagonal holds the pivots
of an LDL^T factorisation, whose signs give the inertia (Sylvester) - the damped system is accepted
only when it is positive definite. Chosen by measurement, see bench/solver.py.
The SuiteSparse inside pyceres is not an option: pyceres exposes no solver for a user matrix
(only whole least-squares problems); bench/pyceres_compare.py compares Ceres' SPARSE_SCHUR solve
with this module's factorisation of the same-sparsity pose Hessian.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from pa_cli import _numba  # noqa: F401  (numba cache folder: see pa_cli/_numba.py)

DIAG_FLOOR = 1e-6  # damping diagonal D = max(|diag(H)|, DIAG_FLOOR * max|diag(H)|), as Ceres clamps
BLOCK = 6


@numba.njit(cache=True)
def _pair_keys(starts, scan_index, n_scans, n_pairs):
    keys = np.empty(n_pairs, dtype=np.int64)
    m = 0
    for i in range(len(starts) - 1):
        for a in range(starts[i], starts[i + 1]):
            for b in range(a + 1, starts[i + 1]):
                keys[m] = scan_index[a] * n_scans + scan_index[b]
                m += 1
    return keys


@numba.njit(parallel=True, cache=True)
def _accumulate(obs_ptr, obs_order, plane_of_obs, starts, scan_index, A, Bt, row_ptr, cols, diag, off):
    """diag[j] = sum_o (A_o - Bt_o^T Bt_o); off[slot(j,k)] = -sum Bt_oj^T Bt_ok (j < k); Bt (O, R, 6)
    has R coupling rows per observation (3 for planes, 4 when the problem has edges)."""
    n_scans = len(obs_ptr) - 1
    for j in numba.prange(n_scans):
        for idx in range(obs_ptr[j], obs_ptr[j + 1]):
            a = obs_order[idx]
            for r in range(6):
                for c in range(6):
                    s = A[a, r, c]
                    for t in range(Bt.shape[1]):
                        s -= Bt[a, t, r] * Bt[a, t, c]
                    diag[j, r, c] += s
            i = plane_of_obs[a]
            lo = row_ptr[j]
            for b in range(a + 1, starts[i + 1]):
                k = scan_index[b]
                hi = row_ptr[j + 1] - 1
                l0 = lo
                while l0 < hi:  # binary search of column k in row j
                    mid = (l0 + hi) // 2
                    if cols[mid] < k:
                        l0 = mid + 1
                    else:
                        hi = mid
                slot = l0
                lo = slot  # scans of a plane are sorted: the next column is further right
                for r in range(6):
                    for c in range(6):
                        s = 0.0
                        for t in range(Bt.shape[1]):
                            s += Bt[a, t, r] * Bt[b, t, c]
                        off[slot, r, c] -= s


class HessianPattern:
    """The block sparsity of H for one problem, with the gauge pose removed."""

    def __init__(self, plane_index: np.ndarray, scan_index: np.ndarray, n_scans: int, fixed_pose: int,
                 starts: np.ndarray, extra_pairs: np.ndarray | None = None):
        """`extra_pairs` (K, 2): pose pairs coupled by pose terms besides those sharing a plane."""
        self.n_scans = int(n_scans)
        self.fixed_pose = int(fixed_pose)
        self.starts = starts
        self.scan_index = np.ascontiguousarray(scan_index, dtype=np.int64)
        self.plane_of_obs = np.ascontiguousarray(plane_index, dtype=np.int64)
        self.obs_order = np.argsort(self.scan_index, kind="stable").astype(np.int64)
        counts = np.bincount(self.scan_index, minlength=self.n_scans)
        self.obs_ptr = np.zeros(self.n_scans + 1, dtype=np.int64)
        np.cumsum(counts, out=self.obs_ptr[1:])

        k = np.diff(starts)
        n_pairs = int(np.sum(k * (k - 1) // 2))
        keys = _pair_keys(starts, self.scan_index, self.n_scans, n_pairs)
        if extra_pairs is not None and len(extra_pairs):
            keys = np.concatenate([keys, self.pair_keys(extra_pairs)])
        keys = np.unique(keys)
        self.keys = keys
        rows, cols = keys // self.n_scans, keys % self.n_scans
        self.cols = cols.astype(np.int64)
        self.row_ptr = np.zeros(self.n_scans + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=self.n_scans), out=self.row_ptr[1:])
        self.n_blocks = len(keys)
        self._build_csc_map(rows, cols)

    def _build_csc_map(self, rows: np.ndarray, cols: np.ndarray) -> None:
        """Index map from the flat block values [diag blocks, off blocks] to CSC data."""
        N, f = self.n_scans, self.fixed_pose
        reduced = np.arange(N) - (np.arange(N) > f)
        reduced[f] = -1
        rr, cc = np.meshgrid(np.arange(BLOCK), np.arange(BLOCK), indexing="ij")
        rr, cc = rr.ravel(), cc.ravel()
        # diag blocks
        diag_src = np.arange(N * 36).reshape(N, 36)
        off_src = N * 36 + np.arange(self.n_blocks * 36).reshape(self.n_blocks, 36)
        keep_d = reduced >= 0
        keep_o = (reduced[rows] >= 0) & (reduced[cols] >= 0)
        rj, ck = reduced[rows[keep_o]], reduced[cols[keep_o]]
        r_all = np.concatenate([
            (BLOCK * reduced[keep_d])[:, None] + rr,
            (BLOCK * rj)[:, None] + rr,  # upper block (j, k)
            (BLOCK * ck)[:, None] + cc,  # lower block (k, j) = transpose
        ]).ravel()
        c_all = np.concatenate([
            (BLOCK * reduced[keep_d])[:, None] + cc,
            (BLOCK * ck)[:, None] + cc,
            (BLOCK * rj)[:, None] + rr,
        ]).ravel()
        src = np.concatenate([diag_src[keep_d], off_src[keep_o], off_src[keep_o]]).ravel()
        self.dim = BLOCK * (N - 1)
        order = np.lexsort((r_all, c_all))
        self.csc_src = src[order]
        self.csc_indices = r_all[order].astype(np.int32)
        self.csc_indptr = np.zeros(self.dim + 1, dtype=np.int32)
        np.cumsum(np.bincount(c_all, minlength=self.dim), out=self.csc_indptr[1:])
        is_diag = r_all[order] == c_all[order]
        self.csc_diag_pos = np.flatnonzero(is_diag)
        self.csc_diag_col = self.csc_indices[self.csc_diag_pos]
        self.free_poses = np.flatnonzero(keep_d)

    def pair_keys(self, pairs: np.ndarray) -> np.ndarray:
        """Keys j * N + k (j < k) of pose pairs (K, 2)."""
        pairs = np.asarray(pairs, dtype=np.int64)
        return np.minimum(pairs[:, 0], pairs[:, 1]) * self.n_scans + np.maximum(pairs[:, 0], pairs[:, 1])

    def assemble(self, A: np.ndarray, Bt: np.ndarray, pose_blocks: list[np.ndarray] = (),
                 pair_blocks: list[tuple[np.ndarray, np.ndarray]] = ()) -> sp.csc_matrix:
        """H (reduced, CSC) from per-observation blocks A (O,6,6) and feature couplings Bt (O,R,6),
        plus per-pose blocks (N,6,6) and (pose pairs (K,2), H_jk blocks (K,6,6)) of pose terms
        (the pairs must be among the pattern's `extra_pairs`)."""
        diag = np.zeros((self.n_scans, BLOCK, BLOCK))
        for blocks in pose_blocks:
            diag += blocks
        off = np.zeros((self.n_blocks, BLOCK, BLOCK))
        for pairs, blocks in pair_blocks:
            if len(pairs):
                upper = (np.asarray(pairs)[:, 0] < np.asarray(pairs)[:, 1])[:, None, None]
                np.add.at(off, np.searchsorted(self.keys, self.pair_keys(pairs)),
                          np.where(upper, blocks, blocks.transpose(0, 2, 1)))
        _accumulate(self.obs_ptr, self.obs_order, self.plane_of_obs, self.starts, self.scan_index,
                    np.ascontiguousarray(A), np.ascontiguousarray(Bt), self.row_ptr, self.cols, diag, off)
        flat = np.concatenate([diag.ravel(), off.ravel()])
        return sp.csc_matrix((flat[self.csc_src], self.csc_indices, self.csc_indptr),
                             shape=(self.dim, self.dim))

    def reduce_vector(self, g: np.ndarray) -> np.ndarray:
        """(N, 6) per-pose vector -> reduced (6(N-1),) without the fixed pose."""
        return g[self.free_poses].ravel()

    def expand_vector(self, x: np.ndarray) -> np.ndarray:
        """Reduced vector -> (N, 6) with zeros at the fixed pose."""
        out = np.zeros((self.n_scans, BLOCK))
        out[self.free_poses] = x.reshape(-1, BLOCK)
        return out


def damped_solve(H: sp.csc_matrix, g: np.ndarray, mu: float, diag_pos: np.ndarray) -> np.ndarray | None:
    """Solve (H + mu D) x = -g; None when the damped matrix is not positive definite.

    D = max(|diag H|, DIAG_FLOOR * max|diag H|). `diag_pos` are the CSC data positions of the
    diagonal (in column order).
    """
    d = np.abs(H.data[diag_pos])
    D = np.maximum(d, DIAG_FLOOR * max(float(d.max(initial=0.0)), 1e-300))
    M = H.copy()
    M.data[diag_pos] += mu * D
    try:
        lu = splu(M, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError:  # exactly singular
        return None
    if not np.array_equal(lu.perm_r, lu.perm_c):  # pivoting happened: inertia unknown
        return None
    if np.any(lu.U.diagonal() <= 0.0):  # LDL^T pivots: some non-positive -> not PD
        return None
    x = lu.solve(-g)
    if not np.all(np.isfinite(x)):
        return None
    return x
