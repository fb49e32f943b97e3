"""The feature problem: observations of features by scans, as point clusters in the scan frame.

This is what the solvers in `pa_cli.adjust` consume and what `pa_cli.planes` produces; the solver
never sees points: clusters are sufficient statistics (BALM2, Theorems 1 and 2, see
`pa_cli.core.clusters`). Each feature has a kind (`feature_kind`): planes (0) now, edges (1) next.
The `.npz` file format is in `pa_cli.io.problem`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from pa_cli.errors import FormatError

log = logging.getLogger(__name__)

SYMMETRY_RTOL = 1e-9  # relative asymmetry a cluster (a sum of outer products) may show from rounding
FEATURE_PLANE = 0
FEATURE_EDGE = 1
FEATURE_KINDS = (FEATURE_PLANE, FEATURE_EDGE)


@dataclass
class FeatureProblem:
    """Observations of features (planes, later edges) by scans, as point clusters in the scan frame.

    `plane_index` is the feature index of each observation (the name of the `.npz` key); features
    are numbered 0..n_planes-1 and `feature_kind[i]` says what feature i is (`FEATURE_PLANE`,
    `FEATURE_EDGE`). `range_clusters`, when the association produced them, are the observations'
    clusters with every point weighted by 1/|p|^2 (`pa_cli.core.clusters.range_weights`); only the pose
    covariance reads them, and a problem built from a subset of the observations leaves them out.
    """

    plane_index: np.ndarray  # (O,) int64, features numbered 0..n_planes-1
    scan_index: np.ndarray  # (O,) int64, scans numbered 0..n_scans-1
    clusters: np.ndarray  # (O, 4, 4) float64
    n_scans: int
    T_world_scan: np.ndarray | None = None  # (N, 4, 4)
    n_dropped_planes: int = field(default=0, compare=False)
    feature_kind: np.ndarray | None = None  # (n_planes,) uint8; None: every feature is a plane
    # (O, 4, 4) float64 or None: per observation sum [p; 1][p; 1]^T / |p|^2 (scan frame, sensor at the
    # origin), the range noise model of the pose covariance (`pa_cli.adjust.covariance`)
    range_clusters: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.feature_kind is None:
            self.feature_kind = np.full(self.n_planes, FEATURE_PLANE, dtype=np.uint8)

    @property
    def n_planes(self) -> int:
        """Number of features (planes and, later, edges)."""
        return int(self.plane_index.max()) + 1 if len(self.plane_index) else 0

    @property
    def n_observations(self) -> int:
        return len(self.plane_index)

    @property
    def n_points(self) -> int:
        return int(round(self.clusters[:, 3, 3].sum()))


def make_problem(plane_index: np.ndarray, scan_index: np.ndarray, clusters: np.ndarray,
                 n_scans: int | None = None, T_world_scan: np.ndarray | None = None,
                 source: str = "plane problem", feature_kind: np.ndarray | None = None,
                 range_clusters: np.ndarray | None = None) -> FeatureProblem:
    """Validate arrays and build a `FeatureProblem`.

    `feature_kind` (F,) gives the kind of every feature index 0..F-1 used by `plane_index`
    (None: all planes). `range_clusters` (O, 4, 4), optional, are kept, dropped and reordered with
    the observations. Features seen by fewer than two scans are dropped (they carry no
    constraint) and the remaining ones are renumbered 0..P-1 in order of their original index.
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
    clusters = _finite_matrices(clusters, "clusters", n_obs, source)
    asym = _relative_asymmetry(clusters, 1.0)
    if n_obs and asym.max() > SYMMETRY_RTOL:
        bad = int(np.argmax(asym))
        raise FormatError(f"{source}: cluster {bad} is not symmetric (relative asymmetry "
                          f"{asym[bad]:.3g}); a cluster is a sum of [p;1][p;1]^T.")
    if n_obs and np.any(clusters[:, 3, 3] < 1):
        bad = int(np.argmin(clusters[:, 3, 3]))
        raise FormatError(f"{source}: cluster {bad} has point count {clusters[bad, 3, 3]:g} "
                          "(entry [3, 3]); every observation needs at least one point.")
    range_clusters = _check_range_clusters(range_clusters, n_obs, source)
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
    feature_kind = _check_feature_kind(feature_kind, plane_index, source)
    if n_obs and scan_index.max() >= n_scans:
        raise FormatError(f"{source}: 'scan_index' refers to scan {int(scan_index.max())} but "
                          f"there are only {n_scans} poses.")

    # Drop planes seen by fewer than two distinct scans; renumber the rest. One key per observation
    # orders them by (plane, scan): a problem already in that order (a saved one) is checked in one pass.
    plane_index = plane_index.astype(np.int64)
    scan_index = scan_index.astype(np.int64)
    key = plane_index * max(int(n_scans), 1) + scan_index
    in_order = bool(np.all(key[1:] > key[:-1]))
    order = np.arange(n_obs) if in_order else np.argsort(key, kind="stable")
    n_duplicates = 0 if in_order else int(np.count_nonzero(np.diff(key[order]) == 0))
    if n_duplicates:
        raise FormatError(f"{source}: {n_duplicates} duplicate (plane, scan) observations; "
                          "merge the clusters of one plane in one scan into one observation.")
    scans_per_plane = np.bincount(plane_index)
    kept_plane = scans_per_plane >= 2
    keep_planes = np.flatnonzero(kept_plane)
    n_dropped = int(np.count_nonzero(scans_per_plane)) - len(keep_planes)
    if n_dropped:
        log.info("%s: dropped %d planes seen by fewer than two scans.", source, n_dropped)
    order = order[kept_plane[plane_index[order]]]  # the kept observations, by (plane, scan)
    unchanged = len(order) == n_obs and in_order  # nothing dropped or moved: the arrays as they are

    def arranged(values: np.ndarray) -> np.ndarray:
        return values if unchanged else values[order]

    new_plane_index = np.cumsum(kept_plane) - 1
    return FeatureProblem(
        plane_index=new_plane_index[plane_index[order]].astype(np.int64),
        scan_index=arranged(scan_index),
        clusters=arranged(clusters),
        n_scans=int(n_scans),
        T_world_scan=T_world_scan,
        n_dropped_planes=n_dropped,
        feature_kind=None if feature_kind is None else feature_kind[keep_planes],
        range_clusters=None if range_clusters is None else arranged(range_clusters),
    )


def _finite_matrices(values: np.ndarray, name: str, n_obs: int, source: str) -> np.ndarray:
    """`values` as float64 after checking the shape (n_obs, 4, 4) and that every entry is finite."""
    if values.shape != (n_obs, 4, 4):
        raise FormatError(f"{source}: '{name}' must have shape ({n_obs}, 4, 4), found {values.shape}.")
    values = values.astype(np.float64)
    if not np.all(np.isfinite(values)):
        raise FormatError(f"{source}: '{name}' contains NaN or inf values.")
    return values


_UPPER = np.flatnonzero(np.triu(np.ones((4, 4)), 1))  # flat positions of the entries above the diagonal
_LOWER = _UPPER % 4 * 4 + _UPPER // 4  # their mirror images, in the same order


def _relative_asymmetry(C: np.ndarray, floor: float) -> np.ndarray:
    """(O,) largest |C - C^T| of each (4, 4) matrix over its largest |entry| (at least `floor`)."""
    flat = C.reshape(len(C), 16)
    scale = np.maximum(np.abs(flat).max(axis=1, initial=0.0), floor)
    return np.abs(flat[:, _UPPER] - flat[:, _LOWER]).max(axis=1, initial=0.0) / scale


def _check_range_clusters(range_clusters: np.ndarray | None, n_obs: int, source: str) -> np.ndarray | None:
    """The validated (O, 4, 4) float64 range clusters: finite, symmetric, positive weight sums."""
    if range_clusters is None:
        return None
    K = _finite_matrices(np.asarray(range_clusters), "range_clusters", n_obs, source)
    asym = _relative_asymmetry(K, np.finfo(np.float64).tiny)
    if n_obs and (asym.max() > SYMMETRY_RTOL or K[:, 3, 3].min() <= 0.0):
        bad = int(np.argmax((asym > SYMMETRY_RTOL) | (K[:, 3, 3] <= 0.0)))
        raise FormatError(f"{source}: range cluster {bad} is not a sum of [p; 1][p; 1]^T / |p|^2 (asymmetry "
                          f"{asym[bad]:.3g}, weight sum {K[bad, 3, 3]:g}); rebuild the problem (pa refine "
                          "--save-problem) or drop the 'range_clusters' array.")
    return K


def _check_feature_kind(feature_kind: np.ndarray | None, plane_index: np.ndarray, source: str) -> np.ndarray | None:
    """The validated (F,) uint8 feature kinds, F covering every index of `plane_index`."""
    if feature_kind is None:
        return None
    kind = np.asarray(feature_kind)
    if kind.ndim != 1 or not np.issubdtype(kind.dtype, np.integer):
        raise FormatError(f"{source}: 'feature_kind' must be a 1-D integer array (one entry per feature), "
                          f"found shape {kind.shape} dtype {kind.dtype}.")
    n_features = int(plane_index.max()) + 1 if len(plane_index) else 0
    if len(kind) < n_features:
        raise FormatError(f"{source}: 'feature_kind' has {len(kind)} entries but 'plane_index' refers "
                          f"to feature {n_features - 1}; give one kind per feature.")
    bad = ~np.isin(kind, FEATURE_KINDS)
    if np.any(bad):
        raise FormatError(f"{source}: 'feature_kind' holds {int(kind[np.argmax(bad)])}; expected "
                          f"{FEATURE_PLANE} (plane) or {FEATURE_EDGE} (edge).")
    return kind.astype(np.uint8)
