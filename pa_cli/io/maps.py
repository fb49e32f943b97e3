"""The merged map: all scans under their poses, voxel-downsampled, written as PLY or LAS/LAZ.

The format follows the suffix of the map path (`MAP_SUFFIXES`):

- `.ply`: binary PLY, vertex properties `x y z` float32 (world frame, metres) and
  `scan_index` int32 (the scan each kept point came from).
- `.las` / `.laz` (LAS 1.4, LAZ compressed with the `lazrs` backend): coordinates in metres
  stored at `LAS_SCALE_M` resolution, the extra dimension `scan_index` (int32) and, when
  the scans have timestamps, `gps_time` = the scan's timestamp plus the point's own time
  offset where the data has per-point times (point format 1; else point format 0, no time).

One point is kept per voxel of edge `map_voxel_m`: the first point falling into it (scans
in order), so every kept point is a real measurement.

Memory stays bounded: each scan is downsampled on its own as it is added, and the merged
buffer is re-downsampled whenever it grows past a threshold, so the map holds at most about
one point per occupied voxel plus one scan's worth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError, OutputError
from pa_cli.geometry import transform_points
from pa_cli.io.atomic import atomic_path
from pa_cli.voxels import voxel_keys

MAP_SUFFIXES = (".ply", ".las", ".laz")
# LAS stores int32 coordinates times a scale: 0.1 mm is finer than any LiDAR's range noise and
# spans +-214 km around the offset.
LAS_SCALE_M = 1e-4


def voxel_downsample(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices (sorted) of the first point in each occupied voxel of edge `voxel_size_m` (m)."""
    if len(points) == 0:
        return np.empty(0, dtype=np.int64)
    _, first = np.unique(voxel_keys(points, voxel_size_m, "refine.map_voxel_m"), return_index=True)
    return np.sort(first)


@dataclass
class MapCloud:
    """The map's points: (K, 3) world points (m), (K,) int32 scan indices, (K,) times (s) or None."""

    points_world: np.ndarray
    scan_index: np.ndarray
    time_s: np.ndarray | None = None


def map_stores_time(path: Path | str) -> bool:
    """True when the map format of `path` (by suffix) has a per-point time (LAS/LAZ gps_time)."""
    return Path(path).suffix.lower() in (".las", ".laz")


class MapAccumulator:
    """Collect scans in the world frame and keep one point per voxel of `voxel_size_m` metres."""

    def __init__(self, voxel_size_m: float, compact_every_points: int) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.compact_every_points = int(compact_every_points)
        self._points: list[np.ndarray] = []
        self._scan: list[np.ndarray] = []
        self._time: list[np.ndarray] | None = None
        self._pending = 0

    def add(self, points_scan: np.ndarray, T_world_scan: np.ndarray, scan_index: int,
            time_s: np.ndarray | None = None) -> None:
        """Add one scan: (M, 3) points in its sensor frame (m), its 4x4 T_world_scan, optional (M,) times (s).

        Give times for every scan or for none.
        """
        points_world = transform_points(T_world_scan, points_scan)
        keep = voxel_downsample(points_world, self.voxel_size_m)
        self._points.append(points_world[keep])
        self._scan.append(np.full(len(keep), scan_index, dtype=np.int32))
        if time_s is not None:
            self._time = [] if self._time is None else self._time
            self._time.append(np.asarray(time_s, dtype=np.float64)[keep])
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
        if self._time is not None:
            self._time = [np.concatenate(self._time)[keep]]
        self._pending = len(keep)

    def result(self) -> MapCloud:
        """The map: one point per voxel (float64 world points, int32 scan indices, times if given)."""
        self._compact()
        if not self._points:
            return MapCloud(np.empty((0, 3)), np.empty(0, dtype=np.int32))
        return MapCloud(self._points[0], self._scan[0], None if self._time is None else self._time[0])


def write_map(path: Path | str, cloud: MapCloud, force: bool = False, suffix: str | None = None) -> None:
    """Write the map in the format of `suffix` (default: the suffix of `path`), atomically."""
    suffix = (suffix or Path(path).suffix).lower()
    if suffix == ".ply":
        write_map_ply(path, cloud.points_world, cloud.scan_index, force=force)
    elif suffix in (".las", ".laz"):
        write_map_las(path, cloud, force=force, compress=suffix == ".laz")
    else:
        raise OutputError(f"{path}: unsupported map format '{suffix}'; expected one of {' '.join(MAP_SUFFIXES)}.")


def read_map(path: Path | str) -> MapCloud:
    """Read a map written by `write_map` (.ply, .las or .laz)."""
    if Path(path).suffix.lower() in (".las", ".laz"):
        return read_map_las(path)
    return MapCloud(*read_map_ply(path))


def check_laz_backend(path: Path | str) -> None:
    """Raise an `OutputError` when no LAZ compressor is installed (needed for a .laz map)."""
    import laspy

    if not laspy.LazBackend.detect_available():
        raise OutputError(f"{path}: writing .laz needs a LAZ backend; install it with "
                          "'pip install lazrs' or write an uncompressed .las map.")


def write_map_las(path: Path | str, cloud: MapCloud, force: bool = False, compress: bool = False) -> None:
    """Write a LAS 1.4 (or LAZ) map: x y z, extra dim `scan_index`, `gps_time` when times are known."""
    import laspy

    if compress:
        check_laz_backend(path)
    header = laspy.LasHeader(point_format=0 if cloud.time_s is None else 1, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="scan_index", type=np.int32,
                                                description="scan the point came from"))
    points = np.asarray(cloud.points_world, dtype=np.float64)
    header.offsets = points.min(axis=0) if len(points) else np.zeros(3)
    header.scales = np.full(3, LAS_SCALE_M)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.scan_index = np.asarray(cloud.scan_index, dtype=np.int32)
    if cloud.time_s is not None:
        las.gps_time = np.asarray(cloud.time_s, dtype=np.float64)
    with atomic_path(path, force) as tmp:
        las.write(str(tmp), do_compress=compress)


def read_map_las(path: Path | str) -> MapCloud:
    """Read a LAS/LAZ map written by `write_map_las`."""
    import laspy

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: map file not found.")
    las = laspy.read(str(path))
    if "scan_index" not in las.point_format.dimension_names:
        raise FormatError(f"{path}: expected a 'scan_index' extra dimension (a map written by pa refine).")
    time_s = np.asarray(las.gps_time, dtype=np.float64) if "gps_time" in las.point_format.dimension_names else None
    return MapCloud(np.column_stack([las.x, las.y, las.z]).astype(np.float64),
                    np.asarray(las.scan_index, dtype=np.int32), time_s)


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
