"""The strategy of the rounds: associate planes, adjust, freeze the association, settle.

    register every consecutive pair (advanced.odometry.measurements: registration): the odometry
        factors' motions, on the scans as recorded, then (motion compensation) once more on the scans
        deskewed along the chain of those motions; start at their chain (`registration_chain`; after a
        loop closure the pose graph of the motions and the closures, `loop_closed_chain`; with
        measurements: initial, at state.T_current), deskewed along it; all of it in the frame of the gauge
        scan's starting pose (`in_gauge_frame`), the result put back in the start's frame after the rounds
    for each round, at most refine.max_rounds:
        association new  -> planes and edges found at the current poses
            (scene.edges auto: the first round keeps the edges for the run only where they leave fewer scans
            poorly constrained than the planes alone)
        association kept -> every point keeps its plane or edge, the clusters are re-summed (re-deskewed)
        adjust the poses (planes, edges, odometry factors; with the motions' noise measured the factors
            are weighed against the planes' point noise, `PlaneBalance`, measured at the features' own
            optimum from the round's start;
            a round after the first starts at the round before's optimum, and with odometry factors the first
            at their chain: with the hierarchical backend its final flat pass alone, `warm_config`)
        freeze the association after advanced.association.rounds once a round moved no pose more
            than advanced.association.settle_m (or after advanced.association.max_rounds: the scans
            its last fresh association moved further are kept in `unsettled_association`; the rounds
            then did not settle, and `pa_cli.refine.stages.association_check` sets those moves against
            the pose covariance)
        from the second fresh association on, its change of the answer (`association_change`: the
            round's result against the round before's) is kept for the covariance
            (`pa_cli.refine.consistency.association_spread`)
        settled when a round moved no pose more than the tolerances and the association settled
        else, with a frozen association and motion compensation: the next start is the deskew
            fixed point's
    assess the poses

Every step takes what it needs and returns what it made; nothing here writes the outputs or the
report. With a work folder (`RoundsWork`) the registered motions and what each round hands the
next (`RoundsCarry`) are kept there, and the rounds continue from what it holds.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any, Protocol

import numpy as np

from pa_cli.adjust import solve
from pa_cli.adjust.covariance import tangent_error
from pa_cli.adjust.hierarchical import choose_backend, warm_config
from pa_cli.adjust.noise_model import PlaneBalance
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel, relative_motions
from pa_cli.config import PaConfig, SolverConfig
from pa_cli.core.geometry import pose_change, rigid_inverse
from pa_cli.core.problem import FeatureProblem
from pa_cli.errors import SolverError
from pa_cli.loops.pose_graph import Edge, optimize_pose_graph
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.edges import EdgeLabels, edges_hold_weak_scans, with_edges
from pa_cli.planes.labels import PointLabels
from pa_cli.planes.windowed import ScanRef, plane_passes
from pa_cli.refine.clock import Progress, Stage
from pa_cli.refine.deskew import DeskewFixedPoint
from pa_cli.refine.memory import check_adjust_memory
from pa_cli.refine.pair_registration import MotionNoise, closure_sigmas, register_consecutive
from pa_cli.refine.stages import assessment, points_at
from pa_cli.refine.state import Assessment, RefineState, RoundsCarry, RoundsResult
from pa_cli.sources import reads_scans_apart

log = logging.getLogger(__name__)

# A round solves again from its optimum with the balance measured from there (`PlaneBalance`) while that moved by
# more than this fraction: the features' optimum from the round's answer need not be the one from its start, so the
# association is made again at nearly the balance of its answer.
BALANCE_TOLERANCE = 0.1
MAX_BALANCE_SOLVES = 4  # solves per round at most (the round's first included)


class RoundsWork(Protocol):
    """Where the rounds keep what they finished (`pa_cli.refine.work.WorkFolder`); a load is
    None when nothing of its kind was kept."""

    def load_motions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any] | None] | None: ...

    def save_motions(self, R_z: np.ndarray, t_z: np.ndarray, sigmas: np.ndarray,
                     noise: dict[str, Any] | None) -> None: ...

    def load_carry(self) -> RoundsCarry | None: ...

    def save_carry(self, carry: RoundsCarry) -> None: ...


def settles(config: PaConfig, moved_m: float, turned_deg: float) -> bool:
    """Whether a solve that moved no pose more than this is within the tolerances (settled)."""
    return moved_m < config.refine.pose_change_tolerance_m and turned_deg < config.refine.pose_change_tolerance_deg


def pair_scans(scans: ScanRef, deskewed: Any, config: PaConfig) -> ScanRef | None:
    """Where window tasks of the registrations of consecutive pairs read their scans (`register_consecutive`):
    `scans` on dask workers (`execution.workers` or a scheduler), and on processes of this machine where a task
    reads its window at the cost of its scans (`reads_scans_apart`: scan files, not a bag or a pcap each task would
    read whole); None for this process, and when the points are deskewed (the deskewed points are this
    process's)."""
    if deskewed is not None:
        return None
    on_workers = config.execution.workers or config.execution.scheduler_address
    return scans if on_workers or reads_scans_apart(scans.path, scans.glob) else None


def registered_motions(source: Any, scans: ScanRef, deskewed: Any, T_start: np.ndarray, config: PaConfig,
                       stage: Stage) -> tuple[OdometryFactors, MotionNoise | None]:
    """Odometry factors measured by registering every consecutive pair of scans (GICP on all their
    points, to its own fixed point from the relative motion of T_start: `register_consecutive`, at
    advanced.registration's voxel and correspondence distance), with the registrations' noise measured on closures
    (`closure_sigmas`, also returned; None where too few pairs registered); a pair whose registration did
    not converge keeps T_start's motion with the odometry model's sigmas, as does every pair when the noise
    was not measured. Pairs whose registered motion differs from T_start's by more than
    `advanced.quality.outlier_sigma` of the odometry model's sigmas (a break of the start) are named in a
    warning."""
    points = points_at(source, deskewed, T_start)
    voxel_m, max_correspondence_m = (config.advanced.registration.voxel_m,
                                     config.advanced.registration.max_correspondence_m)
    with stage("register motions", total=len(source) - 1) as progress:
        pairs = register_consecutive(points, T_start, voxel_m, max_correspondence_m, progress=progress,
                                     scans=pair_scans(scans, deskewed, config),
                                     window_scans=config.advanced.execution.window_scans,
                                     threads=config.execution.threads)
    with stage("motion noise") as progress:
        noise = closure_sigmas(points, pairs, voxel_m, max_correspondence_m, config.execution.threads)
        progress(1, 1)
    R_start, t_start = relative_motions(T_start)
    R = np.where(pairs.converged[:, None, None], pairs.T_prev_next[:, :3, :3], R_start)
    t = np.where(pairs.converged[:, None], pairs.T_prev_next[:, :3, 3], t_start)
    if not pairs.converged.all():
        log.warning("%d of %d consecutive pairs did not register; their odometry factors keep the initial motion.",
                    int((~pairs.converged).sum()), len(pairs.converged))
    factors = OdometryFactors.from_motions(R, t, OdometryModel.from_config(config))
    off_sigmas = factors.normalized_residuals(T_start).max(axis=1)
    broken = np.flatnonzero(off_sigmas > config.advanced.quality.outlier_sigma)
    if len(broken):
        e = factors.residuals(T_start)[broken]
        log.warning("the registrations differ from the start's relative motion by more than %g odometry sigmas at "
                    "%d pair(s) (%s; up to %.2f deg, %.3f m): the start is broken there, and the odometry factors hold "
                    "the registered motions", config.advanced.quality.outlier_sigma, len(broken),
                    ", ".join(f"{j}-{j + 1}" for j in broken[:10]) + (" ..." if len(broken) > 10 else ""),
                    np.rad2deg(np.linalg.norm(e[:, :3], axis=1).max()), np.linalg.norm(e[:, 3:], axis=1).max())
    if noise is None:
        log.info("too few consecutive pairs registered to measure their noise; the odometry factors take the "
                 "odometry model's sigmas.")
        return factors, None
    log.info("registrations' noise measured on %d closures: rotation %s deg, translation %s m (scan axes x, y, z)",
             noise.n_closures, ", ".join(f"{x:.3g}" for x in np.rad2deg(noise.sigmas[:3])),
             ", ".join(f"{x:.3g}" for x in noise.sigmas[3:]))
    sigmas = np.where(pairs.converged[:, None], noise.sigmas[None, :], factors.sigmas)
    return OdometryFactors.from_motions(R, t, factors.model, sigmas), noise


def in_gauge_frame(T_world_scan: np.ndarray, gauge: int) -> np.ndarray:
    """The poses (N, 4, 4) in the frame of scan `gauge`'s pose, that pose exactly the identity."""
    T = rigid_inverse(T_world_scan[gauge][None])[0] @ T_world_scan
    T[gauge] = np.eye(4)
    return T


def registration_chain(factors: OdometryFactors, T_world_scan: np.ndarray, gauge: int) -> np.ndarray:
    """The trajectory (N, 4, 4) that holds every measured relative motion exactly and keeps scan
    `gauge`'s pose of `T_world_scan` (the solver's fixed pose): the optimum of the odometry factors
    alone."""
    T_prev_next = _measured_motions(factors)
    chain = np.tile(np.eye(4), (len(T_prev_next) + 1, 1, 1))
    for j, step in enumerate(T_prev_next):
        chain[j + 1] = chain[j] @ step
    return T_world_scan[gauge] @ rigid_inverse(chain[gauge:gauge + 1])[0] @ chain


def loop_closed_chain(factors: OdometryFactors, T_world_scan: np.ndarray, closures: list[list[int]],
                      config: PaConfig) -> np.ndarray:
    """The trajectory (N, 4, 4) that holds the measured relative motions and the loop stage's closures:
    a pose graph (`pa_cli.loops.pose_graph`) of every consecutive pair's motion (the factors' sigmas)
    and, per closure (anchor scans a, b), the relative pose of a and b in the loop-closed
    `T_world_scan` (the loop edges' sigmas and kernel), solved from `T_world_scan`; scan
    `advanced.solver.fixed_pose` keeps its pose. The rounds' start after a loop closure: as consistent
    from scan to scan as the registrations, as closed as the loops."""
    loops = config.advanced.loops
    edges = [Edge(j, j + 1, T_prev_next, float(factors.sigma_r_rad[j]), float(factors.sigma_t_m[j]))
             for j, T_prev_next in enumerate(_measured_motions(factors))]
    edges += [Edge(a, b, rigid_inverse(T_world_scan[a:a + 1])[0] @ T_world_scan[b],
                   float(np.deg2rad(loops.loop_rotation_sigma_deg)), loops.loop_translation_sigma_m, robust=True)
              for a, b in closures]
    T, _ = optimize_pose_graph(T_world_scan, edges, loops.robust_kernel_sigmas)
    gauge = config.advanced.solver.fixed_pose
    return T_world_scan[gauge] @ rigid_inverse(T[gauge:gauge + 1])[0] @ T


def _measured_motions(factors: OdometryFactors) -> np.ndarray:
    """The factors' measured relative motions as (N-1, 4, 4) rigid motions T_prev_next."""
    T_prev_next = np.tile(np.eye(4), (len(factors.t_z), 1, 1))
    T_prev_next[:, :3, :3], T_prev_next[:, :3, 3] = factors.R_z, factors.t_z
    return T_prev_next


def _chain(factors: OdometryFactors, T_world_scan: np.ndarray, state: RefineState, config: PaConfig) -> np.ndarray:
    """The trajectory that holds the factors' measured motions from T_world_scan: their pose graph with the loop
    stage's closures when it closed a loop (`loop_closed_chain`), else their chain (`registration_chain`)."""
    if _loops_closed(state):
        return loop_closed_chain(factors, T_world_scan, state.loops["closures"], config)
    return registration_chain(factors, T_world_scan, config.advanced.solver.fixed_pose)


def _at_plane_noise(factors: OdometryFactors, balance: PlaneBalance, problem: FeatureProblem,
                    T_world_scan: np.ndarray, config: SolverConfig) -> OdometryFactors:
    """The factors with their cost expressed at the feature term's measured point noise (`PlaneBalance`): both
    terms then weigh their residuals by their own measured noise. The noise is measured at the features' own
    optimum from T_world_scan (`problem` solved alone): there the observations' offsets are the noise their points
    share, while at T_world_scan they also hold its pose errors, which would count as noise, weigh the planes down
    and keep those errors (a start 1 deg / 0.1 m off: a balance of 0.3-0.4 m on a hall of 2 cm point noise)."""
    T_features = solve(problem, T_world_scan, config).T_world_scan
    model = replace(factors.model, point_sigma_m=balance.point_sigma_m(T_features))
    return OdometryFactors.from_motions(factors.R_z, factors.t_z, model, factors.sigmas)


def _loops_closed(state: RefineState) -> bool:
    """Whether the loop stage closed a loop: its poses then hold what consecutive motions cannot."""
    return bool(state.loops.get("n_closures"))


def _solver(config: PaConfig, n_scans: int, factors: OdometryFactors | None) -> tuple[SolverConfig, int]:
    """The backend for this many scans (`choose_backend`) and the iterations its progress bar counts."""
    solver_config, message = choose_backend(config.advanced.solver, n_scans)
    if solver_config.solver == "hierarchical":
        log.info(message or "using the hierarchical backend (advanced.solver.solver).")
        if factors is not None and not solver_config.hierarchical_final_iterations:
            log.warning("the odometry factors act in the hierarchical backend's final flat pass only, "
                        "and advanced.solver.hierarchical_final_iterations is 0.")
    elif config.execution.workers or config.execution.scheduler_address:
        log.warning("the flat %s backend runs in this process; the dask workers run the hierarchical "
                    "backend's windows (advanced.solver.solver: hierarchical).", solver_config.solver)
    budget = solver_config.hierarchical_final_iterations if solver_config.solver == "hierarchical" \
        else solver_config.max_iterations
    return solver_config, budget


def round_edges(planes: FeatureProblem, diagnostics: dict[str, Any], points: Any, T_world_scan: np.ndarray,
                config: PaConfig, first_round: bool, edge_labels: EdgeLabels | None, frozen: bool
                ) -> tuple[FeatureProblem, EdgeLabels | None, dict[str, Any]]:
    """A round's feature problem: its planes with the run's edges (`scene.edges`), those of `edge_labels` (the
    latest fresh association's) in a `frozen` round or found at T_world_scan in a fresh one, with the edge
    association and the round's diagnostics (`with_edges`'). After the first round the run uses edges exactly
    when it holds an edge association. In the first round with scene.edges auto, the edges are looked for only
    where the planes leave some scan poorly constrained, and kept when they leave fewer such scans
    (`edges_hold_weak_scans`); otherwise the planes alone, the diagnostics saying why (`edges.reason`)."""
    if not first_round and edge_labels is None:
        return planes, None, diagnostics
    auto = first_round and config.scene.edges == "auto"
    if auto and not diagnostics.get("poorly_constrained_scans"):
        return planes, None, {**diagnostics, "edges": {"used": False, "reason": "the planes hold every scan"}}
    with_lines = dict(diagnostics)
    problem, edge_labels = with_edges(planes, with_lines, points, T_world_scan, config.edges_config(),
                                      config.advanced.planes.min_constraint_eigenvalue,
                                      frozen=edge_labels if frozen else None, threads=config.execution.threads)
    if auto and not edges_hold_weak_scans(with_lines):
        unused = {**with_lines["edges"], "used": False,
                  "reason": "the edges hold no scan the planes leave poorly constrained"}
        return planes, None, {**diagnostics, "edges": unused}
    return problem, edge_labels, with_lines


def refine_rounds(source: Any, scans: ScanRef, state: RefineState, config: PaConfig, stage: Stage,
                  work: RoundsWork | None = None) -> RoundsResult:
    """Rounds of (deskew, plane association at the current poses, second-order adjustment) from
    the chain of the registered motions (the module docstring gives the strategy); then the assessment of the
    result. With `work`, the rounds start from its carry (when it holds one) and hand
    it each round's carry; the result equals that of rounds run without a stop."""
    cfg = config
    deskewed = state.deskewed
    factors = None
    motion_noise = None  # the record of the registrations' measured noise (`MotionNoise.report`)
    gauge = cfg.advanced.solver.fixed_pose
    # The rounds run in the frame of the gauge scan's pose at their start (`in_gauge_frame`), where the landmarks'
    # voxel grid lies: two starts that differ by a rigid motion (KISS-ICP's frame is scan 0's, --poses keep
    # theirs) cut the scene into the same voxels, and when they register the same motions they compute the same
    # numbers to the last bit (in each start's own frame the last bits differ, and the plane association, a step
    # function of the poses, can amplify that to tenths of a millimetre). The result is put back in the start's
    # frame.
    T_world_grid = state.T_current[gauge].copy()
    T_current = in_gauge_frame(state.T_current, gauge)
    T_start = T_current
    if cfg.refine.odometry_translation_sigma_m is not None:
        # relative motions (of the initial trajectory, or registered) hold what the planes leave free
        if cfg.advanced.odometry.measurements == "registration":
            kept = None if work is None else work.load_motions()
            if kept is None:
                # first on the scans as recorded (the start's velocity errors would distort them), then, with
                # motion compensation, on the scans deskewed along the chain of those motions
                factors, noise = registered_motions(source, scans, None, state.T_initial, cfg, stage)
                if deskewed is not None:
                    factors, noise = registered_motions(source, scans, deskewed,
                                                        _chain(factors, T_current, state, cfg), cfg, stage)
                motion_noise = None if noise is None else noise.report()
                if work is not None:
                    work.save_motions(factors.R_z, factors.t_z, factors.sigmas, motion_noise)
            else:
                R_z, t_z, sigmas, motion_noise = kept
                factors = OdometryFactors.from_motions(R_z, t_z, OdometryModel.from_config(cfg), sigmas)
            T_start = _chain(factors, T_current, state, cfg)
        else:
            factors = OdometryFactors(state.T_initial, OdometryModel.from_config(cfg))
    terms = [] if factors is None else [factors]
    solver_config, budget = _solver(cfg, len(source), factors)
    # on dask workers the passes over the scans are window tasks reading the scans themselves
    # (not with motion compensation: a deskewed scan needs its neighbours' points and the trajectory)
    passes = None if deskewed is not None else plane_passes(scans, cfg.execution, cfg.advanced.execution)
    build = build_plane_problem if passes is None else passes.build

    def in_world(T_grid_scan: np.ndarray) -> np.ndarray:
        return T_world_grid @ T_grid_scan

    carry = (None if work is None else work.load_carry()) or RoundsCarry(0, T_start, [])
    T, rounds = carry.T_world_scan, carry.records
    labels_initial, labels_final = carry.labels_initial, carry.labels_final
    frozen: PointLabels | None = labels_final if carry.frozen else None
    edge_labels = carry.edge_labels  # the edges of the latest fresh association, frozen with its planes
    fixed_point = DeskewFixedPoint(cfg.advanced.degeneracy.lever_arm_m, cfg.advanced.deskew.max_contraction)
    fixed_point.remember(carry.fixed_point)
    settled = False
    unsettled_association = carry.unsettled_association  # the association the cap froze while it still moved
    association_change = carry.association_change  # the latest fresh association's change of the answer
    solver_model = None
    for r in range(carry.next_round, cfg.refine.max_rounds):
        solver_model = result = None  # the last round's solver state is not held through this round's planes
        round_start = T
        association = "new" if frozen is None else "frozen"
        with stage(f"planes {r + 1}", total=len(source)) as progress:  # the round's features, edges included
            points = points_at(source, deskewed, T)
            if frozen is None:
                found: dict[str, Any] = {}  # the per-point labels of the association (`build_plane_problem`)
                problem, diagnostics = build(points, T, cfg.planes_config(), progress=progress, landmarks_out=found)
                problem = replace(problem, T_world_scan=T)
                if problem.n_observations == 0:
                    raise SolverError(f"{source.name}: round {r + 1} found no plane seen by two scans; "
                                      "try a config with larger scene.plane_voxel_m or scene.max_plane_thickness_m "
                                      "(--config outdoor) or check the initial poses.")
                labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks,
                                                      found["kept"], problem)
                plane_problem = problem
                if r == 0:
                    labels_initial = labels
                labels_final = labels
            else:
                problem = plane_problem = frozen.problem(points, T, with_range=True)
                diagnostics = {"association": "frozen (every point keeps its plane)",
                               "n_landmarks": problem.n_planes, "n_observations": problem.n_observations}
                progress(len(source), len(source))
            problem, edge_labels, diagnostics = round_edges(plane_problem, diagnostics, points, T, cfg, r == 0,
                                                            edge_labels, frozen is not None)
        # every later round starts from the round before's optimum, and with pose terms the first from the chain of
        # their measured motions (loop-closed where loops closed), at or near the terms' own optimum, which the
        # hierarchical layers (the features alone) would leave: each runs the final flat pass alone where it fits
        # the budget (`warm_config`)
        round_config = warm_config(solver_config, problem) if r > 0 or terms else solver_config
        round_budget = budget if round_config is solver_config else round_config.max_iterations
        check_adjust_memory(f"adjust {r + 1}", problem, solver_config, cfg)  # warm_config bounds its own
        with stage(f"adjust {r + 1}", total=round_budget) as progress:
            def on_iteration(record: Any, progress: Progress = progress, total: int = round_budget) -> None:
                progress(record.iteration, total)

            if motion_noise is not None:  # both terms at their measured noise
                balance = PlaneBalance(problem)
                factors = _at_plane_noise(factors, balance, problem, T, round_config)
                terms = [factors]
            result = solve(problem, T, round_config, progress=on_iteration, terms=terms)
            iterations = result.report["iterations"]
            balance_solves = 1
            while motion_noise is not None and balance_solves < MAX_BALANCE_SOLVES:
                # the balance measured at the round's own optimum, solved again while it moved
                balanced = _at_plane_noise(factors, balance, problem, result.T_world_scan, round_config)
                if abs(balanced.point_sigma_m / factors.point_sigma_m - 1.0) <= BALANCE_TOLERANCE:
                    break
                factors, terms = balanced, [balanced]
                result = solve(problem, result.T_world_scan, round_config, progress=on_iteration, terms=terms)
                iterations += result.report["iterations"]
                balance_solves += 1
            progress(iterations, iterations)
        moved_m, turned_deg = pose_change(T, result.T_world_scan)
        if association == "new" and r > 0:  # against the answer of the fresh association before
            association_change = tangent_error(in_world(result.T_world_scan), in_world(round_start))
        if association == "new" and r + 1 >= cfg.advanced.association.rounds and (
                moved_m <= cfg.advanced.association.settle_m or r + 1 >= cfg.advanced.association.max_rounds):
            frozen = labels
            if moved_m > cfg.advanced.association.settle_m:
                unsettled_association = _still_moving(in_world(T), in_world(result.T_world_scan), r + 1,
                                                      cfg.advanced.association.settle_m)
        rounds.append({"round": r + 1, "planes": diagnostics, "solver": result.report, "iterations": iterations,
                       "association": association,
                       "n_planes": problem.n_planes, "n_observations": problem.n_observations,
                       "n_points": problem.n_points, "max_pose_change_m": moved_m,
                       "max_pose_change_deg": turned_deg,
                       **({} if motion_noise is None else {"balance_point_sigma_m": factors.point_sigma_m,
                                                            "balance_solves": balance_solves})})
        T = result.T_world_scan
        solver_model = result.model  # reused by the covariance (SolveResult.model)
        log.debug("round %d: poses moved up to %.4g m, %.4g deg", r + 1, moved_m, turned_deg)
        if settles(cfg, moved_m, turned_deg):
            settled = True
            break
        if association == "frozen" and deskewed is not None and r + 1 < cfg.refine.max_rounds:
            # the deskew fixed point (the last round's output stays the adjustment's result)
            T, rounds[-1]["deskew_acceleration"] = fixed_point.next_start(round_start, result.T_world_scan)
        if work is not None and r + 1 < cfg.refine.max_rounds:
            work.save_carry(RoundsCarry(r + 1, T, rounds, labels_initial, labels_final, frozen is not None,
                                        unsettled_association, fixed_point.memory(), association_change,
                                        edge_labels))
    if not settled:
        log.warning("rounds did not settle: round %d still moved a pose %.4g m / %.4g deg (tolerance %g m / "
                    "%g deg); raise refine.max_rounds or check the report.", len(rounds),
                    rounds[-1]["max_pose_change_m"], rounds[-1]["max_pose_change_deg"],
                    cfg.refine.pose_change_tolerance_m, cfg.refine.pose_change_tolerance_deg)
    assert labels_initial is not None and labels_final is not None  # round 1 always associates
    T = in_world(T)
    # each problem keeps the poses it was built at, in the start's frame
    problem, plane_problem = (p if p.T_world_scan is None else replace(p, T_world_scan=in_world(p.T_world_scan))
                              for p in (problem, plane_problem))

    assessed = assessment(source, deskewed, cfg, state.T_initial, T, problem, plane_problem, labels_initial,
                          labels_final, rounds, settled, factors, stage)
    result = RoundsResult(T, problem, plane_problem, labels_final, rounds, settled, terms, factors,
                          solver_model, assessed,
                          unsettled_association=unsettled_association, association_change=association_change,
                          edge_labels=edge_labels, motion_noise=motion_noise)
    _warn_held_by_odometry(result.assessment)
    return result


def _still_moving(T_before: np.ndarray, T_after: np.ndarray, round_number: int, tolerance_m: float
                  ) -> dict[str, Any]:
    """The scans a round moved by more than `tolerance_m` (m), largest first, with their moves (the
    distance and the position change, world frame, m)."""
    change_m = T_after[:, :3, 3] - T_before[:, :3, 3]
    moved_m = np.linalg.norm(change_m, axis=1)
    order = np.argsort(-moved_m, kind="stable")
    scans = [{"scan": int(j), "moved_m": float(moved_m[j]), "change_m": [float(x) for x in change_m[j]]}
             for j in order if moved_m[j] > tolerance_m]
    return {"round": round_number, "max_pose_change_m": float(moved_m.max(initial=0.0)), "settle_m": tolerance_m,
            "scans": scans}


def _warn_held_by_odometry(assessed: Assessment) -> None:
    """The warning for the scans the final poses' features leave to the odometry in some direction."""
    held = assessed.degeneracy.held_by_odometry
    if held:
        directions = sorted({d for h in held for d in h["directions"]})
        log.warning("%d scan(s) are held only by odometry in some direction (the planes constrain it less than "
                    "the odometry factors do): %s%s; directions: %s", len(held),
                    ", ".join(str(h["scan"]) for h in held[:10]), " ..." if len(held) > 10 else "",
                    "; ".join(directions[:4]))
