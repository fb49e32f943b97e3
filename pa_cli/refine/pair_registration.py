"""Registration of consecutive scans: each pair's relative motion by GICP, and the registrations' noise.

Every scan's points are downsampled to a voxel and given point covariances and normals from their
neighbours (small_gicp: generalized ICP, Segal et al. 2009); scan j+1 is registered onto scan j from
the pair's relative motion at the poses given, so the registration sees every surface of the two
scans (walls, poles, trunks, kerbs), not only the planes the adjustment associates.

Three starts. Along a street whose structure repeats (trees, posts, facade bays) or thins out
(facade gaps) a registration's cost has several basins along the road, and a start 10 cm off may end
in a neighbouring one: the registered motion would then depend on the poses given, not only on the
scans. So each pair is also registered from the motions registered for the pairs before and after
it, each from its own start (constant-velocity starts drawn from the data), where such a start
differs from the given one by more than the convergence tolerance, and the result that fits the
scans best is kept: the lowest `truncated_cost`, each source point's squared point-to-plane
distance, or the correspondence distance squared for a point left without a partner. A neighbour's
start is registered to small_gicp's default tolerances first; only when that lands in another basin
than the given start's result (`SAME_BASIN_RAD`, `SAME_BASIN_M`) is it refined and scored. A neighbour's
start that already lies in that basin (within the same bounds of the result) is not registered.

One fixed point per basin. Within a basin the point GICP converges to still depends on where it
started, by up to millimetres: its correspondences change in steps, so a basin holds several fixed
points close together, each with a small catchment of its own. Two starts would then hand the
adjustment motions a few tenths of a millimetre to millimetres apart, and its plane association, a
step function of the poses, can turn such a difference into centimetres. So the kept result is
registered once more from itself snapped to a grid (`snapped`: its rotation vector and translation
rounded to multiples of `SNAP_RAD` and `SNAP_M`), and that registration is the pair's motion: every
start whose result lies in the same grid cell gets the same motion to the last bit. The cells are
much larger than the spread of the fixed points and much smaller than the spacing of the basins, so
the snapped start stays in the kept result's basin; should its registration end in another (beyond
`SAME_BASIN_RAD`, `SAME_BASIN_M`), the kept result stays. A registration that ends in another cell
than its start's is registered again from that cell (`MAX_SNAPS`): the motion is the registration
from the cell that holds it. Two results on either side of a cell's edge (their starts a cell apart)
then end alike unless each side's start leads to a fixed point on its own side.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.core.geometry import exp_so3, log_so3, rigid_inverse
from pa_cli.planes.windowed import ScanRef, read_scans
from pa_cli.runtime.distributed import current_execution

COVARIANCE_NEIGHBOURS = 10  # point covariances and normals from this many neighbours (small_gicp's default)
MAX_ITERATIONS = 50
# Iterations stop when one turns the registration less than 1e-4 rad (1 mm at 10 m) and moves it less
# than 0.1 mm: far below the point noise, so the result is the fixed point its start leads to (small_gicp's
# defaults, 0.1 deg and 1 mm, stop at the start; which fixed point: `snapped`). At that precision some pairs cycle
# between correspondence sets a fraction of a millimetre to a millimetre apart; a registration counts as converged
# when, from its result, a registration to small_gicp's default tolerances converges or ends within
# CYCLE_RAD and CYCLE_M of it (it cycles in place rather than slides).
ROTATION_EPSILON_RAD = 1e-4
TRANSLATION_EPSILON_M = 1e-4
# Twice small_gicp's default tolerances: a registration cycling between two correspondence sets steps back and
# forth by about them (1-1.3 mm on the 16-beam avenues of `bench/robust.py starts`).
CYCLE_RAD = np.deg2rad(0.2)
CYCLE_M = 0.002
# Results of one pair closer than this lie in one basin of its cost: a registration stopped at small_gicp's
# tolerances (0.1 deg, 1 mm) is that close to its fixed point, neighbouring basins lie a structure's spacing
# apart (the pillars, trees or bays of a street: decimetres to metres).
SAME_BASIN_RAD = np.deg2rad(1.0)
SAME_BASIN_M = 0.01
# The grid a kept result is snapped to before its last registration: 5 cm and 1 deg, tens of times the
# millimetres and hundredths of a degree between the fixed points of one basin, a fraction of the spacing of
# the basins; the cells' edges at +-0.5 deg lie beyond the roll and pitch of a pair of a driving platform.
SNAP_M = 0.05
SNAP_RAD = np.deg2rad(1.0)
# A registration from a snapped start may end in the next cell (its start's cell edge lay between two fixed
# points); it is then registered again from that cell, up to this many registrations in all.
MAX_SNAPS = 3
# The registrations' noise is measured on at most this many closures (scans j, j+1, j+2), spread over the sequence:
# a standard deviation from n samples has a relative standard error of 1 / sqrt(2 n), 9 % here, for about two
# registrations each (a 1,000-scan sequence registers 999 pairs).
MAX_CLOSURES = 64
# Fewer closures than this give no measured noise (a standard deviation from 8 samples is within a factor 1.6 at
# 95 %).
MIN_CLOSURES = 8
RESULT_BYTES_PER_PAIR = 140  # a pair's result on its way back from a worker: a 4x4 of float64 and a flag
# Without a cluster the pairs go to processes of this machine (small_gicp holds the GIL: threads would take turns)
# only where each process gets at least this many: a process's start (spawn, imports: about 0.7 s) against about
# 20 ms per pair.
MIN_PAIRS_PER_PROCESS = 100


@dataclass(frozen=True)
class PairRegistrations:
    """The registrations of every consecutive pair (j, j+1) of a sequence of N scans."""

    T_prev_next: np.ndarray  # (N-1, 4, 4): scan j+1 in scan j's frame, as registered
    converged: np.ndarray  # (N-1,) bool: the registration converged (see ROTATION_EPSILON_RAD)


def register_consecutive(points_scan: Sequence[np.ndarray], T_world_scan: np.ndarray, voxel_m: float,
                         max_correspondence_m: float, progress: Callable[[int, int], None] | None = None,
                         scans: ScanRef | None = None, window_scans: int = 100, threads: int = 1
                         ) -> PairRegistrations:
    """Register every scan j+1 onto scan j (`points_scan`: N arrays (M, 3), sensor frames, m), from the
    relative motions of `T_world_scan` (N, 4, 4) and from the motions registered for the pairs beside
    it (see the module docstring). Reads the scans once, three at a time.

    With `scans` (where the scans are) the pairs are window tasks of `window_scans` pairs on
    `current_execution()`'s cluster, or without one on its processes of this machine (windows of at most
    a process's share of the pairs; when there are at least two processes with `MIN_PAIRS_PER_PROCESS`
    pairs each): each worker reads its window's scans from the source itself, with the scans of the
    pairs just before and after the window (their registrations are the window's end pairs' other
    starts), and `points_scan` is not read. A registration depends only on its scans and its starts, so
    the result is the same as in this process. In this process the scans' point covariances and the
    scoring's nearest-neighbour searches run on `threads` threads (each point's on its own: the same
    result on any number)."""
    T_start = rigid_inverse(T_world_scan[:-1]) @ T_world_scan[1:]
    n_pairs = len(T_start)
    execution = current_execution()
    on_processes = execution.spreads(n_pairs, MIN_PAIRS_PER_PROCESS)
    if scans is None or n_pairs == 0 or not (execution.client is not None or on_processes):
        return _register(points_scan, T_start, voxel_m, max_correspondence_m, progress, threads=threads)
    if on_processes:
        window_scans = min(window_scans, -(-n_pairs // execution.processes))

    def window(first: int) -> PairWindow:
        lead, stop = max(first - 1, 0), min(first + window_scans + 1, n_pairs)  # pairs lead..stop-1
        return PairWindow(scans, lead, stop + 1, T_start[lead:stop], voxel_m, max_correspondence_m,
                          n_lead=first - lead, n_trail=stop - min(first + window_scans, n_pairs))

    tasks = (window(first) for first in range(0, n_pairs, window_scans))
    parts = []
    for part in execution.imap(register_window, tasks, window_scans * RESULT_BYTES_PER_PAIR, holds_gil=True):
        parts.append(part)
        if progress is not None:
            progress(sum(len(p.T_prev_next) for p in parts), n_pairs)
    return PairRegistrations(np.concatenate([p.T_prev_next for p in parts]),
                             np.concatenate([p.converged for p in parts]))


@dataclass(frozen=True)
class PairWindow:
    """A task of `register_consecutive`: the pairs of scans first..stop-1 of the sequence `scans` names,
    from their start motions T_prev_next_start (stop - first - 1, 4, 4); the first `n_lead` and the last
    `n_trail` pairs only give their neighbours a start and are not returned."""

    scans: ScanRef
    first: int
    stop: int
    T_prev_next_start: np.ndarray
    voxel_m: float
    max_correspondence_m: float
    n_lead: int = 0
    n_trail: int = 0


def register_window(task: PairWindow) -> PairRegistrations:
    """The registrations of a window's pairs, its scans read from the source (on a worker)."""
    return _register(read_scans(task.scans, task.first, task.stop), task.T_prev_next_start, task.voxel_m,
                     task.max_correspondence_m, None, task.n_lead, task.n_trail)


def _register(points_scan: Sequence[np.ndarray], T_start: np.ndarray, voxel_m: float, max_correspondence_m: float,
              progress: Callable[[int, int], None] | None, n_lead: int = 0, n_trail: int = 0,
              threads: int = 1) -> PairRegistrations:
    """Scan j+1 of `points_scan` registered onto scan j from T_start[j] (len(points_scan) - 1, 4, 4) and
    from the registrations of pairs j - 1 and j + 1 from their own T_start, whichever fits best
    (`truncated_cost`), then once more from that result `snapped` (the module docstring); the first `n_lead`
    and the last `n_trail` pairs are registered only as their neighbours' starts and are not returned. Scans
    prepared and scored on `threads` threads."""
    import small_gicp

    def align(target: tuple, source: tuple, T_guess: np.ndarray, **tolerances: float):
        return small_gicp.align(target[0], source[0], target[1], T_guess, registration_type="GICP",
                                max_correspondence_distance=max_correspondence_m, max_iterations=MAX_ITERATIONS,
                                **tolerances)

    tight = {"rotation_epsilon": ROTATION_EPSILON_RAD, "translation_epsilon": TRANSLATION_EPSILON_M}
    n_all = len(T_start)
    n_pairs = n_all - n_lead - n_trail
    T_prev_next = np.tile(np.eye(4), (n_pairs, 1, 1))
    converged = np.zeros(n_pairs, dtype=bool)
    prepared: dict[int, tuple] = {}  # scans j, j + 1, j + 2: pair j is decided once pair j + 1 is registered
    first: list = [None] * n_all  # each pair registered from its own start (None: a scan without points)

    def decide(j: int) -> None:
        target, source = prepared[j], prepared[j + 1]
        if first[j] is None or not n_lead <= j < n_all - n_trail:
            return
        source_points = source[0].points()[:, :3]
        result, best_cost = first[j], None
        for neighbour in (j - 1, j + 1):
            if not 0 <= neighbour < n_all or first[neighbour] is None:
                continue
            motion = first[neighbour].T_target_source
            if not apart(motion, T_start[j]) or not apart(motion, result.T_target_source, SAME_BASIN_RAD,
                                                          SAME_BASIN_M):
                continue
            other = align(target, source, motion)  # to small_gicp's tolerances: enough to tell the basin
            if not apart(other.T_target_source, result.T_target_source, SAME_BASIN_RAD, SAME_BASIN_M):
                continue
            other = align(target, source, other.T_target_source, **tight)
            if best_cost is None:
                best_cost = truncated_cost(target, source_points, result.T_target_source, max_correspondence_m,
                                           threads)
            cost = truncated_cost(target, source_points, other.T_target_source, max_correspondence_m, threads)
            if cost < best_cost:
                result, best_cost = other, cost
        result = registered_from_its_cell(lambda start: align(target, source, start, **tight), result)
        k = j - n_lead
        T_prev_next[k] = result.T_target_source
        if result.converged:
            converged[k] = True
        else:
            check = align(target, source, T_prev_next[k])
            converged[k] = check.converged or not apart(check.T_target_source, T_prev_next[k], CYCLE_RAD, CYCLE_M)
        if progress is not None:
            progress(k + 1, n_pairs)

    for scan in range(n_all + 1):
        prepared[scan] = _prepare(points_scan[scan], voxel_m, threads)
        if scan == 0:
            continue
        target, source = prepared[scan - 1], prepared[scan]
        if len(target[0].points()) and len(source[0].points()):
            first[scan - 1] = align(target, source, T_start[scan - 1], **tight)
        if scan >= 2:
            decide(scan - 2)
            del prepared[scan - 2]
    if n_all:
        decide(n_all - 1)
    return PairRegistrations(T_prev_next, converged)


@dataclass(frozen=True)
class MotionNoise:
    """The registrations' noise per axis, measured on closures (`closure_sigmas`)."""

    sigmas: np.ndarray  # (6,): rotation about scan j+1's x, y, z (rad), translation along scan j's x, y, z (m)
    n_closures: int

    def report(self) -> dict[str, Any]:
        """The report's `motion_noise` section (degrees and metres)."""
        return {"rotation_sigma_deg": [float(x) for x in np.rad2deg(self.sigmas[:3])],
                "translation_sigma_m": [float(x) for x in self.sigmas[3:]], "n_closures": self.n_closures}


def closure_sigmas(points_scan: Sequence[np.ndarray], pairs: PairRegistrations, voxel_m: float,
                   max_correspondence_m: float, threads: int = 1) -> MotionNoise | None:
    """The noise of the registrations of consecutive pairs, per axis, measured on closures: for scans j, j+1,
    j+2 whose two pairs converged, scan j+2 is registered onto scan j as the pairs are (`_register`, from the
    two registered motions composed), and C = Z_{j,j+2}^-1 Z_{j,j+1} Z_{j+1,j+2} is the identity but for the
    three registrations' errors (`noise_of_closures`: a standard deviation per axis, about the scans' axes,
    which consecutive scans turn little). A registration that ended in a wrong basin raises it: the factors then
    hold every motion more loosely, never more tightly. Errors shared by neighbouring registrations (a tilted road
    tilts both alike) cancel in C and are not counted. At most `MAX_CLOSURES` closures spread evenly over the
    sequence; None with fewer than `MIN_CLOSURES`. Each sigma is at least the registration's convergence tolerance
    (`ROTATION_EPSILON_RAD`, `TRANSLATION_EPSILON_M`), below which a registration does not resolve its motion."""
    ok = np.flatnonzero(pairs.converged[:-1] & pairs.converged[1:])
    if len(ok) < MIN_CLOSURES:
        return None
    chosen = ok[np.unique(np.linspace(0, len(ok) - 1, min(MAX_CLOSURES, len(ok))).round().astype(np.int64))]
    closures = []
    for j in chosen:
        start = pairs.T_prev_next[j] @ pairs.T_prev_next[j + 1]
        skip = _register([points_scan[j], points_scan[j + 2]], start[None], voxel_m, max_correspondence_m, None,
                         threads=threads)
        if skip.converged[0]:
            closures.append(rigid_inverse(skip.T_prev_next)[0] @ start)
    if len(closures) < MIN_CLOSURES:
        return None
    floor = np.r_[np.full(3, ROTATION_EPSILON_RAD), np.full(3, TRANSLATION_EPSILON_M)]
    return MotionNoise(np.maximum(noise_of_closures(np.stack(closures)), floor), len(closures))


def noise_of_closures(C: np.ndarray) -> np.ndarray:
    """(6,) the sigma per axis of each of the three registrations of which the closures C (K, 4, 4) are made:
    the root mean square of their rotation vectors (rad) and translations (m) divided by sqrt(3) (three
    independent errors of about equal size add their variances)."""
    error = np.hstack([log_so3(C[:, :3, :3]), C[:, :3, 3]])
    return np.sqrt(np.mean(error**2, axis=0) / 3.0)


def registered_from_its_cell(register: Callable[[np.ndarray], Any], kept: Any) -> Any:
    """The registration of a pair from the grid cell that holds its result (the module docstring): `register`
    registers the pair from a start (4, 4) and returns a result with `T_target_source`; `kept` is the result
    the starts found. Registered from `kept` snapped, and again from the cell a registration ends in when that
    is another (at most `MAX_SNAPS` in all); `kept` stays when a registration leaves its basin."""
    result, start = kept, snapped(kept.T_target_source)
    for _ in range(MAX_SNAPS):
        registered = register(start)
        if apart(registered.T_target_source, result.T_target_source, SAME_BASIN_RAD, SAME_BASIN_M):
            break
        result, previous, start = registered, start, snapped(registered.T_target_source)
        if np.array_equal(start, previous):
            break
    return result


def snapped(T: np.ndarray) -> np.ndarray:
    """The motion T (4, 4) with its rotation vector (rad) and its translation (m) rounded to multiples of
    `SNAP_RAD` and `SNAP_M`: one start for every motion within a grid cell."""
    out = np.eye(4)
    out[:3, :3] = exp_so3(np.round(log_so3(T[None, :3, :3]) / SNAP_RAD) * SNAP_RAD)[0]
    out[:3, 3] = np.round(T[:3, 3] / SNAP_M) * SNAP_M
    return out


def apart(T_a: np.ndarray, T_b: np.ndarray, rotation_rad: float = ROTATION_EPSILON_RAD,
          translation_m: float = TRANSLATION_EPSILON_M) -> bool:
    """The motions (4, 4) differ by more than `rotation_rad` or `translation_m` (by default a registration's
    convergence tolerance)."""
    d = rigid_inverse(T_a[None])[0] @ T_b
    angle_rad = np.arccos(np.clip((np.trace(d[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return bool(angle_rad > rotation_rad or np.linalg.norm(d[:3, 3]) > translation_m)


def truncated_cost(target: tuple, points_source: np.ndarray, T_target_source: np.ndarray,
                   max_correspondence_m: float, threads: int = 1) -> float:
    """How well the source points (M, 3) fit the `target` (small_gicp cloud with normals, KdTree) at
    `T_target_source`: the sum of their `point_costs` (m^2). Both starts' results are scored on the same
    points, so an answer that leaves points without a partner pays for them."""
    return float(np.sum(point_costs(target, points_source, T_target_source, max_correspondence_m, threads)))


def point_costs(target: tuple, points_source: np.ndarray, T_target_source: np.ndarray, max_correspondence_m: float,
                threads: int = 1) -> np.ndarray:
    """(M,) per source point (M, 3) moved by `T_target_source`: the squared point-to-plane distance (m^2) to its
    nearest `target` point (small_gicp cloud with normals, KdTree), or max_correspondence_m^2 without one within
    max_correspondence_m. The nearest points are searched on `threads` threads."""
    cloud, tree = target
    moved = points_source @ T_target_source[:3, :3].T + T_target_source[:3, 3]
    index, sq_distance_m2 = tree.batch_nearest_neighbor_search(moved, num_threads=threads)
    index, sq_distance_m2 = np.asarray(index), np.asarray(sq_distance_m2)
    near = (index >= 0) & (sq_distance_m2 <= max_correspondence_m**2)
    costs = np.full(len(points_source), max_correspondence_m**2)
    partners = index[near]
    costs[near] = np.einsum("ij,ij->i", cloud.normals()[partners, :3], moved[near] - cloud.points()[partners, :3]) ** 2
    return costs


def _prepare(points: np.ndarray, voxel_m: float, threads: int = 1) -> tuple:
    """small_gicp's (cloud, KdTree) of `points` (M, 3): downsampled, with covariances and normals, those on
    `threads` threads. The downsampling is `preprocess_points`' on one thread, whose voxel order (and so every
    sum over points) no other call of small_gicp gives and no other number of threads keeps; with more threads
    it estimates one-neighbour covariances there (the cheapest it does), which are then estimated again from
    COVARIANCE_NEIGHBOURS neighbours on the threads (each point's on its own: the same on any number)."""
    import small_gicp

    points = np.asarray(points, dtype=np.float64)
    if threads == 1:
        return small_gicp.preprocess_points(points, downsampling_resolution=voxel_m,
                                            num_neighbors=COVARIANCE_NEIGHBOURS)
    cloud, tree = small_gicp.preprocess_points(points, downsampling_resolution=voxel_m, num_neighbors=1)
    small_gicp.estimate_normals_covariances(cloud, tree, num_neighbors=COVARIANCE_NEIGHBOURS, num_threads=threads)
    return cloud, tree
