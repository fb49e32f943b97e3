"""Plane association as window tasks whose workers read the scans: the same problem as the pass
over all scans in this process, in this process and on a 2-process dask LocalCluster alike."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import solve
from pa_cli.config import AdvancedExecutionConfig, ExecutionConfig, PlanesConfig, SolverConfig
from pa_cli.io.trajectory import read_trajectory
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.detect import VoxelStats, accumulate_voxels, merge_voxel_maps
from pa_cli.planes.windowed import ScanRef, WindowedPasses, fold_voxels, plane_passes
from pa_cli.runtime.distributed import execution
from pa_cli.simulate.sensor import SimOptions
from pa_cli.simulate.writer import simulate
from pa_cli.sources import PointsView, ScanSubset, open_source

WINDOW_SCANS = 7  # windows that do not divide the 30 scans: a short last window


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("windowed") / "office"
    simulate(SimOptions(scene="office", scans=30, beams=16, azimuth_steps=180, seed=4), out)
    source = open_source(out / "scans")
    rng = np.random.default_rng(5)
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan.copy()
    T[:, :3, 3] += rng.normal(0, 0.02, (len(T), 3))  # poses off the truth, as odometry leaves them
    return out / "scans", source, T


def _problem(passes, points, T, config):
    found: dict = {}
    build = build_plane_problem if passes is None else passes.build
    problem, diagnostics = build(points, T, config, landmarks_out=found)
    return problem, diagnostics, found


def _assert_same_point_labels(found, ref_found, n_scans):
    """The landmark id of every point of every scan is the same in both associations."""
    assert len(found["landmark_of_point"]) == len(ref_found["landmark_of_point"]) == n_scans
    for labels, reference in zip(found["landmark_of_point"], ref_found["landmark_of_point"], strict=True):
        assert labels.dtype == reference.dtype == np.int32
        np.testing.assert_array_equal(labels, reference)
    assert sum(int((labels >= 0).sum()) for labels in found["landmark_of_point"]) > 1000


def test_merged_window_voxels_equal_the_voxels_of_all_scans(sequence):
    """Voxel statistics add exactly: the windows' voxels merged per key are those of one pass."""
    scans_path, source, T = sequence
    config = PlanesConfig()
    points = [source.points(k) for k in range(len(source))]
    whole = accumulate_voxels(points, T, config)
    parts = [accumulate_voxels(points[first:first + WINDOW_SCANS], T[first:first + WINDOW_SCANS], config)
             for first in range(0, len(points), WINDOW_SCANS)]
    merged = merge_voxel_maps(parts)
    assert len(merged) == len(whole)
    for a, b in zip(merged, whole, strict=True):
        assert isinstance(a, VoxelStats)
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.level, b.level)
        np.testing.assert_allclose(a.count, b.count, rtol=0, atol=0)
        np.testing.assert_allclose(a.mean_world, b.mean_world, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.scatter, b.scatter, rtol=1e-9, atol=1e-9)


def test_folded_window_voxels_equal_the_voxels_of_all_scans(sequence):
    """Windows folded into the merged voxels as they come (in batches) give the voxels of one pass,
    and the driver never holds more unmerged windows than the merged map has voxels (plus one)."""
    scans_path, source, T = sequence
    config = PlanesConfig()
    points = [source.points(k) for k in range(len(source))]
    whole = accumulate_voxels(points, T, config)
    parts = [accumulate_voxels(points[first:first + 3], T[first:first + 3], config)
             for first in range(0, len(points), 3)]
    sizes = [sum(len(level.keys) for level in part) for part in parts]
    held = []

    def arriving():
        for index, part in enumerate(parts):
            held.append(index)
            yield part

    folded = fold_voxels(arriving())
    assert held == list(range(len(parts)))
    assert len(folded) == len(whole)
    for a, b in zip(folded, whole, strict=True):
        np.testing.assert_array_equal(a.keys, b.keys)
        np.testing.assert_array_equal(a.level, b.level)
        np.testing.assert_allclose(a.count, b.count, rtol=0, atol=0)
        np.testing.assert_allclose(a.mean_world, b.mean_world, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.scatter, b.scatter, rtol=1e-9, atol=1e-9)
    again = fold_voxels(iter(parts))
    for a, b in zip(folded, again, strict=True):  # the same batches every time: bit for bit
        np.testing.assert_array_equal(a.mean_world, b.mean_world)
        np.testing.assert_array_equal(a.scatter, b.scatter)
    assert sum(sizes) > 2 * sum(len(level.keys) for level in whole)  # windows overlap: folding saves memory


def test_windowed_passes_give_the_problem_of_the_pass_over_all_scans(sequence):
    scans_path, source, T = sequence
    config = PlanesConfig()
    points = PointsView(source)
    reference, ref_diag, ref_found = _problem(None, points, T, config)
    windowed = WindowedPasses(ScanRef(str(scans_path)), WINDOW_SCANS, cache_bytes=1e9)
    problem, diagnostics, found = _problem(windowed, points, T, config)
    assert reference.n_planes > 5 and reference.n_observations > 100
    np.testing.assert_array_equal(problem.plane_index, reference.plane_index)
    np.testing.assert_array_equal(problem.scan_index, reference.scan_index)
    np.testing.assert_allclose(problem.clusters, reference.clusters, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(problem.range_clusters, reference.range_clusters, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(found["kept"], ref_found["kept"])
    _assert_same_point_labels(found, ref_found, len(source))
    for key in ("n_points_total", "n_points_covered", "n_points_trimmed", "n_landmarks_detected"):
        assert diagnostics[key] == ref_diag[key]


def test_windowed_passes_read_the_subset_of_the_scan_ref(sequence):
    """Workers open the source with the run's --first/--last/--every (`ScanRef.subset`): the
    problem of the pass over the kept scans."""
    scans_path, _, T = sequence
    subset = ScanSubset(first=2, last=25, every=3)
    kept = open_source(scans_path, subset=subset)
    config = PlanesConfig()
    reference, _, ref_found = _problem(None, PointsView(kept), T[kept.indices], config)
    windowed = WindowedPasses(ScanRef(str(scans_path), subset=subset), 3, cache_bytes=1e9)
    problem, _, found = _problem(windowed, PointsView(kept), T[kept.indices], config)
    assert reference.n_planes > 5
    np.testing.assert_array_equal(problem.scan_index, reference.scan_index)
    np.testing.assert_allclose(problem.clusters, reference.clusters, rtol=1e-12, atol=1e-9)
    _assert_same_point_labels(found, ref_found, len(kept))


def test_windowed_association_on_a_local_cluster_equals_in_process(sequence):
    """The whole round (windowed association, then the hierarchical adjustment) on a dask
    LocalCluster of 2 processes, against the same in this process: poses equal to 1e-9."""
    scans_path, source, T = sequence
    config = PlanesConfig()
    solver = SolverConfig(solver="hierarchical", hierarchical_window_scans=8, hierarchical_overlap_scans=2)
    passes = WindowedPasses(ScanRef(str(scans_path)), WINDOW_SCANS, cache_bytes=1e9)
    poses, problems, founds = {}, {}, {}
    for workers in (0, 2):
        with execution(ExecutionConfig(workers=workers, memory_budget_gb=2.0)):
            problems[workers], _, founds[workers] = _problem(passes, PointsView(source), T, config)
            poses[workers] = solve(problems[workers], T, solver).T_world_scan
    np.testing.assert_allclose(poses[2], poses[0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(problems[2].scan_index, problems[0].scan_index)
    np.testing.assert_allclose(problems[2].range_clusters, problems[0].range_clusters, rtol=0, atol=1e-12)
    assert problems[0].range_clusters is not None and np.all(problems[0].range_clusters[:, 3, 3] > 0)
    _assert_same_point_labels(founds[2], founds[0], len(source))
    assert np.abs(poses[0] - T).max() > 1e-4  # the poses did move


def test_windowed_passes_only_with_workers(sequence):
    scans_path, _, _ = sequence
    ref = ScanRef(str(scans_path))
    assert plane_passes(ref, ExecutionConfig(), AdvancedExecutionConfig()) is None
    passes = plane_passes(ref, ExecutionConfig(workers=2), AdvancedExecutionConfig(worker_cache_gb=0.5))
    assert passes.window_scans == AdvancedExecutionConfig().window_scans and passes.cache_bytes == 0.5e9
    assert plane_passes(ref, ExecutionConfig(workers=2), AdvancedExecutionConfig(cache_points=False)).cache_bytes == 0.0
