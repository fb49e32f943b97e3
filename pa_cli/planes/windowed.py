"""Plane association as window tasks: workers read their scans from the source themselves.

`build_plane_problem` makes two passes over the scans (voxel statistics for the landmark
detection, then the association of every scan's points to the landmarks). Here each pass is cut
into windows of `advanced.execution.window_scans` consecutive scans, and every window is one
task of `pa_cli.runtime.distributed.current_execution()`. A task carries where the scans are (`ScanRef`:
the path, `--topic` and `--glob` of the source), the window's scan indices and poses, never
points: the worker opens the source and reads its window's scans itself. What travels back is
small and exact to merge:

- detection: the window's world voxel statistics per subdivision level (count, centroid,
  scatter); the driver merges them per voxel (parallel-axis theorem, `detect.merge_voxel_maps`) and
  finds the landmarks on the merged voxels (`detect.landmarks_from_voxels`), as the in-process
  pass does on the voxels of all scans at once;
- association: the window's observations (landmark id, scan index, scan-frame cluster, range
  cluster) and point counts, and when asked the landmark id of every point of its scans (int32,
  for `pa_cli.planes.labels.PointLabels.from_association`); the driver concatenates them in scan
  order, which is what the in-process pass returns, and verifies the landmarks on them.

So the landmarks are stitched across windows by construction: every window's points land in the
same world voxels, and one landmark is one plane of the merged voxel map, whichever windows saw it.

Point cache: a worker keeps the float32 points of the windows it read, up to
`advanced.execution.worker_cache_gb`, so the association pass (and its refit pass) re-read nothing the
detection pass read on the same worker; tasks of a window go to any worker, so a miss reads the
scan again. The driver holds no point of these passes.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from pa_cli.config import AdvancedExecutionConfig, ExecutionConfig, PlanesConfig
from pa_cli.core.problem import FeatureProblem
from pa_cli.planes.associate import association_pass_in_process, build_plane_problem
from pa_cli.planes.detect import (
    Landmarks,
    Progress,
    VoxelStats,
    accumulate_voxels,
    landmarks_from_voxels,
    merge_voxel_maps,
)
from pa_cli.runtime.distributed import GB, current_execution
from pa_cli.sources import ScanSubset, open_source
from pa_cli.sources.screen import kept_indices

# Bytes a worker's result holds per scan of its window (an association result: a few
# observations of 2 x 16 floats; a detection result: the window's voxels, bounded by the points).
RESULT_BYTES_PER_SCAN = 1e5
# Bytes the per-point landmark ids add per scan when they travel: int32 for up to 2e5 points
# (a 128-beam sweep).
LABEL_BYTES_PER_SCAN = 4 * 2e5


@dataclass(frozen=True)
class ScanRef:
    """Where a worker reads the scans: the source path, its `--topic` / `--glob` / `--first/--last/--every`,
    and the indices of the opened source's scans left out of the sequence (`pa_cli.sources.screen`)."""

    path: str
    topic: str | None = None
    glob: str | None = None
    subset: ScanSubset | None = None
    skipped: tuple[int, ...] = ()


def read_scans(ref: ScanRef, first: int, stop: int) -> list[np.ndarray]:
    """The points (M, 3; float64, scan frame, m) of scans first..stop-1 of the sequence `ref` names, read from
    its source (what a worker does with its window)."""
    source = open_source(ref.path, topic=ref.topic, glob=ref.glob, subset=ref.subset)
    try:
        return [np.asarray(source.points(int(k)), dtype=np.float64) for k in kept_indices(ref.skipped, first, stop)]
    finally:
        source.close()


@dataclass
class _WindowTask:
    """One window of a pass: scans first..stop-1 of `ref` at poses T_world_scan (W, 4, 4)."""

    ref: ScanRef
    first: int
    stop: int
    T_world_scan: np.ndarray
    config: PlanesConfig
    cache_bytes: float
    point_labels: bool = False


class _WindowCache:
    """A worker process's points of the windows it read (float32), least recently used dropped first."""

    def __init__(self) -> None:
        self.windows: OrderedDict[tuple, list[np.ndarray]] = OrderedDict()
        self.n_bytes = 0

    def points(self, task: _WindowTask) -> list[np.ndarray]:
        key = (task.ref, task.first, task.stop)
        if key in self.windows:
            self.windows.move_to_end(key)
            return [p.astype(np.float64) for p in self.windows[key]]

        points = read_scans(task.ref, task.first, task.stop)
        stored = [p.astype(np.float32) for p in points]
        size = sum(p.nbytes for p in stored)
        while self.windows and self.n_bytes + size > task.cache_bytes:
            _, dropped = self.windows.popitem(last=False)
            self.n_bytes -= sum(p.nbytes for p in dropped)
        if size <= task.cache_bytes:
            self.windows[key] = stored
            self.n_bytes += size
        return points


_CACHE = _WindowCache()  # one per worker process (and one in the driver when tasks run in it)


def window_voxels(task: _WindowTask) -> list[VoxelStats]:
    """Detection task: the world voxel statistics of the window's scans, every level."""
    return accumulate_voxels(_CACHE.points(task), task.T_world_scan, task.config)


def window_observations(task: _WindowTask, landmarks: Landmarks
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict, list | None]:
    """Association task: the window's observations (landmark id, scan index in the sequence,
    scan-frame cluster, range cluster) and counts, as `association_pass_in_process` gives them for
    these scans, and with `task.point_labels` the landmark id of each point of each of its scans."""
    labels = [None] * (task.stop - task.first) if task.point_labels else None
    lm, scan, clusters, range_clusters, counts = association_pass_in_process(
        _CACHE.points(task), task.T_world_scan, landmarks, task.config, None, 0, 0, labels)
    return lm, scan + task.first, clusters, range_clusters, counts, labels


def _n_voxels(stats: list[VoxelStats]) -> int:
    return sum(len(level.keys) for level in stats)


def fold_voxels(parts: Iterable[list[VoxelStats]]) -> list[VoxelStats]:
    """`detect.merge_voxel_maps` of all parts, folded as they come: parts are held until they have
    at least as many voxels as the merged statistics so far, then merged into them. The driver's peak is
    then a small multiple of the merged voxel map (not the sum of all parts), and each voxel of
    the merged map is re-merged about log2(parts) times at most while the map grows, about once
    per map-sized batch of parts once it has stopped growing. The batches depend only on the
    parts' sizes in order, so the result is the same every run."""
    merged: list[VoxelStats] | None = None
    pending: list[list[VoxelStats]] = []
    n_pending = 0
    for part in parts:
        pending.append(part)
        n_pending += _n_voxels(part)
        if merged is None or n_pending >= _n_voxels(merged):
            merged = merge_voxel_maps(pending if merged is None else [merged, *pending])
            pending, n_pending = [], 0
    if pending or merged is None:
        merged = merge_voxel_maps(pending if merged is None else [merged, *pending])
    return merged


class WindowedPasses:
    """The two passes of `build_plane_problem` as window tasks on `current_execution()`."""

    def __init__(self, ref: ScanRef, window_scans: int, cache_bytes: float) -> None:
        self.ref = ref
        self.window_scans = window_scans
        self.cache_bytes = cache_bytes

    def _results(self, fn: Callable, T: np.ndarray, config: PlanesConfig, progress: Progress | None, offset: int,
                 total: int, shared: Landmarks | None = None, point_labels: bool = False) -> Iterator:
        """`fn` over the windows of scans 0..len(T)-1, results yielded in scan order as they arrive
        (`Execution.imap`: a bounded number of windows in flight); progress after each window."""
        tasks = (_WindowTask(self.ref, first, min(first + self.window_scans, len(T)),
                             T[first:first + self.window_scans], config, self.cache_bytes, point_labels)
                 for first in range(0, len(T), self.window_scans))
        result_bytes = RESULT_BYTES_PER_SCAN + (LABEL_BYTES_PER_SCAN if point_labels else 0.0)
        results = current_execution().imap(fn, tasks, self.window_scans * result_bytes, shared)
        for k, result in enumerate(results):
            if progress is not None:
                progress(offset + min((k + 1) * self.window_scans, len(T)), total)
            yield result

    def detect(self, scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
               progress: Progress | None = None, progress_total: int | None = None) -> Landmarks:
        """`detect.detect_landmarks` with the voxel pass as window tasks (`scans` is not read).

        The windows' voxel statistics are folded into the merged ones as they arrive (`fold_voxels`):
        the driver holds the merged voxel map and at most about as many voxels again of windows
        not merged yet, never the statistics of every window at once."""
        merged = fold_voxels(self._results(window_voxels, T_world_scan, config, progress, 0,
                                           progress_total or len(T_world_scan)))
        return landmarks_from_voxels(merged, config)

    def associate(self, scans: Sequence[np.ndarray], T: np.ndarray, landmarks: Landmarks, config: PlanesConfig,
                  progress: Progress | None, progress_offset: int, total: int, point_labels: list | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """`associate.association_pass_in_process` as window tasks (`scans` is not read)."""
        landmarks.prepare()  # the lookup tables travel with the landmarks, built once
        parts = list(self._results(window_observations, T, config, progress, progress_offset, total, landmarks,
                                   point_labels is not None))
        counts = {key: sum(p[4][key] for p in parts) for key in parts[0][4]}
        if point_labels is not None:
            point_labels[:] = [labels for p in parts for labels in p[5]]
        return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]), counts)

    def build(self, scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
              progress: Progress | None = None, landmarks_out: dict | None = None) -> tuple[FeatureProblem, dict]:
        """`build_plane_problem` with both passes as window tasks; `scans` only gives the count."""
        return build_plane_problem(scans, T_world_scan, config, progress, landmarks_out, detect=self.detect,
                                   association_pass=self.associate)


def plane_passes(ref: ScanRef, execution_config: ExecutionConfig,
                 advanced: AdvancedExecutionConfig) -> WindowedPasses | None:
    """The windowed passes when tasks run on dask workers (`execution.workers` or a scheduler), in windows and
    with the worker caches of `advanced` (`advanced.execution`); None in this process, where
    `build_plane_problem` reads the scans itself."""
    if not (execution_config.workers or execution_config.scheduler_address):
        return None
    cache_bytes = advanced.worker_cache_gb * GB if advanced.cache_points else 0.0
    return WindowedPasses(ref, advanced.window_scans, cache_bytes)
