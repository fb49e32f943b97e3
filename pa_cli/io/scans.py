"""Scans: folders of PCD / PLY / KITTI BIN point clouds, in the sensor (scan) frame, metres.

Supported files (extension, case-insensitive):

- `.pcd`: versions .5 to .7, ascii, binary and binary_compressed data, read by a strict reader in
  this module that follows PCL's rules (`_read_pcd_header`): tokens separated by any spaces or
  tabs, SIZE/TYPE/COUNT default to 4/F/1, WIDTH x HEIGHT must equal POINTS, missing points are
  an error and points beyond POINTS are ignored with a warning (PCL reads POINTS points).
  Fields with COUNT > 1 are read as (N, COUNT) arrays; x, y, z, intensity and time must have
  COUNT 1.
- `.ply`: ascii, binary_little_endian and binary_big_endian, vertex element with scalar
  properties (a strict reader in this module, see `_read_ply`).
- `.bin`: KITTI velodyne layout, float32 x y z intensity per point, 16 bytes per point.

Per-point fields kept when present: intensity (`intensity`) and time, as stored (raw values in
the file's unit, which `pa_cli.refine.deskew` detects: s, ms, us or ns), from the first of `time`, `t`,
`timestamp`, `offset_time` (Livox, nanoseconds). In a PLY file, `t` next to `s` is a texture
coordinate (PLY's s, t pair) and never a time. Points with a NaN/inf coordinate are dropped and
counted; an empty or all-NaN scan gets a warning. Every failure to read a file is an `InputError` /
`FormatError` naming the file and, for header problems, the header line.
"""

from __future__ import annotations

import io
import logging
import os
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from pa_cli.errors import FormatError, InputError, PaError
from pa_cli.io.atomic import atomic_path

log = logging.getLogger(__name__)

SCAN_EXTENSIONS = (".pcd", ".ply", ".bin")
TIME_FIELDS = ("time", "t", "timestamp", "offset_time")
INTENSITY_FIELDS = ("intensity",)
# Files beside scans that are not scans and need no mention when listing (times.txt, calib.txt).
COMPANION_EXTENSIONS = (".txt",)
KITTI_BIN_BYTES_PER_POINT = 16  # float32 x y z intensity
# The vertex property naming each point's scan in the maps pa writes (`pa_cli.io.maps`): a merged
# map, never a scan, so a folder listing skips PLY files that have it.
PA_MAP_PROPERTY = "scan_index"


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
    """Scan files of `folder` (extensions .pcd .ply .bin), naturally sorted by name; other files
    (but text files, `COMPANION_EXTENSIONS`) are counted in an info record. No file is opened but
    the headers of .ply/.pcd files (`written_by_pa`).

    With `glob` (e.g. `"*.pcd"` or `"**/cloud_*.ply"`) only matching files are used. Maps written
    by pa (`written_by_pa`) are skipped, with an info record counting them. Raises `InputError`
    for a missing folder, a file instead of a folder, no scan files, or scans of more than one
    format (extension): a run reads one format, `--glob` picks it.
    """
    from natsort import natsorted, ns

    folder = Path(folder)
    looked_for = " ".join(SCAN_EXTENSIONS)
    if not folder.exists():
        raise InputError(f"{folder}: scan folder not found; expected a folder of {looked_for} files.")
    if not folder.is_dir():
        raise InputError(f"{folder}: is a file; expected a folder of {looked_for} scan files.")
    if glob:
        candidates = [p for p in folder.glob(glob) if p.is_file()]
    else:  # scandir: the file type comes with the listing, no stat per file (100,000 files in a second)
        with os.scandir(folder) as entries:
            candidates = [Path(e.path) for e in entries if e.is_file()]

    def relative(path: Path) -> str:
        return path.relative_to(folder).as_posix() if glob else path.name

    files = natsorted([p for p in candidates if p.suffix.lower() in SCAN_EXTENSIONS], key=relative, alg=ns.PATH)
    others = [p for p in candidates if p.suffix.lower() not in SCAN_EXTENSIONS + COMPANION_EXTENSIONS]
    if others and files:
        suffixes = " ".join(sorted({p.suffix.lower() or "(no extension)" for p in others}))
        log.info("%s: %d file(s) that are not scans (%s) are not read: %s", folder, len(others), suffixes,
                 _examples(natsorted(others, key=relative, alg=ns.PATH)))
    ours = [p for p in files if written_by_pa(p)]
    if ours:
        log.info("%s: skipped %d file(s) written by pa (maps, never read as scans): %s", folder, len(ours),
                 _examples(ours))
        skipped = set(ours)
        files = [p for p in files if p not in skipped]
    pattern = f" matching --glob '{glob}'" if glob else ""
    if not files:
        if not candidates:
            found = "no files" + pattern
        else:
            suffixes = sorted({p.suffix or "(no extension)" for p in candidates})
            found = f"{len(candidates)} files{pattern} with extensions {' '.join(suffixes)}"
            if ours:
                found += f" ({len(ours)} of them written by pa)"
        raise InputError(
            f"{folder}: no scan files; looked for {looked_for} files and found {found}. "
            "Use --glob to select the scan files (e.g. --glob '*.pcd')."
        )
    _check_one_format(folder, files, pattern)
    return files


def _check_one_format(folder: Path, files: list[Path], pattern: str) -> None:
    """`InputError` when `files` have more than one scan extension: the same scans are often saved
    in two formats, and reading both would double them."""
    by_suffix: dict[str, list[Path]] = {}
    for path in files:
        by_suffix.setdefault(path.suffix.lower(), []).append(path)
    if len(by_suffix) < 2:
        return
    formats = sorted(by_suffix.items(), key=lambda item: -len(item[1]))
    found = "; ".join(f"{len(paths)} {suffix} ({_examples(paths)})" for suffix, paths in formats)
    fix = " or ".join(f"--glob '*{suffix}'" for suffix, _ in formats)
    raise InputError(f"{folder}: scan files{pattern} in {len(formats)} formats: {found}; a run reads one "
                     f"format (the same scans are often saved in two). Pick one with {fix}.")


def _examples(paths: Sequence[Path], shown: int = 2) -> str:
    """The names of the first `shown` of `paths`, for a message."""
    names = ", ".join(p.name for p in paths[:shown])
    return names + (", ..." if len(paths) > shown else "")


def written_by_pa(path: Path) -> bool:
    """True for a PLY or PCD map written by pa (`pa refine`, `pa calibrate`): its points carry the
    `PA_MAP_PROPERTY` field (`pa_cli.io.maps`). Only the header is read; a file whose header cannot
    be read is not pa's (reading it as a scan reports the problem)."""
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".pcd"):
        return False
    try:
        with path.open("rb") as f:
            if suffix == ".ply":
                _, elements, _ = _read_ply_header(path, f)
                return any(e.name == "vertex" and any(name == PA_MAP_PROPERTY for name, _ in e.properties)
                           for e in elements)
            if suffix == ".pcd":
                return PA_MAP_PROPERTY in _read_pcd_header(path, f).fields
    except (OSError, FormatError):
        return False
    return False


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

    Per-point time is taken from the first field named `time`, `t` or `timestamp` (seconds; not
    a PLY texture coordinate `t`); intensity from a field named `intensity`. Points with a
    non-finite coordinate are dropped (counted in `n_dropped_nonfinite`, with a warning).
    """
    path = Path(path)
    suffix = _check_scan_path(path)
    readers = {".pcd": _read_pcd, ".ply": _read_ply, ".bin": _read_kitti_bin}
    try:
        fields = readers[suffix](path)
    except PaError:
        raise
    except OSError as exc:
        raise InputError(f"{path}: cannot read the scan file ({exc.strerror or exc}).") from None
    except Exception as exc:  # a library boundary: whatever pypcd4/numpy raise becomes a FormatError
        first_line = str(exc).splitlines()[0] if str(exc) else ""
        raise FormatError(f"{path}: cannot read the {suffix[1:].upper()} file "
                          f"({type(exc).__name__}: {first_line}).") from None
    return _make_scan(path, fields)


def _check_scan_path(path: Path) -> str:
    """The lower-case suffix of an existing scan file; `InputError` / `FormatError` otherwise."""
    if not path.exists():
        raise InputError(f"{path}: scan file not found.")
    if not path.is_file():
        raise InputError(f"{path}: not a file; expected a {' '.join(SCAN_EXTENSIONS)} scan file.")
    suffix = path.suffix.lower()
    if suffix not in SCAN_EXTENSIONS:
        raise FormatError(f"{path}: unsupported scan extension '{path.suffix}'; expected one of "
                          f"{' '.join(SCAN_EXTENSIONS)} (use --glob to select scan files).")
    return suffix


def _column(path: Path, fields: dict[str, np.ndarray], name: str) -> np.ndarray:
    values = np.asarray(fields[name])
    if values.ndim != 1:
        raise FormatError(f"{path}: field '{name}' holds {values.shape[1]} values per point (COUNT "
                          f"{values.shape[1]}); expected one.")
    return values.astype(np.float64)


def _pick(path: Path, fields: dict[str, np.ndarray], names: Sequence[str]) -> np.ndarray | None:
    for name in names:
        if name in fields:
            return _column(path, fields, name)
    return None


def _make_scan(path: Path, fields: dict[str, np.ndarray]) -> Scan:
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise FormatError(f"{path}: no {'/'.join(missing)} field; expected point fields x y z, "
                          f"found {' '.join(fields) or 'none'}.")
    points = np.column_stack([_column(path, fields, a) for a in "xyz"])
    time = _pick(path, fields, TIME_FIELDS)
    intensity = _pick(path, fields, INTENSITY_FIELDS)
    # the three columns' tests combined: an (N, 3) .all(axis=1) reduces rows of three, 15x slower
    finite = np.isfinite(points[:, 0]) & np.isfinite(points[:, 1]) & np.isfinite(points[:, 2])
    n_dropped = int(len(points) - finite.sum())
    if not len(points):
        log.warning("%s: the scan holds no points.", path)
    elif n_dropped == len(points):
        log.warning("%s: all %d points have NaN/inf coordinates; the scan is empty.", path, n_dropped)
    elif n_dropped:
        log.warning("%s: dropped %d of %d points with NaN/inf coordinates.", path, n_dropped, len(points))
    if n_dropped:
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


# PCD ---------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}
_PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")
_PCD_KEYWORDS = ("VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT",
                 "VIEWPOINT", "POINTS", "DATA")
_PCD_VIEWPOINT_VALUES = 7  # tx ty tz qw qx qy qz
_PCD_SIZE_PREFIX_BYTES = 8  # binary_compressed: uint32 compressed size, uint32 uncompressed size


def _header_lines(f: BinaryIO) -> Iterator[tuple[int, list[str], int]]:
    """(line number, whitespace-separated tokens, offset just past the line) of each line of the
    binary file `f` from its start, for the text headers of PCD and PLY; the caller stops at the
    header's last line, so no point data is read. Bytes that are not ASCII (a Latin-1 comment,
    binary content) become U+FFFD, so they show up in the tokens."""
    offset = 0
    for lineno, line in enumerate(iter(f.readline, b""), start=1):
        offset += len(line)
        yield lineno, line.decode("ascii", errors="replace").split(), offset


def _shown(tokens: list[str]) -> str:
    """A header line as quoted in a message (shortened)."""
    text = " ".join(tokens)
    return repr(text if len(text) <= 60 else text[:57] + "...")


@dataclass
class _PcdHeader:
    fields: list[str]
    dtypes: list[np.dtype]
    counts: list[int]
    n_points: int
    encoding: str
    data_offset: int
    data_line: int  # line number of the first data line


def _pcd_ints(path: Path, lineno: int, tokens: list[str], n_values: int | None) -> list[int]:
    keyword, values = tokens[0], tokens[1:]
    if n_values is not None and len(values) != n_values:
        expected = f"{n_values} value{'s' if n_values != 1 else ''}"
        if keyword in ("SIZE", "TYPE", "COUNT"):
            expected += " (one per field of the FIELDS line)"
        raise FormatError(f"{path}: PCD header line {lineno} {_shown(tokens)}: {len(values)} values, "
                          f"expected {expected}.")
    try:
        numbers = [int(v) for v in values]
    except ValueError:
        numbers = [-1]
    if any(v < 0 for v in numbers):
        raise FormatError(f"{path}: PCD header line {lineno} {_shown(tokens)}: expected non-negative "
                          "integers.")
    return numbers


def _read_pcd_header(path: Path, f: BinaryIO) -> _PcdHeader:
    """Parse a PCD header (versions .5 to .7) line by line, as PCL's reader does.

    Tokens are separated by any run of spaces or tabs; `#` lines are comments; SIZE, TYPE and
    COUNT default to 4, F and 1 per field (PCD .5); without WIDTH and HEIGHT the cloud is
    WIDTH = POINTS, HEIGHT = 1; WIDTH x HEIGHT must equal POINTS. The header ends at DATA.
    """
    found: dict[str, tuple[int, list[str]]] = {}
    for lineno, tokens, end in _header_lines(f):
        if not tokens or tokens[0].startswith("#"):
            continue
        keyword = "FIELDS" if tokens[0] == "COLUMNS" else tokens[0]
        if keyword not in _PCD_KEYWORDS:
            what = "not a PCD file" if not found else "unknown PCD header keyword"
            raise FormatError(f"{path}: {what}: line {lineno} is {_shown(tokens)}; a PCD header has "
                              f"the lines {' '.join(_PCD_KEYWORDS[:-1])} and DATA.")
        found[keyword] = (lineno, tokens)
        if keyword == "DATA":
            return _pcd_header_from_lines(path, found, end, lineno + 1)
    raise FormatError(f"{path}: no PCD 'DATA' line (DATA ascii, binary or binary_compressed) ends the "
                      "header; the file is not a PCD file or is truncated.")


def _pcd_header_from_lines(path: Path, found: dict[str, tuple[int, list[str]]], data_offset: int,
                           data_line: int) -> _PcdHeader:
    if "FIELDS" not in found or len(found["FIELDS"][1]) < 2:
        raise FormatError(f"{path}: PCD header has no FIELDS line naming the fields (e.g. FIELDS x y z).")
    fields = found["FIELDS"][1][1:]
    n_fields = len(fields)
    sizes = _pcd_ints(path, *found["SIZE"], n_fields) if "SIZE" in found else [4] * n_fields
    counts = _pcd_ints(path, *found["COUNT"], n_fields) if "COUNT" in found else [1] * n_fields
    types = ["F"] * n_fields
    if "TYPE" in found:
        lineno, tokens = found["TYPE"]
        types = tokens[1:]
        if len(types) != n_fields:
            raise FormatError(f"{path}: PCD header line {lineno} {_shown(tokens)}: {len(types)} values, "
                              f"expected {n_fields} (one per field of the FIELDS line).")
    dtypes = []
    for name, kind, size in zip(fields, types, sizes, strict=True):
        if (kind, size) not in _PCD_TYPES:
            raise FormatError(f"{path}: PCD field '{name}' has TYPE {kind} with SIZE {size}; expected F "
                              "(size 4 or 8), I or U (size 1, 2, 4 or 8).")
        dtypes.append(np.dtype("<" + _PCD_TYPES[(kind, size)]))
    width = _pcd_ints(path, *found["WIDTH"], 1)[0] if "WIDTH" in found else None
    height = _pcd_ints(path, *found["HEIGHT"], 1)[0] if "HEIGHT" in found else None
    points = _pcd_ints(path, *found["POINTS"], 1)[0] if "POINTS" in found else None
    if points is None:
        if width is None:
            raise FormatError(f"{path}: PCD header has neither POINTS nor WIDTH; cannot tell the "
                              "number of points.")
        points = width * (1 if height is None else height)
    width = points if width is None and height is None else width
    height = 1 if height is None else height
    if width is None:
        raise FormatError(f"{path}: PCD header gives HEIGHT {height} but no WIDTH.")
    if width * height != points:
        raise FormatError(f"{path}: PCD header says WIDTH {width} x HEIGHT {height} = {width * height} "
                          f"points but POINTS {points}; they must agree (PCL refuses such files too).")
    if "VIEWPOINT" in found:
        lineno, tokens = found["VIEWPOINT"]
        if len(tokens) - 1 != _PCD_VIEWPOINT_VALUES:
            raise FormatError(f"{path}: PCD header line {lineno} {_shown(tokens)}: expected "
                              f"{_PCD_VIEWPOINT_VALUES} values (tx ty tz qw qx qy qz).")
    lineno, tokens = found["DATA"]
    encoding = tokens[1] if len(tokens) == 2 else None
    if encoding not in _PCD_ENCODINGS:
        raise FormatError(f"{path}: PCD header line {lineno} {_shown(tokens)}: expected DATA ascii, "
                          "DATA binary or DATA binary_compressed.")
    return _PcdHeader(fields, dtypes, counts, points, encoding, data_offset, data_line)


def _read_pcd(path: Path) -> dict[str, np.ndarray]:
    """Read a PCD file (any field layout; fields with COUNT > 1 become (N, COUNT) arrays).

    Missing points are an error. Data beyond POINTS (extra ASCII rows, or at least one whole
    extra binary point) is ignored with a warning, as PCL reads only POINTS points; a shorter
    tail of binary padding is ignored silently.
    """
    raw = path.read_bytes()
    header = _read_pcd_header(path, io.BytesIO(raw))
    body = raw[header.data_offset:]
    if header.encoding == "ascii":
        columns = _pcd_ascii_columns(path, header, body)
    else:
        columns = _pcd_binary_columns(path, header, body)
    fields: dict[str, np.ndarray] = {}
    for name, column in zip(header.fields, columns, strict=True):
        fields.setdefault(name, column)  # repeated names (PCL's '_' padding): the first one counts
    return fields


def _pcd_ascii_columns(path: Path, header: _PcdHeader, body: bytes) -> list[np.ndarray]:
    lines = body.decode("ascii", errors="replace").splitlines()
    rows = [(header.data_line + k, line.split()) for k, line in enumerate(lines) if line.strip()]
    per_row = sum(header.counts)
    for lineno, tokens in rows:
        if len(tokens) != per_row:
            raise FormatError(f"{path}: line {lineno} of the ASCII data has {len(tokens)} values; the "
                              f"header's fields need {per_row} per point.")
    if len(rows) < header.n_points:
        raise FormatError(f"{path}: PCD header says POINTS {header.n_points} but the ASCII data holds "
                          f"{len(rows)} rows; the file is truncated.")
    if len(rows) > header.n_points:
        _warn_extra_points(path, header.n_points, len(rows))
        rows = rows[:header.n_points]
    try:
        values = np.array([t for _, tokens in rows for t in tokens], dtype=np.float64)
    except ValueError:
        lineno = next(n for n, tokens in rows if not _all_numbers(tokens))
        raise FormatError(f"{path}: line {lineno} of the ASCII data holds a value that is not a "
                          "number.") from None
    values = values.reshape(header.n_points, per_row)
    bounds = np.cumsum([0, *header.counts])
    return [_squeeze(values[:, a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _warn_extra_points(path: Path, n_points: int, n_data: int) -> None:
    log.warning("%s: PCD header says POINTS %d but the data holds %d points; reading the first %d, as "
                "PCL does (fix POINTS, WIDTH and HEIGHT to use them all).", path, n_points, n_data, n_points)


def _all_numbers(tokens: list[str]) -> bool:
    try:
        [float(t) for t in tokens]
    except ValueError:
        return False
    return True


def _squeeze(column: np.ndarray) -> np.ndarray:
    return column[:, 0] if column.shape[1] == 1 else column


def _pcd_point_step(header: _PcdHeader) -> int:
    return sum(dtype.itemsize * count for dtype, count in zip(header.dtypes, header.counts, strict=True))


def _check_pcd_binary_size(path: Path, header: _PcdHeader, n_bytes: int) -> None:
    """DATA binary: `n_bytes` after the header must hold POINTS points (more are warned about by
    the reader, `_pcd_binary_columns`, so that a checked and then read file warns once)."""
    n, point_step = header.n_points, _pcd_point_step(header)
    if n_bytes < n * point_step:
        raise FormatError(f"{path}: PCD header says POINTS {n} ({n * point_step} data bytes) but the file "
                          f"holds {n_bytes} bytes after the header; it is truncated.")


def _pcd_compressed_sizes(path: Path, header: _PcdHeader, prefix: bytes, n_bytes: int) -> tuple[int, int]:
    """DATA binary_compressed: the (compressed, uncompressed) sizes of the 8-byte prefix, checked
    against the header and the `n_bytes` after the header."""
    if len(prefix) < _PCD_SIZE_PREFIX_BYTES:
        raise FormatError(f"{path}: binary_compressed PCD data is shorter than its 8-byte size prefix; "
                          "the file is truncated.")
    compressed_size, uncompressed_size = (int(v) for v in np.frombuffer(prefix[:_PCD_SIZE_PREFIX_BYTES], "<u4"))
    expected_size = header.n_points * _pcd_point_step(header)
    if uncompressed_size != expected_size:
        raise FormatError(f"{path}: binary_compressed PCD data unpacks to {uncompressed_size} bytes but "
                          f"the header's POINTS {header.n_points} and fields need {expected_size}; the "
                          "header and the data disagree.")
    if n_bytes - _PCD_SIZE_PREFIX_BYTES < compressed_size:
        raise FormatError(f"{path}: binary_compressed PCD data declares {compressed_size} compressed bytes "
                          f"but the file holds {n_bytes - _PCD_SIZE_PREFIX_BYTES}; it is truncated.")
    return compressed_size, uncompressed_size


def _pcd_binary_columns(path: Path, header: _PcdHeader, body: bytes) -> list[np.ndarray]:
    n = header.n_points
    if header.encoding == "binary_compressed":
        body = _pcd_decompress(path, header, body)
        columns, offset = [], 0
        for dtype, count in zip(header.dtypes, header.counts, strict=True):
            block = np.frombuffer(body, dtype=dtype, count=n * count, offset=offset)
            columns.append(_squeeze(block.reshape(n, count)))
            offset += n * count * dtype.itemsize
        return columns
    _check_pcd_binary_size(path, header, len(body))
    point_step = _pcd_point_step(header)
    if point_step and len(body) - n * point_step >= point_step:
        _warn_extra_points(path, n, len(body) // point_step)
    dtype = np.dtype([(f"f{k}", dt, (count,)) for k, (dt, count) in
                      enumerate(zip(header.dtypes, header.counts, strict=True))])
    data = np.frombuffer(body, dtype=dtype, count=n)
    return [_squeeze(data[f"f{k}"].reshape(n, count)) for k, count in enumerate(header.counts)]


def _pcd_decompress(path: Path, header: _PcdHeader, body: bytes) -> bytes:
    import lzf

    compressed_size, uncompressed_size = _pcd_compressed_sizes(path, header, body[:_PCD_SIZE_PREFIX_BYTES],
                                                               len(body))
    if uncompressed_size == 0:
        return b""
    compressed = body[_PCD_SIZE_PREFIX_BYTES:_PCD_SIZE_PREFIX_BYTES + compressed_size]
    try:
        data = lzf.decompress(compressed, uncompressed_size)
    except ValueError:
        data = None
    if data is None or len(data) != uncompressed_size:
        raise FormatError(f"{path}: binary_compressed PCD data does not decompress (LZF) to "
                          f"{uncompressed_size} bytes; the file is corrupt.")
    return data


# PLY ---------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_PLY_TEXTURE_PAIR = ("s", "t")  # texture coordinates, never a per-point time


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code or "list")


def _read_ply_header(path: Path, f: BinaryIO) -> tuple[str, list[_PlyElement], int]:
    """(format, elements, offset of the data) of a PLY header, parsed line by line: the header
    ends at the first line that is exactly `end_header` (a comment mentioning it does not)."""
    fmt = None
    elements: list[_PlyElement] = []
    for lineno, tokens, end in _header_lines(f):
        if lineno == 1:
            if tokens != ["ply"]:
                raise FormatError(f"{path}: not a PLY file (the first line is not 'ply').")
            continue
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        where = f"{path}: PLY header line {lineno} {_shown(tokens)}"
        if tokens == ["end_header"]:
            if fmt not in _PLY_FORMATS:
                raise FormatError(f"{path}: PLY format '{fmt}'; expected one of {', '.join(_PLY_FORMATS)}.")
            return fmt, elements, end
        if tokens[0] == "format" and len(tokens) == 3:
            fmt = tokens[1]
        elif tokens[0] == "element" and len(tokens) == 3:
            if not re.fullmatch(r"\d+", tokens[2]):
                raise FormatError(f"{where}: the element count must be a non-negative integer.")
            elements.append(_PlyElement(tokens[1], int(tokens[2]), []))
        elif tokens[0] == "property" and elements:
            if tokens[1] == "list" and len(tokens) == 5:
                elements[-1].properties.append((tokens[4], "list"))
            elif len(tokens) == 3 and tokens[1] in _PLY_TYPES:
                elements[-1].properties.append((tokens[2], _PLY_TYPES[tokens[1]]))
            else:
                raise FormatError(f"{where}: unsupported property; expected 'property TYPE NAME' with "
                                  f"TYPE one of {' '.join(_PLY_TYPES)}.")
        else:
            raise FormatError(f"{where}: unexpected line; expected format, element, property, comment "
                              "or end_header.")
    raise FormatError(f"{path}: PLY header has no 'end_header' line; the file is truncated or not a PLY file.")


def _read_ply(path: Path) -> dict[str, np.ndarray]:
    """Strict PLY reader for the `vertex` element (scalar properties).

    Open3D's reader returns uninitialised memory for truncated binary files and the common
    pure-Python reader (plyfile) is GPL-3.0, so this small reader validates the header and the
    data size itself and reports every problem as a `FormatError`. A `t` property next to an
    `s` property is a texture coordinate (PLY's s, t pair) and is not returned.
    """
    raw = path.read_bytes()
    fmt, elements, data_offset = _read_ply_header(path, io.BytesIO(raw))
    body = raw[data_offset:]
    vi, vertex_offset, dtype = _ply_vertex_layout(path, fmt, elements)
    if fmt == "ascii":
        fields = _ply_ascii_vertices(path, body, sum(e.count for e in elements[:vi]), elements[vi].count,
                                     elements[vi].properties)
    else:
        _check_ply_binary_size(path, elements[vi].count, vertex_offset, dtype, len(body))
        data = np.frombuffer(body, dtype=dtype, count=elements[vi].count, offset=vertex_offset)
        fields = {name: data[name] for name in dtype.names}
    if all(name in fields for name in _PLY_TEXTURE_PAIR):
        for name in _PLY_TEXTURE_PAIR:
            del fields[name]
    return fields


def _ply_vertex_layout(path: Path, fmt: str, elements: list[_PlyElement]) -> tuple[int, int, np.dtype]:
    """(index of the vertex element, byte offset of its data in a binary file, its record dtype)."""
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise FormatError(f"{path}: PLY file has no 'vertex' element (elements: {names}).")
    vi = names.index("vertex")
    if any(t == "list" for _, t in elements[vi].properties):
        raise FormatError(f"{path}: PLY vertex element has list properties; expected scalar x y z ...")
    for element in elements[:vi]:
        if any(t == "list" for _, t in element.properties):
            raise FormatError(f"{path}: PLY element '{element.name}' with list properties comes before "
                              "'vertex'; only files whose vertex data can be located are supported.")
    endian = ">" if fmt == "binary_big_endian" else "<"
    offset = sum(e.count * np.dtype([(p, endian + t) for p, t in e.properties]).itemsize for e in elements[:vi])
    return vi, offset, np.dtype([(p, endian + t) for p, t in elements[vi].properties])


def _check_ply_binary_size(path: Path, n_vertex: int, offset: int, dtype: np.dtype, n_bytes: int) -> None:
    needed = offset + n_vertex * dtype.itemsize
    if n_bytes < needed:
        raise FormatError(f"{path}: PLY header declares {n_vertex} vertices ({needed} data bytes) but "
                          f"the file holds {n_bytes} bytes after the header; it is truncated.")


def _ply_ascii_vertices(path: Path, body: bytes, skip: int, n_vertex: int,
                        props: list[tuple[str, str]]) -> dict[str, np.ndarray]:
    lines = body.decode("ascii", errors="replace").splitlines()
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


# --------------------------------------------------------------------------------------------
# a cheap check of one file's header (no point data read)
# --------------------------------------------------------------------------------------------


def check_scan_header(path: Path | str) -> None:
    """Check a scan file's header and size without reading its points; raise `InputError` /
    `FormatError` as `read_scan` would.

    The header is parsed by the same code as `read_scan`; binary PCD/PLY data sizes, the size
    prefix of binary_compressed PCD and the size of KITTI .bin files are checked against it.
    ASCII data, the LZF stream and the values themselves are checked only by `read_scan`, which
    also gives the warnings (data beyond POINTS), so a file checked and then read warns once.
    """
    path = Path(path)
    suffix = _check_scan_path(path)
    try:
        size = path.stat().st_size
        if suffix == ".bin":
            if size % KITTI_BIN_BYTES_PER_POINT:
                _read_kitti_bin(path)  # raises the FormatError that names the layout
            return
        with path.open("rb") as f:
            if suffix == ".pcd":
                header = _read_pcd_header(path, f)
                if header.encoding == "binary":
                    _check_pcd_binary_size(path, header, size - header.data_offset)
                elif header.encoding == "binary_compressed":
                    _pcd_compressed_sizes(path, header, f.read(_PCD_SIZE_PREFIX_BYTES), size - header.data_offset)
            else:
                fmt, elements, data_offset = _read_ply_header(path, f)
                vi, offset, dtype = _ply_vertex_layout(path, fmt, elements)
                if fmt != "ascii":
                    _check_ply_binary_size(path, elements[vi].count, offset, dtype, size - data_offset)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the scan file ({exc.strerror or exc}).") from None


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
