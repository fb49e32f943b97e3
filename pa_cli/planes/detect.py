"""Plane landmarks from world-frame voxel statistics.

Steps:

1. Every scan is moved to the world frame with its current pose T_world_scan and its points
   are hashed into the finest voxel grid, of edge `voxel_size_m / 2**max_subdivision_levels`
   (`association_threads` scans at once). Per voxel only sufficient statistics are kept (count,
   sum and sum of outer products of the points relative to the voxel centre), so memory grows
   with the occupied voxels, never with scans squared; each coarser grid's statistics, up to
   edge `voxel_size_m`, are summed from its children's (parallel-axis theorem).
2. A voxel is planar when it has at least `min_points` points (all scans together),
   lambda_min / lambda_mid <= `max_eigen_ratio` and sqrt(lambda_min / N) <= `max_thickness_m`
   (eigenvalues of the point covariance). Non-planar voxels are split into their 8 children,
   which are tested in turn (BALM2-style adaptive subdivision), up to `max_subdivision_levels`.
   The planar voxels of all levels are the leaves; every point is in at most one leaf.
3. Region growing: adjacent leaves (also across levels; `neighbourhood` 26 = voxels that touch,
   the default, or 6 = share a face) whose normals differ at most
   `max_normal_angle_deg` and whose centroids lie at most `max_plane_distance_m` from each
   other's plane are joined (connected components of the accepted adjacency graph). Face
   adjacency alone breaks planes oblique to the grid: where the plane only clips a voxel's
   corner, that voxel holds too few points to be tested and the staircase of voxels along the
   plane falls apart into several landmarks; 26-adjacency bridges those gaps.
4. Each merged region is checked with the same planarity test on its merged statistics. A
   region that fails is split by re-seeding: its largest leaf (most points) is the seed, the
   leaves that agree with the seed's plane (same angle and distance tests, against the seed)
   and are connected to it through such leaves form a new region; if that still fails, the
   seed alone becomes the landmark. The rest of the region is re-grown in the next round
   (`max_split_rounds` rounds, all regions at once); leaves left after the last round are dropped.
5. Leaves whose RMS distance to their landmark's plane exceeds `leaf_outlier_sigma` times the
   landmark's robust sigma (point-weighted median of that RMS over its leaves) are dropped
   and the landmark planes refit (`leaf_refit_rounds` times): small voxels next to a corner
   holding points of the crossing plane would otherwise tilt the landmark by degrees.
   Then each landmark must be flat at the noise level of its points: their variance about its
   plane may exceed their noise by at most `MODEL_ERROR_RATIO`**2. The noise is measured where
   a surface's departure from one plane cannot show: each leaf's points and those of the
   adjacent leaves of its landmark, about their one plane (`_local_noise_var`). A cambered or
   undulating road, a curved car or a facade with recesses grown over many leaves fails,
   although every pair of adjacent leaves agrees; it is split by re-seeding as in step 4, each
   part's leaves within `SEED_OFFSET_SIGMAS` noise sigmas of its seed's plane.

6. Sparse growth (`grow_into_sparse`): cells with fewer than `min_points` points (never tested
   on their own) that touch a landmark join it when the RMS distance of their points to its
   plane is within `leaf_outlier_sigma` robust sigmas, ring by ring with a refit per ring;
   only landmarks with a well-determined normal and a gate below `max_plane_distance_m` grow.
   Far, sparsely sampled facades are followed from the few voxels that reach `min_points`.

Per-point work (voxel hashing, sums, leaf lookup, trimming), voxel statistics and adjacency
run in numba kernels (`kernels.py`, hash tables, no sorting of points); other per-voxel work
is numpy over stacks. Work that is parallel by nature uses `association_threads` threads:
scans summed at once, the voxel statistics (a parallel kernel), and the eigen-decompositions
and adjacency of large stacks (row blocks, `in_parts`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from pa_cli.config import PlanesConfig
from pa_cli.core.clusters import RANGE_WEIGHT_FLOOR_M, normal_sigma_rad
from pa_cli.core.geometry import transform_points
from pa_cli.core.voxels import decode_keys, encode_keys, outside_grid_error, voxel_keys
from pa_cli.errors import SolverError
from pa_cli.planes import kernels
from pa_cli.runtime.distributed import GB, current_execution, in_order, process_tree_rss_bytes

_OFFSETS = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
NEIGHBOUR_OFFSETS = {
    6: _OFFSETS[np.abs(_OFFSETS).sum(axis=1) == 1],  # faces
    26: _OFFSETS[np.abs(_OFFSETS).sum(axis=1) > 0],  # faces, edges and corners
}

Progress = Callable[[int, int], None]
_Result = TypeVar("_Result")
MERGE_ROOM_SCANS = 8
"""The voxel accumulator's first scan makes room for the voxels of this many scans like it:
neighbouring scans share most voxels, so the rows of a sequence grow far slower than its scans,
and the table (re-hashed whenever it doubles) rarely grows (a few MB per 10k voxels)."""
MODEL_ERROR_RATIO = np.sqrt(2.0)
"""A landmark's RMS thickness may exceed the local noise of its leaves (`_local_noise_var`) by this factor: the
surface's departure from one plane (camber, curvature, relief) at most as large as the noise itself."""
SEED_OFFSET_SIGMAS = 1.0
"""When a region is split, a leaf joins its seed's part while its centroid lies within this many noise sigmas of
the seed's plane: offsets spread evenly within +-1 sigma add a variance of a third of the noise's."""
VOXEL_STATS_BYTES = 8 + 8 + 8 + 3 * 8 + 9 * 8
"""Bytes of one voxel's `VoxelStats` row: level, key, count, centroid and scatter (int64 and float64)."""
MIN_ROWS_PER_THREAD = 4096
"""Row blocks smaller than this are not split over threads (`in_parts`): starting a thread costs
about as much as the eigen-decomposition of a few thousand 3x3 matrices."""


class _VoxelAccumulator:
    """Per-voxel sums [1, q, q q^T] (q = point minus voxel centre, m) of every subdivision level.

    Points are summed in the voxels of the finest level only; each coarser level's sums are
    those of its 8 children moved to its own centre (parallel-axis theorem), so every point is
    hashed once. One hash table (numba, `kernels`): `scan_sums` sums one scan's points per
    voxel (thread-safe: a scratch per thread), `merge` adds them to the rows of all scans, one
    probe per voxel of the scan; nothing is sorted until `result`. Memory grows with the
    occupied voxels (rows of 10 sums), never with the number of points.
    """

    def __init__(self, voxel_size_m: float, levels: int) -> None:
        self.sizes_m = np.array([voxel_size_m / 2**level for level in range(levels + 1)])
        self.n_rows = 0
        self.row_keys = np.empty(0, np.int64)
        self.sums = np.empty((0, 10))
        self.table = kernels.new_table(0)
        self._scratch = threading.local()

    def scan_sums(self, points_scan: np.ndarray, T_world_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keys (V,) and sums (V, 10) of the finest-level voxels of a scan's points (M, 3) (m,
        scan frame; rows with NaN or inf skipped) at pose T_world_scan (4, 4)."""
        points_scan = np.asarray(points_scan)
        if points_scan.dtype not in (np.float32, np.float64):
            points_scan = points_scan.astype(np.float64)
        scratch = getattr(self._scratch, "arrays", None)
        if scratch is None or len(scratch[2]) < len(points_scan):  # room for one key per point
            n = len(points_scan)
            scratch = (*kernels.new_table(n), np.empty(n, np.int64), np.zeros((n, 10)))
            self._scratch.arrays = scratch
        n_voxels, outside = kernels.scan_voxel_sums(points_scan, np.ascontiguousarray(T_world_scan, np.float64),
                                                     self.sizes_m[-1], *scratch)
        local, _, local_slot, local_sums = scratch
        slots = local_slot[:n_voxels]
        keys, sums = local[slots, 0], local_sums[:n_voxels].copy()  # copies out, then the scratch emptied
        local[slots, 0] = -1
        local_sums[:n_voxels] = 0.0
        if outside:  # raise the error of the coarsest level a point is outside of
            points_world = transform_points(T_world_scan, finite_points(points_scan))
            for size_m in self.sizes_m:
                voxel_keys(points_world, size_m, "scene.plane_voxel_m")
        return keys, sums

    def merge(self, keys: np.ndarray, sums: np.ndarray) -> None:
        """Add one scan's voxel sums (from `scan_sums`); the first scan makes room for the rows
        of MERGE_ROOM_SCANS scans like it at once."""
        if self.n_rows == 0 and len(self.row_keys) < MERGE_ROOM_SCANS * len(keys):
            room = MERGE_ROOM_SCANS * len(keys)
            self.table = kernels.new_table(room)
            self.row_keys = np.empty(room, np.int64)
            self.sums = np.zeros((room, 10))
        n_after = self.n_rows + len(keys)  # rows after the merge, at most: room for them first (doubling)
        if 2 * n_after > len(self.table[0]):  # a table of at least twice the slots, the rows' keys re-inserted
            slots, shift = kernels.new_table(max(n_after, len(self.table[0])))
            kernels.fill_table(slots, shift, self.row_keys[:self.n_rows], np.arange(self.n_rows))
            self.table = (slots, shift)
        if n_after > len(self.row_keys):
            room = max(n_after, 2 * len(self.row_keys))
            self.row_keys = np.concatenate([self.row_keys, np.empty(room - len(self.row_keys), np.int64)])
            self.sums = np.concatenate([self.sums, np.zeros((room - len(self.sums), 10))])
        self.n_rows = kernels.merge_voxel_sums(keys, sums, *self.table, self.row_keys, self.sums, self.n_rows)

    def result(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per level, coarsest first: sorted keys (K,) of the level's voxels and their sums (10, K)."""
        keys = self.row_keys[:self.n_rows]
        order = np.argsort(keys)
        levels = [(keys[order], self.sums[order].T)]
        for size_m in self.sizes_m[:0:-1]:
            levels.append(_parent_sums(*levels[-1], size_m))
        return levels[::-1]


def _parent_sums(keys: np.ndarray, sums: np.ndarray, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Sorted keys and sums (10, K) of the parents (edge 2 size_m) of voxels of edge size_m with
    sorted keys (K,) and sums (10, K) [1, q, q q^T]: each child's sums moved from its centre to
    its parent's by d = child centre - parent centre (q' = q + d), summed per parent in child
    order (`np.bincount`, one pass per sum)."""
    child = decode_keys(keys)
    parent = np.floor_divide(child, 2)
    parent_keys, row = np.unique(encode_keys(parent), return_inverse=True)
    d = (child.astype(np.float64) + 0.5) * size_m - (parent.astype(np.float64) + 0.5) * (2 * size_m)
    count = sums[0]
    moved = [count] + [sums[1 + i] + count * d[:, i] for i in range(3)]
    moved += [sums[col] + sums[1 + i] * d[:, j] + d[:, i] * sums[1 + j] + count * d[:, i] * d[:, j]
              for col, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), start=4)]
    return parent_keys, np.array([np.bincount(row, weights=m, minlength=len(parent_keys)) for m in moved])


@dataclass
class VoxelStats:
    """Statistics of voxels in the world frame: count, centroid (m) and scatter (m^2)."""

    level: np.ndarray  # (V,) int subdivision level, voxel edge = voxel_size_m / 2**level
    keys: np.ndarray  # (V,) int64 key of the voxel at its level
    count: np.ndarray  # (V,) float number of points
    mean_world: np.ndarray  # (V, 3) centroid, world frame (m)
    scatter: np.ndarray  # (V, 3, 3) sum of (p - mean)(p - mean)^T (m^2)


def _stats_from_sums(level: int, keys: np.ndarray, sums: np.ndarray, voxel_size_m: float) -> VoxelStats:
    """Statistics of the voxels of one level (edge voxel_size_m / 2**level) from their keys (K,)
    (untagged) and sums (10, K) [1, q, q q^T] (q about the voxel centre): count, mean = q-sum /
    count, centroid = centre + mean (world frame), scatter = second moments - (count mean_i) mean_j.
    Elementwise numpy (about 14 ms for 180,000 voxels, against a kernel's 1.5 ms and its compilation,
    about 1 s on the first run)."""
    size_m = voxel_size_m / 2**level
    count = sums[0].copy()
    mean = sums[1:4] / count
    mean_world = (decode_keys(keys).astype(np.float64) + 0.5) * size_m + mean.T
    scatter = np.empty((len(keys), 3, 3))
    for (a, b), row in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)), range(4, 10), strict=True):
        scatter[:, a, b] = sums[row] - count * mean[a] * mean[b]
        if a != b:
            scatter[:, b, a] = sums[row] - count * mean[b] * mean[a]
    return VoxelStats(level=np.full(len(keys), level), keys=keys, count=count, mean_world=mean_world,
                      scatter=scatter)


def plane_fit(count: np.ndarray, scatter: np.ndarray,
              threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals (V, 3), thickness sqrt(lambda_min / N) (V,) in m, and lambda_min / lambda_mid (V,).

    Eigen-decomposition of the stacked (V, 3, 3) scatter matrices (vectorised), large stacks
    split over `threads` threads (numpy's LAPACK loop releases the GIL; each matrix is
    decomposed on its own, so the split does not change the result).
    """
    if len(count) == 0:
        return np.empty((0, 3)), np.empty(0), np.empty(0)
    parts = in_parts(np.linalg.eigh, len(scatter), threads, scatter)
    evals = np.maximum(np.concatenate([p[0] for p in parts]), 0.0)
    evecs = np.concatenate([p[1] for p in parts])
    thickness_m = np.sqrt(evals[:, 0] / np.maximum(count, 1.0))
    ratio = evals[:, 0] / np.maximum(evals[:, 1], np.finfo(float).tiny)
    return evecs[:, :, 0], thickness_m, ratio


def in_parts(work: Callable[..., _Result], n: int, threads: int, *arrays: np.ndarray) -> list[_Result]:
    """work(*(a[part] for a in arrays)) for consecutive row blocks of the (n, ...) arrays, in
    order: one block per thread (`threads`, the calling thread takes the first) when every
    block gets at least MIN_ROWS_PER_THREAD rows, else one block. For kernels that release
    the GIL and treat rows independently."""
    n_parts = max(1, min(threads, n // MIN_ROWS_PER_THREAD))
    if n_parts == 1:
        return [work(*arrays)]
    bounds = np.linspace(0, n, n_parts + 1).astype(np.int64)
    blocks = [tuple(a[bounds[k]:bounds[k + 1]] for a in arrays) for k in range(n_parts)]
    with ThreadPoolExecutor(max_workers=n_parts - 1) as pool:
        rest = [pool.submit(work, *block) for block in blocks[1:]]
        first = work(*blocks[0])
        return [first] + [f.result() for f in rest]


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


def merge_voxel_maps(parts: Sequence[list[VoxelStats]]) -> list[VoxelStats]:
    """Per level, the statistics of voxels measured in several parts (each a list of levels, as
    `accumulate_voxels` returns) merged per voxel key: `merge_stats` over the parts' rows in
    order, without concatenating them. Only the keys are concatenated (to number the distinct
    ones, sorted); counts, centroids and scatters are added part by part into the merged rows
    (numba kernels `add_weighted_means`, `add_scatter_about`: the additions of `merge_stats` in
    the same order, so the result is bit-identical to it). Memory: the parts, the merged rows
    and about 40 bytes per input row for numbering the keys.

    Raises `SolverError` before allocating a level's merged rows when they would take the
    memory of this process and its local workers (`process_tree_rss_bytes`) above the memory
    budget (`current_execution()`'s `memory_budget_gb`): the map of a long sequence whose
    revisits do not land in the same voxels grows with its length, and an error naming the
    fix is better than running out of memory."""
    budget_bytes = current_execution().memory_budget_gb * GB
    merged = []
    for level, level_parts in enumerate(zip(*parts, strict=True)):
        unique, group = np.unique(np.concatenate([p.keys for p in level_parts]), return_inverse=True)
        bounds = np.cumsum([0] + [len(p.keys) for p in level_parts])
        n_groups = len(unique)
        need_bytes = process_tree_rss_bytes() + VOXEL_STATS_BYTES * n_groups
        if need_bytes > budget_bytes:
            raise _voxel_budget_error(need_bytes, budget_bytes, n_groups, level)
        count = np.zeros(n_groups)
        weighted_sum = np.zeros((n_groups, 3))
        for k, p in enumerate(level_parts):
            kernels.add_weighted_means(group[bounds[k]:bounds[k + 1]], p.count, p.mean_world, count, weighted_sum)
        mean_world = weighted_sum / np.maximum(count, 1e-300)[:, None]
        del weighted_sum
        scatter = np.zeros((n_groups, 3, 3))
        for k, p in enumerate(level_parts):
            kernels.add_scatter_about(group[bounds[k]:bounds[k + 1]], p.count, p.mean_world, p.scatter, mean_world,
                                       scatter)
        del group
        merged.append(VoxelStats(level=np.full(n_groups, level), keys=unique, count=count, mean_world=mean_world,
                                 scatter=scatter))
    return merged


def _voxel_budget_error(need_bytes: float, budget_bytes: float, n_voxels: int, level: int) -> SolverError:
    return SolverError(
        f"plane detection: merging the windows' voxel statistics needs {need_bytes / GB:.1f} GB in this process "
        f"and its local workers ({n_voxels} distinct voxels at level {level}, {VOXEL_STATS_BYTES} bytes each), "
        f"above execution.memory_budget_gb = {budget_bytes / GB:g}. The voxel map grows with the area "
        "the poses cover: a long sequence whose revisits do not land in the same voxels (drift, no loop closure) "
        "grows it without bound. Fix: refine with --loops (revisits then share their voxels), raise "
        "execution.memory_budget_gb if the machine has the memory, coarsen the detection grid (a larger "
        "scene.plane_voxel_m or fewer advanced.planes.max_subdivision_levels), or refine the sequence in parts.")


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
    sigma_m: np.ndarray  # (L,) robust noise: point-weighted median over leaves of their RMS distance
    count: np.ndarray  # (L,) points at detection (all scans)
    n_voxels: np.ndarray  # (L,) leaves per landmark
    near_keys: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    # (K,) sorted level-0 voxel keys whose 3x3x3 neighbourhood holds leaves of 2+ landmarks ...
    near_landmark: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    # (K,) ... and one of those landmarks per row (a key repeats once per landmark)
    max_normal_angle_deg: float = 10.0  # planes closer in angle count as the same plane
    diagnostics: dict = field(default_factory=dict)
    _tables: tuple | None = field(default=None, repr=False, compare=False)  # built by assign/prepare

    @property
    def n_landmarks(self) -> int:
        return len(self.normal_world)

    def _kernel_tables(self) -> tuple:
        """Hash tables of the leaves (level-tagged key -> landmark + 1) and of near_keys
        (key -> row of its first landmark in near_landmark, and the number of rows), built once."""
        if self._tables is None:
            tagged = [keys | (level << kernels.LEVEL_SHIFT) for level, keys in enumerate(self.leaf_keys)]
            leaf = kernels.build_table(np.concatenate(tagged) if tagged else np.empty(0, np.int64),
                                        np.concatenate(self.leaf_landmark) + 1 if tagged else
                                        np.empty(0, np.int64))
            uniq, start, count = np.unique(self.near_keys, return_index=True, return_counts=True)
            near = kernels.build_table(uniq, np.arange(len(uniq)))
            self._tables = (leaf, near, start.astype(np.int64), count.astype(np.int64))
        return self._tables

    def _label(self, points: np.ndarray, T_world_scan: np.ndarray | None, trim: bool, gate_m: np.ndarray,
               n_sums: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
        """`kernels.label_points` on (M, 3) points (scan frame moved by T_world_scan, or world
        points when it is None) with the gates gate_m (L,) (m) and sums for the first n_sums
        labels; raises when a point lies outside the grid."""
        points = np.asarray(points)
        if points.dtype not in (np.float32, np.float64):
            points = points.astype(np.float64)
        leaf, near, near_start, near_count = self._kernel_tables()
        sizes_m = np.array([self.voxel_size_m / 2**level for level in range(len(self.leaf_keys))])
        labels, sums, range_sums = np.empty(len(points), np.int64), np.zeros((n_sums, 10)), np.zeros((n_sums, 10))
        n_seen, n_trimmed, outside = kernels.label_points(
            np.ascontiguousarray(points), np.eye(4) if T_world_scan is None else
            np.ascontiguousarray(T_world_scan, dtype=np.float64), T_world_scan is not None, trim,
            RANGE_WEIGHT_FLOOR_M**2, sizes_m, sizes_m[0] / sizes_m,
            np.array([len(k) > 0 for k in self.leaf_keys], dtype=np.bool_),
            *leaf, *near, near_start, near_count, np.ascontiguousarray(self.near_landmark, dtype=np.int64),
            np.ascontiguousarray(self.centroid_world, dtype=np.float64),
            np.ascontiguousarray(self.normal_world, dtype=np.float64), np.ascontiguousarray(gate_m, dtype=np.float64),
            float(np.cos(np.deg2rad(self.max_normal_angle_deg))), labels, sums, range_sums,
            np.full(len(sizes_m), -1, np.int64), np.zeros(len(sizes_m), np.int64))
        if outside >= 0:  # the error of the coarsest level a point is outside of
            raise outside_grid_error(float(sizes_m[outside]), "scene.plane_voxel_m")
        return labels, sums, range_sums, int(n_seen), int(n_trimmed)

    def _run_kernel(self, points_world: np.ndarray, trim: bool, gate_m: np.ndarray) -> tuple[np.ndarray, int]:
        labels, _, _, _, n_trimmed = self._label(np.asarray(points_world, dtype=np.float64), None, trim, gate_m, 0)
        return labels, n_trimmed

    def gates_m(self, outlier_sigma: float, sigma_floor_m: float) -> np.ndarray:
        """Trimming gate (L,) of each landmark (m): outlier_sigma * max(sigma_m, sigma_floor_m)."""
        return outlier_sigma * np.maximum(self.sigma_m, sigma_floor_m)

    def observe(self, points_scan: np.ndarray, T_world_scan: np.ndarray,
                gate_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
        """One scan's association in one pass (numba kernel `kernels.label_points`): its rows
        (M, 3) (scan frame, m, float32 or float64; rows with NaN or inf are skipped) moved by
        T_world_scan (4, 4) and assigned with the gates `gate_m` (`gates_m`) as `assign` assigns
        them. Returns the landmark id of each row (M,) int32 (-1: unassigned, trimmed or not
        finite), per landmark the sums (L, 10) [1, x, y, z, xx, xy, xz, yy, yz, zz] of its scan-frame
        points and the same sums weighted by `pa_cli.core.clusters.range_weights`, the number of finite
        rows and the number of trimmed points."""
        labels, sums, range_sums, n_finite, n_trimmed = self._label(points_scan, T_world_scan, True, gate_m,
                                                                    self.n_landmarks)
        return labels.astype(np.int32), sums, range_sums, n_finite, n_trimmed

    def prepare(self) -> None:
        """Build the kernel lookup tables now (they are otherwise built on first use)."""
        self._kernel_tables()

    def assign(self, points_world: np.ndarray, outlier_sigma: float,
               sigma_floor_m: float) -> tuple[np.ndarray, int]:
        """Landmark id (M,) per world point after trimming, and the number of trimmed points.

        A point is trimmed when
        - its distance to the landmark plane exceeds the gate outlier_sigma * max(sigma_m,
          sigma_floor_m) (`sigma_m` is robust, a median over the landmark's voxels, so a few
          voxels holding points of a crossing plane do not widen the gate), or
        - it is ambiguous: a neighbouring landmark (one with leaves in the 3x3x3 level-0
          voxels around the point) that is not the same plane (normals further apart than
          `max_normal_angle_deg`, or the point outside that landmark's gate) has the point
          within its own gate (for a parallel neighbour: within the wider of both gates), or
          nearer than the point's own landmark plane. The junction slab is the other
          landmark's gate, not the wider of both: a rough ground (wide gate) next to a thin wall
          loses only the points a wall point could be, not a band as wide as its own gate. Such points
          lie at a junction of two planes (a corner, a wall foot, a facade step) and may
          belong to either; keeping them would bias the plane they do not belong to.

        Per point in one pass (numba kernel `kernels.label_points`), no sort.
        """
        return self._run_kernel(points_world, True, self.gates_m(outlier_sigma, sigma_floor_m))


def finite_points(points: np.ndarray) -> np.ndarray:
    """(M, 3) float64 points without the rows holding NaN or inf. Every point finite (the usual
    case) is decided from the sum of all coordinates, which any NaN or inf makes non-finite, and
    the points are returned as given (no copy); only otherwise is each row tested."""
    points = np.asarray(points, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # inf - inf or an overflowing sum: some row is tested below
        total = points.sum()
    if np.isfinite(total):
        return points
    return points[np.isfinite(points).all(axis=1)]


def accumulate_voxels(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
                      progress: Progress | None = None,
                      progress_offset: int = 0, progress_total: int | None = None) -> list[VoxelStats]:
    """Pass over the scans: world-frame voxel statistics at every subdivision level.

    `association_threads` scans are read and summed at once; their sums are added in scan
    order, so the result does not depend on the number of threads."""
    levels = config.max_subdivision_levels
    acc = _VoxelAccumulator(config.voxel_size_m, levels)
    total = progress_total if progress_total is not None else len(scans)

    def scan_sums(j: int) -> tuple[np.ndarray, np.ndarray]:
        return acc.scan_sums(scans[j], T_world_scan[j])

    for j, sums in enumerate(in_order(scan_sums, len(scans), config.association_threads)):
        acc.merge(*sums)
        if progress is not None:
            progress(progress_offset + j + 1, total)
    return [_stats_from_sums(level, keys, sums, config.voxel_size_m)
            for level, (keys, sums) in enumerate(acc.result())]


def _select_leaves(stats: list[VoxelStats], config: PlanesConfig) -> tuple[VoxelStats, int, dict]:
    """Planar leaves and sparse cells (fewer than `min_points` points) of the adaptive octree,
    all levels, in one array: the leaves first (their number is returned), then the sparse
    cells; level-0 voxels and children of split voxels. Leaves and sparse cells do not overlap.
    The levels are taken out of `stats` as they are read (the list is left empty), so each
    level's memory is released once its leaves and sparse cells are copied out."""
    leaves: list[VoxelStats] = []
    sparse: list[VoxelStats] = []
    split_keys = None  # sorted keys (at the previous level) of voxels to split
    n_voxels, n_planar = [], []
    for level in range(len(stats)):
        st = stats.pop(0)
        if level > 0:
            if split_keys is None or len(split_keys) == 0:
                break
            parent = encode_keys(np.floor_divide(decode_keys(st.keys), 2))
            pos = np.minimum(np.searchsorted(split_keys, parent), len(split_keys) - 1)
            keep = split_keys[pos] == parent
            st = _subset(st, keep)
        tested = np.flatnonzero(st.count >= config.min_points)  # sparse voxels are never planar
        _, thickness_m, ratio = plane_fit(st.count[tested], st.scatter[tested], config.association_threads)
        planar = np.zeros(len(st.keys), dtype=bool)
        planar[tested] = _is_planar(st.count[tested], thickness_m, ratio, config)
        n_voxels.append(int(len(st.keys)))
        n_planar.append(int(planar.sum()))
        leaves.append(_subset(st, planar))
        sparse.append(_subset(st, st.count < config.min_points))
        split_keys = st.keys[~planar & (st.count >= config.min_points)]  # already sorted
        del st
    stats.clear()
    n_leaf = sum(len(part.keys) for part in leaves)
    return _concat(leaves + sparse), n_leaf, {"n_voxels_per_level": n_voxels, "n_planar_voxels_per_level": n_planar}


_STAT_FIELDS = ("level", "keys", "count", "mean_world", "scatter")


def _subset(st: VoxelStats, mask: np.ndarray) -> VoxelStats:
    return VoxelStats(*(getattr(st, f)[mask] for f in _STAT_FIELDS))


def _concat(parts: list[VoxelStats]) -> VoxelStats:
    return VoxelStats(*(np.concatenate([getattr(p, f) for p in parts]) for f in _STAT_FIELDS))


class _Adjacency:
    """Adjacent cells of an adaptive grid (6: share a face, 26: touch), also across levels,
    through a hash table of the cells' level-tagged keys (numba kernel `cell_neighbours`, the
    sources split over `threads` threads)."""

    def __init__(self, cells: VoxelStats, neighbourhood: int, n_levels: int, threads: int = 1) -> None:
        self.keys = np.ascontiguousarray(cells.keys, dtype=np.int64)
        self.level = cells.level.astype(np.int64)
        self.table = kernels.build_table(self.keys | (self.level << kernels.LEVEL_SHIFT),
                                          np.arange(len(self.keys)))
        self.offsets = np.ascontiguousarray(NEIGHBOUR_OFFSETS[neighbourhood], dtype=np.int64)
        self.n_levels = n_levels
        self.threads = threads

    def pairs(self, sources: np.ndarray, first_target: int = 0, finer: bool = True) -> np.ndarray:
        """(E, 2) pairs (source, target) of adjacent cells, targets with index >= first_target
        (a pair may repeat); without `finer` only targets at the source's level or coarser
        (over all cells as sources, each adjacent pair once or more in one direction)."""
        def part(block: np.ndarray) -> np.ndarray:
            pairs = np.empty((len(self.offsets) * len(block), 2), np.int64)  # one per offset: most sources
            n = kernels.cell_neighbours(block, self.keys, self.level, self.offsets, *self.table, self.n_levels,
                                        first_target, finer, pairs)
            if n > len(pairs):  # more than the room guessed: again, with room for all
                pairs = np.empty((n, 2), np.int64)
                kernels.cell_neighbours(block, self.keys, self.level, self.offsets, *self.table, self.n_levels,
                                        first_target, finer, pairs)
            return pairs[:n]

        sources = np.ascontiguousarray(sources, dtype=np.int64)
        return np.concatenate(in_parts(part, len(sources), self.threads, sources))


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


def _local_noise_var(leaves: VoxelStats, edges: np.ndarray) -> np.ndarray:
    """Per leaf, the variance (m^2) of the points of it and of the leaves it shares an edge with (`edges`) about their
    one plane: the noise at the scale of a few voxels. A leaf alone would underestimate it where its faces cut the
    surface's noise slab (a wall along a face of the grid splits its points by the sign of their noise) or where
    it holds a ring or two of points; a few voxels hold the slab whole and leave out what a surface's departure
    from one plane adds over its whole extent."""
    n = len(leaves.keys)
    centre = np.concatenate([np.arange(n), edges[:, 0], edges[:, 1]])
    member = np.concatenate([np.arange(n), edges[:, 1], edges[:, 0]])
    cnt, _, sc = merge_stats(centre, n, leaves.count[member], leaves.mean_world[member], leaves.scatter[member])
    _, thick, _ = plane_fit(cnt, sc)
    return thick**2 * cnt / np.maximum(cnt - 3.0, 1.0)


def _fits_at_noise(labels: np.ndarray, thickness_m: np.ndarray, leaf_noise_var: np.ndarray,
                   leaf_count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each group of leaves is one plane at its noise level, and that noise (variance, m^2: the leaves'
    local noise, point-weighted). A group fails when its points' variance about its plane exceeds the noise by more
    than MODEL_ERROR_RATIO**2: a curved or cambered surface grown over many leaves."""
    n_groups = len(thickness_m)
    noise_var = np.bincount(labels, leaf_count * leaf_noise_var, minlength=n_groups) / \
        np.maximum(np.bincount(labels, leaf_count, minlength=n_groups), 1.0)
    return thickness_m**2 <= MODEL_ERROR_RATIO**2 * noise_var, noise_var


def _agreeing_pairs(leaves: VoxelStats, normal: np.ndarray, config: PlanesConfig) -> np.ndarray:
    """(E, 2) leaf index pairs that touch and whose planes (normals `normal`) agree (`_agree`): the edges regions grow
    along."""
    pairs = _Adjacency(leaves, config.neighbourhood, config.max_subdivision_levels + 1,
                       config.association_threads).pairs(np.arange(len(leaves.keys)), finer=False)
    ok = _agree(normal[pairs[:, 0]], leaves.mean_world[pairs[:, 0]], normal[pairs[:, 1]],
                leaves.mean_world[pairs[:, 1]], config)
    return pairs[ok]


def grow_regions(leaves: VoxelStats, normal: np.ndarray, edges: np.ndarray, config: PlanesConfig,
                 within: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Landmark id per leaf (-1: dropped) by region growing along `edges` (`_agreeing_pairs`) with planarity check and
    splitting; `normal` (n, 3) holds the leaves' plane normals. With `within` (a landmark id per leaf, -1: none), the
    regions are those landmarks, each kept whole when it is flat at its noise level (`_fits_at_noise`) and split
    otherwise, each part within the noise of its seed's plane."""
    n = len(leaves.keys)
    landmark = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return landmark, {"n_regions_split": 0, "n_leaves_dropped": 0}
    at_noise = within is not None
    if at_noise:
        edges = edges[(within[edges[:, 0]] >= 0) & (within[edges[:, 0]] == within[edges[:, 1]])]
        leaf_noise_var = _local_noise_var(leaves, edges)
    active = np.ones(n, dtype=bool) if within is None else within >= 0
    next_id = 0
    n_split = 0
    for split_round in range(config.max_split_rounds + 1):
        if not active.any():
            break
        if at_noise and split_round == 0:
            comp = within  # the landmarks as they are, also where dropped leaves left one in separate parts
        else:
            comp = _components(n, edges[active[edges[:, 0]] & active[edges[:, 1]]])
        comp_ids, comp = np.unique(comp[active], return_inverse=True)
        act_idx = np.flatnonzero(active)
        n_comp = len(comp_ids)
        cnt, _, sc = merge_stats(comp, n_comp, leaves.count[act_idx], leaves.mean_world[act_idx],
                                 leaves.scatter[act_idx])
        _, thick, ratio = plane_fit(cnt, sc)
        good = _is_planar(cnt, thick, ratio, config)
        if at_noise:
            flat, noise_var = _fits_at_noise(comp, thick, leaf_noise_var[act_idx], leaves.count[act_idx])
            good &= flat
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
        consistent = _agree(normal[seed], leaves.mean_world[seed], normal[idx], leaves.mean_world[idx], config)
        if at_noise:
            # the seed's part: its centroids within the noise of the seed's plane, so the part is flat at that
            # noise (a cambered road splits along its crown)
            offset = np.abs(np.einsum("ij,ij->i", normal[seed], leaves.mean_world[idx] - leaves.mean_world[seed]))
            consistent &= offset <= SEED_OFFSET_SIGMAS * np.sqrt(noise_var[reg])
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
        if at_noise:
            good2 &= _fits_at_noise(g_lab, thick2, leaf_noise_var[g_idx], leaves.count[g_idx])[0]
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


def grow_into_sparse(cells: VoxelStats, n_leaf: int, landmark: np.ndarray,
                     config: PlanesConfig) -> tuple[VoxelStats, np.ndarray, dict]:
    """Extend landmarks over adjacent sparse cells whose points fit the landmark plane.

    `cells` holds the planar leaves (the first `n_leaf` rows, their landmark ids in `landmark`)
    and after them the sparse cells, as `_select_leaves` returns them.

    A sparse cell (fewer than `min_points` points, so never tested for planarity on its own)
    that touches a voxel of landmark L joins L when the RMS distance of its points to L's
    current plane is at most leaf_outlier_sigma * max(sigma_L, outlier_sigma_floor_m), the
    test that keeps a planar leaf in its landmark, here on the cell's sums (RMS^2 =
    (n^T S n + N (n.(mean - c))^2) / N; sigma_L: the landmark's robust sigma from its planar
    leaves). A cell mixing the plane with a crossing surface (a curb face below a sidewalk)
    has a larger RMS and stays out. A cell fitting several landmarks
    joins the nearest (smallest RMS). Growth proceeds in rings (breadth first from the landmark
    voxels through sparse cells only) and each landmark's plane is refit after every ring, so
    a far facade, too sparse for any but a few voxels to reach `min_points`, is followed from
    those seeds as long as its points stay on one plane. Returns the leaves with the joined
    cells appended, the landmark id of each, and counts.
    """
    n_lm = int(landmark.max()) + 1 if len(landmark) and landmark.max() >= 0 else 0
    if n_lm == 0 or len(cells.keys) == n_leaf or not config.grow_into_sparse:
        return _subset(cells, slice(0, n_leaf)), landmark, {"n_sparse_cells_joined": 0, "n_sparse_growth_rings": 0,
                                                            "n_planar_leaves": len(landmark)}
    leaves = _subset(cells, slice(0, n_leaf))
    adjacency = _Adjacency(cells, config.neighbourhood, config.max_subdivision_levels + 1, config.association_threads)
    owner = np.concatenate([landmark, np.full(len(cells.keys) - n_leaf, -1, np.int64)])
    # Per-landmark sums about a fixed origin (its centroid now): N, sum q, sum q q^T.
    used = np.flatnonzero(landmark >= 0)
    cnt, origin, scatter = merge_stats(landmark[used], n_lm, leaves.count[used],
                                       leaves.mean_world[used], leaves.scatter[used])
    s1 = np.zeros((n_lm, 3))
    s2 = scatter.copy()
    normal, _, _ = plane_fit(cnt, scatter)
    _, _, _, _, _, sigma, _ = _landmark_planes(landmark, leaves)
    sigma = np.maximum(sigma, config.outlier_sigma_floor_m)
    gate = config.leaf_outlier_sigma * sigma
    # Only landmarks whose plane is already well determined grow: the normal of its planar
    # leaves within max_normal_uncertainty_deg (a single leaf mixing two surfaces, ground and
    # a sidewalk step, would otherwise be followed into both), and its association gate
    # (outlier_sigma sigmas) within max_plane_distance_m, the smallest step between parallel
    # surfaces to keep apart (a wider gate takes the step's points from the joined cells).
    evals = np.maximum(np.linalg.eigvalsh(scatter), 0.0)
    sigma_normal = normal_sigma_rad(evals, cnt)
    gate[(sigma_normal > np.deg2rad(config.max_normal_uncertainty_deg)) |
         (config.outlier_sigma * sigma > config.max_plane_distance_m)] = -1.0
    frontier = used
    rings = 0
    while len(frontier):
        src, dst = adjacency.pairs(frontier, n_leaf).T
        free = owner[dst] < 0
        src, dst = src[free], dst[free]
        lm = owner[src]
        nrm = normal[lm]
        off = np.einsum("ij,ij->i", nrm, cells.mean_world[dst] - origin[lm] - s1[lm] / cnt[lm, None])
        ss = np.einsum("ij,ijk,ik->i", nrm, cells.scatter[dst], nrm) + cells.count[dst] * off**2
        rms = np.sqrt(np.maximum(ss, 0.0) / cells.count[dst])
        fit = rms <= gate[lm]
        dst, lm, rms = dst[fit], lm[fit], rms[fit]
        if len(dst) == 0:
            break
        order = np.lexsort((rms, dst))
        first = order[np.r_[True, dst[order][1:] != dst[order][:-1]]]
        dst, lm = dst[first], lm[first]
        owner[dst] = lm
        rings += 1
        # add the joined cells to their landmark sums (parallel-axis theorem about the origin)
        q = cells.mean_world[dst] - origin[lm]
        c = cells.count[dst]
        cnt += np.bincount(lm, c, minlength=n_lm)
        for i in range(3):
            s1[:, i] += np.bincount(lm, c * q[:, i], minlength=n_lm)
        add = cells.scatter[dst] + c[:, None, None] * q[:, :, None] * q[:, None, :]
        np.add.at(s2, lm, add)
        touched = np.unique(lm)
        m = s1[touched] / cnt[touched, None]
        normal[touched] = plane_fit(cnt[touched], s2[touched] - cnt[touched, None, None] *
                                    m[:, :, None] * m[:, None, :])[0]
        frontier = dst
    joined = np.flatnonzero(owner[n_leaf:] >= 0)
    out = _subset(cells, np.concatenate([np.arange(n_leaf), n_leaf + joined]))
    return out, np.concatenate([landmark, owner[n_leaf + joined]]), {
        "n_sparse_cells_joined": int(len(joined)), "n_sparse_growth_rings": rings,
        "n_planar_leaves": n_leaf}


def _robust_sigma(labels: np.ndarray, count: np.ndarray, mean: np.ndarray, scatter: np.ndarray,
                  normal: np.ndarray, centroid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per landmark, the point-weighted median over its leaves of the leaf's RMS distance (m)
    to the landmark plane, and that RMS per leaf: sum over the leaf of (n.(p - c))^2 equals
    n^T S n + N (n.(mean - c))^2."""
    n = normal[labels]
    off = np.einsum("ij,ij->i", n, mean - centroid[labels])
    rms = np.sqrt(np.maximum(np.einsum("ij,ijk,ik->i", n, scatter, n) + count * off**2, 0) / count)
    if len(labels) == 0:
        return np.empty(0), rms
    order = np.lexsort((rms, labels))
    lab, w, r = labels[order], count[order], rms[order]
    total = np.bincount(lab, w)
    cum = np.cumsum(w)
    start = np.r_[0.0, cum][np.searchsorted(lab, np.arange(len(total)))]
    # first leaf (in rms order) of each landmark whose cumulative weight reaches half the total
    cand = np.flatnonzero((cum - start[lab]) >= 0.5 * total[lab])
    pick = cand[np.r_[True, lab[cand][1:] != lab[cand][:-1]]]
    return r[pick], rms


def _landmark_planes(landmark: np.ndarray, leaves: VoxelStats, n_planar: int | None = None):
    """Planes of the landmarks; the robust sigma only from the first `n_planar` rows (the
    planar leaves; default all), so that sparse cells joined by `grow_into_sparse` (admitted
    up to leaf_outlier_sigma sigmas) do not widen it."""
    n_lm = int(landmark.max()) + 1 if len(landmark) and landmark.max() >= 0 else 0
    used = np.flatnonzero(landmark >= 0)
    lab = landmark[used]
    cnt, mean, sc = merge_stats(lab, n_lm, leaves.count[used], leaves.mean_world[used],
                                leaves.scatter[used])
    normal, thick, _ = plane_fit(cnt, sc)
    sig = used if n_planar is None else used[used < n_planar]
    sigma, _ = _robust_sigma(landmark[sig], leaves.count[sig], leaves.mean_world[sig],
                             leaves.scatter[sig], normal, mean)
    _, leaf_rms = _robust_sigma(lab, leaves.count[used], leaves.mean_world[used],
                                leaves.scatter[used], normal, mean)
    return used, cnt, mean, normal, thick, sigma, leaf_rms


def detect_landmarks(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
                     progress: Progress | None = None, progress_total: int | None = None) -> Landmarks:
    """Plane landmarks of scans (each (M, 3) scan-frame points, m) at poses T_world_scan (N, 4, 4)."""
    return landmarks_from_voxels(accumulate_voxels(scans, T_world_scan, config, progress, 0, progress_total), config)


def landmarks_from_voxels(stats: list[VoxelStats], config: PlanesConfig) -> Landmarks:
    """Plane landmarks from the world voxel statistics of every level (`accumulate_voxels`).

    `stats` is emptied as its levels are read, so their memory is released while the leaves
    and sparse cells are selected (the caller's list holds nothing afterwards)."""
    cells, n_leaf, diag = _select_leaves(stats, config)
    leaves = _subset(cells, slice(0, n_leaf))
    leaf_normal, _, _ = plane_fit(leaves.count, leaves.scatter, config.association_threads)
    edges = _agreeing_pairs(leaves, leaf_normal, config)
    landmark, grow_diag = grow_regions(leaves, leaf_normal, edges, config)
    diag.update(grow_diag)
    # Drop leaves that do not fit their landmark's plane (for example a small voxel next to a
    # corner holding points of the crossing plane), then refit each landmark without them.
    n_off = 0
    for _ in range(config.leaf_refit_rounds):
        used, cnt, mean, normal, thick, sigma, leaf_rms = _landmark_planes(landmark, leaves)
        gate = config.leaf_outlier_sigma * np.maximum(sigma, config.outlier_sigma_floor_m)
        off = leaf_rms > gate[landmark[used]]
        if not off.any():
            break
        n_off += int(off.sum())
        landmark[used[off]] = -1
        _, landmark[landmark >= 0] = np.unique(landmark[landmark >= 0], return_inverse=True)
    diag["n_leaves_off_plane"] = n_off
    # Landmarks whose surface departs from one plane by more than its noise are split (with the off-plane leaves
    # gone, a landmark's own leaves measure its noise).
    landmark, flat_diag = grow_regions(leaves, leaf_normal, edges, config, within=landmark)
    diag["n_landmarks_split_at_noise"] = flat_diag["n_regions_split"]
    diag["n_leaves_dropped"] += flat_diag["n_leaves_dropped"]
    leaves, landmark, sparse_diag = grow_into_sparse(cells, n_leaf, landmark, config)
    del cells
    diag.update(sparse_diag)
    used, cnt, mean, normal, thick, sigma, _ = _landmark_planes(landmark, leaves,
                                                                sparse_diag["n_planar_leaves"])
    n_vox = np.bincount(landmark[used], minlength=len(cnt))
    leaf_keys, leaf_landmark = [], []
    for level in range(config.max_subdivision_levels + 1):
        at = np.flatnonzero(leaves.level == level)
        order = np.argsort(leaves.keys[at])
        leaf_keys.append(leaves.keys[at][order])
        leaf_landmark.append(landmark[at][order])
    diag["n_leaves"] = int(len(landmark))
    near_keys, near_landmark = _near_landmarks(leaves, landmark)
    return Landmarks(voxel_size_m=config.voxel_size_m, leaf_keys=leaf_keys,
                     leaf_landmark=leaf_landmark, normal_world=normal, centroid_world=mean,
                     thickness_m=thick, sigma_m=sigma, count=cnt, n_voxels=n_vox,
                     near_keys=near_keys, near_landmark=near_landmark,
                     max_normal_angle_deg=config.max_normal_angle_deg, diagnostics=diag)


def _unique_pairs(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct (key, value) pairs of int64 keys and non-negative int64 values, sorted by
    key, then value."""
    uniq_keys, inverse = np.unique(keys, return_inverse=True)
    n_values = int(values.max()) + 1 if len(values) else 1
    code = np.unique(inverse.astype(np.int64) * n_values + values)
    return uniq_keys[code // n_values], code % n_values


def _near_landmarks(leaves: VoxelStats, landmark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(level-0 key, landmark) pairs, sorted by key: the landmarks with a leaf in the 3x3x3
    level-0 voxels around the key, only for keys that have two or more such landmarks."""
    used = np.flatnonzero(landmark >= 0)
    coarse = np.floor_divide(decode_keys(leaves.keys[used]), (2 ** leaves.level[used])[:, None])
    pair_keys, pair_landmark = _unique_pairs(encode_keys(coarse), landmark[used])
    coords = decode_keys(pair_keys)
    keys = np.concatenate([encode_keys(coords + off) for off in _OFFSETS])
    keys, lms = _unique_pairs(keys, np.tile(pair_landmark, len(_OFFSETS)))
    if len(keys) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    _, start, n_per_key = np.unique(keys, return_index=True, return_counts=True)
    multi = np.repeat(n_per_key >= 2, n_per_key)
    return keys[multi], lms[multi]
