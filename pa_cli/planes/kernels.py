"""Numba kernels of plane detection and association (the per-point hot paths).

- An open-addressing hash table (linear probing) from int64 keys to int64 values, stored as
  (S, 2) slots of (key, value) so a probe reads one cache line. Keys are voxel keys of
  `pa_cli.core.voxels`, tagged with their subdivision level in bits 60..61 (`LEVEL_SHIFT`) where one
  table holds several levels (leaves, cells of the adaptive grid); points are hashed, never
  sorted. Empty slots hold -1 (real keys are non-negative).
- `scan_voxel_sums`: per-voxel sums [1, q, q q^T] of one scan's points moved to the world
  frame in the same pass (q = point minus voxel centre, m), thread-safe with a scratch per
  thread; `merge_voxel_sums` adds them to the rows of all scans (rows appended in first-seen
  order).
- `cell_neighbours`: adjacent cells of the adaptive grid, through the table of their keys.
- `label_points`: landmark id per point through the leaf table, trimming by the plane gate and
  the junction rule of `Landmarks.assign`; for the association, one pass per scan that also
  moves the scan's points to the world, skips non-finite rows and sums each landmark's points.
- `pa_cli.core.point_moments.moments_by_label`: per-label sums [1, x, y, z, xx, xy, xz, yy, yz, zz] in point order (the
  same summation order as `np.bincount`); `observation_moments`: the same sums added to given
  rows, plain and range-weighted (the clusters of a fixed per-point association).

The arithmetic per point matches the numpy formulation of `detect.py` (same operations in
the same order), so keys are identical and sums differ only by summation order.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from pa_cli.core.point_moments import add_moments
from pa_cli.core.voxels import KEY_BITS, KEY_MASK, KEY_OFFSET, pack_shifted
from pa_cli.runtime import numba_cache  # noqa: F401  (numba cache folder: see pa_cli/runtime/numba_cache.py)

_pack_shifted = numba.njit(cache=True)(pack_shifted)
LEVEL_SHIFT = 3 * KEY_BITS  # level tag above the 60 key bits
FINEST_LEVEL = np.int64(0)  # a typed constant: a literal 0 argument compiles a second, literal signature
KEY_ONLY = (1 << LEVEL_SHIFT) - 1


@numba.njit(cache=True)
def table_slot(slots: np.ndarray, shift: np.uint64, key: int) -> int:
    """Slot of key, or the empty slot where it would go (linear probing, Fibonacci hashing)."""
    mask = len(slots) - 1
    i = np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> shift)
    while slots[i, 0] != key and slots[i, 0] != -1:
        i = (i + 1) & mask
    return i


@numba.njit(cache=True)
def table_find(slots: np.ndarray, shift: np.uint64, key: int) -> int:
    """Value stored for key, -1 when absent."""
    i = table_slot(slots, shift, key)
    return slots[i, 1] if slots[i, 0] == key else -1


@numba.njit(cache=True)
def table_insert(slots: np.ndarray, shift: np.uint64, key: int, value: int) -> int:
    """Value of key, inserting `value` when absent (the caller keeps the load below 1/2)."""
    i = table_slot(slots, shift, key)
    if slots[i, 0] == -1:
        slots[i, 0] = key
        slots[i, 1] = value
    return slots[i, 1]


def new_table(n_keys: int) -> tuple[np.ndarray, np.uint64]:
    """Empty table with room for n_keys at load <= 1/2: slots (S, 2) of (key, value), hash shift."""
    bits = max(4, int(np.ceil(np.log2(max(2 * n_keys, 2)))))
    return np.full((1 << bits, 2), -1, dtype=np.int64), np.uint64(64 - bits)


@numba.njit(cache=True)
def fill_table(slots: np.ndarray, shift: np.uint64, keys: np.ndarray, values: np.ndarray) -> None:
    """Insert distinct keys with their values."""
    for i in range(len(keys)):
        table_insert(slots, shift, keys[i], values[i])


def build_table(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.uint64]:
    """Table of distinct int64 keys -> int64 values."""
    slots, shift = new_table(len(keys))
    fill_table(slots, shift, np.ascontiguousarray(keys, dtype=np.int64),
               np.ascontiguousarray(values, dtype=np.int64))
    return slots, shift


@numba.njit(cache=True)
def _cell_key(cx: float, cy: float, cz: float, level: int) -> int:
    """Level-tagged key of the voxel with lower corner coordinates (cx, cy, cz) (floored floats);
    -1 when outside the grid."""
    lo = -KEY_OFFSET
    hi = KEY_MASK - KEY_OFFSET
    if not (lo <= cx <= hi and lo <= cy <= hi and lo <= cz <= hi):
        return -1
    sx = np.int64(cx) + KEY_OFFSET
    sy = np.int64(cy) + KEY_OFFSET
    sz = np.int64(cz) + KEY_OFFSET
    return (np.int64(level) << LEVEL_SHIFT) | _pack_shifted(sx, sy, sz)


@numba.njit(cache=True)
def _to_world(T_world_scan: np.ndarray, px: float, py: float, pz: float) -> tuple[float, float, float]:
    """T_world_scan (4, 4) applied to a scan point, with the arithmetic of
    `pa_cli.core.geometry.transform_points` (the same products summed in the same order)."""
    return (px * T_world_scan[0, 0] + py * T_world_scan[0, 1] + pz * T_world_scan[0, 2] + T_world_scan[0, 3],
            px * T_world_scan[1, 0] + py * T_world_scan[1, 1] + pz * T_world_scan[1, 2] + T_world_scan[1, 3],
            px * T_world_scan[2, 0] + py * T_world_scan[2, 1] + pz * T_world_scan[2, 2] + T_world_scan[2, 3])


@numba.njit(cache=True, nogil=True)
def scan_voxel_sums(points_scan: np.ndarray, T_world_scan: np.ndarray, size_m: float, local: np.ndarray,
                    local_shift: np.uint64, local_slot: np.ndarray,
                    local_sums: np.ndarray) -> tuple[int, bool]:
    """Per-voxel sums [1, q, q q^T] of one scan's points (M, 3) (scan frame, float32 or float64)
    moved to the world frame by T_world_scan (4, 4), in voxels of edge size_m: keys (V,) and
    sums (V, 10), voxels in first-seen order, each voxel's points summed in point order. Rows
    holding NaN or inf are skipped (as `detect.finite_points` drops them); each point is moved
    in float64 as `transform_points` moves it, in the same pass (no world copy of the scan).

    Scratch (one set per thread): the table `local` with room for M keys at load <= 1/2,
    `local_slot` (M,) and `local_sums` (M, 10), the table empty and the sums zero on entry.
    Consecutive points of a scan mostly fall in the same voxel: the probe is skipped when the
    key repeats (same sums in the same order).
    Returns (V, outside): the voxels' keys are in `local` at the slots local_slot[:V] and their
    sums in local_sums[:V] (the caller copies them out and empties the scratch); outside when a
    point lies outside the voxel grid (the sums are then partial: raise). The outputs live in
    the caller's arrays: a kernel that allocates compiles numba's allocation code on the first run.
    """
    n_local = 0
    outside = False
    last_key = -1
    row = -1
    for i in range(points_scan.shape[0]):
        px, py, pz = np.float64(points_scan[i, 0]), np.float64(points_scan[i, 1]), np.float64(points_scan[i, 2])
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            continue
        x, y, z = _to_world(T_world_scan, px, py, pz)
        cx, cy, cz = np.floor(x / size_m), np.floor(y / size_m), np.floor(z / size_m)
        key = _cell_key(cx, cy, cz, FINEST_LEVEL)
        if key < 0:
            outside = True
            break
        if key != last_key:
            slot = table_slot(local, local_shift, key)
            if local[slot, 0] == -1:
                local[slot, 0] = key
                local[slot, 1] = n_local
                local_slot[n_local] = slot
                n_local += 1
            row = local[slot, 1]
            last_key = key
        qx = x - (cx + 0.5) * size_m
        qy = y - (cy + 0.5) * size_m
        qz = z - (cz + 0.5) * size_m
        add_moments(local_sums, row, 1.0, qx, qy, qz)
    return n_local, outside


@numba.njit(cache=True, nogil=True)
def merge_voxel_sums(keys: np.ndarray, scan_sums: np.ndarray, slots: np.ndarray, shift: np.uint64,
                     row_keys: np.ndarray, sums: np.ndarray, n_rows: int) -> int:
    """Add one scan's voxel sums (keys (V,), scan_sums (V, 10)) to the global rows (row_keys
    (R,), sums (R, 10), the first n_rows used) through the global table `slots` (key -> row):
    one probe per voxel of the scan, new keys appended as rows. The caller makes room first (the
    table at load <= 1/2 and R >= n_rows + V, `detect._VoxelAccumulator.merge`). Returns n_rows."""
    for r in range(len(keys)):
        row = table_insert(slots, shift, keys[r], n_rows)
        if row == n_rows:
            row_keys[row] = keys[r]
            n_rows += 1
        for c in range(10):
            sums[row, c] += scan_sums[r, c]
    return n_rows


@numba.njit(cache=True, nogil=True)
def add_weighted_means(group: np.ndarray, count: np.ndarray, mean_world: np.ndarray, n: np.ndarray,
                       weighted_sum: np.ndarray) -> None:
    """Add voxels to their groups' counts and count-weighted centroid sums, in row order:
    n[g] += count[i] and weighted_sum[g, k] += count[i] * mean_world[i, k] for g = group[i]
    (the additions of `np.bincount(group, count)` and of `np.bincount(group, count * mean_world[:, k])`
    in the same order, so the sums are bit-identical to theirs)."""
    for i in range(len(group)):
        g = group[i]
        c = count[i]
        n[g] += c
        for k in range(3):
            weighted_sum[g, k] += c * mean_world[i, k]


@numba.njit(cache=True, nogil=True)
def add_scatter_about(group: np.ndarray, count: np.ndarray, mean_world: np.ndarray, scatter: np.ndarray,
                      centre_world: np.ndarray, out: np.ndarray) -> None:
    """Add voxels' scatter moved to their group's centre (parallel-axis theorem), in row order:
    out[g] += scatter[i] + (count[i] d_a) d_b with d = mean_world[i] - centre_world[g], g = group[i]
    (the operations of `detect.merge_stats` per voxel and the additions of its `np.bincount` in the
    same order, so the sums are bit-identical to its)."""
    for i in range(len(group)):
        g = group[i]
        c = count[i]
        for a in range(3):
            d_a = mean_world[i, a] - centre_world[g, a]
            for b in range(3):
                out[g, a, b] += scatter[i, a, b] + c * d_a * (mean_world[i, b] - centre_world[g, b])


@numba.njit(cache=True, nogil=True)
def label_points(points: np.ndarray, T_world_scan: np.ndarray, in_scan_frame: bool, trim: bool,
                 range_floor_m2: float, sizes_m: np.ndarray, scale: np.ndarray, level_has_leaves: np.ndarray,
                 leaf: np.ndarray, leaf_shift: np.uint64, near: np.ndarray, near_shift: np.uint64,
                 near_start: np.ndarray, near_count: np.ndarray, near_landmark: np.ndarray, centroid: np.ndarray,
                 normal: np.ndarray, gate_m: np.ndarray, cos_min: float, labels: np.ndarray, sums: np.ndarray,
                 range_sums: np.ndarray, last_key: np.ndarray, last_val: np.ndarray) -> tuple[int, int, int]:
    """Landmark id of each of the points (M, 3) (float32 or float64) in one pass, and per label
    sums of the labelled points.

    With `in_scan_frame` the rows are scan-frame points: rows holding NaN or inf are skipped
    (label -1) and each point is moved to the world by T_world_scan (4, 4) as
    `pa_cli.core.geometry.transform_points` moves it (no world copy of the scan); otherwise they are
    world points, all looked up (T_world_scan unused).

    The leaf table maps level-tagged leaf keys to landmark id + 1 (0: a leaf of no landmark).
    Leaf lookup from the coarsest level down (the first leaf hit decides, as in
    `Landmarks.assign`); with `trim`, the trimming rules of `Landmarks.assign` (gates gate_m,
    the `near` table of junction voxels). sizes_m[level] must be sizes_m[0] / 2**level:
    x / sizes_m[level] is then exactly (x / sizes_m[0]) * 2**level (scaling by a power of two
    is exact in binary floating point), so one division per coordinate gives the voxel of every
    level (scale[level] = sizes_m[0] / sizes_m[level] = 2**level). Consecutive points mostly share
    voxels: the hash probe is skipped when a key repeats (last_key (levels,) -1 and last_val
    (levels,) on entry: the last key probed per level and its value).

    Writes labels (M,) int64: landmark id, -1 when unassigned, trimmed or skipped. Labelled points
    with a label below n_labels = len(sums) are added in point order to their label's sums (n_labels,
    10) [1, x, y, z, xx, xy, xz, yy, yz, zz] of the points as given (`moments_by_label`) and to the
    same sums weighted by 1 / max(|p|^2, range_floor_m2) in range_sums (n_labels, 10)
    (`pa_cli.core.clusters.range_weights`); both zero on entry. The outputs live in the caller's
    arrays: a kernel that allocates compiles numba's allocation code on the first run.

    Returns (points looked up, points trimmed, outside: the coarsest level whose grid some point
    lies outside of, -1 when none (the results are then incomplete: raise)).
    """
    n = points.shape[0]
    n_labels = sums.shape[0]
    use_near = len(near) > 0
    last_k0 = -1
    last_u = -1
    n_seen = 0
    n_trimmed = 0
    outside = -1
    for i in range(n):
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        labels[i] = -1
        if in_scan_frame:
            if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
                continue
            x, y, z = _to_world(T_world_scan, px, py, pz)
        else:
            x, y, z = px, py, pz
        n_seen += 1
        qx, qy, qz = x / sizes_m[0], y / sizes_m[0], z / sizes_m[0]
        lm = -1
        for level in range(len(sizes_m)):
            if not level_has_leaves[level]:
                continue
            key = _cell_key(np.floor(qx * scale[level]), np.floor(qy * scale[level]), np.floor(qz * scale[level]),
                            level)
            if key < 0:
                if outside < 0 or level < outside:
                    outside = level
                break
            if key == last_key[level]:
                v = last_val[level]
            else:
                v = table_find(leaf, leaf_shift, key)  # landmark + 1, -1: no leaf
                last_key[level] = key
                last_val[level] = v
            if v >= 0:
                lm = v - 1
                break
        if lm < 0:
            continue
        if trim:
            dist = abs((x - centroid[lm, 0]) * normal[lm, 0] + (y - centroid[lm, 1]) * normal[lm, 1] +
                       (z - centroid[lm, 2]) * normal[lm, 2])
            out = dist > gate_m[lm]
            if not out and use_near:  # the near-landmark row only within the gate (one probe per voxel)
                k0 = _cell_key(np.floor(qx), np.floor(qy), np.floor(qz), FINEST_LEVEL)
                if k0 != last_k0:
                    last_u = table_find(near, near_shift, k0) if k0 >= 0 else -1
                    last_k0 = k0
                out = not _kept(x, y, z, lm, last_u, near_start, near_count, near_landmark, centroid, normal,
                                gate_m, cos_min)
            if out:
                n_trimmed += 1
                continue
        labels[i] = lm
        if lm < n_labels:
            add_moments(sums, lm, 1.0, px, py, pz)
            add_moments(range_sums, lm, _range_weight(px, py, pz, range_floor_m2), px, py, pz)
    return n_seen, n_trimmed, outside


@numba.njit(cache=True)
def _range_weight(x: float, y: float, z: float, floor_m2: float) -> float:
    """1 / max(|p|^2, floor_m2) of a point, |p|^2 summed in the order numpy's einsum of
    `pa_cli.core.clusters.range_weights` adds the squares (x, z, then y), so the weights are equal."""
    r2 = x * x + z * z + y * y
    return 1.0 / (r2 if r2 >= floor_m2 else floor_m2)


@numba.njit(cache=True, nogil=True)
def observation_moments(observation: np.ndarray, points: np.ndarray, sums: np.ndarray, range_sums: np.ndarray,
                        with_range: bool, range_floor_m2: float, scratch: np.ndarray, range_scratch: np.ndarray,
                        touched: np.ndarray, rows: np.ndarray) -> None:
    """Add one scan's sums [1, x, y, z, xx, xy, xz, yy, yz, zz] per row of `observation` (M,)
    (points (M, 3), float32 or float64; negative rows skipped) to `sums` (O, 10), and `with_range`
    its sums weighted as in `label_points` to `range_sums` (O, 10): each row's points are summed
    in point order from zero and that sum is added once (as a per-scan bincount would be).
    Scratch: `scratch`, `range_scratch` (O, 10) zero and `touched` (O,) False, on entry and on return;
    `rows` (O,) int64, any values."""
    n_rows = 0
    for i in range(len(observation)):
        o = np.int64(observation[i])  # one signature of its callees whatever the label dtype
        if o < 0:
            continue
        if not touched[o]:
            touched[o] = True
            rows[n_rows] = o
            n_rows += 1
        x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        add_moments(scratch, o, 1.0, x, y, z)
        if with_range:
            add_moments(range_scratch, o, _range_weight(x, y, z, range_floor_m2), x, y, z)
    for r in range(n_rows):
        o = rows[r]
        touched[o] = False
        for c in range(10):
            sums[o, c] += scratch[o, c]
            scratch[o, c] = 0.0
            if with_range:
                range_sums[o, c] += range_scratch[o, c]
                range_scratch[o, c] = 0.0


@numba.njit(cache=True)
def _find_cell(slots: np.ndarray, shift: np.uint64, level: int, cx: int, cy: int, cz: int) -> int:
    """Value of the level-tagged key of voxel coordinates (cx, cy, cz) at `level`; -1 when
    absent or outside the grid."""
    sx = cx + KEY_OFFSET
    sy = cy + KEY_OFFSET
    sz = cz + KEY_OFFSET
    if not (0 <= sx <= KEY_MASK and 0 <= sy <= KEY_MASK and 0 <= sz <= KEY_MASK):
        return -1
    return table_find(slots, shift, (np.int64(level) << LEVEL_SHIFT) | _pack_shifted(sx, sy, sz))


@numba.njit(cache=True)
def _decode(key: int) -> tuple[int, int, int]:
    return (((key >> (2 * KEY_BITS)) & KEY_MASK) - KEY_OFFSET, ((key >> KEY_BITS) & KEY_MASK) - KEY_OFFSET,
            (key & KEY_MASK) - KEY_OFFSET)


@numba.njit(cache=True, nogil=True)
def cell_neighbours(sources: np.ndarray, keys: np.ndarray, level: np.ndarray, offsets: np.ndarray,
                    slots: np.ndarray, shift: np.uint64, n_levels: int, first_target: int,
                    finer: bool, pairs: np.ndarray) -> int:
    """Number E of pairs (source, target): the cells with index >= first_target adjacent to each
    of `sources`, at the source's level or coarser, and with `finer` also at finer levels; the
    first min(E, P) of them are written to pairs (P, 2) (the caller calls again with room for E
    when E > P: a kernel that grows its output compiles numba's allocation code on the first run).

    Cells are voxels of the adaptive grid (keys (V,), untagged, and level (V,)) that do not
    overlap; slots/shift: table of their level-tagged keys -> index. Cells a and b, b at the
    level of a or coarser, are adjacent when b holds the voxel at a's coordinates plus one of
    `offsets` (D, 3). From a source s, the coarser (or same-level) targets are looked up per
    offset; the finer ones at level l are the voxels of the one-voxel shell around s's block of
    level-l voxels that pass that test. A target may repeat.
    """
    n = 0
    room = len(pairs)
    for s in sources:
        ls = level[s]
        cx, cy, cz = _decode(keys[s])
        for d in range(len(offsets)):
            for lb in range(ls + 1):
                k = ls - lb
                b = _find_cell(slots, shift, lb, (cx + offsets[d, 0]) >> k, (cy + offsets[d, 1]) >> k,
                               (cz + offsets[d, 2]) >> k)
                if b >= first_target:
                    if n < room:
                        pairs[n, 0] = s
                        pairs[n, 1] = b
                    n += 1
        for lt in range(ls + 1, n_levels if finer else 0):
            k = lt - ls
            width = 1 << k
            for tx in range((cx << k) - 1, (cx << k) + width + 1):
                for ty in range((cy << k) - 1, (cy << k) + width + 1):
                    for tz in range((cz << k) - 1, (cz << k) + width + 1):
                        if (tx >> k) == cx and (ty >> k) == cy and (tz >> k) == cz:
                            continue  # inside s
                        b = _find_cell(slots, shift, lt, tx, ty, tz)
                        if b < first_target:
                            continue
                        for d in range(len(offsets)):
                            if ((tx + offsets[d, 0]) >> k) == cx and ((ty + offsets[d, 1]) >> k) == cy and \
                                    ((tz + offsets[d, 2]) >> k) == cz:
                                if n < room:
                                    pairs[n, 0] = s
                                    pairs[n, 1] = b
                                n += 1
                                break
    return n



@numba.njit(cache=True)
def _kept(x: float, y: float, z: float, lm: int, u: int, near_start: np.ndarray, near_count: np.ndarray,
          near_landmark: np.ndarray, centroid: np.ndarray, normal: np.ndarray, gate_m: np.ndarray,
          cos_min: float) -> bool:
    """Whether `label_points` (trim on) keeps the world point (x, y, z) on landmark lm, the
    landmark its leaf lookup gives it, with u the row of the near-landmark table for the point's
    level-0 voxel (-1: none): within lm's gate and not at a junction with a neighbouring landmark."""
    dist = abs((x - centroid[lm, 0]) * normal[lm, 0] + (y - centroid[lm, 1]) * normal[lm, 1] +
               (z - centroid[lm, 2]) * normal[lm, 2])
    if dist > gate_m[lm]:
        return False
    if u < 0:
        return True
    for c in range(near_start[u], near_start[u] + near_count[u]):
        other = near_landmark[c]
        if other == lm:
            continue
        d_other = abs((x - centroid[other, 0]) * normal[other, 0] + (y - centroid[other, 1]) * normal[other, 1] +
                      (z - centroid[other, 2]) * normal[other, 2])
        parallel = abs(normal[lm, 0] * normal[other, 0] + normal[lm, 1] * normal[other, 1] +
                       normal[lm, 2] * normal[other, 2]) >= cos_min
        same_plane = parallel and d_other <= gate_m[other]
        wide = max(gate_m[other], gate_m[lm]) if parallel else gate_m[other]
        if not same_plane and (d_other <= wide or d_other < dist):
            return False
    return True


# the kernels plane detection and association call from Python (the others are inlined into these or
# called by them): what a first run compiles (`pa_cli.runtime.numba_cache.announce_compilation`)
ENTRY_KERNELS = (scan_voxel_sums, merge_voxel_sums, fill_table, cell_neighbours, label_points, observation_moments)
