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
(`pa_cli.evaluation.degeneracy.scan_degeneracy`) in a direction d that is mostly a translation. For each,
the scan's points are shifted along d (world frame) over +-`search_m` in steps of `step_m`, and
each shift is scored by the information the landmarks would give the scan along d: 2 (n . d)^2
summed over the points the landmarks take there (`Landmarks.assign` with the association's own
gates, only the landmarks of the plane problem, i.e. those two or more scans observe; n the
landmark's normal). Points on planes parallel to d (the ground, facades along a street) add
nothing, so the score sees only the planes that fix the scan along d. At the scan's current
position a landmark counts only when it takes at least `min_points_per_observation` of the
scan's points, as the association keeps an observation: a few stray points on some landmark
(clutter, a kerb's edge, fragments of other passes through the same place), which the
association drops, do not hold a lost scan where it is. At the shifts searched every point
counts: the landmarks a shift aligns the scan with are found afresh after the move, with the
scan's points in them, so many small ones together are a real signal. A scan is lost along d
when its information there is below the odometry factors' along d, and found at the best shift
(the smallest among equals) when the information there exceeds the odometry's (the planes would
then decide that direction); only then does the scan's pose move by it. A scan the planes hold
at its current position, however weakly, is never moved: a shallow maximum elsewhere is noise.
The caller then associates afresh.

A move is a hypothesis until the landmarks found afresh after it confirm it
(`unconfirmed_moves`): the planes of the new association must hold the scan along its shift more
firmly than it was held where it was, by the odometry factors and the planes of the association
before the move together (Gauss-Newton information along the shift, `held_information`). A search
counts every point at every shift, so on a street lined with clutter (trees, poles, parked cars)
some shift can collect a few more stray points than a weakly held scan keeps at its true position;
the planes re-detected there then hold it no better than the odometry held it before, and the
caller undoes the move.

Before the planes are found afresh, a move must not fit the scan's neighbours in time worse
(`refuted_moves`): the scans themselves, scored pairwise on all their points, judge its pose before and
after the move. Per run of consecutive moved scans, each point of the pairs the run's moves change (scan
j + 1's downsampled points onto scan j at their relative motion) is scored as a registration scores its
starts (`point_costs`) at the poses before and after the moves; a run whose points' cost rose by more than
REFUTE_STANDARD_ERRORS standard errors of that sum (the per-point changes' spread) is moved back. A shift
by one period of a repeated structure (a facade's bays, railing posts) lines the scan's planes up with the
landmarks as well as its true pose does, but not the rest of its points with its neighbours': their cost
rises by many standard errors. A scan whose registration landed in a wrong basin (an odometry that
registered it a step short) fits its neighbours better at the shift that finds it. Where the pairs cannot
tell (a run of scans the planes lost together, moved each its own way by centimetres), the change is
within its noise and the planes decide, as without this check.

The scores of all shifts of a scan come from one numba kernel (`shift_information`), equal bit
for bit to the per-shift `Landmarks.assign` scoring; the lost scans are searched in threads.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from pa_cli.core.geometry import transform_points
from pa_cli.core.problem import FeatureProblem
from pa_cli.core.voxels import outside_grid_error
from pa_cli.evaluation.degeneracy import describe, plane_information, scaled, travel_frames
from pa_cli.planes import kernels
from pa_cli.planes.detect import Landmarks
from pa_cli.refine.pair_registration import pair_point_costs


def weak_translations(problem: FeatureProblem, T_world_scan: np.ndarray, odometry_information: np.ndarray,
                      lever_arm_m: float, information: np.ndarray | None = None) -> dict[int, np.ndarray]:
    """Per scan held only by odometry in a direction that is mostly a translation: the unit world
    translation of its weakest such direction (scaled plane information below the odometry
    factors' along it, see `pa_cli.evaluation.degeneracy`). `information`: the per-scan plane information
    (`plane_information`) when already computed."""
    if information is None:
        information = plane_information(problem, T_world_scan)
    H = scaled(information, lever_arm_m)
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


# Room (m) the shift search keeps for rounding when it skips shifts that provably leave a point's
# voxel and label unchanged or its plane distance outside the gate: far above the rounding of
# world coordinates (about 1e-10 m at 1e5 m), far below a search step.
SKIP_MARGIN_M = 1e-6


def shift_information(landmarks: Landmarks, world: np.ndarray, direction: np.ndarray, along: np.ndarray,
                      shifts_m: np.ndarray, step_m: float, gates: tuple[float, float],
                      min_points: int = 1) -> np.ndarray:
    """The information (m^2/m^2) the landmarks give a scan's world points (M, 3) shifted by each
    of shifts_m (K,) (ascending, step_m apart) along the unit `direction`: per shift the sum of
    along[label] over the labels `Landmarks.assign(world + shift * direction, *gates)` gives,
    the labels fewer than `min_points` points take at that shift counted as none (-1), equal to
    it bit for bit (numba kernel `kernels.shift_information`, which evaluates the assignment
    only at the shifts where a point can reach a landmark with along > 0)."""
    leaf, near, near_start, near_count = landmarks._kernel_tables()
    sizes_m = np.array([landmarks.voxel_size_m / 2**level for level in range(len(landmarks.leaf_keys))])
    has_leaves = np.array([len(k) > 0 for k in landmarks.leaf_keys], dtype=np.bool_)
    gate_m = gates[0] * np.maximum(landmarks.sigma_m, gates[1])
    information, outside_level = kernels.shift_information(
        np.ascontiguousarray(world, dtype=np.float64), np.ascontiguousarray(direction, dtype=np.float64),
        np.ascontiguousarray(shifts_m, dtype=np.float64), float(step_m), np.ascontiguousarray(along, dtype=np.float64),
        int(min_points), SKIP_MARGIN_M, sizes_m, has_leaves, *leaf, *near, near_start, near_count,
        np.ascontiguousarray(landmarks.near_landmark, dtype=np.int64),
        np.ascontiguousarray(landmarks.centroid_world, dtype=np.float64),
        np.ascontiguousarray(landmarks.normal_world, dtype=np.float64), np.ascontiguousarray(gate_m, dtype=np.float64),
        float(np.cos(np.deg2rad(landmarks.max_normal_angle_deg))))
    if outside_level >= 0:
        raise outside_grid_error(float(sizes_m[outside_level]), "scene.plane_voxel_m")
    return information


def _lost_scan_information(landmarks: Landmarks, world: np.ndarray, direction: np.ndarray, along: np.ndarray,
                           odometry: float, shifts_m: np.ndarray, step_m: float, gates: tuple[float, float],
                           min_points: int) -> tuple[float, np.ndarray | None]:
    """(information at the current position, counting the landmarks that take at least
    `min_points` of its points, and per shift, counting every point; None when the planes hold the
    scan here: not lost, not searched)."""
    here = float(shift_information(landmarks, world, direction, along, np.zeros(1), step_m, gates, min_points)[0])
    if not here < odometry:
        return here, None
    information = shift_information(landmarks, world, direction, along, shifts_m, step_m, gates)
    information[shifts_m == 0.0] = here
    return here, information


def held_information(problem: FeatureProblem, T_world_scan: np.ndarray, scans: Sequence[int],
                     directions: np.ndarray) -> np.ndarray:
    """(S,) the features' Gauss-Newton information (m^2/m^2) for each scan moving along its unit
    world direction (the translation block of its `plane_information`), at poses T_world_scan."""
    translation = plane_information(problem, T_world_scan)[np.asarray(scans, dtype=np.int64), 3:, 3:]
    return np.einsum("si,sij,sj->s", directions, translation, directions)


def unconfirmed_moves(problem_before: FeatureProblem, T_before: np.ndarray, problem: FeatureProblem,
                      T_world_scan: np.ndarray, moved: list[dict[str, Any]]) -> list[int]:
    """The scans of `moved`, the records of `relocalise_lost_scans` (poses T_before ->
    T_world_scan), whose moves the planes found after them do not confirm. A move stands when the
    features of `problem` (associated at T_world_scan) hold the scan along its shift more firmly
    than it was held where it was: more information (`held_information`) than the record's
    `odometry_information` plus the information the features of `problem_before` (associated at
    T_before) gave it there. Each record gets `held_before` and `held_after`, those two plane
    informations (m^2/m^2)."""
    if not moved:
        return []
    scans = [m["scan"] for m in moved]
    shifts = T_world_scan[scans, :3, 3] - T_before[scans, :3, 3]
    directions = shifts / np.linalg.norm(shifts, axis=1, keepdims=True)
    before = held_information(problem_before, T_before, scans, directions)
    after = held_information(problem, T_world_scan, scans, directions)
    for m, held_before, held_after in zip(moved, before, after, strict=True):
        m["held_before"], m["held_after"] = float(held_before), float(held_after)
    return [m["scan"] for m in moved if not m["held_after"] > m["odometry_information"] + m["held_before"]]


REFUTE_STANDARD_ERRORS = 3.0
"""A run of moves is refuted when its pairs' points fit worse by more than this many standard errors of the
sum of their cost changes: the rule by which the verdict calls a class of surfaces blurrier."""


def refuted_moves(points: Sequence[np.ndarray], T_before: np.ndarray, T_moved: np.ndarray, moved: list[dict[str, Any]],
                  voxel_m: float, max_correspondence_m: float, threads: int = 1) -> list[int]:
    """The scans of `moved` (records of `relocalise_lost_scans`; poses T_before -> T_moved, (N, 4, 4)) whose
    moves their neighbours in time refute: per run of consecutive moved scans, the `pair_point_costs`
    (downsampled to `voxel_m`, partners within `max_correspondence_m`) of the pairs from the scan before the run
    to the scan after it rose, summed over their points, by more than REFUTE_STANDARD_ERRORS standard errors
    (sqrt(M) times the standard deviation of the M per-point changes). `points[k]`: scan k's points (M, 3), its
    frame, m. Each record gets its run's `pair_cost_before_m2`, `pair_cost_after_m2` and
    `pair_cost_change_standard_errors`."""
    scans = sorted(m["scan"] for m in moved)
    runs: list[list[int]] = []
    for j in scans:
        if runs and j == runs[-1][-1] + 1:
            runs[-1].append(j)
        else:
            runs.append([j])
    n_scans = len(T_before)
    pairs_of = [[j for j in range(run[0] - 1, run[-1] + 1) if 0 <= j < n_scans - 1] for run in runs]
    pairs = sorted({j for run_pairs in pairs_of for j in run_pairs})
    costs = dict(zip(pairs, pair_point_costs(points, (T_before, T_moved), pairs, voxel_m, max_correspondence_m,
                                             threads), strict=True))
    refuted, judged = [], {}
    for run, run_pairs in zip(runs, pairs_of, strict=True):
        both = np.hstack([costs[j] for j in run_pairs]) if run_pairs else np.zeros((2, 0))
        change = both[1] - both[0]
        standard_error = float(np.sqrt(len(change)) * np.std(change)) if len(change) > 1 else 0.0
        rise = float(change.sum())
        sigmas = rise / standard_error if standard_error > 0 else 0.0
        judged.update({j: (float(both[0].sum()), float(both[1].sum()), sigmas) for j in run})
        if rise > REFUTE_STANDARD_ERRORS * standard_error:
            refuted += run
    for m in moved:
        m["pair_cost_before_m2"], m["pair_cost_after_m2"], m["pair_cost_change_standard_errors"] = judged[m["scan"]]
    return refuted


def relocalise_lost_scans(points: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: Landmarks,
                          kept_landmarks: np.ndarray, problem: FeatureProblem, odometry_information: np.ndarray,
                          lever_arm_m: float, search_m: float, step_m: float, outlier_sigma: float,
                          sigma_floor_m: float, min_points_per_observation: int,
                          threads: int = 1) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """(T_world_scan with the lost scans moved, one record per moved scan).

    `points[k]`: scan k's (M, 3) points in its frame (deskewed as for the association);
    `landmarks`, `kept_landmarks`: the association's `Landmarks` and the landmark id of each
    problem plane; `odometry_information` (N, 6, 6): the odometry factors' diagonal Hessian blocks;
    `min_points_per_observation`: the fewest points of a scan on a landmark that count at its
    current position (the association's `advanced.planes.min_points_per_observation`).
    The scans are searched independently, `threads` at a time (the kernel releases the
    GIL); the points are read in the calling thread, at most 2 * `threads` searches ahead.
    """
    weak = weak_translations(problem, T_world_scan, odometry_information, lever_arm_m)
    searches = [(j, direction, float(direction @ odometry_information[j, 3:, 3:] @ direction))
                for j, direction in weak.items()]
    T_out = np.array(T_world_scan, dtype=np.float64, copy=True)
    if not searches:
        return T_out, []
    landmarks.prepare()
    in_problem = np.zeros(landmarks.n_landmarks + 1, dtype=bool)
    in_problem[np.asarray(kept_landmarks, dtype=np.int64)] = True
    normals = np.vstack([landmarks.normal_world, np.zeros((1, 3))])  # label -1 takes the trailing row
    n_steps = int(np.floor(search_m / step_m))
    shifts_m = np.arange(-n_steps, n_steps + 1) * step_m
    by_size = np.argsort(np.abs(shifts_m), kind="stable")  # among equal scores the smallest shift wins
    frames = travel_frames(T_world_scan)
    gates = (outlier_sigma, sigma_floor_m)
    moved = []

    def finish(j: int, direction: np.ndarray, odometry: float, search: Future) -> None:
        here, information = search.result()
        if information is None:  # not lost: the planes hold it here (the search is skipped)
            return
        best = by_size[np.argmax(information[by_size])]
        if not odometry < information[best]:  # not found anywhere
            return
        T_out[j, :3, 3] += shifts_m[best] * direction
        moved.append({"scan": int(j), "shift_m": float(shifts_m[best]),
                      "direction": describe(np.r_[np.zeros(3), direction], frames[j]),
                      "information_before": here, "information_after": float(information[best]),
                      "odometry_information": odometry})

    with ThreadPoolExecutor(max_workers=max(threads, 1)) as pool:
        pending: deque = deque()
        for j, direction, odometry in searches:
            world = transform_points(T_world_scan[j], np.asarray(points[j], dtype=np.float64))
            along = np.where(in_problem, 2.0 * (normals @ direction) ** 2, 0.0)  # per landmark, m^2/m^2 per point
            pending.append((j, direction, odometry, pool.submit(
                _lost_scan_information, landmarks, world, direction, along, odometry, shifts_m, step_m, gates,
                min_points_per_observation)))
            if len(pending) >= 2 * max(threads, 1):
                finish(*pending.popleft())
        while pending:
            finish(*pending.popleft())
    return T_out, moved
