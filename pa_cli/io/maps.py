"""The merged map: all scans under their poses, voxel-downsampled, written as PLY.

PLY vertex properties: `x y z` float32 (world frame, metres) and `scan_index` int32 (the
scan each kept point came from). One point is kept per voxel of edge `map_voxel_m`: the
first point falling into it (scans in order), so every kept point is a real measurement.

Memory stays bounded: each scan is downsampled on its own as it is added, and the merged
buffer is re-downsampled whenever it grows past a threshold, so the map holds at most about
one point per occupied voxel plus one scan's worth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.geometry import transform_points
from pa_cli.io.atomic import atomic_path
from pa_cli.voxels import voxel_keys


def voxel_downsample(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices (sorted) of the first point in each occupied voxel of edge `voxel_size_m` (m)."""
    if len(points) == 0:
        return np.empty(0, dtype=np.int64)
    _, first = np.unique(voxel_keys(points, voxel_size_m, "refine.map_voxel_m"), return_index=True)
    return np.sort(first)


class MapAccumulator:
    """Collect scans in the world frame and keep one point per voxel of `voxel_size_m` metres."""

    def __init__(self, voxel_size_m: float, compact_every_points: int) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.compact_every_points = int(compact_every_points)
        self._points: list[np.ndarray] = []
        self._scan: list[np.ndarray] = []
        self._pending = 0

    def add(self, points_scan: np.ndarray, T_world_scan: np.ndarray, scan_index: int) -> None:
        """Add one scan: (M, 3) points in its sensor frame (m) and its 4x4 T_world_scan."""
        points_world = transform_points(T_world_scan, points_scan)
        keep = voxel_downsample(points_world, self.voxel_size_m)
        self._points.append(points_world[keep])
        self._scan.append(np.full(len(keep), scan_index, dtype=np.int32))
        self._pending += len(keep)
        if self._pending > self.compact_every_points:
            self._compact()

    def _compact(self) -> None:
        if not self._points:
            return
        points = np.concatenate(self._points)
        scan = np.concatenate(self._scan)
        keep = voxel_downsample(points, self.voxel_size_m)
        self._points, self._scan = [points[keep]], [scan[keep]]
        self._pending = len(keep)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3) float64 world points and (K,) int32 scan indices, one point per voxel."""
        self._compact()
        if not self._points:
            return np.empty((0, 3)), np.empty(0, dtype=np.int32)
        return self._points[0], self._scan[0]


def write_map_ply(path: Path | str, points_world: np.ndarray, scan_index: np.ndarray,
                  force: bool = False) -> None:
    """Write a binary PLY with float32 x y z and int32 scan_index, atomically (Open3D tensor API)."""
    from pa_cli._open3d import open3d

    o3d = open3d()
    cloud = o3d.t.geometry.PointCloud()
    cloud.point.positions = o3d.core.Tensor(np.ascontiguousarray(points_world, dtype=np.float32))
    cloud.point["scan_index"] = o3d.core.Tensor(
        np.ascontiguousarray(np.asarray(scan_index, dtype=np.int32).reshape(-1, 1)))
    with atomic_path(path, force) as tmp:
        tmp_ply = tmp.with_suffix(".ply") if tmp.suffix != ".ply" else tmp
        ok = o3d.t.io.write_point_cloud(str(tmp_ply), cloud, write_ascii=False)
        if tmp_ply != tmp:
            tmp_ply.replace(tmp)
        if not ok:
            raise FormatError(f"{path}: Open3D failed to write the map PLY.")


def read_map_ply(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Read a map written by `write_map_ply`: (K, 3) float32 points, (K,) int32 scan indices."""
    from pa_cli._open3d import open3d

    o3d = open3d()
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: map file not found.")
    cloud = o3d.t.io.read_point_cloud(str(path))
    if "scan_index" not in cloud.point:
        raise FormatError(f"{path}: expected a 'scan_index' vertex property (a map written by pa refine).")
    return cloud.point.positions.numpy(), cloud.point["scan_index"].numpy().ravel().astype(np.int32)
