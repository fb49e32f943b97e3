"""The merged map: all scans under their poses, written as PLY, PCD or LAS/LAZ.

The format follows the suffix of the map path (`MAP_SUFFIXES`). Every format holds, per point:
the world coordinates (metres), `scan_index` (int32, the scan that measured the point), and,
when known, `intensity` (as the scans store it) and `time` (s: the scan's timestamp plus the
point's own offset where the data has per-point times).

- `.ply`: binary little-endian PLY, vertex properties `x y z` float32 (float64 for maps computed
  in a local frame away from the world origin, `pa_cli.core.local_frame`, whose world coordinates
  float32 would round to decimetres), `scan_index` int, `intensity` float, `time` double.
- `.pcd`: binary PCD v0.7 with the same fields and types (read by PCL, CloudCompare, pypcd4).
- `.las` / `.laz` (LAS 1.4, LAZ compressed with the `lazrs` backend): coordinates stored at
  `LAS_SCALE_M` resolution, the extra dimension `scan_index` (int32), `gps_time` = the time (point
  format 1; point format 0 without times) and the standard uint16 `intensity` =
  round(intensity x scale) clipped to 0..65535, the scale chosen from the first chunk by
  `las_intensity_scale` (65535 for intensities within [0, 1], 1 for counts up to 65535, else
  65535 / their maximum) and stored in a VLR (`LAS_INTENSITY_VLR`) so `read_map` divides it out.

Which points the map keeps: `pa_cli.io.map_filter`. Memory stays bounded: `write_map` takes the map
as chunks (`chunked`) and writes each as it comes, so neither the map nor the scans are held whole.
"""

from __future__ import annotations

import contextlib
import shutil
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.core.voxels import voxel_keys
from pa_cli.errors import FormatError, InputError, OutputError
from pa_cli.io.atomic import atomic_path
from pa_cli.runtime.open3d_preload import open3d

MAP_SUFFIXES = (".ply", ".pcd", ".las", ".laz")
# LAS stores int32 coordinates times a scale: 0.1 mm is finer than any LiDAR's range noise and
# spans +-214 km around the offset.
LAS_SCALE_M = 1e-4
LAS_INTENSITY_MAX = 65535  # LAS intensity is uint16
# The VLR holding the LAS intensity scale (float64): LAS intensity = round(intensity * scale).
LAS_INTENSITY_VLR = ("pa_cli", 1)
SPOOL_COPY_BYTES = 1 << 24  # a spooled PLY/PCD body is copied behind the header in pieces of this size
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
    """The map's points: (K, 3) world points (m), (K,) int32 scan indices, (K,) times (s) or None,
    (K,) intensities (as the scans store them) or None."""

    points_world: np.ndarray
    scan_index: np.ndarray
    time_s: np.ndarray | None = None
    intensity: np.ndarray | None = None


class ColorBy(str, Enum):
    """What colours a map's points in a picture of it (`pa_cli.io.map_view`): a field of `MapCloud`
    or the height (world z)."""

    scan = "scan"
    time = "time"
    height = "height"
    intensity = "intensity"


@dataclass
class MapPart:
    """Points one scan measured, to be placed by one pose: `scan_index` (the measuring scan),
    `points_scan` (M, 3) in the frame of the pose that places them (m), their times `time_s`
    (M,) s on the clock of the scan timestamps or None, their `intensity` (M,) or None."""

    scan_index: int
    points_scan: np.ndarray
    time_s: np.ndarray | None = None
    intensity: np.ndarray | None = None


def point_times_s(stamp_s: float | None, own_s: np.ndarray | None, n_points: int) -> np.ndarray | None:
    """Per-point times (s) of a scan with timestamp `stamp_s`: the stamp plus each point's own
    offset `own_s` (s) where it has them (else the stamp for every point); None without a stamp."""
    if stamp_s is None:
        return None
    if own_s is None or len(own_s) != n_points:
        return np.full(n_points, float(stamp_s))
    return float(stamp_s) + np.asarray(own_s, dtype=np.float64)


def _joined(values: list[np.ndarray | None]) -> np.ndarray | None:
    return None if any(v is None for v in values) else np.concatenate(values)


def concatenate_clouds(clouds: list[MapCloud]) -> MapCloud:
    """One cloud of the points of `clouds` in order (times and intensities kept when every cloud has them)."""
    if not clouds:
        return MapCloud(np.empty((0, 3)), np.empty(0, dtype=np.int32))
    return MapCloud(np.concatenate([c.points_world for c in clouds]), np.concatenate([c.scan_index for c in clouds]),
                    _joined([c.time_s for c in clouds]), _joined([c.intensity for c in clouds]))


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


def _check_fields(path: Path | str, chunk: MapCloud, first: MapCloud) -> None:
    for name in ("time_s", "intensity"):
        if (getattr(chunk, name) is None) != (getattr(first, name) is None):
            raise FormatError(f"{path}: map chunks must all have per-point {name} or none.")


def write_map(path: Path | str, cloud: MapCloud | Iterable[MapCloud], force: bool = False,
              suffix: str | None = None, float64_coordinates: bool = False) -> int:
    """Write the map in the format of `suffix` (default: the suffix of `path`), atomically; returns
    the number of points written.

    `cloud` is one `MapCloud` or an iterable of them (chunks, written as they come: the map is
    never held whole; give times and intensities in every chunk or in none). `float64_coordinates`:
    PLY/PCD x y z as double (LAS stores scaled integers about an offset, exact either way).
    """
    suffix = (suffix or Path(path).suffix).lower()
    chunks = [cloud] if isinstance(cloud, MapCloud) else cloud
    if suffix in (".ply", ".pcd"):
        header = ply_header if suffix == ".ply" else pcd_map_header
        return _write_spooled(path, chunks, force, float64_coordinates, header)
    if suffix in (".las", ".laz"):
        return _write_las_chunks(path, chunks, force, compress=suffix == ".laz")
    raise OutputError(f"{path}: unsupported map format '{suffix}'; expected one of {' '.join(MAP_SUFFIXES)}.")


def read_map(path: Path | str) -> MapCloud:
    """Read a map written by `write_map` (.ply, .pcd, .las or .laz)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: map file not found; expected a {' / '.join(MAP_SUFFIXES)} map written by "
                         "pa refine.")
    suffix = path.suffix.lower()
    if suffix in (".las", ".laz"):
        return read_map_las(path)
    if suffix == ".pcd":
        return read_map_pcd(path)
    if suffix == ".ply":
        return read_map_ply(path)
    raise InputError(f"{path}: unsupported map format '{path.suffix}'; expected one of {' '.join(MAP_SUFFIXES)}.")


def check_laz_backend(path: Path | str) -> None:
    """Raise an `OutputError` when no LAZ compressor is installed (needed for a .laz map)."""
    import laspy

    if not laspy.LazBackend.detect_available():
        raise OutputError(f"{path}: writing .laz needs a LAZ backend; install it with "
                          "'pip install lazrs' or write an uncompressed .las map.")


# LAS ---------------------------------------------------------------------------------------


def las_intensity_scale(intensity: np.ndarray) -> float:
    """The scale of LAS intensity (uint16) = round(intensity x scale): 65535 for intensities
    within [0, 1] (normalised reflectivity), 1 for counts up to 65535 (8- and 16-bit sensors keep
    their raw values), else 65535 / the largest."""
    largest = float(np.max(intensity)) if len(intensity) else 0.0
    if largest <= 1.0:
        return float(LAS_INTENSITY_MAX)
    return 1.0 if largest <= LAS_INTENSITY_MAX else LAS_INTENSITY_MAX / largest


def _las_header(first: MapCloud) -> Any:
    """A LAS 1.4 header for chunks like `first`: extra dim `scan_index`, `gps_time` (point format 1)
    when it has times, the intensity scale VLR when it has intensities, the offset at its smallest
    coordinates."""
    import laspy

    header = laspy.LasHeader(point_format=0 if first.time_s is None else 1, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="scan_index", type=np.int32,
                                                description="scan the point came from"))
    if first.intensity is not None:
        user_id, record_id = LAS_INTENSITY_VLR
        header.vlrs.append(laspy.VLR(user_id, record_id, "intensity = LAS intensity / scale",
                                     struct.pack("<d", las_intensity_scale(first.intensity))))
    points = np.asarray(first.points_world, dtype=np.float64)
    header.offsets = points.min(axis=0) if len(points) else np.zeros(3)
    header.scales = np.full(3, LAS_SCALE_M)
    return header


def _las_intensity_scale_of(header: Any) -> float | None:
    """The intensity scale stored in a LAS header's VLR, None when the map has no intensities."""
    for vlr in header.vlrs:
        if (vlr.user_id, vlr.record_id) == LAS_INTENSITY_VLR:
            return struct.unpack("<d", vlr.record_data)[0]
    return None


def _write_las_chunks(path: Path | str, chunks: Iterable[MapCloud], force: bool, compress: bool) -> int:
    """Write a LAS 1.4 (or LAZ) map chunk by chunk: x y z, extra dim `scan_index`, `gps_time` when
    the chunks have times, `intensity` (scaled, see `las_intensity_scale`) when they have
    intensities. The offset is the first chunk's minimum (LAS_SCALE_M spans +-214 km around it)."""
    import laspy

    if compress:
        check_laz_backend(path)
    n_points = 0
    with atomic_path(path, force) as tmp, contextlib.ExitStack() as stack:
        writer = first = scale = None
        for chunk in chunks:
            if writer is None:
                writer = stack.enter_context(laspy.open(str(tmp), mode="w", header=_las_header(chunk),
                                                        do_compress=compress))
                first, scale = chunk, _las_intensity_scale_of(writer.header)
            _check_fields(path, chunk, first)
            points = np.asarray(chunk.points_world, dtype=np.float64)
            record = laspy.ScaleAwarePointRecord.zeros(len(points), header=writer.header)
            record.x, record.y, record.z = points[:, 0], points[:, 1], points[:, 2]
            record.scan_index = np.asarray(chunk.scan_index, dtype=np.int32)
            if chunk.time_s is not None:
                record.gps_time = np.asarray(chunk.time_s, dtype=np.float64)
            if scale is not None:
                scaled = np.rint(np.nan_to_num(np.asarray(chunk.intensity, dtype=np.float64)) * scale)
                record.intensity = np.clip(scaled, 0, LAS_INTENSITY_MAX).astype(np.uint16)
            writer.write_points(record)
            n_points += len(points)
        if writer is None:  # no chunk: an empty map
            stack.enter_context(laspy.open(str(tmp), mode="w", header=_las_header(concatenate_clouds([])),
                                           do_compress=compress))
    return n_points


def read_map_las(path: Path | str) -> MapCloud:
    """Read a LAS/LAZ map written by `write_map` (intensities divided by the stored scale)."""
    import laspy

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: map file not found.")
    las = laspy.read(str(path))
    if "scan_index" not in las.point_format.dimension_names:
        raise FormatError(f"{path}: expected a 'scan_index' extra dimension (a map written by pa refine).")
    time_s = np.asarray(las.gps_time, dtype=np.float64) if "gps_time" in las.point_format.dimension_names else None
    scale = _las_intensity_scale_of(las.header)
    intensity = None if scale is None else (np.asarray(las.intensity, dtype=np.float64) / scale).astype(np.float32)
    return MapCloud(np.column_stack([las.x, las.y, las.z]).astype(np.float64),
                    np.asarray(las.scan_index, dtype=np.int32), time_s, intensity)


# PLY and PCD -------------------------------------------------------------------------------

_PLY_TYPES = {"<f4": "float", "<f8": "double", "<i4": "int"}
_PCD_TYPES = {"<f4": ("F", 4), "<f8": ("F", 8), "<i4": ("I", 4)}


def ply_vertex_dtype(float64_coordinates: bool, int_properties: tuple[str, ...] = ("scan_index",)) -> np.dtype:
    """Binary PLY vertex layout: x y z float32 (float64 with `float64_coordinates`), then the
    `int_properties` as int32, little-endian."""
    coordinate = "<f8" if float64_coordinates else "<f4"
    return np.dtype([(axis, coordinate) for axis in "xyz"] + [(name, "<i4") for name in int_properties])


def map_record_dtype(float64_coordinates: bool, with_time: bool, with_intensity: bool) -> np.dtype:
    """One map point of a PLY or PCD map (little-endian, packed): `ply_vertex_dtype` (x y z,
    scan_index), then intensity float32 and time float64 when present."""
    fields = ply_vertex_dtype(float64_coordinates).descr
    fields += [("intensity", "<f4")] * with_intensity + [("time", "<f8")] * with_time
    return np.dtype(fields)


def ply_header(n_points: int, vertex_dtype: np.dtype) -> bytes:
    """The header of a binary little-endian PLY of `n_points` vertices laid out as `vertex_dtype`
    (`ply_vertex_dtype` or `map_record_dtype`)."""
    properties = "".join(f"property {_PLY_TYPES[vertex_dtype[name].str]} {name}\n" for name in vertex_dtype.names)
    return f"ply\nformat binary_little_endian 1.0\nelement vertex {n_points}\n{properties}end_header\n".encode("ascii")



def pcd_map_header(n_points: int, record_dtype: np.dtype) -> bytes:
    """The header of a binary PCD v0.7 of `n_points` points laid out as `record_dtype`."""
    types = [_PCD_TYPES[record_dtype[name].str] for name in record_dtype.names]
    lines = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
             "FIELDS " + " ".join(record_dtype.names), "SIZE " + " ".join(str(size) for _, size in types),
             "TYPE " + " ".join(kind for kind, _ in types), "COUNT " + " ".join("1" for _ in types),
             f"WIDTH {n_points}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n_points}", "DATA binary"]
    return ("\n".join(lines) + "\n").encode("ascii")


def _write_spooled(path: Path | str, chunks: Iterable[MapCloud], force: bool, float64_coordinates: bool,
                   header: Callable[[int, np.ndarray], bytes]) -> int:
    """Write a binary PLY or PCD map (records `map_record_dtype` of the first chunk's fields) chunk
    by chunk, atomically: the records go to a spool file beside the output while the count is
    unknown, then follow the header (`header(n_points, dtype)`) into the output file."""
    n_points = 0
    first = dtype = None
    with atomic_path(path, force) as tmp:
        body = tmp.with_name(tmp.name + ".body")
        try:
            with body.open("wb") as spool:
                for chunk in chunks:
                    if first is None:
                        first = chunk
                        dtype = map_record_dtype(float64_coordinates, chunk.time_s is not None,
                                                 chunk.intensity is not None)
                    _check_fields(path, chunk, first)
                    records = np.empty(len(chunk.points_world), dtype=dtype)
                    for axis, name in enumerate("xyz"):
                        records[name] = chunk.points_world[:, axis]
                    records["scan_index"] = chunk.scan_index
                    if chunk.intensity is not None:
                        records["intensity"] = chunk.intensity
                    if chunk.time_s is not None:
                        records["time"] = chunk.time_s
                    spool.write(records.tobytes())
                    n_points += len(records)
            if dtype is None:  # no chunk: an empty map
                dtype = map_record_dtype(float64_coordinates, with_time=False, with_intensity=False)
            with tmp.open("wb") as out, body.open("rb") as spool:
                out.write(header(n_points, dtype))
                shutil.copyfileobj(spool, out, SPOOL_COPY_BYTES)
        finally:
            body.unlink(missing_ok=True)
    return n_points


def write_map_ply(path: Path | str, points_world: np.ndarray, scan_index: np.ndarray,
                  force: bool = False) -> None:
    """Write a binary PLY with float32 x y z and int32 scan_index, atomically."""
    write_map(path, MapCloud(np.asarray(points_world), np.asarray(scan_index)), force, suffix=".ply")


def read_map_ply(path: Path | str) -> MapCloud:
    """Read a PLY map written by `write_map`: points float32 (float64 when stored as double)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: map file not found.")
    cloud = open3d().t.io.read_point_cloud(str(path))
    if "scan_index" not in cloud.point:
        raise FormatError(f"{path}: expected a 'scan_index' vertex property (a map written by pa refine).")

    def optional(name: str, dtype: type) -> np.ndarray | None:
        return cloud.point[name].numpy().ravel().astype(dtype) if name in cloud.point else None

    return MapCloud(cloud.point.positions.numpy(), cloud.point["scan_index"].numpy().ravel().astype(np.int32),
                    optional("time", np.float64), optional("intensity", np.float32))


def read_map_pcd(path: Path | str) -> MapCloud:
    """Read a PCD map written by `write_map` (with pypcd4)."""
    from pypcd4 import PointCloud

    path = Path(path)
    try:
        data = PointCloud.from_path(path).pc_data
    except Exception as exc:  # a library boundary: whatever pypcd4 raises becomes a FormatError
        raise FormatError(f"{path}: cannot read the PCD map ({type(exc).__name__}: {exc}).") from None
    names = data.dtype.names
    if "scan_index" not in names:
        raise FormatError(f"{path}: expected a 'scan_index' field (a map written by pa refine); found "
                          f"{' '.join(names)}.")
    points = np.column_stack([data[axis] for axis in "xyz"])
    return MapCloud(points, np.asarray(data["scan_index"], dtype=np.int32),
                    np.asarray(data["time"], dtype=np.float64) if "time" in names else None,
                    np.asarray(data["intensity"], dtype=np.float32) if "intensity" in names else None)
