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
(`pa_cli.degeneracy.scan_degeneracy`) in a direction d that is mostly a translation. For each,
the scan's points are shifted along d (world frame) over +-`search_m` in steps of `step_m`, and
each shift is scored by the information the landmarks would give the scan along d: 2 (n . d)^2
summed over the points the landmarks take there (`Landmarks.assign` with the association's own
gates, only the landmarks of the plane problem, i.e. those two or more scans observe; n the
landmark's normal). Points on planes parallel to d (the ground, facades along a street) add
nothing, so the score sees only the planes that fix the scan along d. A scan is lost along d
when its information there is below the odometry factors' along d, and found at the best shift
(the smallest among equals) when the information there exceeds the odometry's (the planes would
then decide that direction); only then does the scan's pose move by it. A scan the planes hold
at its current position, however weakly, is never moved: a shallow maximum elsewhere is noise.
The caller then associates afresh, and the adjustment takes it from there.
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


def _information(landmarks: Any, world: np.ndarray, direction: np.ndarray, along: np.ndarray, shift_m: float,
                 gates: tuple[float, float]) -> float:
    """The information (m^2/m^2) the landmarks give a scan's world points shifted by shift_m along direction."""
    labels, _ = landmarks.assign(world + shift_m * direction, *gates)
    return float(along[labels].sum())


def relocalise_lost_scans(points: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: Any,
                          kept_landmarks: np.ndarray, problem: FeatureProblem, odometry_information: np.ndarray,
                          lever_arm_m: float, search_m: float, step_m: float, outlier_sigma: float,
                          sigma_floor_m: float) -> tuple[np.ndarray, list[dict[str, Any]]]:
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
    normals = np.vstack([landmarks.normal_world, np.zeros((1, 3))])  # label -1 takes the trailing row
    n_steps = int(np.floor(search_m / step_m))
    shifts_m = np.arange(-n_steps, n_steps + 1) * step_m
    by_size = np.argsort(np.abs(shifts_m), kind="stable")  # among equal scores the smallest shift wins
    frames = travel_frames(T_world_scan)
    moved = []
    for j, direction in weak.items():
        world = transform_points(T_out[j], np.asarray(points[j], dtype=np.float64))
        along = np.where(in_problem, 2.0 * (normals @ direction) ** 2, 0.0)  # per landmark, m^2/m^2 per point
        gates = (outlier_sigma, sigma_floor_m)
        odometry = float(direction @ odometry_information[j, 3:, 3:] @ direction)
        here = _information(landmarks, world, direction, along, 0.0, gates)
        if not here < odometry:  # not lost: the planes hold it here (the search is skipped)
            continue
        information = np.array([here if s == 0.0 else _information(landmarks, world, direction, along, s, gates)
                                for s in shifts_m])
        best = by_size[np.argmax(information[by_size])]
        if not odometry < information[best]:  # not found anywhere
            continue
        T_out[j, :3, 3] += shifts_m[best] * direction
        moved.append({"scan": int(j), "shift_m": float(shifts_m[best]),
                      "direction": describe(np.r_[np.zeros(3), direction], frames[j]),
                      "information_before": float(here), "information_after": float(information[best]),
                      "odometry_information": odometry})
    return T_out, moved
