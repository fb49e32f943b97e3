"""Per-point association of a plane problem, kept fixed while the points or poses change.

`build_plane_problem` decides, at one set of poses, which points of which scan observe which
plane. `PointLabels` records that decision per point (the observation each point belongs to, or
-1), so the same association can be re-clustered from other versions of the same points - the
scans deskewed with another trajectory - without finding planes again:

- `pa refine` freezes the association once a round after the first `advanced.association.rounds`
  moved no pose more than `advanced.association.settle_m` (at the latest after
  `advanced.association.max_rounds`): later rounds re-deskew the points with the refined
  trajectory and re-adjust, but no point changes plane, so rounds cannot oscillate between
  associations;
- the quality check scores the initial and the refined poses on the same planes, each with the
  points deskewed by its own trajectory.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pa_cli.core.clusters import RANGE_WEIGHT_FLOOR_M, clusters_from_moments
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.planes.kernels import observation_moments


class PointLabels:
    """The observation (row of `plane_index` / `scan_index`) of every point of every scan, or -1."""

    def __init__(self, plane_index: np.ndarray, scan_index: np.ndarray, n_scans: int,
                 observation_of_point: list[np.ndarray]) -> None:
        self.plane_index = np.asarray(plane_index, dtype=np.int64)
        self.scan_index = np.asarray(scan_index, dtype=np.int64)
        self.n_scans = int(n_scans)
        self.observation_of_point = observation_of_point

    @classmethod
    def from_association(cls, landmark_of_point: Sequence[np.ndarray], n_landmarks: int,
                         kept_landmarks: np.ndarray, problem: FeatureProblem) -> PointLabels:
        """Labels that reproduce `problem` (the result of `associate_landmarks` with its
        `point_labels`, here `landmark_of_point`: the landmark id of each point of each scan,
        -1 for none, of `n_landmarks` landmarks; `kept_landmarks`: the landmark of each problem
        plane): each point is mapped to the problem's observation of its landmark's plane by its
        scan (-1 when the landmark was dropped or the scan does not observe it)."""
        # per scan, its observations by landmark: a table of n_landmarks + 1 entries (the last for landmark -1), filled
        # only at the scan's observations and emptied again, so each point costs one lookup
        landmark_of_plane = np.asarray(kept_landmarks, dtype=np.int64)
        by_scan = np.argsort(problem.scan_index, kind="stable")
        first = np.searchsorted(problem.scan_index[by_scan], np.arange(len(landmark_of_point) + 1))
        observation_of_landmark = np.full(n_landmarks + 1, -1, dtype=np.int32)
        labels = []
        for k, lm in enumerate(landmark_of_point):
            observations = by_scan[first[k]:first[k + 1]]
            landmarks = landmark_of_plane[problem.plane_index[observations]]
            observation_of_landmark[landmarks] = observations
            labels.append(observation_of_landmark[lm])
            observation_of_landmark[landmarks] = -1
        return cls(problem.plane_index, problem.scan_index, problem.n_scans, labels)

    def clusters(self, scans: Sequence[np.ndarray]) -> np.ndarray:
        """(O, 4, 4) scan-frame clusters of the labelled points of `scans` (same point order)."""
        return self._sums(scans, with_range=False)[0]

    def _sums(self, scans: Sequence[np.ndarray], with_range: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The clusters and, `with_range`, the range clusters (`pa_cli.core.clusters.range_weights`), in one
        read: per scan, the sums of each observation's labelled points in point order (numba kernel
        `observation_moments`), added to the observation's totals."""
        n_obs = len(self.plane_index)
        n_range = n_obs if with_range else 0
        sums, range_sums = np.zeros((n_obs, 10)), np.zeros((n_range, 10))
        scratch = (np.zeros((n_obs, 10)), np.zeros((n_range, 10)), np.zeros(n_obs, dtype=np.bool_),
                   np.empty(n_obs, dtype=np.int64))
        for k in range(self.n_scans):
            obs = self.observation_of_point[k]
            if not np.any(obs >= 0):
                continue
            points = np.asarray(scans[k])
            if points.dtype not in (np.float32, np.float64):
                points = points.astype(np.float64)
            observation_moments(obs, np.ascontiguousarray(points), sums, range_sums, with_range,
                                RANGE_WEIGHT_FLOOR_M**2, *scratch)
        return clusters_from_moments(sums), clusters_from_moments(range_sums) if with_range else None

    def problem(self, scans: Sequence[np.ndarray], T_world_scan: np.ndarray | None = None,
                with_range: bool = False) -> FeatureProblem:
        """The plane problem of the same association on `scans` (e.g. re-deskewed points), with the
        range clusters of the pose covariance when `with_range`."""
        C, K = self._sums(scans, with_range)
        return make_problem(self.plane_index, self.scan_index, C, n_scans=self.n_scans, T_world_scan=T_world_scan,
                            source="frozen plane association", range_clusters=K)
