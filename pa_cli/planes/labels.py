"""Per-point association of a plane problem, kept fixed while the points or poses change.

`build_plane_problem` decides, at one set of poses, which points of which scan observe which
plane. `PointLabels` records that decision per point (the observation each point belongs to, or
-1), so the same association can be re-clustered from other versions of the same points - the
scans deskewed with another trajectory - without finding planes again:

- `pa refine` freezes the association after `refine.association_rounds` rounds: later rounds
  re-deskew the points with the refined trajectory and re-adjust, but no point changes plane,
  so rounds cannot oscillate between associations;
- the quality check scores the initial and the refined poses on the same planes, each with the
  points deskewed by its own trajectory.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pa_cli.config import PlanesConfig
from pa_cli.geometry import transform_points
from pa_cli.planes.detect import Landmarks
from pa_cli.problem import FeatureProblem, make_problem

# the 10 distinct entries of the symmetric 4x4 cluster sum [p;1][p;1]^T
_ROWS = np.array([0, 0, 0, 1, 1, 2, 0, 1, 2, 3])
_COLS = np.array([0, 1, 2, 1, 2, 2, 3, 3, 3, 3])


class PointLabels:
    """The observation (row of `plane_index` / `scan_index`) of every point of every scan, or -1."""

    def __init__(self, plane_index: np.ndarray, scan_index: np.ndarray, n_scans: int,
                 observation_of_point: list[np.ndarray]) -> None:
        self.plane_index = np.asarray(plane_index, dtype=np.int64)
        self.scan_index = np.asarray(scan_index, dtype=np.int64)
        self.n_scans = int(n_scans)
        self.observation_of_point = observation_of_point

    @classmethod
    def from_landmarks(cls, scans: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: Landmarks,
                       kept_landmarks: np.ndarray, problem: FeatureProblem, config: PlanesConfig) -> PointLabels:
        """Labels that reproduce `problem` (the result of `associate_landmarks` with these
        landmarks, their kept ids and these scans at these poses): each point gets the landmark
        `landmarks.assign` gives it, mapped to the problem's observation of that plane by that
        scan (-1 when the landmark was dropped or the scan does not observe it)."""
        plane_of_landmark = np.full(landmarks.n_landmarks + 1, -1, dtype=np.int64)
        plane_of_landmark[np.asarray(kept_landmarks, dtype=np.int64)] = np.arange(len(kept_landmarks))
        # observation of (scan, plane) by binary search in the sorted keys scan * P + plane (memory
        # linear in observations, not scans x planes)
        n_planes = max(problem.n_planes, 1)
        keys = problem.scan_index * n_planes + problem.plane_index
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        labels = []
        for k in range(len(scans)):
            points = np.asarray(scans[k], dtype=np.float64)
            lm, _ = landmarks.assign(transform_points(T_world_scan[k], points), config.outlier_sigma,
                                     config.outlier_sigma_floor_m)
            plane = plane_of_landmark[lm]  # lm == -1 picks the trailing -1
            query = k * n_planes + np.maximum(plane, 0)
            at = np.minimum(np.searchsorted(sorted_keys, query), max(len(sorted_keys) - 1, 0))
            found = (plane >= 0) & (sorted_keys[at] == query) if len(sorted_keys) else np.zeros(len(plane), bool)
            obs = np.where(found, order[at] if len(order) else -1, -1)
            labels.append(obs.astype(np.int32))
        return cls(problem.plane_index, problem.scan_index, problem.n_scans, labels)

    def clusters(self, scans: Sequence[np.ndarray]) -> np.ndarray:
        """(O, 4, 4) scan-frame clusters of the labelled points of `scans` (same point order)."""
        n_obs = len(self.plane_index)
        sums = np.zeros((n_obs, 10))
        for k in range(self.n_scans):
            obs = self.observation_of_point[k]
            mask = obs >= 0
            if not np.any(mask):
                continue
            p = np.asarray(scans[k], dtype=np.float64)[mask]
            ph = np.hstack([p, np.ones((len(p), 1))])
            # the scan's own observations only: work linear in its points, not in all observations
            seen, local = np.unique(obs[mask], return_inverse=True)
            for e in range(10):
                sums[seen, e] += np.bincount(local, weights=ph[:, _ROWS[e]] * ph[:, _COLS[e]], minlength=len(seen))
        C = np.zeros((n_obs, 4, 4))
        C[:, _ROWS, _COLS] = sums
        C[:, _COLS, _ROWS] = sums
        return C

    def problem(self, scans: Sequence[np.ndarray], T_world_scan: np.ndarray | None = None) -> FeatureProblem:
        """The plane problem of the same association on `scans` (e.g. re-deskewed points)."""
        return make_problem(self.plane_index, self.scan_index, self.clusters(scans), n_scans=self.n_scans,
                            T_world_scan=T_world_scan, source="frozen plane association")
