"""Association: plane landmarks across scans -> a `FeatureProblem` of planes.

`build_plane_problem` makes two passes over the scans (each scan is read twice, never held;
three times when a landmark is refit, see 3.):

1. `detect.detect_landmarks`: world-frame voxel statistics, planar leaves, region growing.
2. Each scan again: its world points are mapped to landmarks through the leaf voxels, points
   farther than `outlier_sigma` sigmas from their landmark plane are trimmed, and the points
   of each (landmark, scan) are summed into one 4x4 cluster in the SCAN frame, and into one
   range cluster with every point weighted by 1/|p|^2 (`pa_cli.core.clusters.range_weights`; the
   scan frame's origin taken as the sensor, for the pose covariance's range noise model).
   Observations with fewer than `min_points_per_observation` points are dropped, then landmarks
   seen by fewer than two scans.
3. Verification on the kept points (refit from the clusters). A landmark whose kept points
   are thinner than `tilted_thickness_fraction` of its detection sigma was detected on a tilted
   plane (leaves holding junction points of a crossing surface); when its kept points are most of its
   detected points (`refit_min_kept_fraction`) its plane and sigma are replaced by their fit
   and pass 2 is repeated once; landmarks that still fail verification are dropped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pa_cli.config import PlanesConfig
from pa_cli.core.clusters import (
    clusters_from_moments,
    fit_planes,
    normal_sigma_rad,
    sum_by_feature,
    transform_clusters,
)
from pa_cli.core.problem import FeatureProblem, make_problem
from pa_cli.errors import InputError
from pa_cli.planes import kernels
from pa_cli.planes.detect import Landmarks, Progress, detect_landmarks
from pa_cli.planes.sides import split_two_sided
from pa_cli.runtime.numba_cache import announce_compilation
from pa_cli.runtime.warm_up import wait_for_compile_processes

# (scans, T_world_scan, landmarks, config, progress, progress_offset, total) ->
# (landmark id, scan index, scan-frame cluster of each observation, counts)
AssociationPass = Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]]


def _check_inputs(scans: Sequence[np.ndarray], T_world_scan: np.ndarray) -> np.ndarray:
    T = np.asarray(T_world_scan, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"poses: expected an (N, 4, 4) array of T_world_scan, found shape {T.shape}.")
    if len(T) != len(scans):
        raise InputError(f"{len(scans)} scans but {len(T)} poses; pass one pose per scan "
                         "(--poses) in scan order.")
    if not np.all(np.isfinite(T)):
        raise InputError("poses contain NaN or inf values; check the --poses file.")
    return T


def association_pass_in_process(scans: Sequence[np.ndarray], T: np.ndarray, landmarks: Landmarks,
                                config: PlanesConfig, progress: Progress | None, progress_offset: int,
                                total: int, point_labels: list | None = None
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """One read of every scan: landmark id, scan index, scan-frame cluster and range cluster of
    each observation with at least `min_points_per_observation` points, and point counts.
    `point_labels` (a list of one item per scan) receives the landmark id of each point of
    each scan (int32, -1 when unassigned, trimmed or not finite)."""
    landmarks.prepare()  # build the lookup tables once, before the worker threads share them
    gate_m = landmarks.gates_m(config.outlier_sigma, config.outlier_sigma_floor_m)

    def observe(j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, int]:
        # transform, finiteness, assignment and both sums in one pass over the scan as read
        labels, sums_by_lm, range_by_lm, n_finite, trimmed = landmarks.observe(scans[j], T[j], gate_m)
        if point_labels is not None:
            point_labels[j] = labels
        lm = np.flatnonzero(sums_by_lm[:, 0] > 0)  # landmarks hit, ascending id
        return lm, sums_by_lm[lm], clusters_from_moments(range_by_lm[lm]), n_finite, trimmed, j

    lm_parts, scan_parts, cluster_parts, range_parts = [], [], [], []
    n_points = n_covered = n_trimmed = n_small = 0
    # scans are independent here and the kernel releases the GIL
    with ThreadPoolExecutor(max_workers=config.association_threads) as pool:
        for lm, sums, range_sums, n_scan_points, trimmed, j in pool.map(observe, range(len(scans))):
            n_points += n_scan_points
            n_trimmed += trimmed
            enough = sums[:, 0] >= config.min_points_per_observation
            n_small += int((~enough).sum())
            n_covered += int(sums[enough, 0].sum())
            lm_parts.append(lm[enough])
            scan_parts.append(np.full(int(enough.sum()), j, dtype=np.int64))
            cluster_parts.append(clusters_from_moments(sums[enough]))
            range_parts.append(range_sums[enough])
            if progress is not None:
                progress(progress_offset + j + 1, total)
    lm_all = np.concatenate(lm_parts) if lm_parts else np.empty(0, np.int64)
    scan_all = np.concatenate(scan_parts) if scan_parts else np.empty(0, np.int64)
    clusters = np.concatenate(cluster_parts) if cluster_parts else np.empty((0, 4, 4))
    range_clusters = np.concatenate(range_parts) if range_parts else np.empty((0, 4, 4))
    return lm_all, scan_all, clusters, range_clusters, {"n_points": n_points, "n_covered": n_covered,
                                        "n_trimmed": n_trimmed, "n_small": n_small}


def _verify(lm_all: np.ndarray, scan_all: np.ndarray, clusters: np.ndarray, T: np.ndarray,
            landmarks: Landmarks, config: PlanesConfig) -> tuple[np.ndarray, np.ndarray, dict]:
    """Landmarks seen by two or more scans (ids, ascending), which of them pass verification
    on the points they kept, which are tilted detections (see `associate_landmarks`), and the
    kept points' world planes (centroid (K, 3) m, unit normal (K, 3), RMS thickness (K,) m)."""
    seen, n_obs = np.unique(lm_all, return_counts=True)
    multi = seen[n_obs >= 2]
    if len(multi) == 0:
        empty = np.zeros(0, dtype=bool)
        return multi, empty, {"tilted": empty, "centroid": np.empty((0, 3)),
                              "normal": np.empty((0, 3)), "thickness": np.empty(0)}
    keep = np.isin(lm_all, multi)
    trial = FeatureProblem(plane_index=np.searchsorted(multi, lm_all[keep]), scan_index=scan_all[keep],
                         clusters=clusters[keep], n_scans=len(T), T_world_scan=None)
    origin = landmarks.centroid_world[multi]
    n_pts, mean_rel, normal, thick, sigma_n = _world_planes(trial, T, origin)
    plausible = (thick <= config.max_thickness_m) & \
        (sigma_n <= np.deg2rad(config.max_normal_uncertainty_deg))
    # Against the detection sigma itself, not the floored gate sigma: a landmark with sub-floor
    # noise (a grazing roof, 0.8 mm) kept at its floored gate is consistent, not tilted.
    tilted = thick < config.tilted_thickness_fraction * landmarks.sigma_m[multi]
    fixable = n_pts >= config.refit_min_kept_fraction * landmarks.count[multi]
    return multi, plausible & ~tilted, {"tilted": plausible & tilted & fixable,
                                        "centroid": origin + mean_rel,
                                        "normal": normal, "thickness": thick}


def associate_landmarks(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, landmarks: Landmarks,
                        config: PlanesConfig, progress: Progress | None = None,
                        progress_offset: int = 0, progress_total: int | None = None,
                        association_pass: AssociationPass | None = None,
                        point_labels: list | None = None) -> tuple[FeatureProblem, dict, np.ndarray]:
    """Second pass: observation clusters (scan frame) of each (landmark, scan).

    Each landmark seen by two or more scans is verified on the points it kept (refit from the
    clusters): it is dropped when its kept points are thicker than `max_thickness_m` or its
    normal is poorly determined (`max_normal_uncertainty_deg`). Kept points thinner than
    `tilted_thickness_fraction` of the detection sigma mean a tilted detection plane (leaves
    holding junction points of a crossing surface tilt it and widen its sigma, so its gate is too wide to trim that
    surface's points). When those kept points are at least `refit_min_kept_fraction` of the
    landmark's detected points, its plane (`landmarks.normal_world`, `centroid_world`) and
    sigma (`sigma_m`) are replaced IN PLACE by the fit of its kept points and their RMS
    thickness, and the scans are read a third time to trim and cluster against the corrected
    planes (only when some landmark was corrected; no progress calls in that pass). A
    minority subset does not define the landmark's plane (and refitting it moves the
    junction slabs of its neighbours): such landmarks are dropped. After the last pass every
    landmark failing verification is dropped. A landmark observed from both sides of its plane
    is split in two before that verification (`pa_cli.planes.sides`: two faces of a wall; its
    new rows are appended to `landmarks`). Except for such splits `landmarks.assign` reproduces the returned
    clusters; `point_labels` (a list of one item per scan) receives its labels of each point of
    each scan in the last pass (int32, -1 when unassigned, trimmed or not finite).

    `association_pass` replaces the pass over the scans (same arguments and results as
    `association_pass_in_process`; `pa_cli.planes.windowed` runs it as tasks on dask workers).

    Returns the problem, the association counts and the landmark id of each problem plane.
    """
    T = _check_inputs(scans, T_world_scan)
    total = progress_total if progress_total is not None else len(scans)
    run_pass = association_pass or association_pass_in_process
    lm_all, scan_all, clusters, range_clusters, c = run_pass(scans, T, landmarks, config, progress,
                                                             progress_offset, total, point_labels)
    multi, good, fit = _verify(lm_all, scan_all, clusters, T, landmarks, config)
    n_refit = int(fit["tilted"].sum())
    if n_refit:
        refit = multi[fit["tilted"]]
        landmarks.normal_world = landmarks.normal_world.copy()
        landmarks.centroid_world = landmarks.centroid_world.copy()
        landmarks.sigma_m = landmarks.sigma_m.copy()
        landmarks.normal_world[refit] = fit["normal"][fit["tilted"]]
        landmarks.centroid_world[refit] = fit["centroid"][fit["tilted"]]
        landmarks.sigma_m[refit] = fit["thickness"][fit["tilted"]]
        lm_all, scan_all, clusters, range_clusters, c = run_pass(scans, T, landmarks, config, None, 0, total,
                                                                 point_labels)
        multi, good, fit = _verify(lm_all, scan_all, clusters, T, landmarks, config)
    sides = split_two_sided(lm_all, scan_all, clusters, range_clusters, T, landmarks,
                            config.side_grazing_angle_deg, point_labels)
    if sides is not None:  # a landmark seen from both sides of its plane: two surfaces
        lm_all, scan_all, clusters, range_clusters = sides.landmark, sides.scan, sides.clusters, sides.range_clusters
        c["n_covered"] -= sides.n_points_dropped
        multi, good, fit = _verify(lm_all, scan_all, clusters, T, landmarks, config)
    n_single = landmarks.n_landmarks - len(multi)
    kept_landmarks = multi[good]
    keep = np.isin(lm_all, kept_landmarks)
    n_covered = c["n_covered"] - int(clusters[~keep, 3, 3].sum())
    problem = make_problem(lm_all[keep].astype(np.int64), scan_all[keep], clusters[keep],
                           n_scans=len(T), T_world_scan=T, source="plane association",
                           range_clusters=range_clusters[keep])
    n_points = c["n_points"]
    counts = {
        "n_points_total": int(n_points),
        "n_points_covered": int(n_covered),
        "covered_fraction": float(n_covered / n_points) if n_points else 0.0,
        "n_points_trimmed": int(c["n_trimmed"]),
        "n_observations_below_min_points": int(c["n_small"]),
        "n_landmarks_single_scan": int(n_single),
        "n_landmarks_refit": n_refit,
        "n_landmarks_failed_verification": int((~good).sum()),
    }
    return problem, counts, kept_landmarks


def _world_planes(problem: FeatureProblem, T_world_scan: np.ndarray, origin_world: np.ndarray | None):
    """Per plane: point count, centroid relative to origin_world (m), unit normal, RMS
    thickness (m) and normal standard deviation (rad); see `world_plane_stats`."""
    M = np.asarray(T_world_scan, dtype=np.float64)[problem.scan_index]  # fancy index: a copy
    if origin_world is not None:
        M[:, :3, 3] -= origin_world[problem.plane_index]
    C = sum_by_feature(transform_clusters(problem.clusters, M), problem.plane_index, problem.n_planes)
    evals, normal, centroid, n = fit_planes(C)
    return n, centroid, normal, np.sqrt(evals[:, 0] / n), normal_sigma_rad(evals, n)


def world_plane_stats(problem: FeatureProblem, T_world_scan: np.ndarray,
                      origin_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per plane: point count (P,), unit normal (P, 3) and RMS thickness sqrt(lambda_min/N) (P,) in m.

    Clusters are moved to the world frame (T C T^T) relative to `origin_world` (P, 3) (for
    precision far from the origin; default: the world origin) and summed per plane.
    """
    n, _, normal, thickness_m, _ = _world_planes(problem, T_world_scan, origin_world)
    return n, normal, thickness_m


def problem_diagnostics(problem: FeatureProblem, T_world_scan: np.ndarray, config: PlanesConfig,
                        origin_world: np.ndarray | None = None) -> dict:
    """Landmark statistics of a plane problem at poses T_world_scan (JSON-serialisable)."""
    P, n_scans = problem.n_planes, problem.n_scans
    obs_per_lm = np.bincount(problem.plane_index, minlength=P)
    lm_per_scan = np.bincount(problem.scan_index, minlength=n_scans)
    diag: dict = {
        "n_landmarks": int(P),
        "n_observations": int(problem.n_observations),
        "observations_per_landmark": _summary(obs_per_lm, ("min", "median", "max")),
        "landmarks_per_scan": [int(x) for x in lm_per_scan],
    }
    if P == 0:
        diag.update({"thickness_rms_m": {"median": None, "p90": None, "max": None},
                     "constraint_eigenvalue_per_scan": [0.0] * n_scans,
                     "poorly_constrained_scans": list(range(n_scans))})
        return diag
    _, normal_world, thickness_m = world_plane_stats(problem, T_world_scan, origin_world)
    diag["thickness_rms_m"] = _summary(thickness_m, ("median", "p90", "max"))
    # Which scans see normals that span three directions? lambda_min of sum n n^T per scan.
    nrm = normal_world[problem.plane_index]
    A = np.stack([np.bincount(problem.scan_index, nrm[:, i] * nrm[:, j], minlength=n_scans)
                  for i in range(3) for j in range(3)], -1).reshape(n_scans, 3, 3)
    lam = np.linalg.eigvalsh(A)[:, 0]
    diag["constraint_eigenvalue_per_scan"] = [round(float(x), 4) for x in lam]
    diag["poorly_constrained_scans"] = [int(j) for j in np.flatnonzero(lam < config.min_constraint_eigenvalue)]
    return diag


def _summary(values: np.ndarray, which: tuple[str, ...]) -> dict:
    values = np.asarray(values, dtype=np.float64)
    funcs = {"min": np.min, "median": np.median, "max": np.max,
             "p90": lambda x: np.percentile(x, 90)}
    return {k: (float(funcs[k](values)) if len(values) else None) for k in which}


def build_plane_problem(scans: Sequence[np.ndarray], T_world_scan: np.ndarray, config: PlanesConfig,
                        progress: Progress | None = None, landmarks_out: dict | None = None,
                        detect: Callable[..., Landmarks] = detect_landmarks,
                        association_pass: AssociationPass | None = None,
                        ) -> tuple[FeatureProblem, dict]:
    """Plane problem and diagnostics from scans ((M, 3) scan-frame points, m) at T_world_scan (N, 4, 4).

    `scans` may be lazy: each item is read twice (detection pass, association pass), three
    times when some landmark is refit (see `associate_landmarks`; the third pass makes no
    progress calls).
    `progress(done, total)` is called after each scan of each pass (total = 2 N).
    The diagnostics dict (JSON-serialisable) holds the landmark count, observations per
    landmark, points covered, landmarks per scan, poorly constrained scans (smallest eigenvalue
    of the sum of n n^T over the scan's landmark normals below `min_constraint_eigenvalue`),
    the RMS thickness distribution (m), voxel counts and stage times (s).
    With `landmarks_out` (a dict), its keys `landmarks`, `kept` and `landmark_of_point` receive
    the landmarks, the landmark id of each problem plane and the landmark id of each point of
    each scan (for `pa_cli.planes.labels.PointLabels.from_association`).
    `detect` and `association_pass` replace the two passes over the scans (same arguments and
    results as `detect_landmarks` and `association_pass_in_process`; `pa_cli.planes.windowed`
    runs them as tasks on dask workers, which read the scans themselves).
    """
    T = _check_inputs(scans, T_world_scan)
    total = 2 * len(scans)
    wait_for_compile_processes()  # a first run's kernels, compiled in a process of their own: load, not compile again
    announce_compilation(kernels.ENTRY_KERNELS)  # the first run compiles them: say so once
    t0 = time.perf_counter()
    landmarks = detect(scans, T, config, progress, progress_total=total)
    t1 = time.perf_counter()
    point_labels = None if landmarks_out is None else [None] * len(scans)
    problem, counts, kept = associate_landmarks(scans, T, landmarks, config, progress,
                                                progress_offset=len(scans), progress_total=total,
                                                association_pass=association_pass,
                                                point_labels=point_labels)
    t2 = time.perf_counter()
    if landmarks_out is not None:
        landmarks_out.update(landmarks=landmarks, kept=kept, landmark_of_point=point_labels)
    origin = landmarks.centroid_world[kept] if len(kept) else None
    diag = problem_diagnostics(problem, T, config, origin)
    diag.update(counts)
    diag["n_landmarks_detected"] = int(landmarks.n_landmarks)
    diag.update(landmarks.diagnostics)
    warnings = []
    if diag["n_landmarks"] == 0:
        warnings.append("no plane landmark is seen by two scans; check the poses or try another "
                        "scene.plane_voxel_m / scene.max_plane_thickness_m in the config (--config).")
    elif diag["poorly_constrained_scans"]:
        warnings.append(f"{len(diag['poorly_constrained_scans'])} scans see landmark normals that "
                        "do not span three directions; their poses are not fully constrained.")
    diag["warnings"] = warnings
    diag["timings_s"] = {"detect": round(t1 - t0, 3), "associate": round(t2 - t1, 3),
                         "diagnostics": round(time.perf_counter() - t2, 3)}
    return problem, diag
