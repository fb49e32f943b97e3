"""Scans: folders of PCD / PLY / KITTI BIN point clouds, in the sensor (scan) frame, metres.

Supported files (extension, case-insensitive):

- `.pcd`: ascii, binary and binary_compressed encodings (read with pypcd4).
- `.ply`: ascii, binary_little_endian and binary_big_endian, vertex element with scalar
  properties (read with a strict numpy reader in this module, see `_read_ply`).
- `.bin`: KITTI velodyne layout, float32 x y z intensity per point, 16 bytes per point.

Per-point fields kept when present: intensity (`intensity`) and time in seconds (the first
of `time`, `t`, `timestamp`). Points with a NaN/inf coordinate are dropped and counted.
Every failure to read a file is an `InputError` / `FormatError` naming the file.
"""

from __future__ import annotations

import logging
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError, PaError
from pa_cli.io.atomic import atomic_path

log = logging.getLogger(__name__)

SCAN_EXTENSIONS = (".pcd", ".ply", ".bin")
TIME_FIELDS = ("time", "t", "timestamp")
INTENSITY_FIELDS = ("intensity",)
KITTI_BIN_BYTES_PER_POINT = 16  # float32 x y z intensity


@dataclass
class Scan:
    """One LiDAR scan in its sensor frame.

    `points_scan` (N, 3) float64 metres, sensor frame; `time` (N,) float64 seconds (as stored
    in the file, usually relative to the scan's timestamp) or None; `intensity` (N,) float64
    or None; `n_dropped_nonfinite` counts points dropped for a NaN/inf coordinate.
    """

    points_scan: np.ndarray
    time: np.ndarray | None
    intensity: np.ndarray | None
    path: Path
    n_dropped_nonfinite: int = 0

    def __len__(self) -> int:
        return len(self.points_scan)


# --------------------------------------------------------------------------------------------
# folders
# --------------------------------------------------------------------------------------------


def list_scan_files(folder: Path | str, glob: str | None = None) -> list[Path]:
    """Scan files of `folder` (extensions .pcd .ply .bin), naturally sorted by name.

    With `glob` (e.g. `"*.pcd"` or `"**/cloud_*.ply"`) only matching files are used.
    Raises `InputError` for a missing folder, a file instead of a folder, or no scan files.
    """
    from natsort import natsorted, ns

    folder = Path(folder)
    looked_for = " ".join(SCAN_EXTENSIONS)
    if not folder.exists():
        raise InputError(f"{folder}: scan folder not found; expected a folder of {looked_for} files.")
    if not folder.is_dir():
        raise InputError(f"{folder}: is a file; expected a folder of {looked_for} scan files.")
    candidates = [p for p in (folder.glob(glob) if glob else folder.iterdir()) if p.is_file()]
    files = [p for p in candidates if p.suffix.lower() in SCAN_EXTENSIONS]
    if not files:
        pattern = f" matching --glob '{glob}'" if glob else ""
        if not candidates:
            found = "no files" + pattern
        else:
            suffixes = sorted({p.suffix or "(no extension)" for p in candidates})
            found = f"{len(candidates)} files{pattern} with extensions {' '.join(suffixes)}"
        raise InputError(
            f"{folder}: no scan files; looked for {looked_for} files and found {found}. "
            "Use --glob to select the scan files (e.g. --glob '*.pcd')."
        )
    return natsorted(files, key=lambda p: p.relative_to(folder).as_posix(), alg=ns.PATH)


def iter_scans(files: Iterable[Path | str]) -> Iterator[Scan]:
    """Read scans one at a time (only one scan is in memory per step)."""
    for path in files:
        yield read_scan(path)


class ScanFolder(Sequence):
    """Lazy sequence of the scans of a folder: `len`, `[i]` and iteration read one file per access.

    `ScanFolder(folder, glob)` lists the files at construction (errors surface early) and reads
    nothing else until an item is accessed. `.points` is a lazy sequence of the (N, 3) float64
    scan-frame point arrays only (for consumers that need points, e.g. plane association).
    """

    def __init__(self, folder: Path | str | None = None, glob: str | None = None,
                 files: Sequence[Path] | None = None) -> None:
        if files is None:
            if folder is None:
                raise ValueError("ScanFolder needs a folder or a list of files")
            files = list_scan_files(folder, glob)
        self.folder = Path(folder) if folder is not None else None
        self.files: list[Path] = [Path(f) for f in files]

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return ScanFolder(self.folder, files=self.files[index])
        return read_scan(self.files[index])

    def __iter__(self) -> Iterator[Scan]:
        return iter_scans(self.files)

    @property
    def points(self) -> _PointsView:
        return _PointsView(self)


class _PointsView(Sequence):
    """Lazy `Sequence[np.ndarray]` of the (N, 3) scan-frame points of a `ScanFolder`."""

    def __init__(self, scans: ScanFolder) -> None:
        self._scans = scans

    def __len__(self) -> int:
        return len(self._scans)

    def __getitem__(self, index):  # type: ignore[override]
        if isinstance(index, slice):
            return _PointsView(self._scans[index])
        return self._scans[index].points_scan

    def __iter__(self) -> Iterator[np.ndarray]:
        for scan in self._scans:
            yield scan.points_scan


# --------------------------------------------------------------------------------------------
# one file
# --------------------------------------------------------------------------------------------


def read_scan(path: Path | str) -> Scan:
    """Read one scan file (.pcd, .ply or .bin) into a `Scan` (float64, sensor frame, metres).

    Per-point time is taken from the first field named `time`, `t` or `timestamp` (seconds);
    intensity from a field named `intensity`. Points with a non-finite coordinate are dropped
    (counted in `n_dropped_nonfinite`, with a warning).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: scan file not found.")
    if not path.is_file():
        raise InputError(f"{path}: not a file; expected a {' '.join(SCAN_EXTENSIONS)} scan file.")
    suffix = path.suffix.lower()
    readers = {".pcd": _read_pcd, ".ply": _read_ply, ".bin": _read_kitti_bin}
    if suffix not in readers:
        raise FormatError(f"{path}: unsupported scan extension '{path.suffix}'; expected one of "
                          f"{' '.join(SCAN_EXTENSIONS)} (use --glob to select scan files).")
    try:
        fields = readers[suffix](path)
    except PaError:
        raise
    except Exception as exc:  # a library boundary: whatever pypcd4/numpy raise becomes a FormatError
        first_line = str(exc).splitlines()[0] if str(exc) else ""
        raise FormatError(f"{path}: cannot read the {suffix[1:].upper()} file "
                          f"({type(exc).__name__}: {first_line}).") from None
    return _make_scan(path, fields)


def _pick(fields: dict[str, np.ndarray], names: Sequence[str]) -> np.ndarray | None:
    for name in names:
        if name in fields:
            return np.asarray(fields[name], dtype=np.float64).reshape(-1)
    return None


def _make_scan(path: Path, fields: dict[str, np.ndarray]) -> Scan:
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise FormatError(f"{path}: no {'/'.join(missing)} field; expected point fields x y z, "
                          f"found {' '.join(fields) or 'none'}.")
    points = np.column_stack([np.asarray(fields[a], dtype=np.float64).reshape(-1) for a in "xyz"])
    time = _pick(fields, TIME_FIELDS)
    intensity = _pick(fields, INTENSITY_FIELDS)
    finite = np.isfinite(points).all(axis=1)
    n_dropped = int(len(points) - finite.sum())
    if n_dropped:
        log.warning("%s: dropped %d of %d points with NaN/inf coordinates.", path, n_dropped, len(points))
        points = points[finite]
        time = None if time is None else time[finite]
        intensity = None if intensity is None else intensity[finite]
    return Scan(points_scan=np.ascontiguousarray(points), time=time, intensity=intensity, path=path,
                n_dropped_nonfinite=n_dropped)


def _read_kitti_bin(path: Path) -> dict[str, np.ndarray]:
    size = path.stat().st_size
    if size % KITTI_BIN_BYTES_PER_POINT:
        raise FormatError(
            f"{path}: {size} bytes is not a multiple of {KITTI_BIN_BYTES_PER_POINT}; a KITTI .bin "
            "scan holds float32 x y z intensity per point (16 bytes)."
        )
    data = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    return {"x": data[:, 0], "y": data[:, 1], "z": data[:, 2], "intensity": data[:, 3]}


def _read_pcd(path: Path) -> dict[str, np.ndarray]:
    from pypcd4 import PointCloud

    cloud = PointCloud.from_path(path)
    expected = int(cloud.metadata.points)
    if len(cloud.pc_data) != expected:
        raise FormatError(f"{path}: header says {expected} points but the data holds "
                          f"{len(cloud.pc_data)}; the file is truncated or corrupt.")
    data = cloud.pc_data
    return {name: data[name] for name in data.dtype.names}


# PLY ---------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_END_HEADER = re.compile(rb"end_header\r?\n")


def _read_ply(path: Path) -> dict[str, np.ndarray]:
    """Strict PLY reader for the `vertex` element (scalar properties).

    Open3D's reader returns uninitialised memory for truncated binary files and the common
    pure-Python reader (plyfile) is GPL-3.0, so this small reader validates the header and the
    data size itself and reports every problem as a `FormatError`.
    """
    raw = path.read_bytes()
    if not raw.startswith(b"ply"):
        raise FormatError(f"{path}: not a PLY file (the first line is not 'ply').")
    match = _PLY_END_HEADER.search(raw)
    if match is None:
        raise FormatError(f"{path}: PLY header has no 'end_header' line.")
    header = raw[:match.start()].decode("ascii", errors="replace").splitlines()
    body = raw[match.end():]
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property" and elements:
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], "list"))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise FormatError(f"{path}: unsupported PLY property line '{line}'.")
        else:
            raise FormatError(f"{path}: unexpected PLY header line '{line}'.")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise FormatError(f"{path}: PLY format '{fmt}'; expected ascii, binary_little_endian or "
                          "binary_big_endian.")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise FormatError(f"{path}: PLY file has no 'vertex' element (elements: {names}).")
    vi = names.index("vertex")
    _, n_vertex, props = elements[vi]
    if any(t == "list" for _, t in props):
        raise FormatError(f"{path}: PLY vertex element has list properties; expected scalar x y z ...")
    for name, _, eprops in elements[:vi]:
        if any(t == "list" for _, t in eprops):
            raise FormatError(f"{path}: PLY element '{name}' with list properties comes before "
                              "'vertex'; only files whose vertex data can be located are supported.")
    if fmt == "ascii":
        lines = body.decode("ascii", errors="replace").splitlines()
        skip = sum(e[1] for e in elements[:vi])
        rows = lines[skip:skip + n_vertex]
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # numpy warns (not raises) on a non-numeric token
            try:
                values = np.fromstring("\n".join(rows), dtype=np.float64, sep=" ")
            except (ValueError, DeprecationWarning):
                raise FormatError(f"{path}: non-numeric value in the PLY vertex data.") from None
        if len(rows) < n_vertex or values.size != n_vertex * len(props):
            raise FormatError(f"{path}: PLY header declares {n_vertex} vertices with {len(props)} "
                              f"properties, but the data holds {values.size} values in {len(rows)} "
                              "lines; the file is truncated or corrupt.")
        values = values.reshape(n_vertex, len(props))
        return {name: values[:, k] for k, (name, _) in enumerate(props)}
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = sum(e[1] * np.dtype([(p, endian + t) for p, t in e[2]]).itemsize for e in elements[:vi])
    dtype = np.dtype([(p, endian + t) for p, t in props])
    needed = offset + n_vertex * dtype.itemsize
    if len(body) < needed:
        raise FormatError(f"{path}: PLY header declares {n_vertex} vertices ({needed} data bytes) but "
                          f"the file holds {len(body)} bytes after the header; it is truncated.")
    data = np.frombuffer(body, dtype=dtype, count=n_vertex, offset=offset)
    return {name: data[name] for name in dtype.names}


# --------------------------------------------------------------------------------------------
# a cheap check of one file's header (no point data read)
# --------------------------------------------------------------------------------------------

HEADER_MAX_BYTES = 1 << 16  # PCD/PLY headers are a few hundred bytes; a longer one is not a header
_PCD_SIZES = {"1": 1, "2": 2, "4": 4, "8": 8}


def check_scan_header(path: Path | str) -> None:
    """Check a scan file's header and size without reading its points; raise a `FormatError`.

    Catches what makes a scan unreadable later: a missing or unsupported file, a PCD without
    a DATA line or with fewer data bytes than its header declares (binary), a PLY without
    `end_header`, a KITTI .bin whose size is not a multiple of 16 bytes. `read_scan` stays the
    full check; this one only makes the common failures surface before any work.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: scan file not found." if not path.exists()
                         else f"{path}: not a file; expected a {' '.join(SCAN_EXTENSIONS)} scan file.")
    suffix = path.suffix.lower()
    size = path.stat().st_size
    if suffix == ".bin":
        if size % KITTI_BIN_BYTES_PER_POINT:
            _read_kitti_bin(path)  # raises the FormatError that names the layout
        return
    with path.open("rb") as f:
        head = f.read(HEADER_MAX_BYTES)
    if suffix == ".pcd":
        _check_pcd_header(path, head, size)
    elif suffix == ".ply":
        _check_ply_header(path, head, size)
    else:
        raise FormatError(f"{path}: unsupported scan extension '{path.suffix}'; expected one of "
                          f"{' '.join(SCAN_EXTENSIONS)}.")


def _check_ply_header(path: Path, head: bytes, size: int) -> None:
    end = _PLY_END_HEADER.search(head)
    if not head.startswith(b"ply") or end is None:
        raise FormatError(f"{path}: not a PLY file or no 'end_header' line in its first {HEADER_MAX_BYTES} bytes.")
    binary = False
    data_bytes = count = 0
    for line in head[:end.start()].decode("ascii", errors="replace").splitlines():
        parts = line.split()
        if parts[:1] == ["format"]:
            binary = len(parts) > 1 and parts[1].startswith("binary")
        elif parts[:1] == ["element"] and len(parts) == 3 and parts[2].isdigit():
            count = int(parts[2])
        elif parts[:1] == ["property"] and len(parts) == 3 and parts[1] in _PLY_TYPES:
            data_bytes += count * np.dtype(_PLY_TYPES[parts[1]]).itemsize
        elif parts[:2] == ["property", "list"]:
            return  # element sizes vary with the lists: only the full read can check them
    if binary and size - end.end() < data_bytes:
        raise FormatError(f"{path}: PLY header declares {data_bytes} data bytes but the file holds "
                          f"{size - end.end()} after the header; it is truncated.")


def _check_pcd_header(path: Path, head: bytes, size: int) -> None:
    keys: dict[str, list[str]] = {}
    offset = 0
    for raw_line in head.splitlines(keepends=True):
        offset += len(raw_line)
        parts = raw_line.decode("ascii", errors="replace").split()
        if not parts or parts[0].startswith("#"):
            continue
        keys[parts[0].upper()] = parts[1:]
        if parts[0].upper() == "DATA":
            break
    else:
        raise FormatError(f"{path}: no PCD 'DATA' line in the first {HEADER_MAX_BYTES} bytes; "
                          "not a PCD file or a corrupt header.")
    try:
        n_points = int(keys["POINTS"][0]) if "POINTS" in keys else (
            int(keys["WIDTH"][0]) * int(keys.get("HEIGHT", ["1"])[0]))
        counts = [int(c) for c in keys.get("COUNT", ["1"] * len(keys.get("SIZE", [])))]
        bytes_per_point = sum(_PCD_SIZES[s] * c for s, c in zip(keys["SIZE"], counts, strict=False))
    except (KeyError, ValueError, IndexError):
        raise FormatError(f"{path}: PCD header without valid POINTS (or WIDTH/HEIGHT) and SIZE lines.") from None
    data = keys["DATA"][0].lower() if keys["DATA"] else ""
    if data == "binary" and size - offset < n_points * bytes_per_point:
        raise FormatError(f"{path}: PCD header declares {n_points} points ({n_points * bytes_per_point} "
                          f"data bytes) but the file holds {size - offset}; it is truncated.")


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------


def write_pcd(path: Path | str, points_scan: np.ndarray, time: np.ndarray | None = None,
              intensity: np.ndarray | None = None, force: bool = False) -> None:
    """Write a binary PCD with float32 x y z [intensity] [time] fields, atomically.

    `time` is the per-point time in seconds relative to the scan's timestamp.
    """
    from pypcd4 import PointCloud

    columns = [np.asarray(points_scan, dtype=np.float32)]
    fields = ["x", "y", "z"]
    for name, values in (("intensity", intensity), ("time", time)):
        if values is not None:
            columns.append(np.asarray(values, dtype=np.float32).reshape(-1, 1))
            fields.append(name)
    data = np.hstack(columns)
    cloud = PointCloud.from_points(data, fields, [np.float32] * len(fields))
    with atomic_path(path, force) as tmp:
        cloud.save(tmp)
