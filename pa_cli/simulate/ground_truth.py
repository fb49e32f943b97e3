"""Ground-truth plane problems of simulated sequences (exact association by true plane label)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pa_cli.core.clusters import range_weights
from pa_cli.core.point_moments import clusters_by_label, weighted_clusters_by_label
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import read_scan
from pa_cli.io.trajectory import read_trajectory
from pa_cli.simulate.raycast import SimulatedSequence

log = logging.getLogger(__name__)


def build_problem_from_labels(source: Path | str | SimulatedSequence, min_points: int = 10
                              ) -> FeatureProblem:
    """Exact-association plane problem of a simulated sequence, with the GT poses.

    `source` is a `pa simulate` output folder or a `SimulatedSequence`. One observation per
    (true plane label, scan) with at least `min_points` points (points labelled -1 - clutter,
    vegetation, curved cars, a shaped road, mixed pixels - belong to none); the cluster is built from the
    points in the sensor frame as stored, and so is its range cluster (`range_clusters`, the
    points weighted by 1/|p|^2). With motion distortion the stored points are raw
    (not deskewed), so such a problem is NOT exactly consistent with the GT poses.
    """
    plane_parts, scan_parts, cluster_parts, range_parts = [], [], [], []

    def observe(k: int, points: np.ndarray, labels: np.ndarray) -> None:
        lab, cl = clusters_by_label(points, labels, min_points)
        hit = np.isin(labels, lab)
        range_parts.append(weighted_clusters_by_label(points[hit], np.searchsorted(lab, labels[hit]), len(lab),
                                                      range_weights(points[hit])))
        plane_parts.append(lab)
        scan_parts.append(np.full(len(lab), k, np.int64))
        cluster_parts.append(cl)

    if isinstance(source, SimulatedSequence):
        T = source.T_world_scan
        if source.options.motion_distortion:
            log.warning("simulated sequence has motion distortion: clusters use raw points.")
        for k, scan in enumerate(source.scans):
            observe(k, scan.points_scan, scan.labels)
        name = "simulated sequence"
    else:
        folder = Path(source)
        if not folder.is_dir():
            raise InputError(f"{folder}: not a folder; expected the OUT_DIR of `pa simulate`.")
        T = read_trajectory(folder / "gt_poses_kitti.txt").T_world_scan
        meta_path = folder / "meta.json"
        if meta_path.exists() and json.loads(meta_path.read_text()).get("options", {}).get(
                "motion_distortion"):
            log.warning("%s has motion distortion: clusters use raw (not deskewed) points.", folder)
        for k in range(len(T)):
            pcd = folder / "scans" / f"{k:06d}.pcd"
            lab_path = folder / "labels" / f"{k:06d}.npy"
            if not pcd.exists() or not lab_path.exists():
                raise InputError(f"{folder}: missing {pcd.name} or labels/{lab_path.name} for pose {k}; "
                                 "expected one scan and one label file per GT pose.")
            points = read_scan(pcd).points_scan
            labels = np.load(lab_path, allow_pickle=False)
            if labels.shape != (len(points),):
                raise FormatError(f"{lab_path}: {labels.shape[0] if labels.ndim else 0} labels for "
                                  f"{len(points)} points in {pcd.name}; expected one label per point.")
            observe(k, points, labels)
        name = str(folder)
    return make_problem(np.concatenate(plane_parts), np.concatenate(scan_parts),
                        np.concatenate(cluster_parts), n_scans=len(T), T_world_scan=T, source=name,
                        range_clusters=np.concatenate(range_parts))
