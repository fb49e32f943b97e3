"""The files `pa refine` writes: all to temporary files first, renamed only when every one succeeded."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.adjust.covariance import save_covariance
from pa_cli.config import PaConfig, dump_config
from pa_cli.core.local_frame import to_world
from pa_cli.io.atomic import atomic_path
from pa_cli.io.map_filter import MapFilter, PlacedPart
from pa_cli.io.maps import chunked, write_map
from pa_cli.io.problem import save_problem
from pa_cli.io.report import report_to_json
from pa_cli.io.trajectory import Trajectory, format_kitti, format_tum
from pa_cli.refine.clock import Stage
from pa_cli.refine.map_outputs import map_parts, write_overview
from pa_cli.refine.state import RefineState
from pa_cli.refine.work import work_folder_path
from pa_cli.runtime.distributed import in_order, in_order_in_flight
from pa_cli.sources import PointsView


@dataclass(frozen=True)
class RefineOutputs:
    """Every file `pa refine` writes, named after the stem of the map path (.ply, .pcd, .las or .laz)."""

    map_path: Path
    poses_kitti: Path
    poses_tum: Path
    initial_poses_kitti: Path
    report_json: Path
    config_yaml: Path
    covariance_npz: Path
    overview_png: Path
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
            overview_png=Path(f"{stem}_overview.png"),
            problem_npz=None if problem_npz is None else Path(problem_npz),
        )

    @property
    def work_dir(self) -> Path:
        """The run's work folder (`pa_cli.refine.work`): MAP.work beside the map; not an output."""
        return work_folder_path(self.map_path)

    def all(self) -> list[Path]:
        paths = [self.map_path, self.poses_kitti, self.poses_tum, self.initial_poses_kitti,
                 self.report_json, self.config_yaml, self.covariance_npz, self.overview_png]
        return paths + ([self.problem_npz] if self.problem_npz is not None else [])


@dataclass(frozen=True)
class Written:
    """What the map writer counted: the scans' points read (`n_points_in`), the map's points, the
    points outside the range it keeps, and whether it holds intensity and time."""

    n_points_in: int
    n_map_points: int
    n_out_of_range: int
    with_intensity: bool
    with_time: bool


def write_outputs(outputs: RefineOutputs, source: Any, state: RefineState, config: PaConfig, gt: Trajectory | None,
                  force: bool, stage: Stage, report: Callable[[Written], dict[str, Any]]) -> None:
    """Write the map (streamed scan by scan through the map filter: voxel, range; the scans read and placed
    by `execution.threads` threads, kept in order), the refined and initial poses (world frame), the effective
    config, the covariance and the saved problem when there are some, the overview picture (drawn on a thread
    of its own meanwhile), then `report(written)` as the last file; nothing is renamed into place unless all
    succeeded."""
    n_scans = len(source)
    T_refined = state.T_current
    with contextlib.ExitStack() as stack:
        tmp = {p: stack.enter_context(atomic_path(p, force)) for p in outputs.all()
               if p != outputs.covariance_npz or state.covariance is not None}
        with stage("write", total=n_scans) as progress:
            sensor = config.sensor
            map_filter = MapFilter(config.map.voxel_m, sensor.min_range_m, sensor.max_range_m,
                                   state.origin_world_m)
            n_points = [0]
            refined = None if state.deskewed is None else state.deskewed.at(T_refined)
            threads = config.execution.threads
            parts_of = map_parts(source, refined, state.timestamps, poses_at_once=in_order_in_flight(threads))

            def placed(k: int) -> tuple[int, list[PlacedPart]]:  # on a thread: read, range, pose, voxel keys
                parts = parts_of(k)
                return sum(len(part.points_scan) for part in parts), [map_filter.place(p, T_refined[k]) for p in parts]

            def map_clouds() -> Iterator[Any]:
                for k, (n_read, placed_parts) in enumerate(in_order(placed, n_scans, threads)):
                    n_points[0] += n_read
                    for part in placed_parts:
                        yield map_filter.keep(part)
                    progress(k + 1, n_scans)

            stamps = state.timestamps if state.timestamps is not None else np.arange(n_scans, dtype=np.float64)
            T_world_scan = to_world(T_refined, state.origin_world_m)
            T_initial_world = to_world(state.T_initial, state.origin_world_m)
            with ThreadPoolExecutor(max_workers=1) as drawing:  # the picture is drawn while the map streams
                overview = drawing.submit(write_overview, tmp[outputs.overview_png], PointsView(source),
                                          T_initial_world, T_world_scan, state.timestamps, gt, force=True)
                n_map = write_map(tmp[outputs.map_path], chunked(map_clouds()),
                                  force=True, suffix=outputs.map_path.suffix,
                                  float64_coordinates=bool(state.origin_world_m.any()))
                tmp[outputs.poses_kitti].write_text(format_kitti(T_world_scan))
                tmp[outputs.poses_tum].write_text(format_tum(T_world_scan, stamps))
                tmp[outputs.initial_poses_kitti].write_text(format_kitti(T_initial_world))
                tmp[outputs.config_yaml].write_text(dump_config(config))
                if state.covariance is not None:
                    save_covariance(tmp[outputs.covariance_npz], state.covariance.in_world(state.origin_world_m),
                                    force=True)
                if outputs.problem_npz is not None:
                    saved = dataclasses.replace(state.rounds.problem, T_world_scan=T_world_scan)
                    save_problem(tmp[outputs.problem_npz], saved, force=True)
                overview.result()
        # the report is the last small file: every stage time, this one's included, is final
        written = Written(int(n_points[0]), int(n_map), int(map_filter.n_out_of_range),
                          bool(map_filter.with_intensity), state.timestamps is not None)
        tmp[outputs.report_json].write_text(report_to_json(report(written)))
