"""`pa refine`: scans folder -> initial poses -> rounds of (associate planes, adjust) -> map.

`RefinePipeline(...).run()` reads as its list of steps:

    check outputs -> load -> odometry (or --poses) -> loops -> rounds -> evaluate (--gt) -> write

The loops step replaces the initial poses by loop-closed ones (`pa_cli.loops`): every later
step, the odometry prior of the rounds included, starts from the loop-closed trajectory; the
odometry's own poses stay in `T_odometry` and are evaluated under `gt.odometry`.

Frames and units: poses are T_world_scan (N, 4, 4), metres; with KISS-ICP the world is the
frame of scan 0. The plane cost is the sum of squared point-to-plane distances (m^2), and the
RMS point-to-plane distance is sqrt(cost / points on planes) (m).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.config import PaConfig, dump_config
from pa_cli.errors import InputError, SolverError

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class RefineOutputs:
    """Every file `pa refine` writes, named after the stem of the map path."""

    map_ply: Path
    poses_kitti: Path
    poses_tum: Path
    initial_poses_kitti: Path
    report_json: Path
    config_yaml: Path
    problem_npz: Path | None = None

    @classmethod
    def from_map_path(cls, map_ply: Path | str, problem_npz: Path | str | None = None) -> RefineOutputs:
        map_ply = Path(map_ply)
        stem = map_ply.with_suffix("")
        return cls(
            map_ply=map_ply,
            poses_kitti=Path(f"{stem}_poses_kitti.txt"),
            poses_tum=Path(f"{stem}_poses_tum.txt"),
            initial_poses_kitti=Path(f"{stem}_initial_poses_kitti.txt"),
            report_json=Path(f"{stem}_report.json"),
            config_yaml=Path(f"{stem}_config.yaml"),
            problem_npz=None if problem_npz is None else Path(problem_npz),
        )

    def all(self) -> list[Path]:
        paths = [self.map_ply, self.poses_kitti, self.poses_tum, self.initial_poses_kitti,
                 self.report_json, self.config_yaml]
        return paths + ([self.problem_npz] if self.problem_npz is not None else [])


def pose_change(T_before: np.ndarray, T_after: np.ndarray) -> tuple[float, float]:
    """Largest translation change (m) and rotation change (deg) between two (N, 4, 4) pose sets."""
    from pa_cli.evaluation import rotation_angles

    dt_m = np.linalg.norm(T_after[:, :3, 3] - T_before[:, :3, 3], axis=1)
    R_rel = np.einsum("nji,njk->nik", T_before[:, :3, :3], T_after[:, :3, :3])
    return float(dt_m.max(initial=0.0)), float(np.degrees(rotation_angles(R_rel)).max(initial=0.0))


def find_scan_timestamps(scans_dir: Path, n_scans: int, poses_timestamps: np.ndarray | None) -> tuple[
        np.ndarray | None, str]:
    """Per-scan timestamps (s) and where they came from.

    Order: the TUM timestamps of --poses; `times.txt` in the scans folder or its parent (one
    line per scan); else None (the caller writes the scan index and warns).
    """
    from pa_cli.io.trajectory import read_timestamps

    if poses_timestamps is not None and len(poses_timestamps) == n_scans:
        return np.asarray(poses_timestamps, dtype=np.float64), "--poses (TUM)"
    for candidate in (scans_dir / "times.txt", scans_dir.parent / "times.txt"):
        if candidate.is_file():
            stamps = read_timestamps(candidate)
            if len(stamps) == n_scans:
                return stamps, str(candidate)
            log.warning("%s has %d timestamps for %d scans; ignoring it.", candidate, len(stamps), n_scans)
    return None, "scan index (no timestamps found)"


class RefinePipeline:
    """The end-to-end refinement. Construct, then `run()`; returns the report dict."""

    def __init__(self, scans_dir: Path | str, out_map: Path | str, config: PaConfig, *,
                 poses: Path | str | None = None, gt: Path | str | None = None,
                 save_problem: Path | str | None = None, glob: str | None = None,
                 force: bool = False, show_progress: bool = True,
                 config_source: str = "defaults") -> None:
        self.scans_dir = Path(scans_dir)
        self.config = config
        self.poses_path = None if poses is None else Path(poses)
        self.gt_path = None if gt is None else Path(gt)
        self.glob = glob
        self.force = force
        self.show_progress = show_progress
        self.config_source = config_source
        self.outputs = RefineOutputs.from_map_path(out_map, save_problem)
        self.report: dict[str, Any] = {"stage_times_s": {}}
        self.scans: Any = None
        self.T_odometry: np.ndarray | None = None
        self.T_initial: np.ndarray | None = None
        self.T_world_scan: np.ndarray | None = None
        self.timestamps: np.ndarray | None = None
        self.problem: Any = None
        self._points_cache: _Float32Cache | None = None

    # ---------------------------------------------------------------- the steps
    def run(self) -> dict[str, Any]:
        self.check_outputs()
        self.load()
        self.initial_poses()
        self.close_loops()
        self.refine_rounds()
        self.evaluate()
        self.write()
        return self.report

    # ---------------------------------------------------------------- helpers
    @contextlib.contextmanager
    def _stage(self, name: str, total: int | None = None) -> Iterator[Progress]:
        """A labelled progress bar on stderr; the stage's wall time goes into the report."""
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        start = time.perf_counter()
        with Progress(TextColumn("[bold]{task.description:<18}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), console=Console(stderr=True),
                      disable=not self.show_progress, transient=False) as bar:
            task = bar.add_task(name, total=total)

            def update(done: int, total_now: int) -> None:
                bar.update(task, completed=done, total=total_now)

            yield update
        times = self.report["stage_times_s"]
        times[name] = times.get(name, 0.0) + time.perf_counter() - start

    def _points(self) -> Any:
        """The scans as a sequence of (N, 3) scan-frame point arrays, each file read once.

        Plane association reads every scan two or three times per round; with
        `refine.cache_points` the points are kept in memory after their first read, as float32
        (scan files hold float32; 12 bytes per point, 0.36 GB for 30 M points).
        """
        points = getattr(self.scans, "points", self.scans)
        if not self.config.refine.cache_points:
            return points
        if self._points_cache is None:
            self._points_cache = _Float32Cache(points)
        return self._points_cache

    # ---------------------------------------------------------------- steps
    def check_outputs(self) -> None:
        """Refuse existing outputs (without --force) and outputs that are inputs, before any work."""
        from pa_cli.io.atomic import check_writable

        if not self.scans_dir.is_dir():
            raise InputError(f"{self.scans_dir}: scans folder not found; expected a folder of "
                             "PCD/PLY/BIN scans (SCANS_DIR).")
        inputs = [p for p in (self.poses_path, self.gt_path) if p is not None]
        check_writable(self.outputs.all(), self.force, inputs=inputs)

    def load(self) -> None:
        """Open the scans folder lazily (one file read per access)."""
        from pa_cli.io.scans import ScanFolder

        with self._stage("load") as progress:
            self.scans = ScanFolder(self.scans_dir, glob=self.glob)
            n_scans = len(self.scans)
            progress(n_scans, n_scans)
        if n_scans < 2:
            raise InputError(f"{self.scans_dir}: found {n_scans} scan(s); refinement needs at least 2 "
                             "(check --glob).")
        self.report["input"] = {"scans_dir": str(self.scans_dir), "n_scans": n_scans, "glob": self.glob,
                                "poses": None if self.poses_path is None else str(self.poses_path),
                                "gt": None if self.gt_path is None else str(self.gt_path),
                                "config": self.config_source}

    def initial_poses(self) -> None:
        """KISS-ICP odometry, or the poses of --poses (their count must match the scans)."""
        from pa_cli.io.trajectory import read_trajectory

        n_scans = len(self.scans)
        poses_timestamps = None
        if self.poses_path is not None:
            trajectory = read_trajectory(self.poses_path)
            if len(trajectory) != n_scans:
                raise InputError(f"{self.poses_path}: {len(trajectory)} poses for {n_scans} scans in "
                                 f"{self.scans_dir}; --poses needs one pose per scan (check --glob).")
            self.T_initial = trajectory.T_world_scan
            poses_timestamps = trajectory.timestamps
            self.report["initial_poses_source"] = str(self.poses_path)
        else:
            from pa_cli.odometry import run_kiss_icp

            with self._stage("odometry", total=n_scans) as progress:
                self.T_initial = run_kiss_icp(self.scans, self.config.odometry, progress=progress)
            self.report["initial_poses_source"] = "kiss-icp"
        self.T_world_scan = self.T_initial.copy()
        self.timestamps, source = find_scan_timestamps(self.scans_dir, n_scans, poses_timestamps)
        self.report["timestamps_source"] = source

    def close_loops(self) -> None:
        """Loop closure (`loops` config): the rounds then start from the loop-closed poses."""
        self.T_odometry = self.T_initial
        if not self.config.loops.enabled:
            self.report["loops"] = {"enabled": False}
            return
        from pa_cli.loops import close_loops

        with self._stage("loops", total=len(self.scans)) as progress:
            result = close_loops(self._points(), self.T_initial, self.config.loops, progress=progress)
        self.report["loops"] = {"enabled": True, **result.report()}
        log.info("loops: %d closures accepted of %d candidates", self.report["loops"]["n_closures"],
                 self.report["loops"]["n_candidates"])
        self.T_initial = result.T_world_scan
        self.T_world_scan = self.T_initial.copy()

    def refine_rounds(self) -> None:
        """Rounds of (plane association at the current poses, second-order adjustment)."""
        from pa_cli.adjust import PosePrior, solve
        from pa_cli.adjust.common import SolverOptions
        from pa_cli.planes.associate import build_plane_problem

        cfg = self.config
        options = SolverOptions.from_config(cfg.solver)
        prior = None
        if cfg.refine.prior_translation_sigma_m is not None:
            # holds the initial (odometry) poses along directions the planes leave free
            prior = PosePrior.from_sigmas(self.T_initial, cfg.refine.prior_point_sigma_m,
                                          cfg.refine.prior_translation_sigma_m, cfg.refine.prior_rotation_sigma_deg)
        rounds: list[dict[str, Any]] = []
        for r in range(cfg.refine.rounds):
            with self._stage(f"planes {r + 1}", total=len(self.scans)) as progress:
                problem, diagnostics = build_plane_problem(self._points(), self.T_world_scan, cfg.planes,
                                                           progress=progress)
            if problem.n_observations == 0:
                raise SolverError(f"{self.scans_dir}: round {r + 1} found no plane seen by two scans; "
                                  "try a config with larger planes.voxel_size_m or max_thickness_m "
                                  "(configs/outdoor.yaml) or check the initial poses.")
            with self._stage(f"adjust {r + 1}", total=options.max_iterations) as progress:
                def on_iteration(record: Any, progress: Progress = progress) -> None:
                    progress(record.iteration, options.max_iterations)

                result = solve(problem, self.T_world_scan, options, solver=cfg.solver.solver,
                               progress=on_iteration, prior=prior)
            moved_m, turned_deg = pose_change(self.T_world_scan, result.T_world_scan)
            rounds.append({"round": r + 1, "planes": diagnostics, "solver": result.report,
                           "n_planes": problem.n_planes, "n_observations": problem.n_observations,
                           "n_points": problem.n_points, "max_pose_change_m": moved_m,
                           "max_pose_change_deg": turned_deg})
            self.T_world_scan = result.T_world_scan
            self.problem = problem
            log.debug("round %d: poses moved up to %.4g m, %.4g deg", r + 1, moved_m, turned_deg)
            if moved_m < cfg.refine.pose_change_tolerance_m and turned_deg < cfg.refine.pose_change_tolerance_deg:
                break
        self.report["rounds"] = rounds
        self._summarise_cost()

    def _summarise_cost(self) -> None:
        from pa_cli.adjust import plane_cost

        problem = self.problem
        n_points = max(problem.n_points, 1)
        cost_initial = float(plane_cost(problem, self.T_initial))
        cost_final = float(plane_cost(problem, self.T_world_scan))
        flagged = self.report["rounds"][-1]["planes"].get("poorly_constrained_scans", [])
        if flagged:
            log.warning("%d scan(s) poorly constrained by planes (their landmark normals do not span three "
                        "directions; the odometry prior holds what the planes leave free): %s%s", len(flagged),
                        ", ".join(str(j) for j in flagged[:10]), " ..." if len(flagged) > 10 else "")
        self.report["summary"] = {
            "note": "cost and RMS use the last round's plane problem at the initial and refined poses",
            "n_scans": int(problem.n_scans), "n_landmarks": int(problem.n_planes),
            "n_observations": int(problem.n_observations), "n_points_on_planes": int(problem.n_points),
            "cost_initial_m2": cost_initial, "cost_final_m2": cost_final,
            "rms_point_to_plane_initial_m": float(np.sqrt(cost_initial / n_points)),
            "rms_point_to_plane_final_m": float(np.sqrt(cost_final / n_points)),
            "iterations": int(sum(r["solver"].get("iterations", 0) for r in self.report["rounds"])),
            "n_rounds": len(self.report["rounds"]),
        }
        self.report["poorly_constrained_scans"] = flagged

    def evaluate(self) -> None:
        """ATE and RPE of the initial and refined poses against --gt (SE(3)-aligned)."""
        if self.gt_path is None:
            return
        from pa_cli.adjust import plane_cost
        from pa_cli.evaluation import evaluate
        from pa_cli.io.trajectory import Trajectory, read_trajectory

        with self._stage("evaluate") as progress:
            gt = read_trajectory(self.gt_path)
            stamps = self.timestamps if gt.timestamps is not None else None
            if stamps is None and len(gt) != len(self.T_world_scan):
                raise InputError(f"{self.gt_path}: {len(gt)} poses for {len(self.T_world_scan)} scans and no "
                                 "timestamps to associate them; --gt needs one pose per scan.")
            initial = evaluate(gt, Trajectory(self.T_initial, stamps), align="se3")
            refined = evaluate(gt, Trajectory(self.T_world_scan, stamps), align="se3")
            gt_eval: dict[str, Any] = {"initial": initial, "refined": refined}
            if self.T_odometry is not self.T_initial:  # loops ran: "initial" is loop-closed
                gt_eval["odometry"] = evaluate(gt, Trajectory(self.T_odometry, stamps), align="se3")
            if len(gt) == len(self.T_world_scan):
                # the plane cost is invariant to one rigid motion of all poses, so any world frame works
                cost_gt = float(plane_cost(self.problem, gt.T_world_scan))
                gt_eval["cost_at_gt_poses_m2"] = cost_gt
                gt_eval["rms_point_to_plane_at_gt_m"] = float(np.sqrt(cost_gt / max(self.problem.n_points, 1)))
            progress(1, 1)
        self.report["gt"] = gt_eval

    def write(self) -> None:
        """Write every output to a temporary file first; rename them all only if all succeeded."""
        from pa_cli.io.atomic import atomic_path
        from pa_cli.io.maps import MapAccumulator, write_map_ply
        from pa_cli.io.problem import save_problem
        from pa_cli.io.trajectory import format_kitti, format_tum

        out = self.outputs
        n_scans = len(self.scans)
        write_start = time.perf_counter()
        with self._stage("write", total=n_scans) as progress:
            accumulator = MapAccumulator(self.config.refine.map_voxel_m)
            n_points = 0
            points = self._points()  # the cached points when refine.cache_points: no re-read
            for k in range(n_scans):
                points_scan = points[k]
                n_points += len(points_scan)
                accumulator.add(points_scan, self.T_world_scan[k], k)
                progress(k + 1, n_scans)
            points_world, scan_index = accumulator.result()
            self.report["input"]["n_points"] = int(n_points)
            self.report["map"] = {"path": str(out.map_ply), "n_points": int(len(points_world)),
                                  "voxel_m": self.config.refine.map_voxel_m}
            if self.timestamps is None:
                log.warning("no per-scan timestamps (no TUM --poses, no times.txt in %s or its parent); "
                            "%s uses the scan index as time.", self.scans_dir, out.poses_tum)
            stamps = self.timestamps if self.timestamps is not None else np.arange(n_scans, dtype=np.float64)
            self.report["outputs"] = {name: str(p) for name, p in vars(out).items() if p is not None}
            with contextlib.ExitStack() as stack:
                tmp = {p: stack.enter_context(atomic_path(p, self.force)) for p in out.all()}
                write_map_ply(tmp[out.map_ply], points_world, scan_index, force=True)
                tmp[out.poses_kitti].write_text(format_kitti(self.T_world_scan))
                tmp[out.poses_tum].write_text(format_tum(self.T_world_scan, stamps))
                tmp[out.initial_poses_kitti].write_text(format_kitti(self.T_initial))
                tmp[out.config_yaml].write_text(dump_config(self.config))
                if out.problem_npz is not None:
                    problem = self.problem
                    problem.T_world_scan = self.T_world_scan
                    save_problem(tmp[out.problem_npz], problem, force=True)
                # the write stage's time so far (everything but this last small file)
                self.report["stage_times_s"]["write"] = time.perf_counter() - write_start
                self.report["total_time_s"] = float(sum(self.report["stage_times_s"].values()))
                tmp[out.report_json].write_text(_to_json(self.report))


class _Float32Cache:
    """A sequence of point arrays that reads each item once and keeps it as float32."""

    def __init__(self, points: Any) -> None:
        self._points = points
        self._cache: list[np.ndarray | None] = [None] * len(points)

    def __len__(self) -> int:
        return len(self._cache)

    def __getitem__(self, k: int) -> np.ndarray:
        if self._cache[k] is None:
            self._cache[k] = np.asarray(self._points[k], dtype=np.float32)
        return self._cache[k].astype(np.float64)


def _to_json(report: dict[str, Any]) -> str:
    import json

    def default(value: Any) -> Any:
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, Path):
            return str(value)
        return str(value)

    return json.dumps(report, indent=2, default=default) + "\n"
