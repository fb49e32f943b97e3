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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.atomic import atomic_path

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


def load_problem(path: Path | str) -> PlaneProblem:
    """Load and validate a plane-problem `.npz` file."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: plane-problem file not found.")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable .npz plane problem ({exc}).") from None
    missing = [k for k in ("plane_index", "scan_index", "clusters") if k not in arrays]
    if missing:
        raise FormatError(f"{path}: missing arrays {missing}; a plane problem holds "
                          "'plane_index', 'scan_index', 'clusters' and optionally 'poses'.")
    return make_problem(arrays["plane_index"], arrays["scan_index"], arrays["clusters"],
                        T_world_scan=arrays.get("poses"), source=str(path))


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
