"""`pa refine`: scan source -> initial poses -> rounds of (associate planes, adjust) -> map.

`RefinePipeline(...).run()` runs the steps listed by `steps()` in order:

    check inputs -> open scans -> load (scan headers, valid points) -> open the work folder
    -> initial poses -> timestamps -> loops -> deskew -> rounds -> pose covariance -> association check
    -> start check -> evaluate (--gt) -> write

The pipeline owns the scan source, the inputs and the outputs; every step calls a stage
(`pa_cli.refine.stages`, `pa_cli.refine.rounds`) with what it needs and stores what the stage
returned in the explicit `RefineState`. The report is built once, from the state, when the
outputs are written; nothing reads it back. A new stage is a function in `stages.py` (or a step
of the strategy in `rounds.py`) and a step here at its place in the order.

The work folder (`pa_cli.refine.work`, `MAP.work/`) keeps the initial poses, the loop-closed
poses and what each round hands the next as they finish; with `resume` the steps take what it
holds instead of computing it again, and the result equals an uninterrupted run's. It is removed
once the outputs are written (kept with `keep_work`). Before each step over the whole sequence the
memory it will hold is estimated and checked against the budget (`pa_cli.refine.memory`).

The loops step (when `loops.enabled`) replaces the initial poses by loop-closed ones
(`pa_cli.loops`): every later step starts from the loop-closed trajectory (deskew moves it to the
reference instants, the pairs' registrations start from its relative motions, and the rounds from the
pose graph of those motions and the closures); the
odometry's own poses stay in `T_odometry` and are evaluated under `gt.odometry`.

Frames and units: poses are T_world_scan (N, 4, 4), metres; with KISS-ICP the world is the
frame of scan 0. The plane cost is the sum of squared point-to-plane distances (m^2), and the
RMS point-to-plane distance is sqrt(cost / points on planes) (m).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pa_cli.config import PaConfig
from pa_cli.errors import InputError, PaError
from pa_cli.io.atomic import check_writable
from pa_cli.io.dataset_gt import read_ground_truth
from pa_cli.io.maps import check_laz_backend
from pa_cli.io.trajectory import Trajectory, read_trajectory
from pa_cli.planes.windowed import ScanRef
from pa_cli.refine.clock import StageClock
from pa_cli.refine.memory import SequenceSize, check_sequence_memory
from pa_cli.refine.outputs import RefineOutputs, Written, write_outputs
from pa_cli.refine.rounds import refine_rounds
from pa_cli.refine.stages import (
    association_check,
    evaluate_against_gt,
    initial_poses,
    loop_closure,
    motion_compensation,
    pose_covariance,
    scan_timestamps,
    spread_covariance,
    start_check,
)
from pa_cli.refine.state import RefineState
from pa_cli.refine.work import WorkFolder, manifest, open_work_folder
from pa_cli.runtime.distributed import GB, execution
from pa_cli.sources import ScanSubset, SubsetSource, check_out_of_scans, describe_source, open_source
from pa_cli.sources.base import read_issues
from pa_cli.sources.cache import CachedSource
from pa_cli.sources.screen import ScreenedSource

log = logging.getLogger(__name__)


class RefinePipeline:
    """The end-to-end refinement. Construct, then `run()`; returns the report dict. `state`
    holds what the stages made (`RefineState`), `clock` their times."""

    def __init__(self, scans: Path | str, out_map: Path | str, config: PaConfig, *,
                 topic: str | None = None, poses: Path | str | None = None, gt: Path | str | None = None,
                 save_problem: Path | str | None = None, glob: str | None = None,
                 subset: ScanSubset | None = None, force: bool = False, show_progress: bool = True,
                 config_source: str = "defaults", resume: bool = False, keep_work: bool = False) -> None:
        self.scans_path = Path(scans)
        self.topic = topic
        self.config = config
        self.poses_path = None if poses is None else Path(poses)
        self.gt_path = None if gt is None else Path(gt)
        self.glob = glob
        self.subset = subset
        self.force = force
        self.resume = resume
        self.keep_work = keep_work
        self.config_source = config_source
        self.outputs = RefineOutputs.from_map_path(out_map, save_problem)
        self.clock = StageClock(show_progress)
        self.source: Any = None
        self.poses: Trajectory | None = None
        self.gt: Trajectory | None = None
        self.state: RefineState | None = None
        self.work: WorkFolder | None = None
        self.size: SequenceSize | None = None
        self.report: dict[str, Any] = {}

    def steps(self) -> list[Callable[[], None]]:
        """The steps `run()` executes, in order."""
        return [self.check_inputs, self.open_scans, self.load, self.open_work, self.initial_poses, self.find_timestamps,
                self.close_loops, self.prepare_deskew, self.refine_rounds, self.pose_covariance, self.check_association,
                self.check_start, self.spread_covariance, self.evaluate, self.write]

    def run(self) -> dict[str, Any]:
        """Run the steps; the hierarchical adjustment's windows run where `config.execution` says.
        A known failure (`PaError`: a bad input, no planes, ...) removes the work folder, which
        a resumed run would only bring back to it; any other stop (Ctrl-C, lack of memory, a
        crash) keeps it for `--resume`."""
        try:
            with execution(self.config.execution):
                for step in self.steps():
                    step()
        except PaError:
            if self.work is not None:
                self.work.remove()
            raise
        finally:
            if self.work is not None:
                self.work.drain()  # a round's carry still being written (`WorkFolder.save_carry`) is finished
            if self.source is not None:
                self.source.close()
        return self.report

    # ---------------------------------------------------------------- steps
    def check_inputs(self) -> None:
        """Before any work: outputs writable and not in the scan folder (and a LAZ backend for .laz),
        --poses and --gt read."""
        inputs = [p for p in (self.poses_path, self.gt_path, self.scans_path) if p is not None]
        check_writable(self.outputs.all(), self.force, inputs=inputs)
        check_out_of_scans(self.scans_path, self.outputs.map_path, self.force)
        if self.outputs.map_path.suffix.lower() == ".laz":
            check_laz_backend(self.outputs.map_path)
        if self.poses_path is not None:
            self.poses = read_trajectory(self.poses_path)
        if self.gt_path is not None:
            self.gt = read_ground_truth(self.gt_path)

    def open_scans(self) -> None:
        """Open the scan source (lists files or a bag's index; a --first/--last/--every subset, which
        --poses and --gt follow), behind the point cache and the screen that leaves out scans without
        enough valid points (`pa_cli.sources.screen`)."""
        source = open_source(self.scans_path, topic=self.topic, glob=self.glob, subset=self.subset)
        found = describe_source(source)
        if found is not None:
            log.info("%s", found)
        if isinstance(source, SubsetSource):
            log.info("%s: %d of %d scans kept: %s.", source.name, len(source), source.n_source,
                     source.subset.describe())
            self.poses = None if self.poses is None else source.follow(self.poses, by_time=False)
            self.gt = None if self.gt is None else source.follow(self.gt, by_time=True)
        if self.config.advanced.execution.cache_points:
            source = CachedSource(source, self.config.execution.cache_budget_gb * GB)
        self.source = ScreenedSource(source)

    def load(self) -> None:
        """Check every scan (headers, then each scan's valid points), so a corrupt scan is reported
        before any work, and check the counts of --poses and --gt against the scans kept."""
        with self.clock("load") as progress:
            self.source.check()
            n_scans = len(self.source)
            progress(n_scans, n_scans)
        if n_scans < 2:
            raise InputError(f"{self.source.name}: found {n_scans} scan(s); refinement needs at least 2 "
                             "(check --glob or --topic).")
        if self.poses is not None and len(self.poses) != n_scans:
            raise InputError(f"{self.poses_path}: {len(self.poses)} poses for {n_scans} scans in "
                             f"{self.source.name}{self._left_out()}; --poses needs one pose per scan (check --glob).")
        if self.gt is not None and self.gt.timestamps is None and len(self.gt) != n_scans:
            raise InputError(f"{self.gt_path}: {len(self.gt)} poses for {n_scans} scans{self._left_out()} and no "
                             "timestamps to associate them; --gt needs one pose per scan.")

    def _left_out(self) -> str:
        """' (N left out, see the log)' when the source left scans out, for a count message."""
        n_skipped = len(read_issues(self.source).skipped)
        return f" ({n_skipped} left out, see the log)" if n_skipped else ""

    def open_work(self) -> None:
        """The work folder for these inputs (`open_work_folder`: made, continued with --resume, or
        refused), and the sequence's size for the memory checks."""
        expected = manifest(self.scans_path, len(self.source), self.topic, self.glob, self.subset,
                            self.poses_path, self.config)
        self.work = open_work_folder(self.outputs.work_dir, expected, self.resume, self.force)
        self.size = SequenceSize.from_files(len(self.source), expected["scans"]["n_bytes"])

    def initial_poses(self) -> None:
        """KISS-ICP odometry, or the poses of --poses (moved into the local frame); kept in the work folder."""
        kept = self.work.load("odometry")
        if kept is not None:
            arrays, record = kept
            T_odometry = arrays["T_odometry"]
            self.state = RefineState(origin_world_m=arrays["origin_world_m"], T_odometry=T_odometry,
                                     T_initial=T_odometry, T_current=T_odometry.copy(),
                                     initial_poses_source=record["initial_poses_source"])
            return
        if self.poses is None:
            check_sequence_memory("odometry", self.size, self.config)
        self.state = initial_poses(self.source, self.poses, None if self.poses_path is None else str(self.poses_path),
                                   self.config, self.clock)
        self.work.save("odometry", {"T_odometry": self.state.T_odometry, "origin_world_m": self.state.origin_world_m},
                       {"initial_poses_source": self.state.initial_poses_source})

    def find_timestamps(self) -> None:
        """Per-scan timestamps (s): the TUM timestamps of --poses, else the source's, else none."""
        stamps, origin = scan_timestamps(self.source, self.poses, str(self.poses_path),
                                         str(self.outputs.poses_tum))
        self.state = dataclasses.replace(self.state, timestamps=stamps, timestamps_source=origin)

    def close_loops(self) -> None:
        """Loop closure (`loops` config): the later steps then start from the loop-closed poses."""
        if not self.config.loops.enabled:
            return
        kept = self.work.load("loops")
        if kept is None:
            check_sequence_memory("loops", self.size, self.config)
            T_closed, loops = loop_closure(self.source, self.state, self.config, self.clock)
            self.work.save("loops", {"T_world_scan": T_closed}, loops)
        else:
            T_closed, loops = kept[0]["T_world_scan"], kept[1]
        self.state = dataclasses.replace(self.state, T_initial=T_closed, T_current=T_closed.copy(), loops=loops,
                                         odometry_frames=None)

    def prepare_deskew(self) -> None:
        """Motion compensation (`sensor.deskew`): the deskewed points and the rounds' start."""
        T_start, deskewed, info = motion_compensation(self.source, self.config, self.state.timestamps,
                                                      self.state.T_initial, from_odometry=self.poses_path is None)
        self.state = dataclasses.replace(self.state, T_initial=T_start, T_current=T_start.copy(), deskewed=deskewed,
                                         deskew=info)

    def refine_rounds(self) -> None:
        """The rounds (`pa_cli.refine.rounds`) from the state's start, or from the work folder's last round."""
        check_sequence_memory("planes", self.size, self.config)
        scans = ScanRef(str(self.scans_path), self.topic, self.glob, self.subset, self.source.skipped_indices())
        rounds = refine_rounds(self.source, scans, self.state, self.config, self.clock, self.work)
        self.work.wait()  # the last carry written, or its error raised
        self.state = dataclasses.replace(self.state, rounds=rounds, T_current=rounds.T_world_scan)

    def pose_covariance(self) -> None:
        """Per-scan covariance of the refined poses (`stages.pose_covariance`); the solver's state of
        the last round is released with this step."""
        rounds = self.state.rounds
        model, rounds.solver_model = rounds.solver_model, None
        covariance, report = pose_covariance(rounds.problem, self.state.T_current, rounds.terms, model, self.config,
                                             str(self.outputs.covariance_npz), self.clock)
        self.state = dataclasses.replace(self.state, covariance=covariance, covariance_report=report)

    def check_association(self) -> None:
        """An association its cap froze while it still moved (`stages.association_check`): the rounds did not
        settle, a doubt in the verdict naming the scans."""
        self.state = dataclasses.replace(self.state, rounds=association_check(self.state))

    def check_start(self) -> None:
        """Start-consistency (`stages.start_check`): a doubt in the verdict when the refined poses
        follow the start's relative motions beyond the pose covariance's 3 sigma."""
        rounds = start_check(self.state, self.config, len(self.source), self.clock)
        self.state = dataclasses.replace(self.state, rounds=rounds)

    def spread_covariance(self) -> None:
        """The pose covariance plus the spread of the answer over the association
        (`stages.spread_covariance`), after the checks that judge moves against the adjustment's own."""
        covariance, report = spread_covariance(self.state)
        self.state = dataclasses.replace(self.state, covariance=covariance, covariance_report=report)

    def evaluate(self) -> None:
        """ATE and RPE of the initial and refined poses against --gt (SE(3)-aligned)."""
        if self.gt is None:
            return
        gt = evaluate_against_gt(self.gt, self.source, self.state, self.state.rounds.labels_final, self.clock)
        self.state = dataclasses.replace(self.state, gt=gt)

    def write(self) -> None:
        """Write every output (`pa_cli.refine.outputs`), the report last; then remove the work
        folder (unless `keep_work`)."""
        check_sequence_memory("map", self.size, self.config)
        write_outputs(self.outputs, self.source, self.state, self.config, self.gt, self.force, self.clock,
                      self._report)
        if not self.keep_work:
            self.work.remove()

    # ---------------------------------------------------------------- the report
    def _report(self, written: Written) -> dict[str, Any]:
        """The report, built once from the state, the clock and what the writer counted."""
        state, rounds = self.state, self.state.rounds
        assessed = rounds.assessment
        report: dict[str, Any] = {
            "stage_times_s": self.clock.wall_s, "stage_cpu_s": self.clock.cpu_s,
            "input": {"source": self.source.name, "n_scans": len(self.source), "glob": self.glob,
                      "topic": self.topic,
                      "subset": None if self.subset is None or self.subset.is_all else self.subset.describe(),
                      "poses": None if self.poses_path is None else str(self.poses_path),
                      "gt": None if self.gt_path is None else str(self.gt_path), "config": self.config_source,
                      "n_points": written.n_points_in, "read_issues": read_issues(self.source).report()},
            "stage_peak_rss_gb": self.clock.peak_rss_gb,
            "initial_poses_source": state.initial_poses_source,
            "local_frame_origin_m": state.origin_world_m.tolist(),
            "timestamps_source": state.timestamps_source,
            "loops": state.loops,
            "deskew": state.deskew,
            "rounds": rounds.rounds,
            "unsettled_association": rounds.unsettled_association,
            "summary": assessed.summary,
            "degeneracy": assessed.degeneracy.as_report(),
            "poorly_constrained_scans": assessed.degeneracy.held_by_odometry_scans,
            "quality": assessed.quality.as_report(),
            "motion_noise": rounds.motion_noise,
            "covariance": state.covariance_report,
            "start_consistency": rounds.start_consistency,
        }
        if state.gt is not None:
            report["gt"] = state.gt
        sensor = self.config.sensor
        report["map"] = {"path": str(self.outputs.map_path), "n_points": written.n_map_points,
                         "voxel_m": self.config.map.voxel_m,
                         "range_m": [sensor.min_range_m, sensor.max_range_m],
                         "n_out_of_range": written.n_out_of_range, "intensity": written.with_intensity,
                         "time": written.with_time}
        report["outputs"] = {name: str(p) for name, p in vars(self.outputs).items() if p is not None}
        report["total_time_s"] = self.clock.elapsed_s()
        self.report = report
        return report
