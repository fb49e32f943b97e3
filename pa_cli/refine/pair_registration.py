"""Registration of consecutive scans: each pair's relative motion by GICP and the information it carries.

Every scan's points are downsampled to a voxel and given point covariances and normals from their
neighbours (small_gicp: generalized ICP, Segal et al. 2009); scan j+1 is registered onto scan j from
the pair's relative motion at the poses given, so the registration sees every surface of the two
scans (walls, poles, trunks, kerbs), not only the planes the adjustment associates.

The information a registration carries about its relative motion Z = (R, t) (scan j+1 in scan j's
frame) is the Gauss-Newton Hessian of its point-to-plane cost, sum_i d_i^2 over the source points q_i
whose nearest target point lies within the correspondence distance, d_i = n_i . (R q_i + t - p_i)
with the target point's normal n_i. It is in the coordinates of the odometry factors' residual
(`pa_cli.adjust.odometry_factors`): a rotation perturbation on the right of R (scan j+1's frame,
rad) and a translation in scan j's frame (m), d d_i / d rot = q_i x (R^T n_i), d d_i / d t = n_i,
so I = 2 sum_i a_i a_i^T (m^2 per rad^2 and per m^2, the plane information's unit: a point on a plane
square to a direction adds 2 to it). Points are counted after the downsampling, so the information
is a lower bound of what the full scans carry.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pa_cli.core.geometry import rigid_inverse
from pa_cli.planes.windowed import ScanRef, read_scans
from pa_cli.runtime.distributed import current_execution

COVARIANCE_NEIGHBOURS = 10  # point covariances and normals from this many neighbours (small_gicp's default)
MAX_ITERATIONS = 50
# Iterations stop when one turns the registration less than 1e-4 rad (1 mm at 10 m) and moves it less
# than 0.1 mm: far below the point noise, so the result does not depend on where in its basin it started
# (small_gicp's defaults, 0.1 deg and 1 mm, stop at the start). At that precision a few pairs cycle
# between correspondence sets 0.1 mm apart; a registration counts as converged when, from its result, it
# converges at small_gicp's default tolerances.
ROTATION_EPSILON_RAD = 1e-4
TRANSLATION_EPSILON_M = 1e-4
RESULT_BYTES_PER_PAIR = 400  # a pair's result on its way back from a worker: a 4x4 and a 6x6 of float64


@dataclass(frozen=True)
class PairRegistrations:
    """The registrations of every consecutive pair (j, j+1) of a sequence of N scans."""

    T_prev_next: np.ndarray  # (N-1, 4, 4): scan j+1 in scan j's frame, as registered
    information: np.ndarray  # (N-1, 6, 6): rotation (right of R, rad) then translation (scan j's frame, m)
    converged: np.ndarray  # (N-1,) bool: the registration converged (see ROTATION_EPSILON_RAD)


def register_consecutive(points_scan: Sequence[np.ndarray], T_world_scan: np.ndarray, voxel_m: float,
                         max_correspondence_m: float, progress: Callable[[int, int], None] | None = None,
                         scans: ScanRef | None = None, window_scans: int = 100) -> PairRegistrations:
    """Register every scan j+1 onto scan j (`points_scan`: N arrays (M, 3), sensor frames, m), starting
    from the relative motions of `T_world_scan` (N, 4, 4). Reads the scans once, two at a time.

    With `scans` (where the scans are) the pairs are window tasks of `window_scans` pairs on
    `current_execution()`: each worker reads its window's scans from the source itself (the scan at
    a window's end is read by the next window too) and `points_scan` is not read. A registration
    depends only on its two scans and its start, so the result is the same as in this process."""
    T_start = rigid_inverse(T_world_scan[:-1]) @ T_world_scan[1:]
    n_pairs = len(T_start)
    if scans is None or n_pairs == 0:
        return _register(points_scan, T_start, voxel_m, max_correspondence_m, progress)
    tasks = (PairWindow(scans, first, min(first + window_scans, n_pairs) + 1, T_start[first:first + window_scans],
                        voxel_m, max_correspondence_m) for first in range(0, n_pairs, window_scans))
    parts = []
    for part in current_execution().imap(register_window, tasks, window_scans * RESULT_BYTES_PER_PAIR):
        parts.append(part)
        if progress is not None:
            progress(sum(len(p.T_prev_next) for p in parts), n_pairs)
    return PairRegistrations(*(np.concatenate([getattr(p, name) for p in parts])
                               for name in ("T_prev_next", "information", "converged")))


@dataclass(frozen=True)
class PairWindow:
    """A task of `register_consecutive`: the pairs of scans first..stop-1 of the sequence `scans` names,
    from their start motions T_prev_next_start (stop - first - 1, 4, 4)."""

    scans: ScanRef
    first: int
    stop: int
    T_prev_next_start: np.ndarray
    voxel_m: float
    max_correspondence_m: float


def register_window(task: PairWindow) -> PairRegistrations:
    """The registrations of a window's pairs, its scans read from the source (on a worker)."""
    return _register(read_scans(task.scans, task.first, task.stop), task.T_prev_next_start, task.voxel_m,
                     task.max_correspondence_m, None)


def _register(points_scan: Sequence[np.ndarray], T_start: np.ndarray, voxel_m: float, max_correspondence_m: float,
              progress: Callable[[int, int], None] | None) -> PairRegistrations:
    """Scan j+1 of `points_scan` registered onto scan j from T_start[j] (len(points_scan) - 1, 4, 4)."""
    import small_gicp

    n_pairs = len(T_start)
    T_prev_next = np.tile(np.eye(4), (n_pairs, 1, 1))
    information = np.zeros((n_pairs, 6, 6))
    converged = np.zeros(n_pairs, dtype=bool)
    prev = _prepare(points_scan[0], voxel_m)
    for j in range(n_pairs):
        following = _prepare(points_scan[j + 1], voxel_m)
        if len(prev[0].points()) and len(following[0].points()):
            result = small_gicp.align(prev[0], following[0], prev[1], T_start[j], registration_type="GICP",
                                      max_correspondence_distance=max_correspondence_m,
                                      max_iterations=MAX_ITERATIONS, rotation_epsilon=ROTATION_EPSILON_RAD,
                                      translation_epsilon=TRANSLATION_EPSILON_M)
            T_prev_next[j] = result.T_target_source
            converged[j] = result.converged or small_gicp.align(
                prev[0], following[0], prev[1], T_prev_next[j], registration_type="GICP",
                max_correspondence_distance=max_correspondence_m, max_iterations=MAX_ITERATIONS).converged
            information[j] = point_to_plane_information(prev, following[0].points()[:, :3], T_prev_next[j],
                                                        max_correspondence_m)
        prev = following
        if progress is not None:
            progress(j + 1, n_pairs)
    return PairRegistrations(T_prev_next, information, converged)


def _prepare(points: np.ndarray, voxel_m: float) -> tuple:
    """small_gicp's (cloud, KdTree) of `points` (M, 3): downsampled, with covariances and normals."""
    import small_gicp

    return small_gicp.preprocess_points(np.asarray(points, dtype=np.float64), downsampling_resolution=voxel_m,
                                        num_neighbors=COVARIANCE_NEIGHBOURS)


def point_to_plane_information(target: tuple, points_source: np.ndarray, T_target_source: np.ndarray,
                               max_correspondence_m: float) -> np.ndarray:
    """(6, 6) information of the relative motion `T_target_source` (see the module docstring) from the
    source points (M, 3) whose nearest point of the `target` (small_gicp cloud with normals, KdTree)
    is within `max_correspondence_m`."""
    cloud, tree = target
    R, t = T_target_source[:3, :3], T_target_source[:3, 3]
    index, sq_distance_m2 = tree.batch_nearest_neighbor_search(points_source @ R.T + t)
    index, sq_distance_m2 = np.asarray(index), np.asarray(sq_distance_m2)
    near = (index >= 0) & (sq_distance_m2 <= max_correspondence_m**2)
    normals = cloud.normals()[index[near], :3]
    a = np.hstack([np.cross(points_source[near], normals @ R), normals])
    return 2.0 * a.T @ a
