"""`CalibrationRun`: a rig folder -> extrinsics, refined base poses, a merged map and a report.

Steps (`steps()`, in order): check the outputs; open the rig and match scans (`rig_scans`); read
the points (kept in memory: a calibration drive is short); base poses from KISS-ICP on lidar0 or
`--poses`; initial extrinsics from `--init` or the identity; coarse ICP of each LiDAR against
lidar0's map (`coarse`); rounds of plane association at the composite poses and joint damped
Newton on base poses and extrinsics (`composite`, `solver`), until nothing moves more than
`advanced.calibrate.settle_*`; observability (`observability`): when a direction is unobservable, the
coarse stage and the rounds run again from the initial extrinsics with that direction held;
covariance; write (`outputs`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.adjust import solve
from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.calibration.coarse import PlanarTarget, align_extrinsic, voxel_points
from pa_cli.calibration.composite import BLOCK, CalibrationCost, RigLayout
from pa_cli.calibration.observability import analyse_extrinsics, extrinsic_covariance
from pa_cli.calibration.outputs import CalibrationOutputs, write_rig_map
from pa_cli.calibration.rig_scans import open_rig
from pa_cli.calibration.solver import solve_calibration
from pa_cli.config import PaConfig, dump_config
from pa_cli.core.geometry import pose_change, transform_points
from pa_cli.core.local_frame import to_world
from pa_cli.errors import InputError, SolverError
from pa_cli.io.atomic import atomic_path, check_writable
from pa_cli.io.extrinsics import format_extrinsics, lidar_name, read_extrinsics, rotation_to_rpy
from pa_cli.io.map_filter import MapVoxelFilter
from pa_cli.io.maps import concatenate_clouds
from pa_cli.io.report import report_to_json
from pa_cli.io.trajectory import format_kitti, format_tum, read_trajectory
from pa_cli.planes.associate import build_plane_problem
from pa_cli.refine.clock import StageClock
from pa_cli.refine.stages import initial_poses
from pa_cli.sources import ScanSubset, SubsetSource

log = logging.getLogger(__name__)

COVARIANCE_UNITS = "(omega rad, rho m): rotation about and displacement of the LiDAR origin, base frame"


class CalibrationRun:
    """One `pa calibrate` run (see the module docstring); `run()` returns the report. Its base
    poses are in the local frame of `pa_cli.core.local_frame` (at `origin_world_m`); `write` turns them
    and the map back into the world frame."""

    def __init__(self, rig_dir: Path | str, out: Path | str, config: PaConfig, *, init: Path | str | None = None,
                 poses: Path | str | None = None, subset: ScanSubset | None = None, force: bool = False) -> None:
        self.rig_dir = Path(rig_dir)
        self.outputs = CalibrationOutputs.from_extrinsics_path(out)
        self.config = config
        self.init = None if init is None else Path(init)
        self.poses = None if poses is None else Path(poses)
        self.subset = subset
        self.force = force
        self.report: dict[str, Any] = {"command": "calibrate", "rig": str(self.rig_dir), "stage_times_s": {}}
        self.origin_world_m = np.zeros(3)  # base poses are computed in the local frame (pa_cli.core.local_frame)

    def steps(self) -> list:
        return [self.check_outputs, self.open_rig, self.load, self.initial_poses, self.refine_base,
                self.initial_extrinsics, self.calibrate, self.covariance, self.write]

    def run(self) -> dict[str, Any]:
        try:
            for step in self.steps():
                t0 = time.perf_counter()
                step()
                self.report["stage_times_s"][step.__name__] = round(time.perf_counter() - t0, 3)
        finally:
            if hasattr(self, "rig"):
                self.rig.close()
        return self.report

    def check_outputs(self) -> None:
        inputs = [p for p in (self.init, self.poses) if p is not None]
        check_writable(self.outputs.all(), self.force, inputs)

    def open_rig(self) -> None:
        self.rig = open_rig(self.rig_dir, self.config.advanced.calibrate.time_match_tolerance_s, self.subset)
        base = self.rig.sources[0]
        if isinstance(base, SubsetSource):
            log.info("%s: %d of %d base scans kept: %s.", base.name, len(base), base.n_source, base.subset.describe())
        self.report["input"] = {"n_lidars": self.rig.n_lidars, "n_scans": [len(s) for s in self.rig.sources],
                                "matched_by": self.rig.matched_by,
                                "n_matched": [int(len(m)) for m in self.rig.matches]}

    def load(self) -> None:
        """Every matched scan's points (range-filtered by sensor.min_range_m / max_range_m) and the
        virtual-scan layout: v runs over LiDARs, then over that LiDAR's matched pairs."""
        sensor = self.config.sensor
        self.points: list[np.ndarray] = []
        base_of_v, lidar_of_v = [], []
        for k, (source, pairs) in enumerate(zip(self.rig.sources, self.rig.matches, strict=True)):
            for t, i in pairs:
                p = np.asarray(source.points(int(i)), dtype=np.float64)
                r = np.linalg.norm(p, axis=1)
                self.points.append(p[(r >= sensor.min_range_m) & (r <= sensor.max_range_m)])
                base_of_v.append(int(t))
                lidar_of_v.append(k)
        self.layout = RigLayout(np.array(base_of_v, dtype=np.int64), np.array(lidar_of_v, dtype=np.int64),
                                self.rig.n_base, self.rig.n_lidars)
        self.report["input"]["n_points"] = int(sum(len(p) for p in self.points))

    def initial_poses(self) -> None:
        """Base poses: `pa refine`'s initial-poses stage on lidar0 (KISS-ICP, or `--poses` in the local frame)."""
        trajectory = None
        if self.poses is not None:
            trajectory = read_trajectory(self.poses)
            if isinstance(self.rig.sources[0], SubsetSource):
                trajectory = self.rig.sources[0].follow(trajectory, by_time=False)
            if len(trajectory) != self.rig.n_base:
                raise InputError(f"{self.poses}: {len(trajectory)} poses for {self.rig.n_base} scans in "
                                 f"{self.rig.sources[0].name}; give one T_world_base per lidar0 scan.")
        else:
            log.info("base poses: KISS-ICP on %s", self.rig.sources[0].name)
        state = initial_poses(self.rig.sources[0], trajectory, None if self.poses is None else str(self.poses),
                              self.config, StageClock(show_progress=False))
        self.origin_world_m, self.T_initial = state.origin_world_m, state.T_initial
        self.report["initial_poses"] = "kiss-icp on lidar0" if self.poses is None else str(self.poses)
        self.report["local_frame_origin_m"] = self.origin_world_m.tolist()
        self.T_odometry = self.T_initial  # the odometry factors' measurements

    def refine_base(self) -> None:
        """Plane adjustment of the base poses on lidar0 alone (`pa_cli.adjust.solve` with the odometry
        factors), rounds as in `pa refine`: the coarse stage aligns the other LiDARs to lidar0's map,
        which must be consistent first (odometry drifts by centimetres and tenths of a degree)."""

        cfg, calibrate = self.config, self.config.advanced.calibrate
        lay = self.layout
        base_v = np.flatnonzero(lay.lidar_of_virtual == 0)
        points = [self.points[v] for v in base_v]
        T = self.T_initial[lay.base_of_virtual[base_v]]
        rounds = []
        for _ in range(calibrate.max_rounds):
            problem, _ = build_plane_problem(points, T, cfg.planes_config())
            if problem.n_observations == 0:
                break
            result = solve(problem, T, cfg.advanced.solver, terms=self._odometry_terms())
            moved, turned = pose_change(T, result.T_world_scan)
            T = result.T_world_scan
            rounds.append({"n_planes": problem.n_planes, "cost_final_m2": result.report["cost_final_m2"],
                           "max_change_m": moved, "max_change_deg": turned})
            if moved < calibrate.settle_translation_m and turned < calibrate.settle_rotation_deg:
                break
        self.T_initial = T
        self.report["base_rounds"] = rounds

    def initial_extrinsics(self) -> None:
        if self.init is not None:
            self.X_initial = read_extrinsics(self.init, self.rig.n_lidars)
        else:
            log.warning("no --init: starting every extrinsic at the identity; a hand-measured --init "
                        "EXTRINSICS.yaml (xyz_m, rpy_deg per LiDAR) is safer when the LiDARs point apart.")
            self.X_initial = np.tile(np.eye(4), (self.rig.n_lidars, 1, 1))
        self.report["initial_extrinsics"] = "identity" if self.init is None else str(self.init)

    def _odometry_terms(self) -> list:
        if self.config.refine.odometry_translation_sigma_m is None or self.rig.n_base < 2:
            return []
        return [OdometryFactors(self.T_odometry, OdometryModel.from_config(self.config))]

    def _coarse(self, X: np.ndarray, bases: list[np.ndarray]) -> tuple[np.ndarray, list[dict]]:
        cfg = self.config.advanced.calibrate
        lay = self.layout
        base_v = np.flatnonzero(lay.lidar_of_virtual == 0)
        world = np.concatenate([transform_points(self.T_initial[lay.base_of_virtual[v]], self.points[v])
                                for v in base_v])
        target = PlanarTarget(voxel_points(world, cfg.coarse_voxel_m), cfg, self.config.advanced.planes)
        X = X.copy()
        reports = []
        for k in range(1, lay.n_lidars):
            scans = [(int(lay.base_of_virtual[v]), voxel_points(self.points[v], cfg.coarse_voxel_m))
                     for v in np.flatnonzero(lay.lidar_of_virtual == k)]
            X[k], rep = align_extrinsic(target, scans, self.T_initial, X[k], cfg, bases[k - 1])
            reports.append({"lidar": k, **rep})
        return X, reports

    def _rounds(self, X: np.ndarray, bases: list[np.ndarray]) -> tuple[np.ndarray, list[dict], CalibrationCost]:
        cfg, calibrate = self.config, self.config.advanced.calibrate
        lay = self.layout
        state = lay.join(self.T_initial, X)
        terms = self._odometry_terms()
        rounds = []
        cost = None
        for r in range(calibrate.max_rounds):
            problem, diag = build_plane_problem(self.points, lay.composite(state), cfg.planes_config())
            if problem.n_observations == 0:
                raise SolverError(f"{self.rig_dir}: round {r + 1} found no plane seen by two scans; try larger "
                                  "scene.plane_voxel_m or scene.max_plane_thickness_m (--config indoor|outdoor|PATH, "
                                  "`pa config show`), or check --init / --poses.")
            cost = CalibrationCost(problem, lay, terms, cfg.advanced.solver.eigen_gap_tolerance)
            # directions this round's association leaves weak are held for the round
            weak = analyse_extrinsics(cost.derivatives(state)[3], lay.n_base, lay.n_lidars, calibrate.lever_arm_m,
                                      cfg.advanced.odometry.point_sigma_m, calibrate.unobservable_sigma_m, bases)
            new_state, solver = solve_calibration(cost, state, cfg.advanced.solver, [o.basis for o in weak])
            moved, turned = pose_change(state, new_state)
            solver.pop("history", None)
            rounds.append({"round": r + 1, "held": [w for o in weak for w in o.unobservable],
                           "n_planes": problem.n_planes, "n_observations": problem.n_observations,
                           "n_points": problem.n_points, "solver": solver, "max_change_m": moved,
                           "max_change_deg": turned})
            state = new_state
            log.info("calibration round %d: %d planes, cost %.6g m^2, moved %.3g m / %.3g deg", r + 1,
                     problem.n_planes, solver["cost_final_m2"], moved, turned)
            if moved < calibrate.settle_translation_m and turned < calibrate.settle_rotation_deg:
                break
        self.state = state
        return state, rounds, cost

    def calibrate(self) -> None:
        """Coarse stage and rounds; again from the initial extrinsics with the unobservable directions held."""
        cfg = self.config
        lay = self.layout
        bases = [np.eye(BLOCK)] * (lay.n_lidars - 1)
        held: dict[int, list[str]] = {k: [] for k in range(1, lay.n_lidars)}
        attempts = []
        while True:
            X, coarse = self._coarse(self.X_initial, bases)
            state, rounds, cost = self._rounds(X, bases)
            observability = analyse_extrinsics(cost.derivatives(state)[3], lay.n_base, lay.n_lidars,
                                               cfg.advanced.calibrate.lever_arm_m, cfg.advanced.odometry.point_sigma_m,
                                               cfg.advanced.calibrate.unobservable_sigma_m)
            attempts.append({"coarse": coarse, "rounds": rounds, "held": [held[k] for k in sorted(held)]})
            if any(held.values()) or not any(o.unobservable for o in observability):
                break
            bases = [o.basis for o in observability]
            held = {o.lidar: o.unobservable for o in observability}
            log.warning("unobservable: %s; held at the initial extrinsics and solved again.",
                        "; ".join(w for words in held.values() for w in words))
        self.bases, self.cost, self.observability = bases, cost, observability
        self.unobservable = held
        self.report["attempts"] = attempts
        self.report["observability"] = [o.as_dict() for o in observability]
        T_world_base, self.X = lay.split(state)
        self.T_world_base = T_world_base.copy()

    def covariance(self) -> None:
        lay = self.layout
        state = lay.join(self.T_world_base, self.X)
        problem = self.cost.problem
        _, _, _, H_gn, _ = self.cost.derivatives(state)
        plane_cost = self.cost.features.cost(lay.composite(state))
        n_free = BLOCK * (lay.n_base - 1) + sum(B.shape[1] for B in self.bases)
        dof = max(problem.n_points - 3 * problem.n_planes - n_free, 1)
        self.residual_variance_m2 = plane_cost / dof
        self.extrinsic_cov = extrinsic_covariance(H_gn, lay.n_base, lay.n_lidars, self.bases,
                                                  self.residual_variance_m2)

    def _extrinsic_notes(self) -> dict[int, dict]:
        notes = {}
        for k in range(1, self.layout.n_lidars):
            sigma = np.sqrt(np.maximum(np.diag(self.extrinsic_cov[k - 1]), 0.0))
            notes[k] = {"sigma_rotation_deg": [round(float(v), 6) for v in np.rad2deg(sigma[:3])],
                        "sigma_translation_mm": [round(float(v), 4) for v in 1e3 * sigma[3:]],
                        "unobservable": self.unobservable[k]}
        return notes

    def write(self) -> None:
        """Every output to a temporary file first; all renamed into place only when all succeeded."""

        out, lay, cfg = self.outputs, self.layout, self.config
        notes = self._extrinsic_notes()
        self.report["extrinsics"] = {
            lidar_name(k): {"T_base_lidar": self.X[k], "xyz_m": self.X[k][:3, 3],
                            "rpy_deg": np.rad2deg(rotation_to_rpy(self.X[k][:3, :3])),
                            **({"covariance": self.extrinsic_cov[k - 1],
                                "covariance_units": COVARIANCE_UNITS,
                                **notes[k]} if k else {})}
            for k in range(lay.n_lidars)}
        self.report["residual_sigma_m"] = float(np.sqrt(self.residual_variance_m2))
        self.report["config"] = dump_config(cfg)
        self.report["outputs"] = {name: str(p) for name, p in vars(out).items()}
        composite = lay.composite(lay.join(self.T_world_base, self.X))
        parts = []
        for k in range(lay.n_lidars):
            voxel_filter = MapVoxelFilter(cfg.map.voxel_m, self.origin_world_m)
            cloud = concatenate_clouds([voxel_filter.add(self.points[v], composite[v], int(lay.base_of_virtual[v]))
                                        for v in np.flatnonzero(lay.lidar_of_virtual == k)])
            parts.append((cloud.points_world, cloud.scan_index, np.full(len(cloud.scan_index), k)))
        stamps = self.rig.base_timestamps if self.rig.base_timestamps is not None \
            else np.arange(lay.n_base, dtype=np.float64)
        with contextlib.ExitStack() as stack:
            tmp = {p: stack.enter_context(atomic_path(p, self.force)) for p in out.all()}
            tmp[out.extrinsics].write_text(format_extrinsics(self.X, notes))
            T_world_base = to_world(self.T_world_base, self.origin_world_m)
            tmp[out.base_poses_kitti].write_text(format_kitti(T_world_base))
            tmp[out.base_poses_tum].write_text(format_tum(T_world_base, stamps))
            write_rig_map(tmp[out.map_ply], *(np.concatenate(a) for a in zip(*parts, strict=True)), force=True,
                          float64_coordinates=bool(self.origin_world_m.any()))
            tmp[out.report_json].write_text(report_to_json(self.report))
