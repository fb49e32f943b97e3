"""Plane landmarks from world-frame voxel statistics.

Steps (issue 6, items 1 and 2):

1. Every scan is moved to the world frame with its current pose T_world_scan and its points
   are hashed into a voxel grid of edge `voxel_size_m` and, when `max_subdivision_levels` > 0,
   into the finer grids of edge `voxel_size_m / 2**level` at the same time. Per voxel only
   sufficient statistics are kept (count, sum and sum of outer products of the points relative
   to the voxel centre), so memory grows with the occupied voxels, never with scans squared.
2. A voxel is planar when it has at least `min_points` points (all scans together),
   lambda_min / lambda_mid <= `max_eigen_ratio` and sqrt(lambda_min / N) <= `max_thickness_m`
   (eigenvalues of the point covariance). Non-planar voxels are split into their 8 children,
   which are tested in turn (BALM2-style adaptive subdivision), up to `max_subdivision_levels`.
   The planar voxels of all levels are the leaves; every point is in at most one leaf.
3. Region growing: face-adjacent leaves (also across levels) whose normals differ at most
   `max_normal_angle_deg` and whose centroids lie at most `max_plane_distance_m` from each
   other's plane are joined (connected components of the accepted adjacency graph).
4. Each merged region is checked with the same planarity test on its merged statistics. A
   region that fails is split by re-seeding: its largest leaf (most points) is the seed, the
   leaves that agree with the seed's plane (same angle and distance tests, against the seed)
   and are connected to it through such leaves form a new region; if that still fails, the
   seed alone becomes the landmark. The rest of the region is re-grown in the next round
   (`max_split_rounds` rounds, all regions at once); leaves left after the last round are dropped.

All of it is vectorised over points and voxels (numpy sort / reduceat / eigh over stacks).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pa_cli.config import PlanesConfig
from pa_cli.errors import InputError

KEY_BITS = 20
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
PENDING_ROWS_BEFORE_REDUCE = 2_000_000  # bounds the memory of not-yet-merged voxel sums
FACE_DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                           dtype=np.int64)

Progress = Callable[[int, int], None]


def encode_keys(coords: np.ndarray, voxel_size_m: float = 1.0) -> np.ndarray:
    """int64 hash of (M, 3) integer voxel coordinates (KEY_BITS bits per axis)."""
    shifted = coords.astype(np.int64) + KEY_OFFSET
    if len(shifted) and (shifted.min() < 0 or shifted.max() > KEY_MASK):
        reach_m = KEY_OFFSET * voxel_size_m
        raise InputError(f"points lie more than {reach_m:.0f} m from the world origin, beyond the "
                         f"voxel grid of {voxel_size_m:g} m cells; check the poses or raise "
                         "planes.voxel_size_m in the config (--config).")
    return (shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2]


def decode_keys(keys: np.ndarray) -> np.ndarray:
    """(M, 3) int64 voxel coordinates of int64 keys made by `encode_keys`."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.column_stack([(keys >> (2 * KEY_BITS)) & KEY_MASK, (keys >> KEY_BITS) & KEY_MASK,
                            keys & KEY_MASK]) - KEY_OFFSET


def transform_points(T_world_scan: np.ndarray, points_scan: np.ndarray) -> np.ndarray:
    """(M, 3) world points R p + t of (M, 3) scan-frame points (metres)."""
    return points_scan @ T_world_scan[:3, :3].T + T_world_scan[:3, 3]


def _reduce_by_key(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique keys and the sum of the rows of `values` for each key."""
    if len(keys) == 0:
        return keys[:0], values[:0]
    order = np.argsort(keys, kind="stable")
    keys_sorted = keys[order]
    starts = np.flatnonzero(np.r_[True, keys_sorted[1:] != keys_sorted[:-1]])
    return keys_sorted[starts], np.add.reduceat(values[order], starts, axis=0)


def _moment_rows(q: np.ndarray) -> np.ndarray:
    """(M, 10) rows [1, x, y, z, xx, xy, xz, yy, yz, zz] of (M, 3) points."""
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    return np.column_stack([np.ones(len(q)), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z])


class _VoxelAccumulator:
    """Per-voxel sums of [1, q, q q^T] (q = point minus voxel centre, m), merged lazily."""

    def __init__(self) -> None:
        self._keys: list[np.ndarray] = []
        self._sums: list[np.ndarray] = []
        self._pending = 0

    def add(self, keys: np.ndarray, rows: np.ndarray) -> None:
        k, s = _reduce_by_key(keys, rows)
        self._keys.append(k)
        self._sums.append(s)
        self._pending += len(k)
        if self._pending > PENDING_ROWS_BEFORE_REDUCE:
            self._compact()

    def _compact(self) -> None:
        if len(self._keys) > 1:
            k, s = _reduce_by_key(np.concatenate(self._keys), np.concatenate(self._sums))
            self._keys, self._sums = [k], [s]
        self._pending = len(self._keys[0]) if self._keys else 0

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        if not self._keys:
            return np.empty(0, np.int64), np.empty((0, 10))
        self._compact()
        return self._keys[0], self._sums[0]


@dataclass
class VoxelStats:
    """Statistics of voxels in the world frame: count, centroid (m) and scatter (m^2)."""

    level: np.ndarray  # (V,) int subdivision level, voxel edge = voxel_size_m / 2**level
    keys: np.ndarray  # (V,) int64 key of the voxel at its level
    count: np.ndarray  # (V,) float number of points
    mean_world: np.ndarray  # (V, 3) centroid, world frame (m)
    scatter: np.ndarray  # (V, 3, 3) sum of (p - mean)(p - mean)^T (m^2)


def _stats_from_sums(level: int, keys: np.ndarray, sums: np.ndarray, voxel_size_m: float) -> VoxelStats:
    size_m = voxel_size_m / 2**level
    count = sums[:, 0]
    mean_local = sums[:, 1:4] / count[:, None]
    xx, xy, xz, yy, yz, zz = (sums[:, i] for i in range(4, 10))
    second = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                       np.stack([xz, yz, zz], -1)], axis=1)
    scatter = second - count[:, None, None] * mean_local[:, :, None] * mean_local[:, None, :]
    centre_world = (decode_keys(keys) + 0.5) * size_m
    return VoxelStats(level=np.full(len(keys), level), keys=keys, count=count,
                      mean_world=centre_world + mean_local, scatter=scatter)


def plane_fit(count: np.ndarray, scatter: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (V, 3), thickness sqrt(lambda_min / N) (V,) in m, and lambda_min / lambda_mid (V,).

    Eigen-decomposition of the stacked (V, 3, 3) scatter matrices (vectorised).
    """
    if len(count) == 0:
        return np.empty((0, 3)), np.empty(0), np.empty(0)
    evals, evecs = np.linalg.eigh(scatter)
    evals = np.maximum(evals, 0.0)
    thickness_m = np.sqrt(evals[:, 0] / np.maximum(count, 1.0))
    ratio = evals[:, 0] / np.maximum(evals[:, 1], np.finfo(float).tiny)
    return evecs[:, :, 0], thickness_m, ratio


def merge_stats(labels: np.ndarray, n_groups: int, count: np.ndarray, mean: np.ndarray,
                scatter: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Count, centroid and scatter of groups of voxels (parallel-axis theorem, vectorised)."""
    n = np.bincount(labels, count, minlength=n_groups)
    m = np.column_stack([np.bincount(labels, count * mean[:, i], minlength=n_groups)
                         for i in range(3)]) / np.maximum(n, 1e-300)[:, None]
    d = mean - m[labels]
    per_voxel = scatter + count[:, None, None] * d[:, :, None] * d[:, None, :]
    s = np.stack([np.bincount(labels, per_voxel[:, i, j], minlength=n_groups)
                  for i in range(3) for j in range(3)], axis=-1).reshape(n_groups, 3, 3)
    return n, m, s


def _is_planar(count: np.ndarray, thickness_m: np.ndarray, ratio: np.ndarray,
               config: PlanesConfig) -> np.ndarray:
    return (count >= config.min_points) & (ratio <= config.max_eigen_ratio) & \
        (thickness_m <= config.max_thickness_m)


@dataclass
class Landmarks:
    """Plane landmarks: the leaf voxels of each landmark and its world plane.

    `assign(points_world)` maps world points to landmark ids (-1: none or trimmed outlier).
    """

    voxel_size_m: float
    leaf_keys: list[np.ndarray]  # per level, sorted int64 keys of the leaves
    leaf_landmark: list[np.ndarray]  # per level, landmark id of each leaf (or -1)
    normal_world: np.ndarray  # (L, 3) unit normal
    centroid_world: np.ndarray  # (L, 3) m
    thickness_m: np.ndarray  # (L,) RMS point-to-plane distance at detection
    count: np.ndarray  # (L,) points at detection (all scans)
    n_voxels: np.ndarray  # (L,) leaves per landmark
    diagnostics: dict = field(default_factory=dict)

    @property
    def n_landmarks(self) -> int:
        return len(self.normal_world)

    def lookup(self, points_world: np.ndarray) -> np.ndarray:
        """Landmark id (M,) of the leaf holding each world point, -1 when none (no trimming)."""
        labels = np.full(len(points_world), -1, dtype=np.int64)
        for level, (keys, landmark) in enumerate(zip(self.leaf_keys, self.leaf_landmark, strict=True)):
            if len(keys) == 0:
                continue
            size_m = self.voxel_size_m / 2**level
            k = encode_keys(np.floor(points_world / size_m), size_m)
            pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
            hit = keys[pos] == k
            labels[hit] = landmark[pos[hit]]
        return labels

    def assign(self, points_world: np.ndarray, outlier_sigma: float,
               sigma_floor_m: float) -> tuple[np.ndarray, int]:
        """Landmark id (M,) per world point after trimming, and the number of trimmed points.

        A point is trimmed when its distance to the landmark plane exceeds
        outlier_sigma * max(thickness_m, sigma_floor_m).
        """
        labels = self.lookup(points_world)
        on = np.flatnonzero(labels >= 0)
        lm = labels[on]
        dist_m = np.abs(np.einsum("ij,ij->i", points_world[on] - self.centroid_world[lm],
                                  self.normal_world[lm]))
        sigma_m = np.maximum(self.thickness_m[lm], sigma_floor_m)
        out = dist_m > outlier_sigma * sigma_m
        labels[on[out]] = -1
        return labels, int(out.sum())


def accumulate_voxels(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
                      progress: Progress | None = None,
                      progress_offset: int = 0, progress_total: int | None = None) -> list[VoxelStats]:
    """Pass over the scans: world-frame voxel statistics at every subdivision level."""
    levels = config.max_subdivision_levels
    accumulators = [_VoxelAccumulator() for _ in range(levels + 1)]
    total = progress_total if progress_total is not None else len(scans)
    for j in range(len(scans)):
        points_scan = np.asarray(scans[j], dtype=np.float64)
        points_scan = points_scan[np.all(np.isfinite(points_scan), axis=1)]
        points_world = transform_points(T_world_scan[j], points_scan)
        for level, acc in enumerate(accumulators):
            size_m = config.voxel_size_m / 2**level
            coords = np.floor(points_world / size_m)
            keys = encode_keys(coords, size_m)
            acc.add(keys, _moment_rows(points_world - (coords + 0.5) * size_m))
        if progress is not None:
            progress(progress_offset + j + 1, total)
    return [_stats_from_sums(level, *acc.result(), config.voxel_size_m)
            for level, acc in enumerate(accumulators)]


def _select_leaves(stats: list[VoxelStats], config: PlanesConfig) -> tuple[VoxelStats, dict]:
    """Planar leaves of the adaptive octree, all levels concatenated."""
    leaves: list[VoxelStats] = []
    split_keys = None  # sorted keys (at the previous level) of voxels to split
    n_voxels, n_planar = [], []
    for level, st in enumerate(stats):
        if level > 0:
            if split_keys is None or len(split_keys) == 0:
                break
            parent = encode_keys(np.floor_divide(decode_keys(st.keys), 2))
            pos = np.minimum(np.searchsorted(split_keys, parent), len(split_keys) - 1)
            keep = split_keys[pos] == parent
            st = VoxelStats(st.level[keep], st.keys[keep], st.count[keep], st.mean_world[keep],
                            st.scatter[keep])
        _, thickness_m, ratio = plane_fit(st.count, st.scatter)
        planar = _is_planar(st.count, thickness_m, ratio, config)
        n_voxels.append(int(len(st.keys)))
        n_planar.append(int(planar.sum()))
        leaves.append(VoxelStats(st.level[planar], st.keys[planar], st.count[planar],
                                 st.mean_world[planar], st.scatter[planar]))
        split_keys = st.keys[~planar & (st.count >= config.min_points)]  # already sorted
    cat = VoxelStats(*(np.concatenate([getattr(lf, f) for lf in leaves])
                       for f in ("level", "keys", "count", "mean_world", "scatter")))
    return cat, {"n_voxels_per_level": n_voxels, "n_planar_voxels_per_level": n_planar}


def _adjacent_pairs(leaves: VoxelStats) -> np.ndarray:
    """(E, 2) index pairs of face-adjacent leaves, also across subdivision levels."""
    pairs = []
    levels = leaves.level
    index_by_level = {lv: np.flatnonzero(levels == lv) for lv in np.unique(levels)}
    sorted_by_level = {}
    for lv, idx in index_by_level.items():
        order = np.argsort(leaves.keys[idx])
        sorted_by_level[lv] = (leaves.keys[idx][order], idx[order])
    for la, idx_a in index_by_level.items():
        coords_a = decode_keys(leaves.keys[idx_a])
        for direction in FACE_DIRECTIONS:
            neighbour = coords_a + direction
            for lb in range(int(la) + 1):
                if lb not in sorted_by_level:
                    continue
                keys_b, idx_b = sorted_by_level[lb]
                anc = encode_keys(np.floor_divide(neighbour, 2 ** (int(la) - lb)))
                pos = np.minimum(np.searchsorted(keys_b, anc), len(keys_b) - 1)
                hit = keys_b[pos] == anc
                pairs.append(np.column_stack([idx_a[hit], idx_b[pos[hit]]]))
    if not pairs:
        return np.empty((0, 2), np.int64)
    return np.concatenate(pairs)


def _agree(normal_a: np.ndarray, mean_a: np.ndarray, normal_b: np.ndarray, mean_b: np.ndarray,
           config: PlanesConfig) -> np.ndarray:
    """Angle and plane-distance tests between (E, 3) planes a and b (both directions)."""
    cos_min = np.cos(np.deg2rad(config.max_normal_angle_deg))
    d = mean_b - mean_a
    return (np.abs(np.einsum("ij,ij->i", normal_a, normal_b)) >= cos_min) & \
        (np.abs(np.einsum("ij,ij->i", normal_a, d)) <= config.max_plane_distance_m) & \
        (np.abs(np.einsum("ij,ij->i", normal_b, d)) <= config.max_plane_distance_m)


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def grow_regions(leaves: VoxelStats, config: PlanesConfig) -> tuple[np.ndarray, dict]:
    """Landmark id per leaf (-1: dropped) by region growing with planarity check and splitting."""
    n = len(leaves.keys)
    landmark = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return landmark, {"n_regions_split": 0, "n_leaves_dropped": 0}
    normal, _, _ = plane_fit(leaves.count, leaves.scatter)
    pairs = _adjacent_pairs(leaves)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    ok = _agree(normal[pairs[:, 0]], leaves.mean_world[pairs[:, 0]], normal[pairs[:, 1]],
                leaves.mean_world[pairs[:, 1]], config)
    edges = pairs[ok]
    active = np.ones(n, dtype=bool)
    next_id = 0
    n_split = 0
    for _ in range(config.max_split_rounds + 1):
        if not active.any():
            break
        e = edges[active[edges[:, 0]] & active[edges[:, 1]]]
        comp = _components(n, e)
        comp_ids, comp = np.unique(comp[active], return_inverse=True)
        act_idx = np.flatnonzero(active)
        n_comp = len(comp_ids)
        cnt, _, sc = merge_stats(comp, n_comp, leaves.count[act_idx], leaves.mean_world[act_idx],
                                 leaves.scatter[act_idx])
        _, thick, ratio = plane_fit(cnt, sc)
        good = _is_planar(cnt, thick, ratio, config)
        # accept planar regions
        good_ids = np.flatnonzero(good)
        new_id = np.full(n_comp, -1, dtype=np.int64)
        new_id[good_ids] = next_id + np.arange(len(good_ids))
        next_id += len(good_ids)
        take = good[comp]
        landmark[act_idx[take]] = new_id[comp[take]]
        active[act_idx[take]] = False
        bad_ids = np.flatnonzero(~good)
        if len(bad_ids) == 0:
            break
        n_split += len(bad_ids)
        # re-seed failing regions at their largest leaf
        sel = ~take
        idx = act_idx[sel]
        reg = comp[sel]
        order = np.lexsort((-leaves.count[idx], reg))
        first = np.r_[True, reg[order][1:] != reg[order][:-1]]
        seed_of_region = np.full(n_comp, -1, dtype=np.int64)
        seed_of_region[reg[order][first]] = idx[order][first]
        seed = seed_of_region[reg]
        consistent = _agree(normal[seed], leaves.mean_world[seed], normal[idx],
                            leaves.mean_world[idx], config)
        cons_mask = np.zeros(n, dtype=bool)
        cons_mask[idx[consistent]] = True
        e2 = edges[cons_mask[edges[:, 0]] & cons_mask[edges[:, 1]]]
        comp2 = _components(n, e2)
        grown = cons_mask[idx] & (comp2[idx] == comp2[seed])
        g_idx = idx[grown]
        g_reg = reg[grown]
        g_ids, g_lab = np.unique(g_reg, return_inverse=True)
        cnt2, _, sc2 = merge_stats(g_lab, len(g_ids), leaves.count[g_idx],
                                   leaves.mean_world[g_idx], leaves.scatter[g_idx])
        _, thick2, ratio2 = plane_fit(cnt2, sc2)
        good2 = _is_planar(cnt2, thick2, ratio2, config)
        # regions whose grown part is planar: take it; else take the seed alone
        region_new = next_id + np.arange(len(g_ids))
        next_id += len(g_ids)
        take2 = good2[g_lab] | (g_idx == seed_of_region[g_reg])
        landmark[g_idx[take2]] = region_new[g_lab[take2]]
        active[g_idx[take2]] = False
    # renumber compactly (some seeded ids may be unused)
    used = landmark >= 0
    _, landmark[used] = np.unique(landmark[used], return_inverse=True)
    return landmark, {"n_regions_split": int(n_split), "n_leaves_dropped": int(active.sum())}


def detect_landmarks(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
                     progress: Progress | None = None, progress_total: int | None = None) -> Landmarks:
    """Plane landmarks of scans (each (M, 3) scan-frame points, m) at poses T_world_scan (N, 4, 4)."""
    stats = accumulate_voxels(scans, T_world_scan, config, progress, 0, progress_total)
    leaves, diag = _select_leaves(stats, config)
    del stats
    landmark, grow_diag = grow_regions(leaves, config)
    diag.update(grow_diag)
    n_lm = int(landmark.max()) + 1 if len(landmark) and landmark.max() >= 0 else 0
    used = landmark >= 0
    cnt, mean, sc = merge_stats(landmark[used], n_lm, leaves.count[used], leaves.mean_world[used],
                                leaves.scatter[used])
    normal, thick, _ = plane_fit(cnt, sc)
    n_vox = np.bincount(landmark[used], minlength=n_lm)
    leaf_keys, leaf_landmark = [], []
    for level in range(config.max_subdivision_levels + 1):
        at = np.flatnonzero(leaves.level == level)
        order = np.argsort(leaves.keys[at])
        leaf_keys.append(leaves.keys[at][order])
        leaf_landmark.append(landmark[at][order])
    diag["n_leaves"] = int(len(landmark))
    return Landmarks(voxel_size_m=config.voxel_size_m, leaf_keys=leaf_keys,
                     leaf_landmark=leaf_landmark, normal_world=normal, centroid_world=mean,
                     thickness_m=thick, count=cnt, n_voxels=n_vox, diagnostics=diag)
