"""Merging voxel maps part by part: bit-identical to `merge_stats` over the concatenated rows."""

import subprocess
import sys
import time

import numpy as np
import pytest

from pa_cli.config import ExecutionConfig, PlanesConfig
from pa_cli.errors import SolverError
from pa_cli.planes.detect import (
    VoxelStats,
    accumulate_voxels,
    landmarks_from_voxels,
    merge_stats,
    merge_voxel_maps,
)
from pa_cli.runtime.distributed import GB, execution, process_tree_rss_bytes


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


def test_merge_voxel_maps_refuses_a_map_beyond_the_budget_before_allocating_it():
    """The check counts the memory held now and the merged rows about to be allocated."""
    rng = np.random.default_rng(5)
    parts = [[_random_level(rng, 0, 2000, 10000)] for _ in range(3)]
    n_distinct = len(np.unique(np.concatenate([p[0].keys for p in parts])))
    held_gb = process_tree_rss_bytes() / GB
    with execution(ExecutionConfig(memory_budget_gb=held_gb * 0.9)):
        with pytest.raises(SolverError, match=r"execution\.memory_budget_gb.*--loops"):
            merge_voxel_maps(parts)
    with execution(ExecutionConfig(memory_budget_gb=held_gb + 0.5)):
        assert len(merge_voxel_maps(parts)[0].keys) == n_distinct


def test_process_tree_rss_counts_the_child_processes():
    alone = process_tree_rss_bytes()
    child = subprocess.Popen([sys.executable, "-c", "import numpy, time; a = numpy.ones(40_000_000); time.sleep(30)"])
    try:
        deadline = time.monotonic() + 20.0
        while process_tree_rss_bytes() < alone + 0.2 * GB and time.monotonic() < deadline:
            time.sleep(0.1)
        assert process_tree_rss_bytes() >= alone + 0.2 * GB  # the child's 0.32 GB array is counted
    finally:
        child.kill()
        child.wait()


def test_landmarks_from_voxels_releases_the_levels_it_reads():
    """The caller's list is emptied (the levels' memory is released while leaves are selected),
    and the landmarks are those of the same voxels read again."""
    rng = np.random.default_rng(6)
    ground = np.column_stack([rng.uniform(-8, 8, 20000), rng.uniform(-8, 8, 20000), rng.normal(0, 0.005, 20000)])
    wall = np.column_stack([rng.uniform(-8, 8, 20000), np.full(20000, 6.0) + rng.normal(0, 0.005, 20000),
                            rng.uniform(0, 4, 20000)])
    scans = [np.vstack([ground, wall])]
    T = np.eye(4)[None]
    config = PlanesConfig()
    stats = accumulate_voxels(scans, T, config)
    landmarks = landmarks_from_voxels(stats, config)
    assert stats == []
    again = landmarks_from_voxels(accumulate_voxels(scans, T, config), config)
    assert landmarks.n_landmarks >= 2
    np.testing.assert_array_equal(landmarks.normal_world, again.normal_world)
    normals = np.abs(landmarks.normal_world[np.argsort(-landmarks.count)[:2]])
    assert sorted(np.argmax(normals, axis=1)) == [1, 2]  # the wall (normal y) and the ground (normal z)
    np.testing.assert_allclose(normals.max(axis=1), 1.0, atol=1e-3)
