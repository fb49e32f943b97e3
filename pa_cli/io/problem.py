"""The plane-problem file (`.npz`): the interchange format of `pa adjust` and the benchmarks.

Arrays (O observations, N scans):

- `plane_index` (O,) int64: the plane (landmark) of each observation.
- `scan_index`  (O,) int64: the scan of each observation, 0 <= scan_index < N.
- `clusters`    (O, 4, 4) float64: point cluster of the observation, the sum over the scan's
  points p (scan frame, metres) on that plane of [p; 1][p; 1]^T. Entry [3, 3] is the point count.
- `poses`       (N, 4, 4) float64, optional: T_world_scan of every scan.

The solver never sees points: clusters are sufficient statistics (BALM2, Theorems 1 and 2).
"""

from __future__ import annotations

import logging
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.atomic import atomic_path
from pa_cli.io.trajectory import ORTHO_WARN, check_rotation_deviation, orthonormalize

log = logging.getLogger(__name__)

SYMMETRY_RTOL = 1e-9


@dataclass
class PlaneProblem:
    """Observations of planes by scans, as point clusters in the scan frame."""

    plane_index: np.ndarray  # (O,) int64, planes numbered 0..n_planes-1
    scan_index: np.ndarray  # (O,) int64, scans numbered 0..n_scans-1
    clusters: np.ndarray  # (O, 4, 4) float64
    n_scans: int
    T_world_scan: np.ndarray | None = None  # (N, 4, 4)
    n_dropped_planes: int = field(default=0, compare=False)

    @property
    def n_planes(self) -> int:
        return int(self.plane_index.max()) + 1 if len(self.plane_index) else 0

    @property
    def n_observations(self) -> int:
        return len(self.plane_index)

    @property
    def n_points(self) -> int:
        return int(round(self.clusters[:, 3, 3].sum()))


def points_to_cluster(points_scan: np.ndarray) -> np.ndarray:
    """Point cluster sum [p;1][p;1]^T of (M, 3) points, as a (4, 4) float64 array."""
    ph = np.hstack([points_scan, np.ones((len(points_scan), 1))])
    return ph.T @ ph


def make_problem(plane_index: np.ndarray, scan_index: np.ndarray, clusters: np.ndarray,
                 n_scans: int | None = None, T_world_scan: np.ndarray | None = None,
                 source: str = "plane problem") -> PlaneProblem:
    """Validate arrays and build a `PlaneProblem`.

    Planes seen by fewer than two scans are dropped (they carry no constraint) and the
    remaining planes are renumbered 0..P-1 in order of their original index.
    """
    plane_index = np.asarray(plane_index)
    scan_index = np.asarray(scan_index)
    clusters = np.asarray(clusters)
    if plane_index.ndim != 1 or not np.issubdtype(plane_index.dtype, np.integer):
        raise FormatError(f"{source}: 'plane_index' must be a 1-D integer array, "
                          f"found shape {plane_index.shape} dtype {plane_index.dtype}.")
    if scan_index.ndim != 1 or not np.issubdtype(scan_index.dtype, np.integer):
        raise FormatError(f"{source}: 'scan_index' must be a 1-D integer array, "
                          f"found shape {scan_index.shape} dtype {scan_index.dtype}.")
    n_obs = len(plane_index)
    if len(scan_index) != n_obs:
        raise FormatError(f"{source}: 'plane_index' has {n_obs} entries but 'scan_index' has "
                          f"{len(scan_index)}; both need one entry per observation.")
    if clusters.shape != (n_obs, 4, 4):
        raise FormatError(f"{source}: 'clusters' must have shape ({n_obs}, 4, 4), "
                          f"found {clusters.shape}.")
    clusters = clusters.astype(np.float64)
    if not np.all(np.isfinite(clusters)):
        raise FormatError(f"{source}: 'clusters' contains NaN or inf values.")
    scale = np.maximum(np.abs(clusters).max(axis=(1, 2)), 1.0)
    asym = np.abs(clusters - clusters.transpose(0, 2, 1)).max(axis=(1, 2)) / scale
    if n_obs and asym.max() > SYMMETRY_RTOL:
        bad = int(np.argmax(asym))
        raise FormatError(f"{source}: cluster {bad} is not symmetric (relative asymmetry "
                          f"{asym[bad]:.3g}); a cluster is a sum of [p;1][p;1]^T.")
    if n_obs and np.any(clusters[:, 3, 3] < 1):
        bad = int(np.argmin(clusters[:, 3, 3]))
        raise FormatError(f"{source}: cluster {bad} has point count {clusters[bad, 3, 3]:g} "
                          "(entry [3, 3]); every observation needs at least one point.")
    if n_obs and (plane_index.min() < 0 or scan_index.min() < 0):
        raise FormatError(f"{source}: 'plane_index' and 'scan_index' must be non-negative.")
    if T_world_scan is not None:
        T_world_scan = np.asarray(T_world_scan, dtype=np.float64)
        if T_world_scan.ndim != 3 or T_world_scan.shape[1:] != (4, 4):
            raise FormatError(f"{source}: 'poses' must have shape (N, 4, 4), "
                              f"found {T_world_scan.shape}.")
        if not np.all(np.isfinite(T_world_scan)):
            raise FormatError(f"{source}: 'poses' contains NaN or inf values.")
        if n_scans is None:
            n_scans = len(T_world_scan)
        elif n_scans != len(T_world_scan):
            raise FormatError(f"{source}: {len(T_world_scan)} poses for {n_scans} scans.")
    if n_scans is None:
        n_scans = int(scan_index.max()) + 1 if n_obs else 0
    if n_obs and scan_index.max() >= n_scans:
        raise FormatError(f"{source}: 'scan_index' refers to scan {int(scan_index.max())} but "
                          f"there are only {n_scans} poses.")

    # Drop planes seen by fewer than two distinct scans; renumber the rest.
    plane_index = plane_index.astype(np.int64)
    scan_index = scan_index.astype(np.int64)
    pairs = np.unique(np.column_stack([plane_index, scan_index]), axis=0) if n_obs else \
        np.empty((0, 2), np.int64)
    if len(pairs) != n_obs:
        raise FormatError(f"{source}: {n_obs - len(pairs)} duplicate (plane, scan) observations; "
                          "merge the clusters of one plane in one scan into one observation.")
    planes, scans_per_plane = np.unique(plane_index, return_counts=True)
    keep_planes = planes[scans_per_plane >= 2]
    n_dropped = len(planes) - len(keep_planes)
    if n_dropped:
        log.info("%s: dropped %d planes seen by fewer than two scans.", source, n_dropped)
    keep = np.isin(plane_index, keep_planes)
    new_plane_index = np.searchsorted(keep_planes, plane_index[keep])
    order = np.lexsort((scan_index[keep], new_plane_index))
    return PlaneProblem(
        plane_index=new_plane_index[order].astype(np.int64),
        scan_index=scan_index[keep][order],
        clusters=clusters[keep][order],
        n_scans=int(n_scans),
        T_world_scan=T_world_scan,
        n_dropped_planes=n_dropped,
    )


_NPY_MAGIC = b"\x93NUMPY"
_NPZ_ARRAYS = ("plane_index", "scan_index", "clusters", "poses")
_NPZ_REQUIRED = ("plane_index", "scan_index", "clusters")
_NPZ_HELP = ("a plane problem is an .npz archive (np.savez) of the arrays 'plane_index', 'scan_index', "
             "'clusters' and optionally 'poses' (see `pa refine --save-problem`)")


def _npz_headers(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of every array of an `.npz`, from the `.npy` headers inside the zip,
    without decompressing the data; each header's shape must match its member's size."""
    with path.open("rb") as f:
        start = f.read(len(_NPY_MAGIC))
    if start == _NPY_MAGIC:
        raise FormatError(f"{path}: is a .npy file (one array), not an .npz archive; {_NPZ_HELP}.")
    if not zipfile.is_zipfile(path):
        raise FormatError(f"{path}: not a readable .npz plane problem (not a zip archive); {_NPZ_HELP}.")
    headers = {}
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            if not info.filename.endswith(".npy"):
                continue
            name = info.filename[:-len(".npy")]
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(member)
                else:
                    raise FormatError(f"{path}: array '{name}' has .npy format version {version}; "
                                      "expected 1.0 or 2.0 (as np.savez writes).")
                header_bytes = member.tell()
            declared = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            if dtype.hasobject or declared != info.file_size - header_bytes:
                raise FormatError(f"{path}: array '{name}' declares shape {shape} of {dtype} "
                                  f"({declared} bytes) but holds {info.file_size - header_bytes} bytes; "
                                  "the file is corrupt.")
            headers[name] = (tuple(shape), dtype)
    return headers


def _check_declared_arrays(path: Path, headers: dict[str, tuple[tuple[int, ...], np.dtype]]) -> None:
    """The checks of `make_problem` that need only shapes and dtypes, made on the headers."""
    missing = [k for k in _NPZ_REQUIRED if k not in headers]
    if missing:
        raise FormatError(f"{path}: missing arrays {missing}; {_NPZ_HELP}.")
    for name in ("plane_index", "scan_index"):
        shape, dtype = headers[name]
        if len(shape) != 1 or dtype.kind not in "iu":
            raise FormatError(f"{path}: '{name}' must be a 1-D integer array, found shape {shape} "
                              f"dtype {dtype}.")
    n_obs = headers["plane_index"][0][0]
    if headers["scan_index"][0][0] != n_obs:
        raise FormatError(f"{path}: 'plane_index' has {n_obs} entries but 'scan_index' has "
                          f"{headers['scan_index'][0][0]}; both need one entry per observation.")
    for name, first in (("clusters", n_obs), ("poses", None)):
        if name not in headers:
            continue
        shape, dtype = headers[name]
        if dtype.kind not in "iuf":
            raise FormatError(f"{path}: '{name}' holds {dtype} values; expected float64 numbers.")
        if len(shape) != 3 or shape[1:] != (4, 4) or (first is not None and shape[0] != first):
            raise FormatError(f"{path}: '{name}' must have shape ({'N' if first is None else first}, 4, 4), "
                              f"found {shape}.")


def _rigid_poses(path: Path, T_world_scan: np.ndarray) -> np.ndarray:
    """Poses after the trajectory reader's rotation rule (re-orthonormalised above its warning
    threshold); a bottom row farther than that threshold from 0 0 0 1 is an error."""
    T = np.array(T_world_scan, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        return T  # make_problem names the NaN/inf
    bottom = np.abs(T[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    if len(T) and bottom.max() > ORTHO_WARN:
        bad = int(np.argmax(bottom))
        raise FormatError(f"{path}: pose {bad} has bottom row {T[bad, 3].tolist()}; a pose T_world_scan "
                          "is a rigid transform with bottom row 0 0 0 1.")
    R_ortho, deviation = orthonormalize(T[:, :3, :3])
    check_rotation_deviation(path, deviation, "has a rotation block that deviates from a rotation by",
                             "rotations of 'poses' re-orthonormalised",
                             "'poses' must hold rigid transforms T_world_scan")
    replace = deviation > ORTHO_WARN
    T[replace, :3, :3] = R_ortho[replace]
    T[:, 3, :] = [0.0, 0.0, 0.0, 1.0]
    return T


def load_problem(path: Path | str) -> PlaneProblem:
    """Load and validate a plane-problem `.npz` file.

    The `.npy` headers inside the archive are checked (names, dtypes, shapes, sizes) before
    any array is decompressed; poses must be rigid (the rotation rule of the trajectory reader).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: plane-problem file not found.")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a plane-problem .npz file.")
    try:
        _check_declared_arrays(path, _npz_headers(path))
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files if k in _NPZ_ARRAYS}
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable .npz plane problem ({exc}).") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the plane-problem file ({exc.strerror or exc}).") from None
    poses = arrays.get("poses")
    return make_problem(arrays["plane_index"], arrays["scan_index"], arrays["clusters"],
                        T_world_scan=None if poses is None else _rigid_poses(path, poses), source=str(path))


def save_problem(path: Path | str, problem: PlaneProblem, force: bool = False) -> None:
    """Write a plane problem as `.npz` (atomically)."""
    arrays = {
        "plane_index": problem.plane_index.astype(np.int64),
        "scan_index": problem.scan_index.astype(np.int64),
        "clusters": problem.clusters.astype(np.float64),
    }
    if problem.T_world_scan is not None:
        arrays["poses"] = problem.T_world_scan.astype(np.float64)
    with atomic_path(path, force) as tmp:
        with tmp.open("wb") as f:
            np.savez_compressed(f, **arrays)
