"""Merging voxel maps part by part: bit-identical to `merge_stats` over the concatenated rows."""

import numpy as np
import pytest

from pa_cli.config import ExecutionConfig, PlanesConfig
from pa_cli.distributed import GB, execution
from pa_cli.errors import SolverError
from pa_cli.planes.detect import (
    KEY_NUMBERING_BYTES,
    VOXEL_STATS_BYTES,
    VoxelStats,
    accumulate_voxels,
    merge_stats,
    merge_voxel_maps,
)


def _random_level(rng: np.random.Generator, level: int, n: int, key_range: int) -> VoxelStats:
    keys = np.sort(rng.choice(key_range, size=n, replace=False)).astype(np.int64)
    points = rng.normal(size=(n, 4, 3))
    d = points - points.mean(axis=1, keepdims=True)
    return VoxelStats(level=np.full(n, level), keys=keys, count=rng.integers(1, 50, n).astype(float),
                      mean_world=rng.normal(scale=100.0, size=(n, 3)), scatter=np.einsum("nki,nkj->nij", d, d))


def test_merge_voxel_maps_is_merge_stats_over_the_concatenated_rows_bit_for_bit():
    rng = np.random.default_rng(3)
    parts = [[_random_level(rng, level, n, 3 * n) for level in range(2)] for n in (400, 900, 50, 700)]
    merged = merge_voxel_maps(parts)
    assert len(merged) == 2
    for level, result in enumerate(merged):
        rows = [p[level] for p in parts]
        unique, group = np.unique(np.concatenate([r.keys for r in rows]), return_inverse=True)
        assert len(unique) < sum(len(r.keys) for r in rows)  # keys repeat across parts: some voxels merge
        count, mean, scatter = merge_stats(group, len(unique), np.concatenate([r.count for r in rows]),
                                           np.concatenate([r.mean_world for r in rows]),
                                           np.concatenate([r.scatter for r in rows]))
        np.testing.assert_array_equal(result.keys, unique)
        np.testing.assert_array_equal(result.level, np.full(len(unique), level))
        np.testing.assert_array_equal(result.count, count)
        np.testing.assert_array_equal(result.mean_world, mean)
        np.testing.assert_array_equal(result.scatter, scatter)


def test_merge_voxel_maps_of_split_scans_are_the_voxels_of_all_points():
    """Ground truth: the maps of two halves of a point set merge into the map of the whole set."""
    rng = np.random.default_rng(4)
    scans = [rng.uniform(-6.0, 6.0, size=(3000, 3)) for _ in range(6)]
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, :3, 3] = rng.normal(scale=0.3, size=(6, 3))
    config = PlanesConfig()
    whole = accumulate_voxels(scans, T, config)
    halves = [accumulate_voxels(scans[:2], T[:2], config), accumulate_voxels(scans[2:], T[2:], config)]
    merged = merge_voxel_maps(halves)
    for a, b in zip(merged, whole, strict=True):
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.count, b.count)
        np.testing.assert_allclose(a.mean_world, b.mean_world, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.scatter, b.scatter, rtol=1e-9, atol=1e-9)


def test_merge_voxel_maps_refuses_a_map_beyond_the_driver_budget_before_allocating_it():
    rng = np.random.default_rng(5)
    parts = [[_random_level(rng, 0, 2000, 10000)] for _ in range(3)]
    held_bytes = sum(getattr(p[0], f).nbytes for p in parts for f in ("level", "keys", "count", "mean_world",
                                                                      "scatter"))
    n_rows = 3 * 2000
    n_distinct = len(np.unique(np.concatenate([p[0].keys for p in parts])))
    need_gb = (held_bytes + VOXEL_STATS_BYTES * n_distinct + KEY_NUMBERING_BYTES * n_rows) / GB
    with execution(ExecutionConfig(), memory_budget_gb=need_gb * 0.99):
        with pytest.raises(SolverError, match=r"solver\.memory_budget_gb.*--loops"):
            merge_voxel_maps(parts)
    with execution(ExecutionConfig(), memory_budget_gb=need_gb * 1.01):
        assert len(merge_voxel_maps(parts)[0].keys) == n_distinct

