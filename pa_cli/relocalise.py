"""Scans the planes lost at their initial pose: a search along their weak direction.

Plane landmarks are detected and associated at the current poses. A scan whose initial pose is
off by more than the landmarks' gates (a few centimetres) in a direction the rest of the
sequence fixes loses exactly the points that would correct it: they are trimmed as outliers of
the planes the other scans define, its plane information in that direction is (nearly) zero,
and the odometry factors, which hold the wrong relative motion, keep it where it is, round after
round. Odometry typically breaks this way at the start of a sequence (a constant-velocity model
starting from rest registers the first scans short of their true motion) and along featureless
stretches.

`relocalise_lost_scans` finds such scans: those held only by odometry
(`pa_cli.degeneracy.scan_degeneracy`) in a direction that is mostly a translation. For each,
the scan's points are shifted along that direction (world frame) over +-`search_m` in steps of
`step_m`, and each shift is scored by the points the landmarks take (`Landmarks.assign` with the
association's own gates, counting only the landmarks of the plane problem, i.e. those two or more
scans observe). The shift with the most points wins (the smallest shift among equals) when it
gains at least `min_gain_points` points over the current position (one observation's worth,
`planes.min_points_per_observation`); the scan's pose moves by it. The caller then associates
afresh, and the adjustment takes it from there.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pa_cli.degeneracy import describe, plane_information, scaled, travel_frames
from pa_cli.geometry import transform_points
from pa_cli.problem import FeatureProblem


def weak_translations(problem: FeatureProblem, T_world_scan: np.ndarray, odometry_information: np.ndarray,
                      lever_arm_m: float) -> dict[int, np.ndarray]:
    """Per scan held only by odometry in a direction that is mostly a translation: the unit world
    translation of its weakest such direction (scaled plane information below the odometry
    factors' along it, see `pa_cli.degeneracy`)."""
    H = scaled(plane_information(problem, T_world_scan), lever_arm_m)
    lam, vec = np.linalg.eigh(H)
    out: dict[int, np.ndarray] = {}
    for j in range(problem.n_scans):
        O = scaled(odometry_information[j], lever_arm_m)
        odometry = np.einsum("ik,ij,jk->k", vec[j], O, vec[j])
        for k in np.flatnonzero(lam[j] < odometry):  # ascending eigenvalues: weakest first
            rot, trans = vec[j, :3, k], vec[j, 3:, k]
            if np.linalg.norm(trans) >= np.linalg.norm(rot):
                out[j] = trans / np.linalg.norm(trans)
                break
    return out


def relocalise_lost_scans(points: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: Any,
                          kept_landmarks: np.ndarray, problem: FeatureProblem, odometry_information: np.ndarray,
                          lever_arm_m: float, search_m: float, step_m: float, outlier_sigma: float,
                          sigma_floor_m: float, min_gain_points: int) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """(T_world_scan with the lost scans moved, one record per moved scan).

    `points[k]`: scan k's (M, 3) points in its frame (deskewed as for the association);
    `landmarks`, `kept_landmarks`: the association's `Landmarks` and the landmark id of each
    problem plane; `odometry_information` (N, 6, 6): the odometry factors' diagonal Hessian blocks.
    """
    weak = weak_translations(problem, T_world_scan, odometry_information, lever_arm_m)
    T_out = np.array(T_world_scan, dtype=np.float64, copy=True)
    if not weak:
        return T_out, []
    landmarks.prepare()
    in_problem = np.zeros(landmarks.n_landmarks + 1, dtype=bool)
    in_problem[np.asarray(kept_landmarks, dtype=np.int64)] = True
    n_steps = int(np.floor(search_m / step_m))
    shifts_m = np.arange(-n_steps, n_steps + 1) * step_m
    by_size = np.argsort(np.abs(shifts_m), kind="stable")  # among equal counts the smallest shift wins
    frames = travel_frames(T_world_scan)
    moved = []
    for j, direction in weak.items():
        world = transform_points(T_out[j], np.asarray(points[j], dtype=np.float64))
        counts = np.empty(len(shifts_m), dtype=np.int64)
        for i, s in enumerate(shifts_m):
            labels, _ = landmarks.assign(world + s * direction, outlier_sigma, sigma_floor_m)
            counts[i] = int(in_problem[labels].sum())  # label -1 indexes the trailing False
        best = by_size[np.argmax(counts[by_size])]
        here = counts[n_steps]
        if counts[best] - here < min_gain_points:
            continue
        T_out[j, :3, 3] += shifts_m[best] * direction
        moved.append({"scan": int(j), "shift_m": float(shifts_m[best]),
                      "direction": describe(np.r_[np.zeros(3), direction], frames[j]),
                      "points_on_landmarks_before": int(here), "points_on_landmarks_after": int(counts[best])})
    return T_out, moved
