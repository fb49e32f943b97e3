"""The merged map: all scans under their poses, voxel-downsampled, written as PLY or LAS/LAZ.

The format follows the suffix of the map path (`MAP_SUFFIXES`):

- `.ply`: binary PLY, vertex properties `x y z` float32 (world frame, metres; float64 for maps
  computed in a local frame away from the world origin, `pa_cli.core.local_frame`, whose world
  coordinates float32 would round to decimetres) and `scan_index` int32 (the scan each kept point
  came from).
- `.las` / `.laz` (LAS 1.4, LAZ compressed with the `lazrs` backend): coordinates in metres
  stored at `LAS_SCALE_M` resolution, the extra dimension `scan_index` (int32) and, when
  the scans have timestamps, `gps_time` = the scan's timestamp plus the point's own time
  offset where the data has per-point times (point format 1; else point format 0, no time).

One point is kept per voxel of edge `map.voxel_m`: the first point falling into it (scans
in order), so every kept point is a real measurement.

Memory stays bounded: `MapVoxelFilter` returns each scan's points in voxels not yet occupied and
holds only the occupied voxels' keys (8 bytes per voxel); `write_map` takes the map as chunks
(`chunked`) and writes each as it comes, so neither the map nor the scans are held whole.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.core.geometry import transform_points
from pa_cli.core.voxels import voxel_keys
from pa_cli.errors import FormatError, InputError, OutputError
from pa_cli.io.atomic import atomic_path
from pa_cli.runtime.open3d_preload import open3d

MAP_SUFFIXES = (".ply", ".las", ".laz")
# LAS stores int32 coordinates times a scale: 0.1 mm is finer than any LiDAR's range noise and
# spans +-214 km around the offset.
LAS_SCALE_M = 1e-4
PLY_COPY_BYTES = 1 << 24  # the spooled PLY body is copied behind the header in pieces of this size
# Points per chunk of a written map (28-36 bytes each while a chunk fills): tens of MB, so a map is
# never held whole and the writes stay large.
MAP_CHUNK_POINTS = 1_000_000


def voxel_downsample(points: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices (sorted) of the first point in each occupied voxel of edge `voxel_size_m` (m)."""
    if len(points) == 0:
        return np.empty(0, dtype=np.int64)
    _, first = np.unique(voxel_keys(points, voxel_size_m, "map.voxel_m"), return_index=True)
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


class _SortedKeySet:
    """A growing set of int64 voxel keys: a sorted main array plus recent sorted chunks, merged
    into the main array every `MERGE_CHUNKS` chunks (membership is a binary search per array)."""

    MERGE_CHUNKS = 64

    def __init__(self) -> None:
        self._main = np.empty(0, dtype=np.int64)
        self._chunks: list[np.ndarray] = []

    def contains(self, keys: np.ndarray) -> np.ndarray:
        """(M,) bool: which of `keys` are in the set."""
        found = np.zeros(len(keys), dtype=bool)
        for sorted_keys in (self._main, *self._chunks):
            if len(sorted_keys):
                at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
                found |= sorted_keys[at] == keys
        return found

    def add(self, sorted_new: np.ndarray) -> None:
        """Add sorted keys that are not in the set yet."""
        self._chunks.append(sorted_new)
        if len(self._chunks) >= self.MERGE_CHUNKS:
            self._main = np.sort(np.concatenate([self._main, *self._chunks]))
            self._chunks = []


class MapVoxelFilter:
    """Scans in the local frame at `origin_world_m` (`pa_cli.core.local_frame`; default the world frame),
    keeping one point per voxel of `voxel_size_m` metres of that frame: the first in the order the
    scans are added. `add` returns a scan's new points in the world frame; only the occupied
    voxels' keys are held (8 bytes each), never the points."""

    def __init__(self, voxel_size_m: float, origin_world_m: np.ndarray | None = None) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.origin_world_m = np.zeros(3) if origin_world_m is None else np.asarray(origin_world_m, dtype=np.float64)
        self._occupied = _SortedKeySet()

    def add(self, points_scan: np.ndarray, T_local_scan: np.ndarray, scan_index: int,
            time_s: np.ndarray | None = None) -> MapCloud:
        """The points of one scan ((M, 3) in its sensor frame, m; its 4x4 pose in the local frame;
        optional (M,) times, s) that fall into voxels no earlier point occupies, in the world frame
        (float64 when the origin is not zero)."""
        points_local = transform_points(T_local_scan, points_scan)
        keys = voxel_keys(points_local, self.voxel_size_m, "map.voxel_m") if len(points_local) else \
            np.empty(0, dtype=np.int64)
        unique_keys, first = np.unique(keys, return_index=True)
        new = ~self._occupied.contains(unique_keys)
        self._occupied.add(unique_keys[new])
        keep = np.sort(first[new])
        points_world = points_local[keep] + self.origin_world_m if self.origin_world_m.any() else points_local[keep]
        return MapCloud(points_world, np.full(len(keep), scan_index, dtype=np.int32),
                        None if time_s is None else np.asarray(time_s, dtype=np.float64)[keep])


def concatenate_clouds(clouds: list[MapCloud]) -> MapCloud:
    """One cloud of the points of `clouds` in order (times kept when every cloud has them)."""
    if not clouds:
        return MapCloud(np.empty((0, 3)), np.empty(0, dtype=np.int32))
    times = [c.time_s for c in clouds]
    return MapCloud(np.concatenate([c.points_world for c in clouds]), np.concatenate([c.scan_index for c in clouds]),
                    None if any(t is None for t in times) else np.concatenate(times))


def chunked(clouds: Iterable[MapCloud], chunk_points: int = MAP_CHUNK_POINTS) -> Iterator[MapCloud]:
    """`clouds` regrouped into chunks of at least `chunk_points` points (the last may hold fewer)."""
    pending: list[MapCloud] = []
    n_pending = 0
    for cloud in clouds:
        pending.append(cloud)
        n_pending += len(cloud.points_world)
        if n_pending >= chunk_points:
            yield concatenate_clouds(pending)
            pending, n_pending = [], 0
    if pending:
        yield concatenate_clouds(pending)


def write_map(path: Path | str, cloud: MapCloud | Iterable[MapCloud], force: bool = False,
              suffix: str | None = None, float64_coordinates: bool = False) -> int:
    """Write the map in the format of `suffix` (default: the suffix of `path`), atomically; returns
    the number of points written.

    `cloud` is one `MapCloud` or an iterable of them (chunks, written as they come: the map is
    never held whole; give times in every chunk or in none). `float64_coordinates`: PLY x y z as
    double (LAS stores scaled integers about an offset, exact either way).
    """
    suffix = (suffix or Path(path).suffix).lower()
    chunks = [cloud] if isinstance(cloud, MapCloud) else cloud
    if suffix == ".ply":
        return _write_ply_chunks(path, chunks, force, float64_coordinates)
    if suffix in (".las", ".laz"):
        return _write_las_chunks(path, chunks, force, compress=suffix == ".laz")
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


def _las_header(first: MapCloud) -> Any:
    """A LAS 1.4 header for chunks like `first`: extra dim `scan_index`, `gps_time` (point format 1)
    when it has times, the offset at its smallest coordinates."""
    import laspy

    header = laspy.LasHeader(point_format=0 if first.time_s is None else 1, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="scan_index", type=np.int32,
                                                description="scan the point came from"))
    points = np.asarray(first.points_world, dtype=np.float64)
    header.offsets = points.min(axis=0) if len(points) else np.zeros(3)
    header.scales = np.full(3, LAS_SCALE_M)
    return header


def _write_las_chunks(path: Path | str, chunks: Iterable[MapCloud], force: bool, compress: bool) -> int:
    """Write a LAS 1.4 (or LAZ) map chunk by chunk: x y z, extra dim `scan_index`, `gps_time` when
    the chunks have times. The offset is the first chunk's minimum (LAS_SCALE_M spans +-214 km
    around it)."""
    import laspy

    if compress:
        check_laz_backend(path)
    n_points = 0
    with atomic_path(path, force) as tmp, contextlib.ExitStack() as stack:
        writer = None
        for chunk in chunks:
            if writer is None:
                writer = stack.enter_context(laspy.open(str(tmp), mode="w", header=_las_header(chunk),
                                                        do_compress=compress))
                with_time = chunk.time_s is not None
            if (chunk.time_s is not None) != with_time:
                raise FormatError(f"{path}: map chunks must all have per-point times or none.")
            points = np.asarray(chunk.points_world, dtype=np.float64)
            record = laspy.ScaleAwarePointRecord.zeros(len(points), header=writer.header)
            record.x, record.y, record.z = points[:, 0], points[:, 1], points[:, 2]
            record.scan_index = np.asarray(chunk.scan_index, dtype=np.int32)
            if with_time:
                record.gps_time = np.asarray(chunk.time_s, dtype=np.float64)
            writer.write_points(record)
            n_points += len(points)
        if writer is None:  # no chunk: an empty map
            stack.enter_context(laspy.open(str(tmp), mode="w", header=_las_header(concatenate_clouds([])),
                                           do_compress=compress))
    return n_points


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


_PLY_TYPES = {"<f4": "float", "<f8": "double", "<i4": "int"}


def ply_vertex_dtype(float64_coordinates: bool, int_properties: tuple[str, ...] = ("scan_index",)) -> np.dtype:
    """Binary PLY vertex layout: x y z float32 (float64 with `float64_coordinates`), then the
    `int_properties` as int32, little-endian."""
    coordinate = "<f8" if float64_coordinates else "<f4"
    return np.dtype([(axis, coordinate) for axis in "xyz"] + [(name, "<i4") for name in int_properties])


def ply_header(n_points: int, vertex_dtype: np.dtype) -> bytes:
    """The header of a binary little-endian PLY of `n_points` vertices laid out as `vertex_dtype`
    (`ply_vertex_dtype`)."""
    properties = "".join(f"property {_PLY_TYPES[vertex_dtype[name].str]} {name}\n" for name in vertex_dtype.names)
    return f"ply\nformat binary_little_endian 1.0\nelement vertex {n_points}\n{properties}end_header\n".encode("ascii")


def _write_ply_chunks(path: Path | str, chunks: Iterable[MapCloud], force: bool,
                      float64_coordinates: bool = False) -> int:
    """Write a binary PLY (float32 or float64 x y z, int32 scan_index) chunk by chunk, atomically:
    the vertices go to a spool file beside the output while the count is unknown, then follow the
    header into the output file."""
    vertex_dtype = ply_vertex_dtype(float64_coordinates)
    n_points = 0
    with atomic_path(path, force) as tmp:
        body = tmp.with_name(tmp.name + ".body")
        try:
            with body.open("wb") as spool:
                for chunk in chunks:
                    vertices = np.empty(len(chunk.points_world), dtype=vertex_dtype)
                    for axis, name in enumerate("xyz"):
                        vertices[name] = chunk.points_world[:, axis]
                    vertices["scan_index"] = chunk.scan_index
                    spool.write(vertices.tobytes())
                    n_points += len(vertices)
            with tmp.open("wb") as out, body.open("rb") as spool:
                out.write(ply_header(n_points, vertex_dtype))
                shutil.copyfileobj(spool, out, PLY_COPY_BYTES)
        finally:
            body.unlink(missing_ok=True)
    return n_points


def write_map_ply(path: Path | str, points_world: np.ndarray, scan_index: np.ndarray,
                  force: bool = False) -> None:
    """Write a binary PLY with float32 x y z and int32 scan_index, atomically."""
    _write_ply_chunks(path, [MapCloud(np.asarray(points_world), np.asarray(scan_index))], force)


def read_map_ply(path: Path | str) -> tuple[np.ndarray, np.ndarray]:
    """Read a map written by `write_map_ply`: (K, 3) points (float32, or float64 when stored as
    double), (K,) int32 scan indices."""
    o3d = open3d()
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: map file not found.")
    cloud = o3d.t.io.read_point_cloud(str(path))
    if "scan_index" not in cloud.point:
        raise FormatError(f"{path}: expected a 'scan_index' vertex property (a map written by pa refine).")
    return cloud.point.positions.numpy(), cloud.point["scan_index"].numpy().ravel().astype(np.int32)
