"""A sparse symmetric positive definite matrix M factorised once, and Hutchinson's probes of U^T M^-1 U.

QDLDL (`qdldl`) factorises P M P^T = L D L^T (AMD ordering P, L unit lower-triangular, D diagonal).
Its Python binding solves one right-hand side per call, each a pass over the whole factor;
`_solve_columns` takes the factor (`Solver.factors`) and solves a block of right-hand sides in one
forward and one backward pass, each entry of L applied to a row of the block (contiguous, vector
code): the factor is read once per block instead of once per column. `probe_sums` forms the
right-hand sides U z of a block of probes z, solves them and gathers z . (U^T x) per column of U, in
the factor's numbering and without forming U: its columns are given by their few entries.
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


@numba.njit(cache=True, nogil=True)
def _scatter_probes(position, rows, values, bits, x):
    """x[position[rows[o, m]]] += sum_c values[o, c, m] z[o, c] with z = 2 bits - 1 (o, c, probe), for every
    observation o and entry m (rows[o, m] < 0: no entry)."""
    n_obs, n_columns, n_rows = values.shape
    k = x.shape[1]
    z = np.empty((n_columns, k))
    for o in range(n_obs):
        for c in range(n_columns):
            for p in range(k):
                z[c, p] = 2.0 * bits[o, c, p] - 1.0
        for m in range(n_rows):
            if rows[o, m] < 0:
                continue
            i = position[rows[o, m]]
            for c in range(n_columns):
                v = values[o, c, m]
                for p in range(k):
                    x[i, p] += v * z[c, p]


@numba.njit(cache=True, nogil=True)
def _probe_products(position, rows, values, bits, x, total):
    """total[o, c] += sum_p z[o, c, p] sum_m values[o, c, m] x[position[rows[o, m]], p], z = 2 bits - 1."""
    n_obs, n_columns, n_rows = values.shape
    k = x.shape[1]
    gathered = np.empty((n_columns, k))  # sum_m values[o, c, m] x[., p] of one observation
    for o in range(n_obs):
        gathered[:] = 0.0
        for m in range(n_rows):
            if rows[o, m] < 0:
                continue
            i = position[rows[o, m]]
            for c in range(n_columns):
                v = values[o, c, m]
                for p in range(k):
                    gathered[c, p] += v * x[i, p]
        for c in range(n_columns):
            s = 0.0
            for p in range(k):
                s += (2.0 * bits[o, c, p] - 1.0) * gathered[c, p]
            total[o, c] += s


KERNELS = (_solve_columns, _scatter_probes, _probe_products)  # (`numba_cache.announce_compilation`)


class PositiveDefiniteFactor:
    """L D L^T of a sparse symmetric positive definite matrix given by its upper triangle (CSC)."""

    def __init__(self, upper: sp.csc_matrix):
        """Raises ValueError when the matrix is singular or not positive definite (a pivot <= 0)."""
        import qdldl

        announce_compilation(KERNELS)  # the first probes compile them: say so once
        try:
            L, self.pivots, self.order = qdldl.Solver(upper, upper=True).factors()
        except (ValueError, RuntimeError) as exc:  # a zero pivot
            raise ValueError(f"the LDL^T factorisation failed: {exc}") from exc
        if not np.all(self.pivots > 0.0):
            raise ValueError("a pivot of the LDL^T factorisation is not positive")
        self.indptr, self.indices, self.data = L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data
        self.position = np.empty(len(self.order), np.int64)  # row r of M is row position[r] of the factor's
        self.position[self.order] = np.arange(len(self.order))

    def probe_sums(self, rows: np.ndarray, values: np.ndarray, bits: np.ndarray) -> np.ndarray:
        """(O, C) sum over the probes p of z_p,oc (U^T M^-1 U z_p)_oc, the columns (o, c) of U holding
        values[o, c] (O, C, R) at the rows rows[o] (O, R; -1: no entry) of M, for the probes z = 2 bits - 1
        (bits (O, C, P) of 0 and 1), solved in one block."""
        x = np.zeros((len(self.position), bits.shape[2]))
        _scatter_probes(self.position, rows, values, bits, x)
        _solve_columns(self.indptr, self.indices, self.data, self.pivots, x)
        total = np.zeros(values.shape[:2])
        _probe_products(self.position, rows, values, bits, x, total)
        return total
