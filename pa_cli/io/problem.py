"""The feature-problem file (`.npz`): the interchange format of `pa adjust` and the benchmarks.

Arrays (O observations, N scans, F features):

- `plane_index` (O,) int64: the feature (landmark) of each observation (the name predates edge
  features; it is the feature index).
- `scan_index`  (O,) int64: the scan of each observation, 0 <= scan_index < N.
- `clusters`    (O, 4, 4) float64: point cluster of the observation, the sum over the scan's
  points p (scan frame, metres) on that plane of [p; 1][p; 1]^T. Entry [3, 3] is the point count.
- `poses`       (N, 4, 4) float64, optional: T_world_scan of every scan.
- `feature_kind` (F,) uint8, optional: the kind of every feature, 0 plane, 1 edge
  (`pa_cli.problem.FEATURE_PLANE`, `FEATURE_EDGE`); absent: every feature is a plane.

The problem type and its validation are in `pa_cli.problem`.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError, InputError
from pa_cli.io.atomic import atomic_path
from pa_cli.problem import FeatureProblem, make_problem


def load_problem(path: Path | str) -> FeatureProblem:
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
                        T_world_scan=arrays.get("poses"), source=str(path),
                        feature_kind=arrays.get("feature_kind"))


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
    with atomic_path(path, force) as tmp:
        with tmp.open("wb") as f:
            np.savez_compressed(f, **arrays)
