"""The stages of `pa refine` around the rounds: each takes what it needs and returns what it made.

initial poses -> timestamps -> loops -> motion compensation -> (rounds: `pa_cli.refine.rounds`)
-> assessment -> pose covariance -> evaluation against ground truth.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np
import scipy.sparse as sp

from pa_cli.adjust import plane_cost
from pa_cli.adjust.covariance import covariance_report, node_sets, timed_pose_covariance
from pa_cli.adjust.hierarchical import choose_backend, warm_config
from pa_cli.adjust.linalg import PAIR_MAX_SCANS
from pa_cli.adjust.odometry_factors import OdometryFactors
from pa_cli.config import PaConfig
from pa_cli.core.local_frame import local_origin_m, to_local, to_world
from pa_cli.core.problem import FeatureProblem
from pa_cli.errors import InputError, SolverError
from pa_cli.evaluation import evaluate
from pa_cli.evaluation.degeneracy import describe, scan_degeneracy, travel_frames
from pa_cli.evaluation.free_space import free_space_check
from pa_cli.evaluation.quality import (
    assess,
    decided_by_planes,
    mean_map_entropy,
    pair_tie_information,
    pair_ties,
    rms_point_to_plane,
)
from pa_cli.io.trajectory import Trajectory
from pa_cli.loops import close_loops
from pa_cli.planes.labels import PointLabels
from pa_cli.planes.warm_up import warm_up_in_background
from pa_cli.refine.clock import Stage
from pa_cli.refine.consistency import LISTED_SCANS, association_spread, association_within, start_consistency
from pa_cli.refine.deskew import (
    DeskewedPoints,
    TimedScans,
    kiss_icp_pose_offsets_s,
    scan_reference_times,
    shift_in_time,
)
from pa_cli.refine.odometry import ReplayedFrames, kiss_frame_voxel_m, run_kiss_icp
from pa_cli.refine.state import Assessment, RefineState, RoundsResult
from pa_cli.runtime.distributed import GB
from pa_cli.sources import PointsView

log = logging.getLogger(__name__)

# Bytes per 6x6 pose block of the covariance's selected inversion: the Hessian block, its factor's
# block and the inverse's block on the same pattern, 36 float64 each.
COVARIANCE_BYTES_PER_BLOCK = 3 * 36 * 8


def points_at(source: Any, deskewed: DeskewedPoints | None, T_world_scan: np.ndarray) -> Any:
    """The scans' points as a sequence of (N, 3) scan-frame arrays, motion-compensated with the
    trajectory T_world_scan when deskewing."""
    if deskewed is None:
        return PointsView(source)
    return deskewed.at(T_world_scan)


def points_by_pose_set(source: Any, deskewed: DeskewedPoints | None,
                       pose_sets: dict[str, np.ndarray]) -> dict[str, Any]:
    """`points_at` for each pose set of `pose_sets` (name -> T_world_scan); without deskewing the points
    do not depend on the poses, and every pose set gets the same view (the free-space check reads each
    scan once for all of them)."""
    if deskewed is None:
        return dict.fromkeys(pose_sets, PointsView(source))
    return {name: points_at(source, deskewed, T) for name, T in pose_sets.items()}


def frames_serve_loops(config: PaConfig) -> bool:
    """Whether the loop stage runs and KISS-ICP's thinned frames are fine enough for its local maps: thinned to at
    most `advanced.loops.local_map_voxel_m`."""
    return config.loops.enabled and (kiss_frame_voxel_m(config.sensor, config.advanced.kiss_icp)
                                     <= config.advanced.loops.local_map_voxel_m)


def initial_poses(source: Any, poses: Trajectory | None, poses_name: str | None, config: PaConfig,
                  stage: Stage) -> RefineState:
    """The state at the start: KISS-ICP odometry, or the poses of --poses moved into the local frame. With loops,
    KISS-ICP's thinned frames are kept for the local maps (`odometry_frames`) when its voxel for them is at most
    the local maps' (`advanced.loops.local_map_voxel_m`); the loop stage then reads no scan."""
    origin_world_m = np.zeros(3)
    frames = None
    if poses is not None:
        origin_world_m = local_origin_m(poses.T_world_scan)
        T_odometry = to_local(poses.T_world_scan, origin_world_m)
        if origin_world_m.any():
            log.info("%s: the poses lie far from the world origin; computing in a local frame at %s m "
                     "(outputs are in the world frame).", poses_name, ", ".join(f"{v:.0f}" for v in origin_world_m))
        initial_source = str(poses_name)
    else:
        warm_up_in_background()  # the plane kernels load while the odometry runs
        if frames_serve_loops(config):
            frames = []

        def keep_frame(k: int, points_scan: np.ndarray) -> None:
            frames.append(points_scan.astype(np.float32))

        with stage("odometry", total=len(source)) as progress:
            T_odometry = run_kiss_icp(source, config.sensor, config.advanced.kiss_icp, progress=progress,
                                      on_frame=None if frames is None else keep_frame)
        initial_source = "kiss-icp"
    return RefineState(origin_world_m=origin_world_m, T_odometry=T_odometry, T_initial=T_odometry,
                       T_current=T_odometry.copy(), initial_poses_source=initial_source, odometry_frames=frames)


def scan_timestamps(source: Any, poses: Trajectory | None, poses_name: str | None, tum_out: str
                    ) -> tuple[np.ndarray | None, str]:
    """Per-scan timestamps (s) and where they came from: the TUM timestamps of --poses, else the
    source's, else none (the scan index stands in for time in the TUM output `tum_out`)."""
    if poses is not None and poses.timestamps is not None:
        return np.asarray(poses.timestamps, dtype=np.float64), f"{poses_name} (TUM)"
    found = source.timestamps()
    if found.stamps_s is None:
        log.warning("no per-scan timestamps (%s; no TUM --poses); %s uses the scan index as time.",
                    found.origin, tum_out)
        return None, "scan index"
    return found.stamps_s, found.origin


def loop_closure(source: Any, state: RefineState, config: PaConfig, stage: Stage) -> tuple[np.ndarray, dict[str, Any]]:
    """Loop closure (`loops` config) from `state.T_initial`: the loop-closed poses and the report's `loops` section.
    With KISS-ICP's poses the local maps merge its thinned frames (`state.odometry_frames`, or, when a resumed run
    did not keep them, the same frames made again from the scans: `ReplayedFrames`), else the scans of `source`."""
    frames = state.odometry_frames
    if frames is None and state.initial_poses_source == "kiss-icp" and frames_serve_loops(config):
        frames = ReplayedFrames(source, state.T_odometry, config.sensor, config.advanced.kiss_icp)
    T_initial = state.T_initial
    points = PointsView(source) if frames is None else frames
    with stage("loops", total=len(source)) as progress:
        result = close_loops(points, T_initial, config.advanced.loops, config.loops.min_separation_m,
                             progress=progress, threads=config.execution.threads, thinned=frames is not None)
    report = {"enabled": True, **result.report()}
    log.info("loops: %d closures accepted of %d candidates", report["n_closures"], report["n_candidates"])
    return result.T_world_scan, report


def motion_compensation(source: Any, config: PaConfig, timestamps: np.ndarray | None, T_initial: np.ndarray,
                        from_odometry: bool) -> tuple[np.ndarray, DeskewedPoints | None, dict[str, Any]]:
    """Decide motion compensation (`sensor.deskew`) and read the per-point times once. Returns the
    rounds' start (KISS-ICP's poses moved to the scans' reference instants when `from_odometry`),
    the deskewed points (None when off) and the report's `deskew` section."""
    mode = config.sensor.deskew
    info: dict[str, Any] = {"mode": mode, "enabled": False}
    if mode == "off":
        return T_initial, None, info
    timed = TimedScans(source)
    if timed.unit is None:
        if mode == "on":
            raise InputError(f"{source.name}: sensor.deskew is 'on' but no scan has usable per-point "
                             f"times: {timed.problem}. Set sensor.deskew to auto or off.")
        info["reason"] = timed.problem
        if timed.suspect:
            log.warning("%s: motion compensation is off: %s.", source.name, timed.problem)
        return T_initial, None, info
    stamps_s, stamps_source = scan_reference_times(timed, timestamps)
    if from_odometry:
        # KISS-ICP's pose of a scan holds at another instant of the sweep: move it to the reference
        offsets_s = kiss_icp_pose_offsets_s(timed, config.advanced.kiss_icp.deskew)
        T_initial = shift_in_time(T_initial, stamps_s, offsets_s)
        info["kiss_icp_pose_instant"] = ("end of sweep (its deskew)" if config.advanced.kiss_icp.deskew else
                                         "mean point time (raw sweep)") + ", moved to the reference instant"
    deskewed = DeskewedPoints(timed.points, timed.times_s, stamps_s, T_initial)
    info.update(enabled=True, **timed.report(), scan_times_source=stamps_source)
    if timed.n_with_times < len(source):
        log.warning("%d of %d scans have no per-point times; they are used without motion compensation.",
                    len(source) - timed.n_with_times, len(source))
    return T_initial, deskewed, info


def _summary(problem: FeatureProblem, T_initial: np.ndarray, T_world_scan: np.ndarray, rounds: list[dict[str, Any]],
             settled: bool, factors: OdometryFactors | None) -> dict[str, Any]:
    """The report's summary: the last round's plane problem at the initial and at the given poses."""
    n_points = max(problem.n_points, 1)
    cost_initial = float(plane_cost(problem, T_initial))
    cost_final = float(plane_cost(problem, T_world_scan))
    summary = {
        "note": "cost and RMS use the last round's plane problem at the initial and refined poses; "
                "see quality for the cross-scored comparison",
        "n_scans": int(problem.n_scans), "n_landmarks": int(problem.n_planes),
        "n_observations": int(problem.n_observations), "n_points_on_planes": int(problem.n_points),
        "cost_initial_m2": cost_initial, "cost_final_m2": cost_final,
        "rms_point_to_plane_initial_m": float(np.sqrt(cost_initial / n_points)),
        "rms_point_to_plane_final_m": float(np.sqrt(cost_final / n_points)),
        "iterations": int(sum(r.get("iterations", r["solver"].get("iterations", 0)) for r in rounds)),
        "n_rounds": len(rounds),
        "settled": bool(settled),
    }
    if factors is not None:
        summary["odometry_cost_initial_m2"] = factors.cost(T_initial)
        summary["odometry_cost_final_m2"] = factors.cost(T_world_scan)
    return summary


def map_entropy(source: Any, deskewed: DeskewedPoints | None, config: PaConfig, pose_sets: dict[str, np.ndarray],
                stage: Stage) -> dict[str, Any]:
    """`mean_map_entropy` of the scans under each pose set of `pose_sets` (name -> T_world_scan),
    on the same map points and query points (`advanced.quality`'s entropy keys)."""
    quality = config.advanced.quality
    with stage("map entropy") as progress:
        if deskewed is None:
            counts = [len(source.points(k)) for k in range(len(source))]
        else:  # the re-binned scans: points from their own and their neighbours' sweeps
            counts = [sum(len(index) for _, index in deskewed.sources(j)) for j in range(len(source))]
        entropy = mean_map_entropy({name: points_at(source, deskewed, T) for name, T in pose_sets.items()}, pose_sets,
                                   counts, quality.entropy_radius_m, quality.entropy_min_neighbours,
                                   quality.entropy_max_map_points, quality.entropy_query_points)
        progress(1, 1)
    return entropy


def assessment(source: Any, deskewed: DeskewedPoints | None, config: PaConfig, T_initial: np.ndarray,
               T_world_scan: np.ndarray, problem: FeatureProblem, plane_problem: FeatureProblem,
               labels_initial: PointLabels, labels_final: PointLabels, rounds: list[dict[str, Any]], settled: bool,
               factors: OdometryFactors | None, stage: Stage) -> Assessment:
    """The evidence on the poses T_world_scan against T_initial (`pa_cli.evaluation.quality`):
    the summary, the degeneracy of the last round's features (weakest direction per scan, scans
    held only by odometry) and the verdict from cross-scored RMS, map entropy, free space
    (`pa_cli.evaluation.free_space`), odometry agreement, ties and settling."""
    quality, lever_arm_m = config.advanced.quality, config.advanced.degeneracy.lever_arm_m
    # the motions at the odometry model's sigmas: what the planes must see is a break of the odometry's scale
    # (decimetres, a degree), not one of the registrations' noise (millimetres)
    odometry = None if factors is None else OdometryFactors.from_motions(factors.R_z, factors.t_z, factors.model)
    odometry_information = None if odometry is None else odometry.linearize(T_world_scan).pose_blocks
    degeneracy = scan_degeneracy(problem, T_world_scan, lever_arm_m, odometry_information)
    pose_sets = {"initial": T_initial, "refined": T_world_scan}
    rms: dict[str, dict[str, float]] = {}
    with stage("plane RMS") as progress:
        for name, labels in (("planes_at_initial_poses", labels_initial), ("planes_at_refined_poses", labels_final)):
            rms[name] = {pose_set: rms_point_to_plane(labels.problem(points_at(source, deskewed, T)), T)
                         for pose_set, T in pose_sets.items()}
        progress(1, 1)
    entropy = map_entropy(source, deskewed, config, pose_sets, stage)
    with stage("free space") as progress:
        # the sharpest RMS point-to-plane bounds the range noise from above: points scatter about their planes by it
        noise_m = min(r for association in rms.values() for r in association.values())
        free_space = free_space_check(points_by_pose_set(source, deskewed, pose_sets), pose_sets, noise_m,
                                      quality.entropy_radius_m)
        progress(1, 1)
    sigmas = ties = words = decide = None
    if odometry is not None:
        sigmas = odometry.normalized_residuals(T_world_scan)
        tie_information = pair_tie_information(plane_problem, T_world_scan)
        ties, directions = pair_ties(tie_information, odometry.weights)
        frames = travel_frames(T_world_scan)
        words = [describe(np.r_[d[:3] * lever_arm_m, d[3:]], frames[j + 1])
                 for j, d in enumerate(directions)]
        decide = decided_by_planes(tie_information, odometry.residuals(T_world_scan), odometry.weights, T_world_scan)
    verdict = assess(rms, sigmas, ties, settled, quality.outlier_sigma, quality.rms_tolerance, entropy,
                     quality.entropy_tolerance_nats, planes_decide=decide, tie_words=words,
                     held=degeneracy.held_by_odometry, entropy_standard_errors=quality.entropy_standard_errors,
                     free_space=free_space)
    return Assessment(_summary(problem, T_initial, T_world_scan, rounds, settled, factors), degeneracy, verdict)


def covariance_lower_bound_gb(problem: FeatureProblem) -> float:
    """A lower bound of the pose covariance's memory (GB): the fewest 6x6 blocks of the matrices
    it may invert (the factor and the inverse have at least those). With a set S of features as
    nodes (`pa_cli.adjust.covariance._block_pattern`) the matrix has a block per scan, per node, per
    observation of a node and per pair of scans sharing a feature not in S (the nonzeros of R R^T,
    R the scan-feature incidence without S); the bound is the least over the sets the covariance
    chooses from (`node_sets`, with the features seen by more than PAIR_MAX_SCANS scans as the
    candidates)."""
    k = np.bincount(problem.plane_index, minlength=max(problem.n_planes, 1))
    best = np.inf
    for as_node in node_sets(k, k > PAIR_MAX_SCANS):
        paired = ~as_node[problem.plane_index]
        incidence = sp.csr_matrix((np.ones(int(paired.sum()), dtype=np.float32),
                                   (problem.scan_index[paired], problem.plane_index[paired])),
                                  shape=(problem.n_scans, len(k)))
        shared = (incidence @ incidence.T).nnz  # each off-diagonal pair twice; scans with a feature once
        pairs = (shared - np.count_nonzero(np.diff(incidence.indptr))) / 2
        best = min(best, problem.n_scans + int(as_node.sum()) + int(np.count_nonzero(~paired)) + pairs)
    return best * COVARIANCE_BYTES_PER_BLOCK / GB


def pose_covariance(problem: FeatureProblem, T_world_scan: np.ndarray, terms: list[Any], model: Any,
                    config: PaConfig, covariance_path: str, stage: Stage) -> tuple[Any, dict[str, Any]]:
    """Per-scan covariance of the poses (`pa_cli.adjust.covariance`) from the last round's feature
    problem (with the range clusters of its association) and the pose terms, relative to the gauge
    pose, with the noise model `advanced.covariance.noise_model`; `model` is the last solve's state
    (None: built afresh). Returns (None, {"error": ...}) when it would exceed the memory budget or
    the Hessian is singular (a scan the features leave free and no prior): `covariance_path` is
    then not written."""
    needed_gb = covariance_lower_bound_gb(problem)
    budget_gb = config.execution.memory_budget_gb
    if needed_gb > budget_gb:
        message = (f"the pose covariance needs at least {needed_gb:.1f} GB, above execution.memory_budget_gb = "
                   f"{budget_gb:g} (its matrix has a block for every pair of scans sharing a plane, or for "
                   "every observation of the planes it takes as nodes)")
        log.warning("no pose covariance (%s is not written): %s.", covariance_path, message)
        return None, {"error": message}
    with stage("covariance") as progress:
        try:
            covariance, report = timed_pose_covariance(
                problem, T_world_scan, fixed_pose=config.advanced.solver.fixed_pose,
                eigen_gap_tolerance=config.advanced.solver.eigen_gap_tolerance, terms=terms,
                noise_model=config.advanced.covariance.noise_model, memory_budget_gb=budget_gb,
                max_block_products=config.advanced.covariance.max_block_products, model=model)
        except SolverError as exc:
            log.warning("no pose covariance (%s is not written): %s", covariance_path, exc)
            covariance, report = None, {"error": str(exc)}
        progress(1, 1)
    return covariance, report


def association_check(state: RefineState) -> RoundsResult:
    """The rounds' result once the association its cap froze while it still moved is judged: the rounds did
    not settle (`settled` false, a doubt in the verdict naming the scans and how far they moved), and the
    moves are set against the pose covariance (`association_within`, in the report and the reason): within
    its 3 sigma they are below what the data resolve, beyond it the association decides the answer."""
    rounds = state.rounds
    unsettled = rounds.unsettled_association
    if unsettled is None:
        return rounds
    position_m2 = None if state.covariance is None else state.covariance.position_covariance_m2()
    judged = {**unsettled, **association_within(unsettled, position_m2)}
    if position_m2 is None:
        judge, named = "no pose covariance to judge them by", unsettled["scans"]
    elif judged["within_3_sigma"]:
        judge = f"every one within 3 sigma of the pose covariance (at most {judged['max_sigmas']:.1f} sigma)"
        named = unsettled["scans"]
    else:
        named = [s for s in unsettled["scans"] if s["scan"] in judged["scans_beyond_3_sigma"]]
        judge = (f"{len(named)} of them beyond 3 sigma of the pose covariance (up to {judged['max_sigmas']:.1f} "
                 "sigma)")
    listed = ", ".join(f"{s['scan']} ({s['moved_m']:.3f} m)" for s in named[:LISTED_SCANS])
    reason = (f"the rounds did not settle: the association was frozen by advanced.association.max_rounds while "
              f"its last fresh association (round {unsettled['round']}) still moved {len(unsettled['scans'])} "
              f"scan(s) by more than advanced.association.settle_m ({unsettled['settle_m']:g} m), up to "
              f"{unsettled['max_pose_change_m']:.4f} m, {judge} (scans {listed}"
              f"{' ...' if len(named) > LISTED_SCANS else ''})")
    log.warning("%s.", reason[0].upper() + reason[1:])
    assessed = rounds.assessment
    quality = dataclasses.replace(assessed.quality.with_doubt(reason), settled=False)
    assessed = dataclasses.replace(assessed, quality=quality, summary={**assessed.summary, "settled": False})
    return dataclasses.replace(rounds, settled=False, assessment=assessed, unsettled_association=judged)


def start_check(state: RefineState, config: PaConfig, n_scans: int, stage: Stage) -> RoundsResult:
    """The rounds' result after the start-consistency check (`pa_cli.refine.consistency`), when
    `advanced.quality.start_check` is on and the rounds have odometry factors: its record, and a
    doubt in the verdict when scans end beyond the pose covariance's 3 sigma."""
    rounds = state.rounds
    if not config.advanced.quality.start_check or rounds.odometry_factors is None:
        return rounds
    solver_config = warm_config(choose_backend(config.advanced.solver, n_scans)[0], rounds.problem)
    position_m2 = None if state.covariance is None else state.covariance.position_covariance_m2()
    with stage("start check") as progress:
        check = start_consistency(rounds.problem, state.T_current, rounds.odometry_factors,
                                  solver_config, position_m2)
        progress(1, 1)
    assessed = rounds.assessment
    if not check.consistent:
        log.warning("%s.", check.reason()[0].upper() + check.reason()[1:])
        assessed = dataclasses.replace(assessed, quality=assessed.quality.with_doubt(check.reason()))
    return dataclasses.replace(rounds, assessment=assessed, start_consistency=check.report())


def spread_covariance(state: RefineState) -> tuple[Any, dict[str, Any] | None]:
    """The pose covariance and its report once the spread of the answer over the association is
    added (`pa_cli.refine.consistency.association_spread`); unchanged without a covariance or with
    one fresh association (nothing to compare it with)."""
    rounds, covariance, report = state.rounds, state.covariance, state.covariance_report
    if covariance is None or rounds.association_change is None:
        return covariance, report
    fresh = [record["round"] for record in rounds.rounds if record["association"] == "new"]
    spread, record = association_spread(covariance, rounds.association_change, fresh[-1])
    log.info("the association's spread adds up to %.4f m (median %.4f m) to the poses' 1-sigma (round %d against "
             "round %d).", record["max_added_position_sigma_m"], record["median_added_position_sigma_m"],
             fresh[-1], fresh[-1] - 1)
    return spread, {**report, **covariance_report(spread), "association_spread": record}


def evaluate_against_gt(gt: Trajectory, source: Any, state: RefineState, labels_final: PointLabels,
                        stage: Stage) -> dict[str, Any]:
    """ATE and RPE of the initial and refined poses (and the odometry's when loops ran) against the
    ground truth (SE(3)-aligned); with one truth pose per scan, the plane cost of the last
    association (`labels_final`) at the truth and at the initial poses too."""
    with stage("evaluate") as progress:
        stamps = state.timestamps if gt.timestamps is not None else None

        def against_gt(T_local_scan: np.ndarray) -> dict[str, Any]:
            return evaluate(gt, Trajectory(to_world(T_local_scan, state.origin_world_m), stamps), align="se3")

        result: dict[str, Any] = {"initial": against_gt(state.T_initial), "refined": against_gt(state.T_current)}
        if state.loops["enabled"]:  # "initial" is loop-closed
            result["odometry"] = against_gt(state.T_odometry)
        if len(gt) == len(state.T_current):
            # the plane cost is invariant to one rigid motion of all poses, so the truth counts in
            # its own local frame; the last association, its points deskewed with each trajectory in turn
            T_gt = to_local(gt.T_world_scan, local_origin_m(gt.T_world_scan))
            for name, T in (("gt", T_gt), ("initial", state.T_initial)):
                problem = labels_final.problem(points_at(source, state.deskewed, T))
                cost = float(plane_cost(problem, T))
                result[f"cost_at_{name}_poses_m2"] = cost
                result[f"rms_point_to_plane_at_{name}_m"] = float(np.sqrt(cost / max(problem.n_points, 1)))
        progress(1, 1)
    return result
