"""The occupied voxels of the map writer (`pa_cli.io.map_filter.MapVoxelFilter`): a growing set of voxel
keys (`pa_cli.core.voxels`: non-negative int64) in an open-addressing hash table, tested and filled
by one numba pass over a scan's keys (`VoxelKeySet.add_new`).

The table has a power of two of int64 slots, EMPTY in the free ones. A key sits in the slot of its
Fibonacci hash (the top bits of key x FIBONACCI_MULTIPLIER, modulo 2^64) or in the first free slot
after it (linear probing). The table is kept at most MAX_LOAD full: before a scan's keys could fill
it beyond that, it doubles and every key is placed again. It holds 16 to 32 bytes per key (48 while
it doubles).
"""

from __future__ import annotations

import numba
import numpy as np

from pa_cli.runtime.numba_cache import announce_compilation  # (and numba's cache folder: see that module)

EMPTY = -1  # a free slot: voxel keys are non-negative
# keys per slot at most: linear probing then needs about 2.5 probes for a key not in the table
MAX_LOAD = 0.5
FIBONACCI_MULTIPLIER = 0x9E3779B97F4A7C15  # 2^64 / golden ratio: neighbouring voxels' keys land far apart
INITIAL_SLOTS = 1 << 16  # 512 kB: the voxels of a few scans before the first doubling


@numba.njit(cache=True, inline="always")
def _home_slot(key, shift):
    """The slot a key hashes to: the top 64 - shift bits of key x FIBONACCI_MULTIPLIER (modulo 2^64)."""
    return np.int64((np.uint64(key) * np.uint64(FIBONACCI_MULTIPLIER)) >> np.uint64(shift))


@numba.njit(cache=True)
def _add_new(keys, table, shift):
    """Indices (ascending) of the keys not in `table` before them (the first occurrence of each key the
    table did not hold), which are inserted."""
    mask = len(table) - 1
    new = np.empty(len(keys), np.int64)
    n_new = 0
    for i in range(len(keys)):
        key = keys[i]
        slot = _home_slot(key, shift)
        while table[slot] != key:
            if table[slot] == EMPTY:
                table[slot] = key
                new[n_new] = i
                n_new += 1
                break
            slot = (slot + 1) & mask
    return new[:n_new]


@numba.njit(cache=True)
def _place(old_table, table, shift):
    """Every key of `old_table` into the empty `table`."""
    mask = len(table) - 1
    for key in old_table:
        if key != EMPTY:
            slot = _home_slot(key, shift)
            while table[slot] != EMPTY:
                slot = (slot + 1) & mask
            table[slot] = key


def _shift(n_slots: int) -> int:
    """The right shift that leaves log2(n_slots) bits of a 64-bit hash."""
    return 64 - (n_slots.bit_length() - 1)


class VoxelKeySet:
    """A growing set of voxel keys (module docstring); `n_keys` counts them."""

    def __init__(self) -> None:
        self._table = np.full(INITIAL_SLOTS, EMPTY, dtype=np.int64)
        self.n_keys = 0
        announce_compilation(KERNELS)  # the first map write compiles them: say so once

    def add_new(self, keys: np.ndarray) -> np.ndarray:
        """Indices (ascending) of the (M,) `keys` that are new: in the set neither before nor earlier in
        `keys`. Every key of `keys` is in the set afterwards."""
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        n_slots = len(self._table)
        while self.n_keys + len(keys) > MAX_LOAD * n_slots:
            n_slots *= 2
        if n_slots > len(self._table):
            table = np.full(n_slots, EMPTY, dtype=np.int64)
            _place(self._table, table, _shift(n_slots))
            self._table = table
        new = _add_new(keys, self._table, _shift(n_slots))
        self.n_keys += len(new)
        return new


KERNELS = (_add_new, _place)  # what `VoxelKeySet` compiles (`numba_cache.announce_compilation`)
