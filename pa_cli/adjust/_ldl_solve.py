"""A sparse symmetric positive definite matrix factorised once, solved for many right-hand sides at once.

QDLDL (`qdldl`) factorises P M P^T = L D L^T (AMD ordering P, L unit lower-triangular, D diagonal).
Its Python binding solves one right-hand side per call, each a pass over the whole factor;
`_solve_columns` takes the factor (`Solver.factors`) and solves a block of right-hand sides in one
forward and one backward pass, each entry of L applied to a row of the block (contiguous, vector
code): the factor is read once per block instead of once per column.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from pa_cli.runtime.numba_cache import announce_compilation  # (and numba's cache folder: see that module)


@numba.njit(cache=True, nogil=True)
def _solve_columns(indptr, indices, data, pivots, x):
    """x (n, k) <- (L D L^T)^-1 x in place: L's strictly lower entries in compressed columns (`indptr`,
    `indices`, `data`), D's entries `pivots` (n,)."""
    n, k = x.shape
    for j in range(n):  # L y = x: row j is final once the columns before it are subtracted
        for q in range(indptr[j], indptr[j + 1]):
            i, v = indices[q], data[q]
            for c in range(k):
                x[i, c] -= v * x[j, c]
    for j in range(n):
        for c in range(k):
            x[j, c] /= pivots[j]
    for j in range(n - 1, -1, -1):  # L^T x = z: x_j = z_j - sum over the rows i below j of L_ij x_i
        for q in range(indptr[j], indptr[j + 1]):
            i, v = indices[q], data[q]
            for c in range(k):
                x[j, c] -= v * x[i, c]


class PositiveDefiniteFactor:
    """L D L^T of a sparse symmetric positive definite matrix given by its upper triangle (CSC)."""

    def __init__(self, upper: sp.csc_matrix):
        """Raises ValueError when the matrix is singular or not positive definite (a pivot <= 0)."""
        import qdldl

        announce_compilation((_solve_columns,))  # the first solve compiles it: say so once
        try:
            L, self.pivots, self.order = qdldl.Solver(upper, upper=True).factors()
        except (ValueError, RuntimeError) as exc:  # a zero pivot
            raise ValueError(f"the LDL^T factorisation failed: {exc}") from exc
        if not np.all(self.pivots > 0.0):
            raise ValueError("a pivot of the LDL^T factorisation is not positive")
        self.indptr, self.indices, self.data = L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """The solution X (n, k) of M X = rhs (n, k)."""
        x = np.ascontiguousarray(rhs[self.order], dtype=np.float64)
        _solve_columns(self.indptr, self.indices, self.data, self.pivots, x)
        out = np.empty_like(x)
        out[self.order] = x
        return out
