"""Numba kernels of the pose-pair form of the Newton system (`pa_cli.adjust.linalg`).

Used only when a problem takes the pair form (every plane's K_i (K_i - 1) / 2 pose-pair blocks
summed into H directly), so `pa adjust` on problems that take the augmented form never imports
numba. `_pair_keys` lists the pose pair key j * N + k of every pair of scans sharing a plane;
`_accumulate` sums the blocks in one sequential pass over the observations (a pass by pose would
gather each pose's observations from all over the arrays: cache and TLB misses that grow with
the problem).
"""

from __future__ import annotations

import numba
import numpy as np

from pa_cli.runtime import numba_cache  # noqa: F401  (numba cache folder: see pa_cli/runtime/numba_cache.py)


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


@numba.njit(cache=True)
def _accumulate(plane_of_obs, starts, scan_index, A, Bt, row_ptr, cols, diag, off):
    """diag[j] = sum_o (A_o - Bt_o^T Bt_o); off[slot(j,k)] = -sum Bt_oj^T Bt_ok (j < k); Bt (O, R, 6)
    has R coupling rows per observation (3 for planes, 4 when the problem has edges). One pass
    over the observations in their stored order (sorted by feature), so A and Bt are read
    sequentially and every sum takes its terms in ascending observation order."""
    for a in range(len(plane_of_obs)):
        j = scan_index[a]
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
            lo = slot
            for r in range(6):
                for c in range(6):
                    s = 0.0
                    for t in range(Bt.shape[1]):
                        s += Bt[a, t, r] * Bt[b, t, c]
                    off[slot, r, c] -= s
