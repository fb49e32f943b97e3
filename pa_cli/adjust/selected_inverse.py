"""Diagonal blocks of the inverse of a sparse symmetric positive definite block matrix.

`diagonal_blocks_of_inverse(H)` returns the 6x6 diagonal blocks of H^-1 without forming H^-1:

1. **Ordering.** The block graph of H (one node per 6x6 block row) is ordered to keep the fill
   of the factor small; the natural order, reverse Cuthill-McKee and minimum degree (SuperLU's
   MMD on the block graph) are analysed symbolically and the one with the fewest block
   operations is used.
2. **Symbolic factorisation** on the block graph: elimination tree, then the row structure of
   the factor by walking the tree (Davis, "Direct Methods for Sparse Linear Systems", 4.1-4.2).
3. **Block LDL^T**: H = L D L^T with L unit lower-triangular in 6x6 blocks and D block diagonal
   (right-looking, every D_j checked positive definite by a Cholesky factorisation).
4. **Selected inversion** (Takahashi, Fagan and Chen 1973): Z = H^-1 satisfies L^T Z = D^-1 L^-1,
   whose upper triangle gives, for columns j from last to first with S = struct(L_{:,j}):

       Z_kj = - sum_{i in S} Z_ki L_ij        (k in S)
       Z_jj = D_j^-1 - sum_{k in S} L_kj^T Z_kj

   Only the blocks of Z on the pattern of L are computed (the pattern is closed under this
   recursion), so memory and time are those of the factorisation: linear in the block rows for
   a banded (sequential) pose graph.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee
from scipy.sparse.linalg import splu

from pa_cli.errors import SolverError

BLOCK = 6
# relative step of the central difference in `diagonal_blocks_of_sandwich`: truncation ~ step^2,
# round-off ~ (selected-inversion accuracy, about 1e-10 relative) / step; both below 1e-6 here
SANDWICH_STEP = 1e-4


@numba.njit(cache=True)
def _etree(indptr, indices, perm_inv):
    """Elimination tree of the permuted symmetric block graph (-1 = root)."""
    n = len(indptr) - 1
    parent = np.full(n, -1, np.int64)
    ancestor = np.full(n, -1, np.int64)
    # adjacency of new column k: the old neighbours of old node perm[k]; visit in new order
    order = np.empty(n, np.int64)
    for old in range(n):
        order[perm_inv[old]] = old
    for k in range(n):
        old = order[k]
        for t in range(indptr[old], indptr[old + 1]):
            i = perm_inv[indices[t]]
            while i != -1 and i < k:
                nxt = ancestor[i]
                ancestor[i] = k
                if nxt == -1:
                    parent[i] = k
                i = nxt
    return parent, order


@numba.njit(cache=True)
def _row_structure(indptr, indices, perm_inv, parent, order, colptr, rows, fill):
    """Count (fill=False) or fill (fill=True) the block rows of every column of L.

    Row j of L is the union of the tree paths from each neighbour i < j up to j (cs_ereach);
    rows are met in increasing j, so every column's row list comes out sorted.
    """
    n = len(indptr) - 1
    mark = np.full(n, -1, np.int64)
    count = np.zeros(n, np.int64)
    for j in range(n):
        mark[j] = j
        old = order[j]
        for t in range(indptr[old], indptr[old + 1]):
            i = perm_inv[indices[t]]
            while i < j and mark[i] != j:
                mark[i] = j
                if fill:
                    rows[colptr[i] + count[i]] = j
                count[i] += 1
                i = parent[i]
    return count


@numba.njit(cache=True)
def _cholesky6(A, out):
    """Lower Cholesky factor of a 6x6 matrix into `out`; False when not positive definite."""
    for c in range(BLOCK):
        s = A[c, c]
        for k in range(c):
            s -= out[c, k] * out[c, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        out[c, c] = d
        for r in range(c + 1, BLOCK):
            t = A[r, c]
            for k in range(c):
                t -= out[r, k] * out[c, k]
            out[r, c] = t / d
        for r in range(c):
            out[r, c] = 0.0
    return True


@numba.njit(cache=True)
def _spd_inverse6(A, out, work):
    """Inverse of a 6x6 symmetric positive definite matrix via Cholesky; False if not PD."""
    if not _cholesky6(A, work):
        return False
    # out = L^-T L^-1: invert L column by column into out, then multiply
    inv_l = np.zeros((BLOCK, BLOCK))
    for c in range(BLOCK):
        inv_l[c, c] = 1.0 / work[c, c]
        for r in range(c + 1, BLOCK):
            s = 0.0
            for k in range(c, r):
                s -= work[r, k] * inv_l[k, c]
            inv_l[r, c] = s / work[r, r]
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(max(r, c), BLOCK):
                s += inv_l[k, r] * inv_l[k, c]
            out[r, c] = s
    return True


@numba.njit(cache=True)
def _sub_abt(C, A, B):
    """C -= A B^T (6x6)."""
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(BLOCK):
                s += A[r, k] * B[c, k]
            C[r, c] -= s


@numba.njit(cache=True)
def _set_ab(C, A, B):
    """C = A B (6x6)."""
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(BLOCK):
                s += A[r, k] * B[k, c]
            C[r, c] = s


@numba.njit(cache=True)
def _add_ab(C, A, B):
    """C += A B (6x6)."""
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(BLOCK):
                s += A[r, k] * B[k, c]
            C[r, c] += s


@numba.njit(cache=True)
def _add_atb(C, A, B):
    """C += A^T B (6x6)."""
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(BLOCK):
                s += A[k, r] * B[k, c]
            C[r, c] += s


@numba.njit(cache=True)
def _factor_and_invert(colptr, rows, L, D, Z_diag):
    """Block LDL^T and selected inversion, in place.

    On entry L holds the strictly lower blocks of H on the pattern of the factor (zero where
    fill appears) and D the diagonal blocks. On return Z_diag holds the diagonal blocks of
    H^-1 and L the blocks of H^-1 on the factor's pattern. Returns the first column whose
    pivot block is not positive definite (then the outputs are meaningless), or -1.
    """
    n = len(colptr) - 1
    D_inv = np.empty((n, BLOCK, BLOCK))
    work = np.empty((BLOCK, BLOCK))
    max_s = 1
    for j in range(n):
        max_s = max(max_s, colptr[j + 1] - colptr[j])
    W = np.empty((max_s, BLOCK, BLOCK))
    for j in range(n):  # right-looking block LDL^T
        if not _spd_inverse6(D[j], D_inv[j], work):
            return j
        lo, hi = colptr[j], colptr[j + 1]
        s = hi - lo
        for a in range(s):
            W[a] = L[lo + a]
            _set_ab(L[lo + a], W[a], D_inv[j])
        for a in range(s):
            k = rows[lo + a]
            _sub_abt(D[k], L[lo + a], W[a])
            q = colptr[k]
            for b in range(a + 1, s):
                row = rows[lo + b]
                while rows[q] != row:  # struct(j) below k is a subset of struct(k): merge walk
                    q += 1
                _sub_abt(L[q], L[lo + b], W[a])
    acc = W
    for j in range(n - 1, -1, -1):  # Takahashi: columns > j of L already hold Z
        lo, hi = colptr[j], colptr[j + 1]
        s = hi - lo
        for a in range(s):
            _set_ab(acc[a], Z_diag[rows[lo + a]], L[lo + a])
        for a in range(s):
            k = rows[lo + a]
            q = colptr[k]
            for b in range(a + 1, s):
                row = rows[lo + b]
                while rows[q] != row:
                    q += 1
                _add_atb(acc[a], L[q], L[lo + b])  # Z_{k,row} = Z_{row,k}^T
                _add_ab(acc[b], L[q], L[lo + a])
        z = D_inv[j].copy()
        for a in range(s):
            _add_atb(z, L[lo + a], acc[a])
        for a in range(s):
            L[lo + a] = -acc[a]
        Z_diag[j] = 0.5 * (z + z.T)
    return -1


def block_matrix(H: sp.spmatrix) -> sp.bsr_matrix:
    """H as a block sparse row matrix of 6x6 blocks with sorted block columns."""
    Hb = H if isinstance(H, sp.bsr_matrix) and H.blocksize == (BLOCK, BLOCK) else \
        sp.bsr_matrix(H, blocksize=(BLOCK, BLOCK))
    Hb.sort_indices()
    return Hb


def _candidate_orders(graph: sp.csr_matrix) -> dict[str, np.ndarray]:
    """Block orderings to compare: natural, reverse Cuthill-McKee, SuperLU's minimum degree."""
    n = graph.shape[0]
    orders = {"natural": np.arange(n), "rcm": np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True))}
    # minimum degree of SuperLU on a diagonally dominant matrix of the same pattern (values unused)
    pattern = graph.astype(np.float64).tocsc()
    pattern.data[:] = -1.0
    pattern = pattern + sp.diags(np.asarray(abs(pattern).sum(axis=1)).ravel() + 1.0)
    lu = splu(pattern.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
              options={"SymmetricMode": True})
    orders["mmd"] = np.asarray(lu.perm_c)  # perm_c[old] = new position
    orders["mmd"] = np.argsort(orders["mmd"])  # -> order[new] = old
    return orders


class BlockSymbolic:
    """Pattern of the block factor for one ordering: column pointers and sorted block rows."""

    def __init__(self, graph: sp.csr_matrix, order: np.ndarray):
        n = graph.shape[0]
        self.order = np.asarray(order, dtype=np.int64)  # order[new] = old
        self.perm_inv = np.empty(n, np.int64)  # perm_inv[old] = new
        self.perm_inv[self.order] = np.arange(n)
        indptr = graph.indptr.astype(np.int64)
        indices = graph.indices.astype(np.int64)
        parent, _ = _etree(indptr, indices, self.perm_inv)
        counts = _row_structure(indptr, indices, self.perm_inv, parent, self.order,
                                np.zeros(n + 1, np.int64), np.empty(0, np.int64), False)
        self.colptr = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=self.colptr[1:])
        self.rows = np.empty(self.colptr[-1], np.int64)
        _row_structure(indptr, indices, self.perm_inv, parent, self.order, self.colptr, self.rows, True)
        # sorted keys (column * n + row) of the factor's blocks, to place H's blocks
        self.keys = np.repeat(np.arange(n), counts) * n + self.rows
        # block products of the factorisation and the selected inversion: ~1.5 s^2 per column
        self.work = int(np.sum(counts.astype(np.float64) ** 2))


def analyse(H: sp.spmatrix) -> BlockSymbolic:
    """The cheapest of the candidate block orderings of H (by the block products it needs)."""
    Hb = block_matrix(H)
    n = Hb.shape[0] // BLOCK
    graph = sp.csr_matrix((np.ones(len(Hb.indices)), Hb.indices, Hb.indptr), shape=(n, n))
    graph = graph - sp.diags(graph.diagonal())
    graph.eliminate_zeros()
    graph.sort_indices()
    candidates = [BlockSymbolic(graph, order) for order in _candidate_orders(graph).values()]
    return min(candidates, key=lambda sym: sym.work)


def diagonal_blocks_of_inverse(H: sp.spmatrix, symbolic: BlockSymbolic | None = None) -> np.ndarray:
    """The 6x6 diagonal blocks (n, 6, 6) of H^-1 for a sparse symmetric positive definite H (6n, 6n).

    `symbolic` (from `analyse(H)`) may be reused across matrices of the same pattern.
    Raises `SolverError` when H is not positive definite.
    """
    if H.shape[0] != H.shape[1] or H.shape[0] % BLOCK:
        raise SolverError(f"expected a square matrix of 6x6 blocks, found shape {H.shape}.")
    sym = analyse(H) if symbolic is None else symbolic
    Hb = block_matrix(H)
    n = Hb.shape[0] // BLOCK
    block_row = np.repeat(np.arange(n), np.diff(Hb.indptr))
    new_r, new_c = sym.perm_inv[block_row], sym.perm_inv[Hb.indices]
    D = np.zeros((n, BLOCK, BLOCK))
    diag = new_r == new_c
    D[new_r[diag]] = Hb.data[diag]
    lower = new_r > new_c
    L = np.zeros((len(sym.rows), BLOCK, BLOCK))
    # position of block row new_r in column new_c: rows are sorted within each column
    L[np.searchsorted(sym.keys, new_c[lower] * n + new_r[lower])] = Hb.data[lower]
    Z_diag = np.zeros((n, BLOCK, BLOCK))
    bad = _factor_and_invert(sym.colptr, sym.rows, L, D, Z_diag)
    if bad >= 0:
        raise SolverError(f"the Hessian is not positive definite (pivot block of block row {sym.order[bad]}); "
                          "the covariance needs poses at a converged optimum with every pose constrained.")
    return Z_diag[sym.perm_inv]


def diagonal_blocks_of_sandwich(H: sp.spmatrix, M: sp.spmatrix, symbolic: BlockSymbolic | None = None
                                ) -> np.ndarray:
    """Diagonal blocks (n, 6, 6) of H^-1 M H^-1 for SPD H and PSD M.

    H^-1 M H^-1 = d/dt (H - t M)^-1 at t = 0, taken by a central difference of two selected
    inversions at t = +-h with h = SANDWICH_STEP * trace(H) / trace(M): the truncation error
    is O(h^2 |H^-1 M|^2), relative about SANDWICH_STEP^2 when M is of the order of H's scale.
    """
    Hb, Mb = block_matrix(H), block_matrix(M)
    sym = analyse(Hb) if symbolic is None else symbolic
    scale_M = abs(Mb.diagonal().sum())
    if scale_M == 0.0:  # M = 0 (symmetric PSD M with zero trace): the sandwich is zero
        return np.zeros((H.shape[0] // BLOCK, BLOCK, BLOCK))
    h = SANDWICH_STEP * abs(Hb.diagonal().sum()) / scale_M
    if np.array_equal(Hb.indptr, Mb.indptr) and np.array_equal(Hb.indices, Mb.indices):
        def shifted(sign: float) -> sp.bsr_matrix:  # same block pattern: combine the block values
            return sp.bsr_matrix((Hb.data + sign * h * Mb.data, Hb.indices, Hb.indptr), shape=Hb.shape)
    else:
        def shifted(sign: float) -> sp.bsr_matrix:
            return block_matrix((Hb + sign * h * Mb).tocsr())
    plus = diagonal_blocks_of_inverse(shifted(-1.0), sym)
    minus = diagonal_blocks_of_inverse(shifted(1.0), sym)
    return (plus - minus) / (2.0 * h)
