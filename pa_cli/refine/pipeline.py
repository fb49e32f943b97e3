"""`pa refine`: scan source -> initial poses -> rounds of (associate planes, adjust) -> map.

`RefinePipeline(...).run()` runs the methods listed by `steps()` in order:

    check inputs -> open scans -> load (scan headers) -> initial poses -> timestamps -> loops
    -> deskew -> rounds -> pose covariance -> evaluate (--gt) -> write

Each step reads and sets attributes of the pipeline and adds its part of the report. A new
step (deskewing, a quality check) is a method added to `steps()` at its place in the order.

The loops step (when `loops.enabled`) replaces the initial poses by loop-closed ones
(`pa_cli.loops`): every later step starts from the loop-closed trajectory (deskew moves it to the
reference instants, the odometry factors of the rounds take its relative motions); the
odometry's own poses stay in `T_odometry` and are evaluated under `gt.odometry`.

Frames and units: poses are T_world_scan (N, 4, 4), metres; with KISS-ICP the world is the
frame of scan 0. The plane cost is the sum of squared point-to-plane distances (m^2), and the
RMS point-to-plane distance is sqrt(cost / points on planes) (m).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.adjust import plane_cost, solve
from pa_cli.adjust.covariance import node_sets, save_covariance, timed_pose_covariance
from pa_cli.adjust.hierarchical import choose_backend
from pa_cli.adjust.linalg import PAIR_MAX_SCANS
from pa_cli.adjust.odometry_factors import HeldHorizontal, OdometryFactors, OdometryModel, held_motions
from pa_cli.config import PaConfig, dump_config
from pa_cli.core.geometry import pose_change
from pa_cli.core.local_frame import local_origin_m, to_local, to_world
from pa_cli.errors import InputError, SolverError
from pa_cli.evaluation import evaluate
from pa_cli.evaluation.degeneracy import describe, plane_information, scan_degeneracy, travel_frames
from pa_cli.evaluation.quality import (
    assess,
    decided_by_planes,
    mean_map_entropy,
    pair_tie_information,
    pair_ties,
    rms_point_to_plane,
)
from pa_cli.io.atomic import atomic_path, check_writable
from pa_cli.io.maps import MapVoxelFilter, check_laz_backend, chunked, map_stores_time, write_map
from pa_cli.io.problem import save_problem
from pa_cli.io.report import report_to_json
from pa_cli.io.trajectory import Trajectory, format_kitti, format_tum, read_trajectory
from pa_cli.loops import close_loops
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.edges import with_edges
from pa_cli.planes.labels import PointLabels
from pa_cli.planes.warm_up import warm_up_in_background
from pa_cli.planes.windowed import ScanRef, plane_passes
from pa_cli.refine.deskew import (
    DeskewedPoints,
    DeskewFixedPoint,
    TimedScans,
    kiss_icp_pose_offsets_s,
    scan_reference_times,
    shift_in_time,
)
from pa_cli.refine.odometry import run_kiss_icp
from pa_cli.refine.pair_registration import register_consecutive
from pa_cli.refine.relocalise import relocalise_lost_scans, unconfirmed_moves
from pa_cli.runtime.distributed import GB, execution
from pa_cli.sources import PointsView, open_source
from pa_cli.sources.cache import CachedSource

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class RefineOutputs:
    """Every file `pa refine` writes, named after the stem of the map path (.ply, .las or .laz)."""

    map_path: Path
    poses_kitti: Path
    poses_tum: Path
    initial_poses_kitti: Path
    report_json: Path
    config_yaml: Path
    covariance_npz: Path
    problem_npz: Path | None = None

    @classmethod
    def from_map_path(cls, map_path: Path | str, problem_npz: Path | str | None = None) -> RefineOutputs:
        map_path = Path(map_path)
        stem = map_path.with_suffix("")
        return cls(
            map_path=map_path,
            poses_kitti=Path(f"{stem}_poses_kitti.txt"),
            poses_tum=Path(f"{stem}_poses_tum.txt"),
            initial_poses_kitti=Path(f"{stem}_initial_poses_kitti.txt"),
            report_json=Path(f"{stem}_report.json"),
            config_yaml=Path(f"{stem}_config.yaml"),
            covariance_npz=Path(f"{stem}_covariance.npz"),
            problem_npz=None if problem_npz is None else Path(problem_npz),
        )

    def all(self) -> list[Path]:
        paths = [self.map_path, self.poses_kitti, self.poses_tum, self.initial_poses_kitti,
                 self.report_json, self.config_yaml, self.covariance_npz]
        return paths + ([self.problem_npz] if self.problem_npz is not None else [])


# Bytes per 6x6 pose block of the covariance's selected inversion: the Hessian block, its factor's
# block and the inverse's block on the same pattern, 36 float64 each.
COVARIANCE_BYTES_PER_BLOCK = 3 * 36 * 8


def covariance_lower_bound_gb(problem: Any) -> float:
    """A lower bound of the pose covariance's memory (GB): the fewest 6x6 blocks of the matrices
    it may invert (the factor and the inverse have at least those). With a set S of features as
    nodes (`pa_cli.adjust.covariance._block_pattern`) the matrix has a block per scan, per node, per
    observation of a node and per pair of scans sharing a feature not in S (the nonzeros of R R^T,
    R the scan-feature incidence without S); the bound is the least over the sets the covariance
    chooses from (`node_sets`, with the features seen by more than PAIR_MAX_SCANS scans as the
    candidates)."""
    import scipy.sparse as sp


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


def _peak_rss_gb() -> float:
    """This process's peak resident set size so far (GB; Linux reports ru_maxrss in kB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GB


class RefinePipeline:
    """The end-to-end refinement. Construct, then `run()`; returns the report dict.

    Its poses (`T_initial`, `T_odometry`, `T_world_scan`) are in the local frame of
    `pa_cli.core.local_frame` (the world frame moved by `origin_world_m`, whole kilometres; zero near
    the world origin); `evaluate` and `write` turn them back into the world frame.
    """

    def __init__(self, scans: Path | str, out_map: Path | str, config: PaConfig, *,
                 topic: str | None = None, poses: Path | str | None = None, gt: Path | str | None = None,
                 save_problem: Path | str | None = None, glob: str | None = None,
                 force: bool = False, show_progress: bool = True,
                 config_source: str = "defaults") -> None:
        self.scans_path = Path(scans)
        self.topic = topic
        self.config = config
        self.poses_path = None if poses is None else Path(poses)
        self.gt_path = None if gt is None else Path(gt)
        self.glob = glob
        self.force = force
        self.show_progress = show_progress
        self.config_source = config_source
        self.outputs = RefineOutputs.from_map_path(out_map, save_problem)
        self.report: dict[str, Any] = {"stage_times_s": {}, "stage_cpu_s": {}}
        self.source: Any = None
        self.poses: Any = None
        self.gt: Any = None
        self.T_odometry: np.ndarray | None = None
        self.T_initial: np.ndarray | None = None
        self.T_world_scan: np.ndarray | None = None
        self.origin_world_m = np.zeros(3)  # the local frame's origin (pa_cli.core.local_frame)
        self.timestamps: np.ndarray | None = None
        self.problem: Any = None
        self._deskewed: Any = None  # DeskewedPoints when motion compensation is on
        self.odometry_factors: Any = None
        self.labels_initial: Any = None  # PointLabels of the first and of the last association
        self.labels_final: Any = None
        self.plane_problem: Any = None  # the last round's planes only (the quality ties use it)
        self.settled = False
        self.terms: list[Any] = []
        self.covariance: Any = None
        self.solver_model: Any = None

    def steps(self) -> list[Callable[[], None]]:
        """The steps `run()` executes, in order."""
        return [self.check_inputs, self.open_scans, self.load, self.initial_poses, self.find_timestamps,
                self.close_loops, self.prepare_deskew, self.refine_rounds, self.pose_covariance, self.evaluate,
                self.write]

    def run(self) -> dict[str, Any]:
        """Run the steps; the hierarchical adjustment's windows run where `config.execution` says."""
        try:
            with execution(self.config.execution, self.config.solver.memory_budget_gb):
                for step in self.steps():
                    step()
        finally:
            if self.source is not None:
                self.source.close()
        return self.report

    # ---------------------------------------------------------------- helpers
    @contextlib.contextmanager
    def _stage(self, name: str, total: int | None = None) -> Iterator[Progress]:
        """A labelled progress bar on stderr; the stage's wall and process CPU times (all threads)
        and the process's peak RSS at its end go into the report."""
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        start, start_cpu = time.perf_counter(), time.process_time()
        with Progress(TextColumn("[bold]{task.description:<18}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), console=Console(stderr=True),
                      disable=not self.show_progress, transient=False) as bar:
            task = bar.add_task(name, total=total)

            def update(done: int, total_now: int) -> None:
                bar.update(task, completed=done, total=total_now)

            yield update
        times, cpu = self.report["stage_times_s"], self.report["stage_cpu_s"]
        times[name] = times.get(name, 0.0) + time.perf_counter() - start
        cpu[name] = cpu.get(name, 0.0) + time.process_time() - start_cpu
        self.report.setdefault("stage_peak_rss_gb", {})[name] = _peak_rss_gb()

    def _points(self) -> Any:
        """The scans' points as a sequence of (N, 3) scan-frame arrays (for plane association)."""
        return PointsView(self.source)

    # ---------------------------------------------------------------- steps
    def check_inputs(self) -> None:
        """Before any work: outputs writable (and a LAZ backend for .laz), --poses and --gt read."""

        inputs = [p for p in (self.poses_path, self.gt_path, self.scans_path) if p is not None]
        check_writable(self.outputs.all(), self.force, inputs=inputs)
        if self.outputs.map_path.suffix.lower() == ".laz":
            check_laz_backend(self.outputs.map_path)
        if self.poses_path is not None:
            self.poses = read_trajectory(self.poses_path)
        if self.gt_path is not None:
            self.gt = read_trajectory(self.gt_path)

    def open_scans(self) -> None:
        """Open the scan source (lists files or a bag's index) and check the counts of --poses and --gt."""

        source = open_source(self.scans_path, topic=self.topic, glob=self.glob)
        self.source = CachedSource(source, self.config.refine.cache_budget_gb * GB) \
            if self.config.refine.cache_points else source
        n_scans = len(self.source)
        if n_scans < 2:
            raise InputError(f"{self.source.name}: found {n_scans} scan(s); refinement needs at least 2 "
                             "(check --glob or --topic).")
        if self.poses is not None and len(self.poses) != n_scans:
            raise InputError(f"{self.poses_path}: {len(self.poses)} poses for {n_scans} scans in "
                             f"{self.source.name}; --poses needs one pose per scan (check --glob).")
        if self.gt is not None and self.gt.timestamps is None and len(self.gt) != n_scans:
            raise InputError(f"{self.gt_path}: {len(self.gt)} poses for {n_scans} scans and no "
                             "timestamps to associate them; --gt needs one pose per scan.")
        self.report["input"] = {"source": self.source.name, "n_scans": n_scans, "glob": self.glob,
                                "topic": self.topic,
                                "poses": None if self.poses_path is None else str(self.poses_path),
                                "gt": None if self.gt_path is None else str(self.gt_path),
                                "config": self.config_source}

    def load(self) -> None:
        """Check every scan's header (reads no points), so a corrupt scan is reported before any work."""
        n_scans = len(self.source)
        with self._stage("load", total=n_scans) as progress:
            self.source.check()
            progress(n_scans, n_scans)

    def initial_poses(self) -> None:
        """KISS-ICP odometry, or the poses of --poses (moved into the local frame)."""
        if self.poses is not None:
            self.origin_world_m = local_origin_m(self.poses.T_world_scan)
            self.T_initial = to_local(self.poses.T_world_scan, self.origin_world_m)
            self.report["initial_poses_source"] = str(self.poses_path)
            if self.origin_world_m.any():
                log.info("%s: the poses lie far from the world origin; computing in a local frame at %s m "
                         "(outputs are in the world frame).", self.poses_path,
                         ", ".join(f"{v:.0f}" for v in self.origin_world_m))
        else:
            warm_up_in_background()  # the plane kernels load while the odometry runs
            with self._stage("odometry", total=len(self.source)) as progress:
                self.T_initial = run_kiss_icp(self.source, self.config.odometry, progress=progress)
            self.report["initial_poses_source"] = "kiss-icp"
        self.report["local_frame_origin_m"] = self.origin_world_m.tolist()
        self.T_world_scan = self.T_initial.copy()

    def find_timestamps(self) -> None:
        """Per-scan timestamps (s): the TUM timestamps of --poses, else the source's, else none."""
        if self.poses is not None and self.poses.timestamps is not None:
            self.timestamps = np.asarray(self.poses.timestamps, dtype=np.float64)
            self.report["timestamps_source"] = f"{self.poses_path} (TUM)"
            return
        found = self.source.timestamps()
        self.timestamps = found.stamps_s
        self.report["timestamps_source"] = found.origin if found.stamps_s is not None else "scan index"
        if found.stamps_s is None:
            log.warning("no per-scan timestamps (%s; no TUM --poses); %s uses the scan index as time.",
                        found.origin, self.outputs.poses_tum)

    def close_loops(self) -> None:
        """Loop closure (`loops` config): the rounds then start from the loop-closed poses."""
        self.T_odometry = self.T_initial
        if not self.config.loops.enabled:
            self.report["loops"] = {"enabled": False}
            return

        with self._stage("loops", total=len(self.source)) as progress:
            result = close_loops(self._points(), self.T_initial, self.config.loops, progress=progress)
        self.report["loops"] = {"enabled": True, **result.report()}
        log.info("loops: %d closures accepted of %d candidates", self.report["loops"]["n_closures"],
                 self.report["loops"]["n_candidates"])
        self.T_initial = result.T_world_scan
        self.T_world_scan = self.T_initial.copy()

    def prepare_deskew(self) -> None:
        """Decide motion compensation (`refine.deskew`) and read the per-point times once."""
        mode = self.config.refine.deskew
        info: dict[str, Any] = {"mode": mode, "enabled": False}
        self.report["deskew"] = info
        if mode == "off":
            return
        timed = TimedScans(self.source, self.config.refine.deskew_max_sweep_s)
        if timed.unit is None:
            if mode == "on":
                raise InputError(f"{self.source.name}: refine.deskew is 'on' but no scan has usable per-point "
                                 f"times: {timed.problem}. Set refine.deskew to auto or off.")
            info["reason"] = timed.problem
            if timed.suspect:
                log.warning("%s: motion compensation is off: %s.", self.source.name, timed.problem)
            return
        stamps_s, source = scan_reference_times(timed, self.timestamps)
        if self.poses_path is None:
            # KISS-ICP's pose of a scan holds at another instant of the sweep: move it to the reference
            offsets_s = kiss_icp_pose_offsets_s(timed, self.config.odometry.deskew)
            self.T_initial = shift_in_time(self.T_initial, stamps_s, offsets_s)
            self.T_world_scan = self.T_initial.copy()
            info["kiss_icp_pose_instant"] = ("end of sweep (its deskew)" if self.config.odometry.deskew else
                                             "mean point time (raw sweep)") + ", moved to the reference instant"
        self._deskewed = DeskewedPoints(timed.points, timed.times_s, stamps_s, self.T_world_scan)
        info.update(enabled=True, **timed.report(), scan_times_source=source)
        if timed.n_with_times < len(self.source):
            log.warning("%d of %d scans have no per-point times; they are used without motion compensation.",
                        len(self.source) - timed.n_with_times, len(self.source))

    def _points_at(self, T_world_scan: np.ndarray) -> Any:
        """The scans' points, motion-compensated with the trajectory T_world_scan when deskewing."""
        if self._deskewed is None:
            return self._points()
        return self._deskewed.at(T_world_scan)

    def refine_rounds(self) -> None:
        """Rounds of (deskew, plane association at the current poses, second-order adjustment).

        The first `refine.association_rounds` rounds find planes afresh, and so does every later one
        until a round moves no pose more than `refine.association_settle_m` (its association, made at
        poses that then hardly moved, is kept) or `refine.max_association_rounds` rounds have; later
        rounds keep every point's plane and only re-deskew and re-adjust. The loop stops when a round
        moves no pose more than the tolerances (settled) or after `refine.max_rounds`.
        """

        cfg = self.config
        if cfg.refine.odometry_translation_sigma_m is not None:
            # relative motions of the initial trajectory hold what the planes leave free
            self.odometry_factors = OdometryFactors(self.T_initial, OdometryModel.from_config(cfg.refine))
        terms = [] if self.odometry_factors is None else [self.odometry_factors]
        solver_config, message = choose_backend(cfg.solver, len(self.source))
        if solver_config.solver == "hierarchical":
            log.info(message or "using the hierarchical backend (solver.solver).")
            if self.odometry_factors is not None and not solver_config.hierarchical_final_iterations:
                log.warning("the odometry factors act in the hierarchical backend's final flat pass only, "
                            "and solver.hierarchical_final_iterations is 0.")
        elif cfg.execution.workers or cfg.execution.scheduler_address:
            log.warning("the flat %s backend runs in this process; the dask workers run the hierarchical "
                        "backend's windows (solver.solver: hierarchical).", solver_config.solver)
        budget = solver_config.hierarchical_final_iterations if solver_config.solver == "hierarchical" \
            else solver_config.max_iterations  # iterations the progress bar counts
        # on dask workers the passes over the scans are window tasks reading the scans themselves
        # (not with motion compensation: a deskewed scan needs its neighbours' points and the trajectory)
        passes = None if self._deskewed is not None else plane_passes(
            ScanRef(str(self.scans_path), self.topic, self.glob), cfg.execution, cfg.refine.cache_points)
        build = build_plane_problem if passes is None else passes.build
        rounds: list[dict[str, Any]] = []
        frozen: PointLabels | None = None
        fixed_point = DeskewFixedPoint(cfg.refine.degeneracy_lever_arm_m, cfg.refine.deskew_max_contraction)
        settled = False
        for r in range(cfg.refine.max_rounds):
            self.solver_model = None  # the last round's solver state is not held through this round's planes
            points = self._points_at(self.T_world_scan)
            rounds_start = self.T_world_scan
            association = "new" if frozen is None else "frozen"
            if frozen is None:
                with self._stage(f"planes {r + 1}", total=len(self.source)) as progress:
                    found: dict[str, Any] = {}
                    problem, diagnostics = build(points, self.T_world_scan, cfg.planes,
                                                 progress=progress, landmarks_out=found)
                    if problem.n_observations:
                        points, problem, diagnostics, found = self._relocalise(points, found, problem,
                                                                               diagnostics, build)
                if problem.n_observations == 0:
                    raise SolverError(f"{self.source.name}: round {r + 1} found no plane seen by two scans; "
                                      "try a config with larger planes.voxel_size_m or max_thickness_m "
                                      "(configs/outdoor.yaml) or check the initial poses.")
                labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks,
                                                      found["kept"], problem)
                self.plane_problem = problem
                if r == 0:
                    self.labels_initial = labels
                self.labels_final = labels
            else:
                problem = self.plane_problem = frozen.problem(points, self.T_world_scan, with_range=True)
                diagnostics = {"association": "frozen (every point keeps its plane)",
                               "n_landmarks": problem.n_planes, "n_observations": problem.n_observations}
            # edges (when `edges.enabled`) are found afresh at the current poses every round
            problem = with_edges(problem, diagnostics, points, self.T_world_scan, cfg.edges,
                                 cfg.planes.min_constraint_eigenvalue)
            with self._stage(f"adjust {r + 1}", total=budget) as progress:
                def on_iteration(record: Any, progress: Progress = progress) -> None:
                    progress(record.iteration, budget)

                result = solve(problem, self.T_world_scan, solver_config, progress=on_iteration, terms=terms)
                iterations = result.report["iterations"]
                progress(iterations, iterations)
            moved_m, turned_deg = pose_change(self.T_world_scan, result.T_world_scan)
            if association == "new" and r + 1 >= cfg.refine.association_rounds and (
                    moved_m <= cfg.refine.association_settle_m or r + 1 >= cfg.refine.max_association_rounds):
                frozen = labels
            rounds.append({"round": r + 1, "planes": diagnostics, "solver": result.report,
                           "association": association,
                           "n_planes": problem.n_planes, "n_observations": problem.n_observations,
                           "n_points": problem.n_points, "max_pose_change_m": moved_m,
                           "max_pose_change_deg": turned_deg})
            self.T_world_scan = result.T_world_scan
            self.problem = problem
            self.solver_model = result.model  # reused by the covariance (SolveResult.model)
            log.debug("round %d: poses moved up to %.4g m, %.4g deg", r + 1, moved_m, turned_deg)
            if self._settles(moved_m, turned_deg):
                settled = True
                break
            if association == "frozen" and self._deskewed is not None and r + 1 < cfg.refine.max_rounds:
                # the deskew fixed point (the last round's output stays the adjustment's result)
                self.T_world_scan, rounds[-1]["deskew_acceleration"] = fixed_point.next_start(rounds_start,
                                                                                              result.T_world_scan)
        self.report["rounds"] = rounds
        self.settled = settled
        if not settled:
            log.warning("rounds did not settle: round %d still moved a pose %.4g m / %.4g deg (tolerance %g m / "
                        "%g deg); raise refine.max_rounds or check the report.", len(rounds),
                        rounds[-1]["max_pose_change_m"], rounds[-1]["max_pose_change_deg"],
                        cfg.refine.pose_change_tolerance_m, cfg.refine.pose_change_tolerance_deg)
        self.terms = terms
        self._assess()
        self.report["held_horizontal"] = None
        if self.odometry_factors is not None and "upright" in self.report["quality"]["blurrier_surfaces"]:
            self._hold_horizontal(solver_config, terms)
        self._warn_held_by_odometry()

    def _settles(self, moved_m: float, turned_deg: float) -> bool:
        """Whether a solve that moved no pose more than this is within the tolerances (settled)."""
        refine = self.config.refine
        return moved_m < refine.pose_change_tolerance_m and turned_deg < refine.pose_change_tolerance_deg

    def _assess(self) -> None:
        """The report's summary, degeneracy and verdict of the current poses."""
        self._summarise_cost()
        self._degeneracy()
        self._quality()

    def _hold_horizontal(self, solver_config: Any, terms: list[Any]) -> None:
        """The refined map is blurrier on upright surfaces (walls, poles, trunks), which see the
        horizontal position and the heading: the planes moved those directions wrongly (on a street
        whose planes are ground patches, their slight tilts and curvature decide them). The last
        round's problem is solved again with every consecutive pair's horizontal motion and heading
        change held (`HeldHorizontal`), first at the initial trajectory's; then every pair is
        registered at the held poses (GICP of the two scans' points, `pa_cli.refine.pair_registration`) and
        the hold moves to the registration's motion in the directions it sees better than the odometry
        factor (`held_motions`). The height, roll and pitch stay the planes' and the odometry's. With
        motion compensation the scans (and the planes' points) are deskewed along the held poses before
        each registration, until a pass moves no pose more than the tolerances or `refine.max_rounds`
        passes (the deskew fixed point, as the rounds'). The report's summary, degeneracy and quality
        are those of the held poses; the covariance is that of the planes and the odometry factors."""

        cfg = self.config
        upright = self.report["quality"]["map_entropy"]["surfaces"]["upright"]
        T_refined = self.T_world_scan  # its verticals define the held directions
        information = plane_information(self.problem, T_refined)
        passes: list[dict[str, Any]] = []

        def hold(factors: OdometryFactors, record: dict[str, Any]) -> tuple[np.ndarray, bool]:
            with self._stage(f"hold horizontal {len(passes) + 1}") as progress:
                result = solve(self.problem, self.T_world_scan, solver_config,
                               terms=[*terms, HeldHorizontal(factors, T_refined, information)])
                progress(1, 1)
            moved_m, turned_deg = pose_change(self.T_world_scan, result.T_world_scan)
            passes.append({**record, "max_pose_change_m": moved_m, "max_pose_change_deg": turned_deg,
                           "solver": result.report})
            return result.T_world_scan, self._settles(moved_m, turned_deg)

        # the scans are deskewed along the current poses: first the initial trajectory's horizontal
        self.T_world_scan, _ = hold(self.odometry_factors, {"held_at": "initial trajectory"})
        fixed_point = DeskewFixedPoint(cfg.refine.degeneracy_lever_arm_m, cfg.refine.deskew_max_contraction)
        n_passes = 1 if self._deskewed is None else cfg.refine.max_rounds
        for k in range(n_passes):
            pass_start = self.T_world_scan
            points = self._points_at(pass_start)
            if self._deskewed is not None:
                self.plane_problem = self.labels_final.problem(points, pass_start, with_range=True)
                self.problem = with_edges(self.plane_problem, {}, points, pass_start, cfg.edges,
                                          cfg.planes.min_constraint_eigenvalue)
            with self._stage(f"register pairs {k + 1}", total=len(self.source) - 1) as progress:
                pairs = register_consecutive(points, pass_start, cfg.refine.hold_registration_voxel_m,
                                             cfg.refine.hold_registration_max_correspondence_m, progress=progress)
            seen = np.where(pairs.converged[:, None, None], pairs.information, 0.0)
            R_held, t_held, registered = held_motions(self.odometry_factors, pairs.T_prev_next, seen, T_refined,
                                                      cfg.refine.degeneracy_lever_arm_m)
            T_result, settled = hold(OdometryFactors.from_motions(R_held, t_held, self.odometry_factors.model),
                                     {"held_at": "registration", "n_converged": int(pairs.converged.sum()),
                                      "n_directions_registered": int(registered.sum()),
                                      "pairs_held_at_initial": [int(j) for j in np.flatnonzero(registered == 0)]})
            self.T_world_scan = T_result
            if settled or self._deskewed is None:
                break
            if k + 1 < n_passes:
                self.T_world_scan, passes[-1]["deskew_acceleration"] = fixed_point.next_start(pass_start, T_result)
        else:  # the deskewed points still move the held poses
            self.settled = False
            log.warning("the held passes did not settle: pass %d still moved a pose %.4g m / %.4g deg.",
                        len(passes), passes[-1]["max_pose_change_m"], passes[-1]["max_pose_change_deg"])
        self.solver_model = None  # its Hessian holds the held term; the covariance is built without it
        self._assess()
        after = self.report["quality"]["map_entropy"]["surfaces"]["upright"]["mme_nats"]["refined"]
        moved_m, turned_deg = pose_change(T_refined, self.T_world_scan)
        n_pairs = len(registered)
        note = (f"the planes left the upright surfaces blurrier ({upright['mme_nats']['initial']:.4f} -> "
                f"{upright['mme_nats']['refined']:.4f} nats), so every consecutive pair's horizontal motion and "
                f"heading change are held at a registration of the two scans ({int(registered.sum())} of "
                f"{3 * n_pairs} directions of {n_pairs} pairs; the initial trajectory's where it sees less than the "
                f"odometry), which moved the poses up to {moved_m:.4f} m, {turned_deg:.4f} deg; the upright surfaces "
                f"are now {after:.4f} nats, and the height, roll and pitch are the planes'")
        self.report["quality"]["reasons"].append(note)
        self.report["held_horizontal"] = {"upright_mme_nats_unheld": upright["mme_nats"], "n_pairs": n_pairs,
                                          "max_pose_change_m": moved_m, "max_pose_change_deg": turned_deg,
                                          "passes": passes}
        log.warning("%s.", note[0].upper() + note[1:])

    def _relocalise(self, points: Any, found: dict[str, Any], problem: Any, diagnostics: dict[str, Any],
                    build: Callable[..., Any]) -> tuple[Any, Any, dict[str, Any], dict[str, Any]]:
        """Move the scans the planes lost along their weak direction (`pa_cli.refine.relocalise`) and
        associate afresh; the moves the new association does not hold (`unconfirmed_moves`) are
        undone, and the planes found once more when some move stands. Returns the points (deskewed
        along the final trajectory), the plane problem, its diagnostics (with `relocalised_scans`,
        the moves kept, and `relocalisations_undone`) and its `landmarks_out` dict. Needs the
        odometry factors (they say which directions the planes leave to the odometry)."""
        if self.odometry_factors is None:
            return points, problem, diagnostics, found

        cfg = self.config
        started_s = time.perf_counter()
        odometry = self.odometry_factors.linearize(self.T_world_scan)
        T_before = self.T_world_scan
        self.T_world_scan, moved = relocalise_lost_scans(
            points, T_before, found["landmarks"], found["kept"], problem,
            odometry.pose_blocks, cfg.refine.degeneracy_lever_arm_m,
            cfg.refine.relocalise_search_m, cfg.refine.relocalise_step_m, cfg.planes.outlier_sigma,
            cfg.planes.outlier_sigma_floor_m, cfg.planes.min_points_per_observation,
            threads=cfg.planes.association_threads, odometry_pair_information=odometry.pair_blocks,
            max_group_scans=cfg.refine.relocalise_max_group_scans)
        before = (points, problem, {**diagnostics, "relocalised_scans": [], "relocalisations_undone": []}, found)
        if not moved:
            return before

        def associate() -> tuple[Any, Any, dict[str, Any], dict[str, Any]]:
            moved_points = self._points_at(self.T_world_scan)  # deskewed along the moved trajectory
            new_found: dict[str, Any] = {}
            new_problem, new_diagnostics = build(moved_points, self.T_world_scan, cfg.planes, landmarks_out=new_found)
            return moved_points, new_problem, new_diagnostics, new_found

        points, problem, diagnostics, found = associate()
        undone = unconfirmed_moves(before[1], T_before, problem, self.T_world_scan, moved)
        is_undone = [any(a <= m["scan"] <= b for a, b in undone) for m in moved]
        kept = [m for m, undo in zip(moved, is_undone, strict=True) if not undo]
        dropped = [m for m, undo in zip(moved, is_undone, strict=True) if undo]
        if undone:
            log.info("undid the relocalisation of scan(s) %s: the planes found after a move held the scan no "
                     "more firmly than the odometry and the planes held it before",
                     ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in undone))
            for first, last in undone:
                self.T_world_scan[first:last + 1] = T_before[first:last + 1]
            if not kept:
                return (*before[:2], {**before[2], "relocalisations_undone": moved}, before[3])
            points, problem, diagnostics, found = associate()
        log.info("relocalised %d scan(s) the planes lost (search %.1f s): %s", len(kept),
                 time.perf_counter() - started_s, ", ".join(f"{m['scan']} by {m['shift_m']:+.2f} m" for m in kept[:10]))
        return points, problem, {**diagnostics, "relocalised_scans": kept, "relocalisations_undone": dropped}, found

    def pose_covariance(self) -> None:
        """Per-scan covariance of the refined poses (`pa_cli.adjust.covariance`), from the last
        round's plane problem (with the range clusters of its association) and the pose terms,
        relative to the gauge pose, with the noise model `refine.covariance_noise_model`. When the Hessian is
        singular (a scan the planes leave free and no prior) no covariance file is written."""
        model, self.solver_model = self.solver_model, None  # released with this stage, whatever it decides
        needed_gb = covariance_lower_bound_gb(self.problem)
        budget_gb = self.config.solver.memory_budget_gb
        if needed_gb > budget_gb:
            message = (f"the pose covariance needs at least {needed_gb:.1f} GB, above solver.memory_budget_gb = "
                       f"{budget_gb:g} (its matrix has a block for every pair of scans sharing a plane, or for "
                       "every observation of the planes it takes as nodes)")
            log.warning("no pose covariance (%s is not written): %s.", self.outputs.covariance_npz, message)
            self.report["covariance"] = {"error": message}
            return
        with self._stage("covariance") as progress:
            try:
                self.covariance, self.report["covariance"] = timed_pose_covariance(
                    self.problem, self.T_world_scan, fixed_pose=self.config.solver.fixed_pose,
                    eigen_gap_tolerance=self.config.solver.eigen_gap_tolerance, terms=self.terms,
                    noise_model=self.config.refine.covariance_noise_model, memory_budget_gb=budget_gb,
                    max_block_products=self.config.solver.covariance_max_block_products, model=model)
            except SolverError as exc:
                log.warning("no pose covariance (%s is not written): %s", self.outputs.covariance_npz, exc)
                self.report["covariance"] = {"error": str(exc)}
            progress(1, 1)

    def _summarise_cost(self) -> None:
        problem = self.problem
        n_points = max(problem.n_points, 1)
        cost_initial = float(plane_cost(problem, self.T_initial))
        cost_final = float(plane_cost(problem, self.T_world_scan))
        summary = {
            "note": "cost and RMS use the last round's plane problem at the initial and refined poses; "
                    "see quality for the cross-scored comparison",
            "n_scans": int(problem.n_scans), "n_landmarks": int(problem.n_planes),
            "n_observations": int(problem.n_observations), "n_points_on_planes": int(problem.n_points),
            "cost_initial_m2": cost_initial, "cost_final_m2": cost_final,
            "rms_point_to_plane_initial_m": float(np.sqrt(cost_initial / n_points)),
            "rms_point_to_plane_final_m": float(np.sqrt(cost_final / n_points)),
            "iterations": int(sum(r["solver"].get("iterations", 0) for r in self.report["rounds"])),
            "n_rounds": len(self.report["rounds"]),
            "settled": bool(self.settled),
        }
        if self.odometry_factors is not None:
            summary["odometry_cost_initial_m2"] = self.odometry_factors.cost(self.T_initial)
            summary["odometry_cost_final_m2"] = self.odometry_factors.cost(self.T_world_scan)
        self.report["summary"] = summary

    def _degeneracy(self) -> None:
        """Per-scan information of the last round's features (planes and edges) at the current poses: weakest
        direction, scans held only by odometry."""
        odometry_information = None
        if self.odometry_factors is not None:
            odometry_information = self.odometry_factors.linearize(self.T_world_scan).pose_blocks
        degeneracy = scan_degeneracy(self.problem, self.T_world_scan, self.config.refine.degeneracy_lever_arm_m,
                                     odometry_information)
        self.report["degeneracy"] = degeneracy
        self.report["poorly_constrained_scans"] = degeneracy["held_by_odometry_scans"]

    def _warn_held_by_odometry(self) -> None:
        """The warning for the scans the final poses' features leave to the odometry in some direction."""
        held = self.report["degeneracy"]["held_by_odometry"]
        if held:
            directions = sorted({d for h in held for d in h["directions"]})
            log.warning("%d scan(s) are held only by odometry in some direction (the planes constrain it less than "
                        "the odometry factors do): %s%s; directions: %s", len(held),
                        ", ".join(str(h["scan"]) for h in held[:10]), " ..." if len(held) > 10 else "",
                        "; ".join(directions[:4]))

    def _quality(self) -> None:
        """The honest verdict (`pa_cli.evaluation.quality`): cross-scored RMS, map entropy, odometry agreement, ties,
        settling."""
        pose_sets = {"initial": self.T_initial, "refined": self.T_world_scan}
        rms: dict[str, dict[str, float]] = {}
        for name, labels in (("planes_at_initial_poses", self.labels_initial),
                             ("planes_at_refined_poses", self.labels_final)):
            rms[name] = {pose_set: rms_point_to_plane(labels.problem(self._points_at(T)), T)
                         for pose_set, T in pose_sets.items()}
        cfg = self.config.refine
        with self._stage("map entropy") as progress:
            if self._deskewed is None:
                counts = [len(self.source.points(k)) for k in range(len(self.source))]
            else:  # the re-binned scans: points from their own and their neighbours' sweeps
                counts = [sum(len(index) for _, index in self._deskewed.sources(j)) for j in range(len(self.source))]
            entropy = mean_map_entropy({name: self._points_at(T) for name, T in pose_sets.items()}, pose_sets,
                                       counts, cfg.quality_entropy_radius_m, cfg.quality_entropy_min_neighbours,
                                       cfg.quality_entropy_max_map_points, cfg.quality_entropy_query_points,
                                       cfg.quality_entropy_min_sigma_m)
            progress(1, 1)
        factors, T = self.odometry_factors, self.T_world_scan
        sigmas = ties = words = decide = None
        if factors is not None:
            sigmas = factors.normalized_residuals(T)
            tie_information = pair_tie_information(self.plane_problem, T)
            ties, directions = pair_ties(tie_information, factors.weights)
            frames = travel_frames(T)
            words = [describe(np.r_[d[:3] * cfg.degeneracy_lever_arm_m, d[3:]], frames[j + 1])
                     for j, d in enumerate(directions)]
            decide = decided_by_planes(tie_information, factors.residuals(T), factors.weights, T)
        self.report["quality"] = assess(rms, sigmas, ties, self.settled, cfg.quality_outlier_sigma,
                                        cfg.quality_rms_tolerance, entropy, cfg.quality_entropy_tolerance_nats,
                                        planes_decide=decide, tie_words=words,
                                        held=self.report["degeneracy"]["held_by_odometry"],
                                        entropy_standard_errors=cfg.quality_entropy_standard_errors)

    def evaluate(self) -> None:
        """ATE and RPE of the initial and refined poses against --gt (SE(3)-aligned)."""
        if self.gt is None:
            return

        gt = self.gt
        with self._stage("evaluate") as progress:
            stamps = self.timestamps if gt.timestamps is not None else None

            def against_gt(T_local_scan: np.ndarray) -> dict[str, Any]:
                return evaluate(gt, Trajectory(to_world(T_local_scan, self.origin_world_m), stamps), align="se3")

            gt_eval: dict[str, Any] = {"initial": against_gt(self.T_initial), "refined": against_gt(self.T_world_scan)}
            if self.report["loops"]["enabled"]:  # "initial" is loop-closed
                gt_eval["odometry"] = against_gt(self.T_odometry)
            if len(gt) == len(self.T_world_scan):
                # the plane cost is invariant to one rigid motion of all poses, so the truth counts in
                # its own local frame; the last association, its points deskewed with each trajectory in turn
                T_gt = to_local(gt.T_world_scan, local_origin_m(gt.T_world_scan))
                for name, T in (("gt", T_gt), ("initial", self.T_initial)):
                    problem = self.labels_final.problem(self._points_at(T))
                    cost = float(plane_cost(problem, T))
                    gt_eval[f"cost_at_{name}_poses_m2"] = cost
                    gt_eval[f"rms_point_to_plane_at_{name}_m"] = float(np.sqrt(cost / max(problem.n_points, 1)))
            progress(1, 1)
        self.report["gt"] = gt_eval

    def write(self) -> None:
        """Write every output to a temporary file first; rename them all only if all succeeded."""

        out = self.outputs
        n_scans = len(self.source)
        with_time = map_stores_time(out.map_path) and self.timestamps is not None
        with contextlib.ExitStack() as stack:
            tmp = {p: stack.enter_context(atomic_path(p, self.force)) for p in out.all()
                   if p != out.covariance_npz or self.covariance is not None}
            with self._stage("write", total=n_scans) as progress:
                voxel_filter = MapVoxelFilter(self.config.refine.map_voxel_m, self.origin_world_m)
                n_points = [0]
                refined = None if self._deskewed is None else self._deskewed.at(self.T_world_scan)

                def map_parts() -> Iterator[Any]:
                    for k in range(n_scans):
                        for source_k, points_scan, own_s in self._map_parts(k, refined):
                            n_points[0] += len(points_scan)
                            time_s = None
                            if with_time:
                                known = own_s is not None and len(own_s) == len(points_scan)
                                time_s = self.timestamps[source_k] + (own_s if known else np.zeros(len(points_scan)))
                            yield voxel_filter.add(points_scan, self.T_world_scan[k], source_k, time_s)
                        progress(k + 1, n_scans)

                n_map = write_map(tmp[out.map_path], chunked(map_parts(), self.config.refine.map_chunk_points),
                                  force=True, suffix=out.map_path.suffix,
                                  float64_coordinates=bool(self.origin_world_m.any()))
                self.report["input"]["n_points"] = int(n_points[0])
                self.report["map"] = {"path": str(out.map_path), "n_points": int(n_map),
                                      "voxel_m": self.config.refine.map_voxel_m}
                stamps = self.timestamps if self.timestamps is not None else np.arange(n_scans, dtype=np.float64)
                self.report["outputs"] = {name: str(p) for name, p in vars(out).items() if p is not None}
                T_world_scan = to_world(self.T_world_scan, self.origin_world_m)
                tmp[out.poses_kitti].write_text(format_kitti(T_world_scan))
                tmp[out.poses_tum].write_text(format_tum(T_world_scan, stamps))
                tmp[out.initial_poses_kitti].write_text(format_kitti(to_world(self.T_initial, self.origin_world_m)))
                tmp[out.config_yaml].write_text(dump_config(self.config))
                if self.covariance is not None:
                    save_covariance(tmp[out.covariance_npz], self.covariance.in_world(self.origin_world_m), force=True)
                if out.problem_npz is not None:
                    refined = dataclasses.replace(self.problem, T_world_scan=T_world_scan)
                    save_problem(tmp[out.problem_npz], refined, force=True)
            # the report is the last small file: every stage time, this one's included, is final
            self.report["total_time_s"] = float(sum(self.report["stage_times_s"].values()))
            tmp[out.report_json].write_text(report_to_json(self.report))

    def _map_parts(self, k: int, deskewed: Any) -> list[tuple[int, np.ndarray, np.ndarray | None]]:
        """The points placed by pose k, by the scan that measured them: (scan, (M, 3) points in scan
        k's frame, their times (s) relative to that scan's timestamp or None). Deskewed points are
        motion-compensated into scan k's frame (`DeskewedPoints.parts` of `deskewed`, the scans at the
        refined trajectory; None without motion compensation)."""
        if deskewed is not None:
            return deskewed.parts(k)
        return [(k, self.source.points(k), self.source.point_times(k))]
