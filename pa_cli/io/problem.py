"""The feature-problem file (`.npz`): the interchange format of `pa adjust` and the benchmarks.

Arrays (O observations, N scans, F features):

- `plane_index` (O,) int64: the feature (landmark) of each observation (the name predates edge
  features; it is the feature index).
- `scan_index`  (O,) int64: the scan of each observation, 0 <= scan_index < N.
- `clusters`    (O, 4, 4) float64: point cluster of the observation, the sum over the scan's
  points p (scan frame, metres) on that plane of [p; 1][p; 1]^T. Entry [3, 3] is the point count.
- `poses`       (N, 4, 4) float64, optional: T_world_scan of every scan.
- `feature_kind` (F,) uint8, optional: the kind of every feature, 0 plane, 1 edge
  (`pa_cli.core.problem.FEATURE_PLANE`, `FEATURE_EDGE`); absent: every feature is a plane.
- `range_clusters` (O, 4, 4) float64, optional: per observation the sum over the same points of
  [p; 1][p; 1]^T / |p|^2 (scan frame, the sensor at its origin; |p| floored at
  `pa_cli.core.clusters.RANGE_WEIGHT_FLOOR_M`). Entry [3, 3] is the sum of the weights (1/m^2). The pose
  covariance's range noise model uses them (`pa_cli.adjust.covariance`); files without them load
  and get the per-observation model.

The problem type and its validation are in `pa_cli.core.problem`.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from pa_cli.core.geometry import orthonormalize
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.errors import FormatError, InputError
from pa_cli.io.atomic import atomic_path
from pa_cli.io.files import check_input_file
from pa_cli.io.trajectory import ORTHO_WARN, check_rotation_deviation

_NPY_MAGIC = b"\x93NUMPY"
_NPZ_ARRAYS = ("plane_index", "scan_index", "clusters", "poses", "feature_kind", "range_clusters")
_NPZ_REQUIRED = ("plane_index", "scan_index", "clusters")
_NPZ_HELP = ("a plane problem is an .npz archive (np.savez) of the arrays 'plane_index', 'scan_index', "
             "'clusters' and optionally 'poses', 'feature_kind' and 'range_clusters' (see `pa refine --save-problem`)")


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
    for name in ("plane_index", "scan_index", "feature_kind"):
        if name not in headers:
            continue
        shape, dtype = headers[name]
        if len(shape) != 1 or dtype.kind not in "iu":
            raise FormatError(f"{path}: '{name}' must be a 1-D integer array, found shape {shape} "
                              f"dtype {dtype}.")
    n_obs = headers["plane_index"][0][0]
    if headers["scan_index"][0][0] != n_obs:
        raise FormatError(f"{path}: 'plane_index' has {n_obs} entries but 'scan_index' has "
                          f"{headers['scan_index'][0][0]}; both need one entry per observation.")
    for name, first in (("clusters", n_obs), ("range_clusters", n_obs), ("poses", None)):
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


def load_problem(path: Path | str, range_clusters: bool = True) -> FeatureProblem:
    """Load and validate a plane-problem `.npz` file.

    The `.npy` headers inside the archive are checked (names, dtypes, shapes, sizes) before
    any array is decompressed; poses must be rigid (the rotation rule of the trajectory reader).
    With `range_clusters` False the 'range_clusters' array (only the pose covariance reads it) is
    neither decompressed nor kept.
    """
    path = Path(path)
    check_input_file(path, "plane-problem .npz")
    try:
        _check_declared_arrays(path, _npz_headers(path))
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files if k in _NPZ_ARRAYS and (range_clusters or k != "range_clusters")}
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable .npz plane problem ({exc}).") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the plane-problem file ({exc.strerror or exc}).") from None
    poses = arrays.get("poses")
    return make_problem(arrays["plane_index"], arrays["scan_index"], arrays["clusters"],
                        T_world_scan=None if poses is None else _rigid_poses(path, poses), source=str(path),
                        feature_kind=arrays.get("feature_kind"), range_clusters=arrays.get("range_clusters"))


def save_problem(path: Path | str, problem: FeatureProblem, force: bool = False) -> None:
    """Write a feature problem as `.npz` (atomically)."""
    arrays = {
        "plane_index": problem.plane_index.astype(np.int64),
        "scan_index": problem.scan_index.astype(np.int64),
        "clusters": problem.clusters.astype(np.float64),
        "feature_kind": problem.feature_kind.astype(np.uint8),
    }
    if problem.T_world_scan is not None:
        arrays["poses"] = problem.T_world_scan.astype(np.float64)
    if problem.range_clusters is not None:
        arrays["range_clusters"] = problem.range_clusters.astype(np.float64)
    with atomic_path(path, force) as tmp:
        with tmp.open("wb") as f:
            np.savez_compressed(f, **arrays)
