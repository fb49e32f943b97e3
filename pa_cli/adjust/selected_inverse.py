"""Sparse LDL^T in 6x6 blocks: diagonal blocks of the inverse of a symmetric positive definite block
matrix, and solves.

`diagonal_blocks_of_inverse(H)` returns the 6x6 diagonal blocks of H^-1 without forming H^-1:

1. **Ordering.** The block graph of H (one node per 6x6 block row) is ordered to keep the fill
   of the factor small; the natural order, reverse Cuthill-McKee and nested dissection (METIS,
   `pymetis`) are analysed symbolically (block rows per column only) and the one with the fewest
   block operations is used. The natural order suits a sequence's band, nested dissection
   revisits and feature nodes; minimum degree (SuperLU's MMD, which orders by factorising
   numerically) was never the cheapest of them on the benchmark problems and cost more time than
   the others together, so it is not among them.
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

Steps 3-4 are 6x6 block products C += alpha A B, emitted as LLVM vector code (`_block6.nn6`).

`BlockLDL` does steps 1-2 once per pattern and step 3 per matrix, then solves with the factor
(forward and backward substitution, `_solve`): the Newton solver's damped systems
(`pa_cli.adjust.linalg`), whose auxiliary features take a block each, their unknowns padded with
identity rows.

`diagonal_blocks_of_feature_inverses` does steps 3-4 for matrices given by their feature blocks
(block diagonal minus per-feature couplings, as the Newton system holds them), assembled directly
into the factor's block storage: one matrix, or two whose couplings are linear in a step (every
block product formed once for both, inverted in parallel). The assembly runs over column ranges
of the factor in parallel threads; within a block, each entry is summed from the observations'
coupling rows expanded to the block's flat layout, a loop over contiguous entries.

Feature nodes. A feature seen by K scans couples them pairwise: K (K - 1) / 2 blocks, and a plane
every scan sees (the ground of a town, the floor of a building) makes H dense and the factor's
work cubic in the scans. Such a feature can instead be a node of its own (6 unknowns z = (y, w),
3 each), as in the Newton system's augmented form: with its couplings V = [U, s Y] (6 x 6 per
observing scan) and the node block C = [[0, I], [I, -I]], whose inverse is [[I, I], [I, 0]],

    [ D   V ]                                                   D - V C^-1 V^T
    [ V^T C ]   has the Schur complement onto the poses         = D - (U U^T + s (U Y^T + Y U^T)),

the same matrix as the pair blocks, still exactly linear in s, and the poses' blocks of its
inverse are those of H^-1. Its nnz is linear in K, and the ordering (which sees the nodes) keeps
the factor sparse. The augmented matrix is indefinite: congruent to diag(H, C...), so H is
positive definite exactly when every pose pivot is and every node pivot has three negative and
three positive eigenvalues (each node pivot is C - V^T X V with X positive definite, whose lower
right block is negative definite and whose Schur complement onto the upper left is I - U^T X U,
positive definite when H is); node pivots are inverted through their eigen-decomposition.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from pa_cli.adjust._block6 import nn6
from pa_cli.core.neighbourhoods import first_not_below
from pa_cli.errors import SolverError
from pa_cli.runtime.numba_cache import announce_compilation  # (and numba's cache folder: see that module)

BLOCK = 6
LINEAR_RANK = 3  # coupling rows per observation of the two-matrix assembly (planes)


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


@numba.njit(cache=True, inline="always")
def _zero6(block):
    """block (6, 6) = 0, entry by entry (a slice assignment compiles numba's shape-error path)."""
    for r in range(BLOCK):
        for c in range(BLOCK):
            block[r, c] = 0.0


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
def _indefinite_inverse6(A, out, negatives):
    """Inverse of a symmetric 6x6 matrix with exactly `negatives` negative eigenvalues (and no zero
    one, relative to the largest) via its eigen-decomposition; False otherwise."""
    lam, vec = np.linalg.eigh(0.5 * (A + A.T))
    scale = max(abs(lam[0]), abs(lam[BLOCK - 1]))
    n_negative = 0
    for k in range(BLOCK):
        if not abs(lam[k]) > 1e-14 * scale:
            return False
        if lam[k] < 0.0:
            n_negative += 1
    if n_negative != negatives:
        return False
    for r in range(BLOCK):
        for c in range(BLOCK):
            s = 0.0
            for k in range(BLOCK):
                s += vec[r, k] * vec[c, k] / lam[k]
            out[r, c] = s
    return True


@numba.njit(cache=True, nogil=True)
def _factor(colptr, rows, L, D, D_inv, negatives):
    """Block LDL^T, right-looking, in place.

    On entry L holds the strictly lower blocks of H on the pattern of the factor (zero where fill
    appears) and D the diagonal blocks. On return L holds the unit lower factor's blocks below the
    diagonal, D the pivots and D_inv their inverses. Pivot j must be positive definite when
    negatives[j] = 0 (a pose), else have exactly negatives[j] negative eigenvalues (a feature node,
    see the module docstring). Returns the first column whose pivot block is not so (then the
    outputs are meaningless), or -1.
    """
    n = len(colptr) - 1
    work = np.empty((BLOCK, BLOCK))
    max_s = 1
    for j in range(n):
        max_s = max(max_s, colptr[j + 1] - colptr[j])
    V = np.empty((max_s, BLOCK, BLOCK))
    for j in range(n):
        if negatives[j] == 0:
            if not _spd_inverse6(D[j], D_inv[j], work):
                return j
        elif not _indefinite_inverse6(D[j], D_inv[j], negatives[j]):
            return j
        lo, hi = colptr[j], colptr[j + 1]
        s = hi - lo
        for a in range(s):  # V_a = H_(row a, j)^T, then L_a = H_(row a, j) D_j^-1
            for r in range(BLOCK):
                for c in range(BLOCK):
                    V[a, c, r] = L[lo + a, r, c]
                    L[lo + a, r, c] = 0.0
            nn6(L[lo + a], V[a].T, D_inv[j], 1.0)
        for a in range(s):
            k = rows[lo + a]
            nn6(D[k], L[lo + a], V[a], -1.0)
            q = colptr[k]
            for b in range(a + 1, s):
                row = rows[lo + b]
                while rows[q] != row:  # struct(j) below k is a subset of struct(k): merge walk
                    q += 1
                nn6(L[q], L[lo + b], V[a], -1.0)
    return -1


@numba.njit(cache=True, inline="always")
def _subtract_product6(out, A, v):
    """out (6,) -= A v, A any 6x6 array (a transposed view gives A^T v), entry by entry."""
    for r in range(BLOCK):
        s = 0.0
        for c in range(BLOCK):
            s += A[r, c] * v[c]
        out[r] -= s


@numba.njit(cache=True, nogil=True)
def _solve(colptr, rows, L, D_inv, x):
    """x (n, 6) <- (L D L^T)^-1 x in place, for the factor of `_factor` (the factor's numbering): forward
    substitution with L, the pivots' inverses, backward substitution with L^T."""
    n = len(colptr) - 1
    y = np.empty(BLOCK)
    for j in range(n):  # L y = x: x_j is final once the columns before it are subtracted
        for q in range(colptr[j], colptr[j + 1]):
            _subtract_product6(x[rows[q]], L[q], x[j])
    for j in range(n):  # x_j <- D_j^-1 x_j
        for r in range(BLOCK):
            y[r] = 0.0
        _subtract_product6(y, D_inv[j], x[j])
        for r in range(BLOCK):
            x[j, r] = -y[r]
    for j in range(n - 1, -1, -1):  # L^T x = z: x_j = z_j - sum over the rows k below j of L_kj^T x_k
        for q in range(colptr[j], colptr[j + 1]):
            _subtract_product6(x[j], L[q].T, x[rows[q]])


@numba.njit(cache=True, nogil=True)
def _factor_and_invert(colptr, rows, L, D, Z_diag, negatives):
    """Block LDL^T (`_factor`) and selected inversion, in place: on return Z_diag holds the diagonal
    blocks of H^-1 and L the blocks of H^-1 on the factor's pattern. Returns `_factor`'s result."""
    n = len(colptr) - 1
    D_inv = np.empty((n, BLOCK, BLOCK))
    bad = _factor(colptr, rows, L, D, D_inv, negatives)
    if bad >= 0:
        return bad
    max_s = 1
    for j in range(n):
        max_s = max(max_s, colptr[j + 1] - colptr[j])
    acc = np.empty((max_s, BLOCK, BLOCK))
    for j in range(n - 1, -1, -1):  # Takahashi: columns > j of L already hold Z
        lo, hi = colptr[j], colptr[j + 1]
        s = hi - lo
        for a in range(s):
            _zero6(acc[a])
            nn6(acc[a], Z_diag[rows[lo + a]], L[lo + a], 1.0)
        for a in range(s):
            k = rows[lo + a]
            q = colptr[k]
            for b in range(a + 1, s):
                row = rows[lo + b]
                while rows[q] != row:
                    q += 1
                nn6(acc[a], L[q].T, L[lo + b], 1.0)  # Z_{k,row} = Z_{row,k}^T
                nn6(acc[b], L[q], L[lo + a], 1.0)
        z = D_inv[j]  # D_j^-1 is not read again
        for a in range(s):
            nn6(z, L[lo + a].T, acc[a], 1.0)
        for a in range(s):
            for r in range(BLOCK):
                for c in range(BLOCK):
                    L[lo + a, r, c] = -acc[a, r, c]
        for r in range(BLOCK):
            for c in range(BLOCK):
                Z_diag[j, r, c] = 0.5 * (z[r, c] + z[c, r])
    return -1


def block_matrix(H: sp.spmatrix) -> sp.bsr_matrix:
    """H as a block sparse row matrix of 6x6 blocks with sorted block columns."""
    Hb = H if isinstance(H, sp.bsr_matrix) and H.blocksize == (BLOCK, BLOCK) else \
        sp.bsr_matrix(H, blocksize=(BLOCK, BLOCK))
    Hb.sort_indices()
    return Hb


def _candidate_orders(graph: sp.csr_matrix) -> dict[str, np.ndarray]:
    """Block orderings to compare: natural, reverse Cuthill-McKee and METIS nested dissection."""
    import pymetis

    n = graph.shape[0]
    orders = {"natural": np.arange(n), "rcm": np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True))}
    if graph.nnz:  # METIS: perm[new] = old
        adjacency = pymetis.CSRAdjacency(graph.indptr, graph.indices)
        orders["nd"] = np.asarray(pymetis.nested_dissection(adjacency)[0], np.int64)
    return orders


def _graph_arrays(graph: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """The block graph's index arrays as int64 (the kernels' type)."""
    return graph.indptr.astype(np.int64), graph.indices.astype(np.int64)


def _column_counts(indptr: np.ndarray, indices: np.ndarray, order: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the ordering `order` (order[new] = old): perm_inv (perm_inv[old] = new), the elimination
    tree and the block rows per column of the factor."""
    n = len(indptr) - 1
    perm_inv = np.empty(n, np.int64)
    perm_inv[order] = np.arange(n)
    parent, _ = _etree(indptr, indices, perm_inv)
    counts = _row_structure(indptr, indices, perm_inv, parent, order, np.zeros(n + 1, np.int64),
                            np.empty(0, np.int64), False)
    return perm_inv, parent, counts


def _work(counts: np.ndarray) -> int:
    """Block products of the factorisation and the selected inversion: ~1.5 s^2 per column of s rows."""
    return int(np.sum(counts.astype(np.float64) ** 2))


class BlockSymbolic:
    """Pattern of the block factor for one ordering: column pointers and sorted block rows."""

    def __init__(self, graph: sp.csr_matrix, order: np.ndarray,
                 counted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        """`counted`: `_column_counts` of this graph and order, when already computed."""
        indptr, indices = _graph_arrays(graph)
        self.order = np.asarray(order, dtype=np.int64)  # order[new] = old
        n = len(self.order)
        self.perm_inv, parent, counts = _column_counts(indptr, indices, self.order) if counted is None else counted
        self.colptr = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=self.colptr[1:])
        self.rows = np.empty(self.colptr[-1], np.int64)
        _row_structure(indptr, indices, self.perm_inv, parent, self.order, self.colptr, self.rows, True)
        # sorted keys (column * n + row) of the factor's blocks, to place H's blocks
        self.keys = np.repeat(np.arange(n), counts) * n + self.rows
        self.work = _work(counts)


def block_graph(n: int, rows: np.ndarray, cols: np.ndarray) -> sp.csr_matrix:
    """Symmetric adjacency (n, n) of the block pairs (rows[k], cols[k]), without the diagonal."""
    off = rows != cols
    r, c = np.concatenate([rows[off], cols[off]]), np.concatenate([cols[off], rows[off]])
    graph = sp.csr_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    graph.sum_duplicates()
    graph.sort_indices()
    return graph


def analyse_graph(graph: sp.csr_matrix) -> BlockSymbolic:
    """The cheapest of the candidate block orderings of a block graph (by the block products it needs)."""
    announce_compilation(_KERNELS)  # the first selected inversion compiles them: say so once
    indptr, indices = _graph_arrays(graph)
    counted = [(order, _column_counts(indptr, indices, np.asarray(order, np.int64)))
               for order in _candidate_orders(graph).values()]
    order, best = min(counted, key=lambda item: _work(item[1][2]))  # only the cheapest one's rows are filled
    return BlockSymbolic(graph, order, best)


def analyse(H: sp.spmatrix) -> BlockSymbolic:
    """`analyse_graph` on the block pattern of H."""
    Hb = block_matrix(H)
    n = Hb.shape[0] // BLOCK
    return analyse_graph(block_graph(n, np.repeat(np.arange(n), np.diff(Hb.indptr)), Hb.indices))


def _factor_slots(sym: BlockSymbolic, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For block (rows[k], cols[k]) of H (original numbering, rows != cols): its slot in the factor's
    block storage and whether the slot holds its transpose (the slot is (new row, new column) with
    new row > new column)."""
    n = len(sym.perm_inv)
    new_r, new_c = sym.perm_inv[rows], sym.perm_inv[cols]
    transposed = new_r < new_c
    lo, hi = np.minimum(new_r, new_c), np.maximum(new_r, new_c)
    return np.searchsorted(sym.keys, lo * n + hi), transposed


def _check_pivots(sym: BlockSymbolic, bad: int) -> None:
    if bad == -2:
        raise SolverError("two scans share a feature but their block pair is not in the analysed pattern "
                          "(the symbolic analysis was made for another problem).")
    if bad >= 0:
        raise SolverError(f"the Hessian is not positive definite (pivot block of block row {sym.order[bad]}); "
                          "the covariance needs poses at a converged optimum with every pose constrained.")


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
    D = np.zeros((n, BLOCK, BLOCK))
    diag = block_row == Hb.indices
    D[sym.perm_inv[block_row[diag]]] = Hb.data[diag]
    L = np.zeros((len(sym.rows), BLOCK, BLOCK))
    lower = sym.perm_inv[block_row] > sym.perm_inv[Hb.indices]  # each pair once, as (new row > new column)
    L[_factor_slots(sym, block_row[lower], Hb.indices[lower])[0]] = Hb.data[lower]
    Z_diag = np.zeros((n, BLOCK, BLOCK))
    _check_pivots(sym, _factor_and_invert(sym.colptr, sym.rows, L, D, Z_diag, np.zeros(n, np.int64)))
    return Z_diag[sym.perm_inv]


BLOCK_ENTRIES = BLOCK * BLOCK


class BlockLDL:
    """The block LDL^T of symmetric positive definite matrices of one scalar pattern, for solves.

    The matrix is given as the values of its upper triangle in compressed columns (`indptr`,
    `indices`) whose unknowns are grouped into blocks of up to 6: unknown u is entry offset[u] of
    block node[u] (of n_nodes). A block entry no unknown holds is an identity row, coupled to
    nothing. The ordering and the symbolic analysis are done once (`analyse_graph`); `factorise`
    refactorises numerically and `solve` solves with the last factorisation.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, node: np.ndarray, offset: np.ndarray,
                 n_nodes: int):
        col = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
        block_row, block_col = node[indices], node[col]
        a, b = offset[indices], offset[col]
        announce_compilation(_SOLVE_KERNELS)  # the first solve compiles them: say so once
        self.sym = analyse_graph(block_graph(n_nodes, block_row, block_col))
        position = self.sym.perm_inv * BLOCK_ENTRIES  # a node's diagonal block in the factor's storage
        diagonal = np.flatnonzero(block_row == block_col)
        mirrored = diagonal[a[diagonal] != b[diagonal]]  # the lower triangle of a diagonal block
        self._d_source = np.concatenate([diagonal, mirrored])
        self._d_target = np.concatenate([position[block_row[diagonal]] + BLOCK * a[diagonal] + b[diagonal],
                                         position[block_row[mirrored]] + BLOCK * b[mirrored] + a[mirrored]])
        off = np.flatnonzero(block_row != block_col)
        slots, transposed = _factor_slots(self.sym, block_row[off], block_col[off])
        self._l_source = off
        self._l_target = slots * BLOCK_ENTRIES + np.where(transposed, BLOCK * b[off] + a[off], BLOCK * a[off] + b[off])
        held = np.zeros((n_nodes, BLOCK), dtype=bool)
        held[node, offset] = True
        free_node, free_offset = np.nonzero(~held)
        self._identity = position[free_node] + (BLOCK + 1) * free_offset
        self._unknown = self.sym.perm_inv[node] * BLOCK + offset  # unknown u in the factor's (n, 6) vectors
        self._negatives = np.zeros(n_nodes, np.int64)
        self._L = self._D_inv = None

    def factorise(self, data: np.ndarray) -> bool:
        """LDL^T of the matrix with upper-triangle values `data` (the pattern's order); False when it is
        not positive definite (a pivot block that is not)."""
        n = len(self.sym.perm_inv)
        D = np.zeros(n * BLOCK_ENTRIES)
        D[self._identity] = 1.0
        D[self._d_target] = data[self._d_source]
        L = np.zeros(len(self.sym.rows) * BLOCK_ENTRIES)
        L[self._l_target] = data[self._l_source]
        L, D = L.reshape(-1, BLOCK, BLOCK), D.reshape(n, BLOCK, BLOCK)
        D_inv = np.empty_like(D)
        if _factor(self.sym.colptr, self.sym.rows, L, D, D_inv, self._negatives) >= 0:
            self._L = self._D_inv = None
            return False
        self._L, self._D_inv = L, D_inv
        return True

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """The solution x of M x = rhs (the pattern's unknowns) for the last matrix factorised."""
        x = np.zeros((len(self.sym.perm_inv), BLOCK))
        x.ravel()[self._unknown] = rhs
        _solve(self.sym.colptr, self.sym.rows, self._L, self._D_inv, x)
        return x.ravel()[self._unknown]


@numba.njit(cache=True)
def _expand_rows(U, X, first):
    """X[first + t, 6 r + c] = U[t, r] and X[first + R + t, 6 r + c] = U[t, c] for the coupling rows
    U (R, 6) of one observation: a block entry (r, c) of U_hi^T U_lo is then the sum over t of
    X_hi[t] X_lo[R + t] at the same flat position, a loop over contiguous entries."""
    R = U.shape[0]
    for t in range(R):
        for r in range(BLOCK):
            for c in range(BLOCK):
                X[first + t, BLOCK * r + c] = U[t, r]
                X[first + R + t, BLOCK * r + c] = U[t, c]


@numba.njit(cache=True, inline="always")
def _subtract_product(out, X, hi, lo, rank):
    """out (36,) -= U_hi^T U_lo (flat), from the expanded rows X (`_expand_rows`, first = 0)."""
    if rank == LINEAR_RANK:  # the planes' rows: one pass over the entries
        for e in range(BLOCK_ENTRIES):
            out[e] = out[e] - X[hi, 0, e] * X[lo, 3, e] - X[hi, 1, e] * X[lo, 4, e] - X[hi, 2, e] * X[lo, 5, e]
        return
    for t in range(rank):
        for e in range(BLOCK_ENTRIES):
            out[e] -= X[hi, t, e] * X[lo, rank + t, e]


@numba.njit(cache=True, inline="always")
def _subtract_linear(first, second, X, hi, lo, s_first, s_second):
    """first (36,) -= U_hi^T U_lo + s_first (Y_hi^T U_lo + U_hi^T Y_lo) and the same with s_second
    into second (flat blocks), for three coupling rows expanded in X: U at rows 0-5, Y at 6-11
    (`_expand_rows`). One loop over the 36 contiguous entries, which the compiler vectorises."""
    for e in range(BLOCK_ENTRIES):
        p = X[hi, 0, e] * X[lo, 3, e] + X[hi, 1, e] * X[lo, 4, e] + X[hi, 2, e] * X[lo, 5, e]
        d = ((X[hi, 6, e] * X[lo, 3, e] + X[hi, 0, e] * X[lo, 9, e])
             + (X[hi, 7, e] * X[lo, 4, e] + X[hi, 1, e] * X[lo, 10, e])
             + (X[hi, 8, e] * X[lo, 5, e] + X[hi, 2, e] * X[lo, 11, e]))
        first[e] -= p + s_first * d
        second[e] -= p + s_second * d


@numba.njit(cache=True, nogil=True)
def _add_feature_blocks(column_begin, column_end, starts, obs, new_block, colptr, rows, Bt, Bt_extra, steps, D, L):
    """Add every feature's couplings to the matrices m = 0, 1 in D[m] and L[m] (the factor's storage,
    permuted) in the factor's columns column_begin..column_end-1: with the coupling rows U_o = Bt_o
    and Y_o = Bt_extra_o of the observations o of a feature, block row j gets
    -(U_o^T U_o + steps[m] (Y_o^T U_o + U_o^T Y_o)) for its observations o and block pair (j, k) of a
    feature -(U_j^T U_k + steps[m] (Y_j^T U_k + U_j^T Y_k)), exactly linear in steps[m]. One matrix
    (steps = [0], Y not read) or two (three coupling rows). Feature i's observations are
    obs[starts[i]:starts[i + 1]], in the factor's order (their factor blocks `new_block`, ascending;
    `_feature_observations`), so that the slots of one column are found by one walk down its sorted
    rows; every block is formed once for all the matrices, entry by entry from the observations'
    rows expanded to the block's flat layout (`_expand_rows`). Every block receives the features'
    terms in feature order, whatever the column range. False when a pair is not in the factor's
    pattern (nothing is written for it)."""
    linear = len(steps) == 2
    rank = Bt.shape[1]
    n, n_slots = D.shape[1], L.shape[1]
    D_first, D_second = D[0].reshape(n, BLOCK_ENTRIES), D[len(steps) - 1].reshape(n, BLOCK_ENTRIES)
    L_first, L_second = L[0].reshape(n_slots, BLOCK_ENTRIES), L[len(steps) - 1].reshape(n_slots, BLOCK_ENTRIES)
    s_first, s_second = steps[0], steps[len(steps) - 1]
    max_obs = 0
    for i in range(len(starts) - 1):
        max_obs = max(max_obs, starts[i + 1] - starts[i])
    X = np.empty((max_obs, 4 * rank if linear else 2 * rank, BLOCK_ENTRIES))
    for i in range(len(starts) - 1):
        first, count = starts[i], starts[i + 1] - starts[i]
        if count == 0 or new_block[first] >= column_end or new_block[first + count - 1] < column_begin:
            continue
        for a in range(count):
            _expand_rows(Bt[obs[first + a]], X[a], 0)
            if linear:
                _expand_rows(Bt_extra[obs[first + a]], X[a], 2 * rank)
        for a in range(count):
            lo_blk = new_block[first + a]
            if lo_blk < column_begin:
                continue
            if lo_blk >= column_end:
                break
            q, q_end = colptr[lo_blk], colptr[lo_blk + 1]
            for b in range(a, count):  # the diagonal block, then the blocks below it in this column
                if b == a:
                    out_first, out_second = D_first[lo_blk], D_second[lo_blk]
                else:
                    hi_blk = new_block[first + b]
                    while q < q_end and rows[q] < hi_blk:
                        q += 1
                    if q >= q_end or rows[q] != hi_blk:
                        return False
                    out_first, out_second = L_first[q], L_second[q]
                if linear:  # one call site each: the inlined loops are compiled once
                    _subtract_linear(out_first, out_second, X, b, a, s_first, s_second)
                else:
                    _subtract_product(out_first, X, b, a, rank)
    return True


def _feature_observations(starts: np.ndarray, block_of_obs: np.ndarray, perm_inv: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The observations `_add_feature_blocks` visits: (starts (features + 1,), obs, new_block), per
    feature its observations in a block >= 0 sorted by their block in the factor's order
    (new_block = perm_inv[block])."""
    feature = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    kept = np.flatnonzero(block_of_obs >= 0)
    new_block = perm_inv[block_of_obs[kept]]
    order = np.lexsort((new_block, feature[kept]))
    counts = np.bincount(feature[kept], minlength=len(starts) - 1)
    return np.r_[0, np.cumsum(counts)].astype(np.int64), kept[order].astype(np.int64), new_block[order]


def _in_threads(work: list) -> list:
    """The results of the calls `work` (functions of no argument: nogil kernels), run on at most
    numba.config.NUMBA_NUM_THREADS threads at once (read from the config: asking numba for its thread
    count would start a threading layer, and with Open3D loaded probe its older TBB with a warning)."""
    threads = min(len(work), numba.config.NUMBA_NUM_THREADS)
    if threads <= 1:
        return [call() for call in work]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(lambda call: call(), work))


def _add_feature_blocks_in_parallel(column_bounds: np.ndarray, starts: np.ndarray, block_of_obs: np.ndarray,
                                    perm_inv: np.ndarray, colptr: np.ndarray, rows: np.ndarray, Bt: np.ndarray,
                                    Bt_extra: np.ndarray, steps: np.ndarray, D: np.ndarray, L: np.ndarray) -> bool:
    """`_add_feature_blocks` on the column ranges column_bounds[t]..column_bounds[t + 1], one thread
    each (each writes its own columns' blocks, in the same order as one pass); False when any is.
    Observations with block -1 (the gauge pose) are skipped."""
    first, obs, new_block = _feature_observations(starts, block_of_obs, perm_inv)
    return all(_in_threads([
        lambda t=t: _add_feature_blocks(column_bounds[t], column_bounds[t + 1], first, obs, new_block, colptr, rows,
                                        Bt, Bt_extra, steps, D, L)
        for t in range(len(column_bounds) - 1)]))


@numba.njit(cache=True, nogil=True)
def _congruence(colptr, rows, order, M, D, L):
    """Blocks of H -> M^T H M in place, M block diagonal (M[old block]): the factor's column j and
    block row rows[.] are the old blocks order[j], order[rows[.]]."""
    work = np.empty((BLOCK, BLOCK))
    for j in range(len(colptr) - 1):
        Mj = M[order[j]]
        _zero6(work)
        nn6(work, D[j], Mj, 1.0)
        _zero6(D[j])
        nn6(D[j], Mj.T, work, 1.0)
        for q in range(colptr[j], colptr[j + 1]):
            _zero6(work)
            nn6(work, L[q], Mj, 1.0)
            _zero6(L[q])
            nn6(L[q], M[order[rows[q]]].T, work, 1.0)


@numba.njit(cache=True, inline="always")
def _factor_slot(colptr, rows, row, col):
    """Index of block (row, col), row > col (new numbering), in the factor's storage; -1 when the
    pattern lacks it (a binary search of the column's sorted rows)."""
    start, end = colptr[col], colptr[col + 1]
    slot = start + first_not_below(rows[start:end], row)
    return slot if slot < end and rows[slot] == row else -1


@numba.njit(cache=True, nogil=True)
def _add_feature_nodes(starts, block_of_obs, node_of_feature, perm_inv, colptr, rows, Bt, Bt_extra, steps, D, L):
    """The features with a node (node_of_feature[i] >= 0, a block row of the augmented matrix, see
    the module docstring) into D[m] and L[m] (the factor's storage, permuted): the node block
    C = [[0, I], [I, -I]] (r = Bt.shape[1] <= 3 coupled pairs of unknowns (y_a, w_a) = (a, 3 + a);
    unknowns left over get 1) and, per observation o in block j >= 0, the coupling block (j, node)
    with column a = Bt[o, a] and column 3 + a = steps[m] Bt_extra[o, a]. False when a block is not in
    the factor's pattern (nothing more is written for its feature)."""
    r = Bt.shape[1]
    ok = True
    for i in range(len(starts) - 1):
        node = node_of_feature[i]
        if node < 0:
            continue
        f = perm_inv[node]
        for m in range(len(steps)):
            _zero6(D[m, f])
            for a in range(3):
                if a < r:
                    D[m, f, a, 3 + a] = 1.0
                    D[m, f, 3 + a, a] = 1.0
                    D[m, f, 3 + a, 3 + a] = -1.0
                else:
                    D[m, f, a, a] = 1.0
                    D[m, f, 3 + a, 3 + a] = 1.0
        for o in range(starts[i], starts[i + 1]):
            if block_of_obs[o] < 0:
                continue
            j = perm_inv[block_of_obs[o]]
            below = f > j  # the factor stores block (f, j) = coupling^T, else (j, f) = coupling
            q = _factor_slot(colptr, rows, f, j) if below else _factor_slot(colptr, rows, j, f)
            if q < 0:
                ok = False
                break
            for m in range(len(steps)):
                for a in range(r):
                    for e in range(BLOCK):
                        u, y = Bt[o, a, e], steps[m] * Bt_extra[o, a, e]
                        if below:
                            L[m, q, a, e] += u
                            L[m, q, 3 + a, e] += y
                        else:
                            L[m, q, e, a] += u
                            L[m, q, e, 3 + a] += y
    return ok


def _invert_each(order: np.ndarray, colptr: np.ndarray, rows: np.ndarray, M: np.ndarray, D: np.ndarray,
                 L: np.ndarray, Z_diag: np.ndarray, negatives: np.ndarray, bad: np.ndarray) -> None:
    """Matrices m = 0.. on threads of their own (at most numba's thread count at once): the
    congruence with M (`_congruence`) and `_factor_and_invert`; bad[m] = its result."""
    def invert(m: int) -> int:
        _congruence(colptr, rows, order, M, D[m], L[m])
        return _factor_and_invert(colptr, rows, L[m], D[m], Z_diag[m], negatives)

    bad[:] = _in_threads([lambda m=m: invert(m) for m in range(len(D))])


def diagonal_blocks_of_feature_inverses(sym: BlockSymbolic, starts: np.ndarray, block_of_obs: np.ndarray,
                                        Bt: np.ndarray, Bt_extra: np.ndarray, steps: np.ndarray,
                                        block_terms: np.ndarray, pairs: np.ndarray, pair_terms: np.ndarray,
                                        congruence: np.ndarray, feature_node: np.ndarray | None = None
                                        ) -> np.ndarray:
    """Diagonal blocks (m, n, 6, 6) of H_m^-1 for m matrices of one block pattern (`sym`), each

        H_m = block_terms[m] (n, 6, 6) on the diagonal
              - sum over features i of (U_i U_i^T + steps[m] (Y_i U_i^T + U_i Y_i^T))
                (U_i, Y_i stack the coupling rows Bt[o]^T, Bt_extra[o]^T (6 x r) of the feature's
                observations, in block block_of_obs[o])
              + pair_terms[m] (K, 6, 6) at the block pairs `pairs` (K, 2)
                (pair_terms[m, k] is the block (pairs[k, 0], pairs[k, 1]); its transpose is implied),

    then congruent M^T H_m M with `congruence` M = blockdiag (n, 6, 6) (a change of coordinates per
    block), assembled directly into the factor's storage (no sparse matrix; every feature block
    formed once for all m) and inverted in parallel over m: the result is the diagonal blocks of
    (M^T H_m M)^-1. Observations sorted by feature (`starts`); block -1 marks observations left out
    (gauge pose). `feature_node` (features,): the block row of the feature's node (n.., see the
    module docstring; `sym` is then the pattern of the n poses and the nodes) or -1 for pair
    blocks. Raises `SolverError` when some H_m is not positive definite. One matrix
    (steps = [0]) or two (then with `LINEAR_RANK` coupling rows per observation, else `SolverError`).
    """
    if not (len(steps) == 2 or (len(steps) == 1 and steps[0] == 0.0)):
        raise SolverError(f"expected one matrix (steps [0]) or two; got steps {steps}.")
    if len(steps) == 2 and np.shape(Bt)[1] != LINEAR_RANK:
        raise SolverError(f"two matrices need {LINEAR_RANK} coupling rows per observation; got {np.shape(Bt)[1]}.")
    m, n_poses, n = len(steps), len(block_terms[0]), len(sym.perm_inv)
    negatives = np.zeros(n, np.int64)
    if n > n_poses:  # feature nodes: identity congruence, pair blocks only for the other features
        feature_node = np.ascontiguousarray(feature_node, dtype=np.int64)
        congruence = np.concatenate([congruence, np.tile(np.eye(BLOCK), (n - n_poses, 1, 1))])
        negatives[sym.perm_inv[n_poses:]] = Bt.shape[1]
        node_obs = np.repeat(feature_node >= 0, np.diff(starts))
        pair_block_of_obs = np.where(node_obs, -1, block_of_obs)
    else:
        pair_block_of_obs = block_of_obs
    D = np.zeros((m, n, BLOCK, BLOCK))
    D[:, sym.perm_inv[:n_poses]] = block_terms
    L = np.zeros((m, len(sym.rows), BLOCK, BLOCK))
    if len(pairs):
        slots, transposed = _factor_slots(sym, pairs[:, 0], pairs[:, 1])
        blocks = np.where(transposed[:, None, None], pair_terms.transpose(0, 1, 3, 2), pair_terms)
        for k in range(m):
            np.add.at(L[k], slots, blocks[k])
    Bt, Bt_extra, steps, congruence = (np.ascontiguousarray(a, dtype=np.float64)
                                       for a in (Bt, Bt_extra, steps, congruence))
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    # column ranges of about equal numbers of factor blocks, one per thread
    share = np.linspace(0.0, len(sym.rows) + n, numba.config.NUMBA_NUM_THREADS + 1)
    column_bounds = np.searchsorted(sym.colptr + np.arange(n + 1), share).astype(np.int64)
    column_bounds[-1] = n
    if not _add_feature_blocks_in_parallel(column_bounds, starts, np.ascontiguousarray(pair_block_of_obs, np.int64),
                                           sym.perm_inv, sym.colptr, sym.rows, Bt, Bt_extra, steps, D, L):
        _check_pivots(sym, -2)
    if n > n_poses and not _add_feature_nodes(starts, np.ascontiguousarray(block_of_obs, np.int64), feature_node,
                                              sym.perm_inv, sym.colptr, sym.rows, Bt, Bt_extra, steps, D, L):
        _check_pivots(sym, -2)
    Z_diag = np.zeros((m, n, BLOCK, BLOCK))
    bad = np.full(m, -1, np.int64)
    _invert_each(sym.order, sym.colptr, sym.rows, congruence, D, L, Z_diag, negatives, bad)
    for k in range(m):
        _check_pivots(sym, int(bad[k]))
    return Z_diag[:, sym.perm_inv[:n_poses]]


# the kernels a selected inversion and a solve call from Python (`pa_cli.runtime.numba_cache.announce_compilation`)
_KERNELS = (_etree, _row_structure, _add_feature_blocks, _add_feature_nodes, _congruence, _factor_and_invert)
_SOLVE_KERNELS = (_etree, _row_structure, _factor, _solve)


def dense_diagonal_blocks_of_feature_inverses(starts: np.ndarray, block_of_obs: np.ndarray, Bt: np.ndarray,
                                              Bt_extra: np.ndarray, steps: np.ndarray, block_terms: np.ndarray,
                                              pairs: np.ndarray, pair_terms: np.ndarray, congruence: np.ndarray
                                              ) -> np.ndarray:
    """The diagonal blocks (m, n, 6, 6) of `diagonal_blocks_of_feature_inverses` (the same matrices
    H_m, congruence and arguments; every feature in pair form) from the dense matrices M^T H_m M
    (n x n blocks), by block Cholesky and selected inversion in numpy (`_dense_inverse_blocks`).
    The work grows with n^3 (the selected inversion's with the factor's fill, linear in n for a
    sequence), but nothing is compiled: the cheaper choice for a few dozen block rows. Raises
    `SolverError` when some H_m is not positive definite."""
    if not (len(steps) == 2 or (len(steps) == 1 and steps[0] == 0.0)):
        raise SolverError(f"expected one matrix (steps [0]) or two; got steps {steps}.")
    m, n = len(steps), len(block_terms[0])
    n_features, rank = len(starts) - 1, np.shape(Bt)[1]
    kept = block_of_obs >= 0
    feature = np.repeat(np.arange(n_features), np.diff(starts))[kept]

    def stacked(coupling_rows: np.ndarray) -> np.ndarray:
        """(n, 6, features, rank): feature i's coupling rows at its observations' blocks, so that the
        contraction of stacked(U) with itself over (features, rank) sums every feature's U_i U_i^T."""
        out = np.zeros((n, BLOCK, n_features, rank))
        out[block_of_obs[kept], :, feature, :] = np.asarray(coupling_rows)[kept].transpose(0, 2, 1)
        return out

    U = stacked(Bt)
    UU = np.einsum("jaft,lbft->jlab", U, U)  # numpy's loops, not BLAS: no thread pool to wake
    YU = np.einsum("jaft,lbft->jlab", stacked(Bt_extra), U) if m == 2 else None
    Z = np.empty((m, n, BLOCK, BLOCK))
    for k in range(m):
        H = -UU if YU is None else -(UU + steps[k] * (YU + YU.transpose(1, 0, 3, 2)))  # H[j, l]: block (j, l)
        H[np.arange(n), np.arange(n)] += block_terms[k]
        if len(pairs):
            np.add.at(H, (pairs[:, 0], pairs[:, 1]), pair_terms[k])
            np.add.at(H, (pairs[:, 1], pairs[:, 0]), pair_terms[k].transpose(0, 2, 1))
        H = np.einsum("jba,jlbc,lcd->jlad", congruence, H, congruence)
        Z[k] = _dense_inverse_blocks(H)
    return Z


def _dense_inverse_blocks(H: np.ndarray) -> np.ndarray:
    """Diagonal blocks (n, 6, 6) of the inverse of a symmetric positive definite matrix given by its
    blocks H (n, n, 6, 6) (H[j, l] is block (j, l); overwritten): block Cholesky H = L L^T, then
    the selected inversion of the module docstring on the full pattern, Z_{>j,j} = -Z_{>j,>j} W_j and
    Z_jj = C_j^-T C_j^-1 - W_j^T Z_{>j,j} with W_j = L_{>j,j} C_j^-1 (C_j = L_jj), by stacked 6x6
    products (each too small for BLAS to start threads). Raises `SolverError` when H is not positive
    definite."""
    n = len(H)
    pivot_inverse = np.empty((n, BLOCK, BLOCK))  # C_j^-1
    for j in range(n):  # right-looking: column j, then the trailing matrix
        try:
            pivot_inverse[j] = np.linalg.inv(np.linalg.cholesky(H[j, j]))
        except np.linalg.LinAlgError:
            raise SolverError(f"the Hessian is not positive definite (pivot block of block row {j}); the covariance "
                              "needs poses at a converged optimum with every pose constrained.") from None
        W = H[j + 1:, j] @ (pivot_inverse[j].T @ pivot_inverse[j])  # L_ij C_j^-1 = H_ij H_jj^-1
        H[j + 1:, j] = W  # W_j, kept in place of the column
        H[j + 1:, j + 1:] -= W[:, None] @ (W @ H[j, j]).transpose(0, 2, 1)[None]  # L_ij L_kj^T
    Z = np.zeros_like(H)
    for j in range(n - 1, -1, -1):
        W = H[j + 1:, j]
        Z[j + 1:, j] = -(Z[j + 1:, j + 1:] @ W[None]).sum(axis=1)
        Z[j, j + 1:] = Z[j + 1:, j].transpose(0, 2, 1)
        z = pivot_inverse[j].T @ pivot_inverse[j] - (W.transpose(0, 2, 1) @ Z[j + 1:, j]).sum(axis=0)
        Z[j, j] = 0.5 * (z + z.T)
    return Z[np.arange(n), np.arange(n)]
