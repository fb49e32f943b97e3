"""Simulated multi-LiDAR rigs (`pa simulate --rig RIG.yaml`): the rig file and the rig folder.

Rig file (YAML): a list of LiDARs, each mounted on the vehicle that follows the scene's path
(vehicle frame: x forward, y left, z up, at the scene's sensor height):

    lidars:
      - xyz_m: [0.0, 0.0, 0.0]      # mounting position in the vehicle frame (m)
        rpy_deg: [0.0, 0.0, 0.0]    # mounting roll, pitch, yaw (deg), R = Rz(yaw) Ry(pitch) Rx(roll)
        beams: 16                   # 16, 32 or 64
        vfov_deg: 30                # optional: vertical field of view (deg), default by beams
        hfov_deg: 360               # optional: horizontal field of view (deg) centred on the LiDAR's x axis
      - {xyz_m: [0.3, -0.5, 0.2], rpy_deg: [0, 10, -90], beams: 32, hfov_deg: 180}

The first LiDAR is the base: the base frame is its frame. The rig folder holds `lidar0/`,
`lidar1/`, ... (binary PCD scans `%06d.pcd`, sensor frame, same indexing for every LiDAR: scan k
of every LiDAR is cast at time k * 0.1 s), `times.txt`, `gt_poses_kitti.txt` / `gt_poses_tum.txt`
(T_world_base), `gt_extrinsics.yaml` (true T_base_lidar, the `pa calibrate --out` format), the
normalised `rig.yaml` and `meta.json`. Each LiDAR's range noise has its own stream
(seed * MAX_LIDARS + k).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from pa_cli import __version__
from pa_cli.core.geometry import rigid_inverse
from pa_cli.errors import UsageError
from pa_cli.io.extrinsics import format_extrinsics, pose_from_xyz_rpy
from pa_cli.io.files import read_input_bytes
from pa_cli.io.scans import write_pcd
from pa_cli.io.trajectory import format_kitti, format_tum
from pa_cli.simulate.raycast import Simulator
from pa_cli.simulate.sensor import BEAM_CHOICES, SCAN_PERIOD_S, SimOptions, in_horizontal_fov
from pa_cli.simulate.writer import building_dir, check_simulation

MAX_LIDARS = 16  # LiDARs a rig file may list (also the stride of the per-LiDAR noise seeds)
RIG_HINT = ("a rig file is 'lidars:' followed by a list of {xyz_m: [x, y, z], rpy_deg: [roll, pitch, yaw], "
            "beams: 16|32|64, vfov_deg (optional), hfov_deg (optional)}; see README 'Multi-LiDAR calibration'")


@dataclass
class RigLidar:
    """One LiDAR of a rig file: mounting pose on the vehicle, beams and fields of view (deg)."""

    xyz_m: tuple[float, float, float]
    rpy_deg: tuple[float, float, float]
    beams: int
    vfov_deg: float | None = None
    hfov_deg: float = 360.0

    def T_vehicle_lidar(self) -> np.ndarray:
        return pose_from_xyz_rpy(np.array(self.xyz_m), np.deg2rad(self.rpy_deg))


def _number_list(path: Path, where: str, value: object) -> tuple[float, float, float]:
    array = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.empty(0)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise UsageError(f"{path}: {where} must be a list of 3 finite numbers, found {value!r}; {RIG_HINT}.")
    return tuple(float(v) for v in array)


def read_rig(path: Path | str) -> list[RigLidar]:
    """The LiDARs of a rig file (errors name the file, the entry and the expected form)."""
    path = Path(path)
    raw = read_input_bytes(path, "rig", RIG_HINT)
    try:
        data = yaml.safe_load(raw.decode("utf-8", errors="replace"))
    except yaml.YAMLError as exc:
        raise UsageError(f"{path}: not valid YAML ({exc}); {RIG_HINT}.") from None
    entries = data.get("lidars") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not 2 <= len(entries) <= MAX_LIDARS:
        raise UsageError(f"{path}: expected 'lidars:' with 2 to {MAX_LIDARS} entries; {RIG_HINT}.")
    lidars = []
    for k, entry in enumerate(entries):
        where = f"lidars[{k}]"
        if not isinstance(entry, dict):
            raise UsageError(f"{path}: {where} must be a mapping; {RIG_HINT}.")
        unknown = set(entry) - {"xyz_m", "rpy_deg", "beams", "vfov_deg", "hfov_deg"}
        if unknown:
            raise UsageError(f"{path}: {where} has unknown keys {', '.join(sorted(map(str, unknown)))}; {RIG_HINT}.")
        beams = entry.get("beams")
        if beams not in BEAM_CHOICES:
            raise UsageError(f"{path}: {where}.beams must be one of 16, 32, 64; found {beams!r}.")
        vfov = entry.get("vfov_deg")
        if vfov is not None and not (isinstance(vfov, int | float) and 0 < vfov < 180):
            raise UsageError(f"{path}: {where}.vfov_deg must be in (0, 180) degrees; found {vfov!r}.")
        hfov = entry.get("hfov_deg", 360.0)
        if not (isinstance(hfov, int | float) and 0 < hfov <= 360):
            raise UsageError(f"{path}: {where}.hfov_deg must be in (0, 360] degrees; found {hfov!r}.")
        lidars.append(RigLidar(_number_list(path, f"{where}.xyz_m", entry.get("xyz_m")),
                               _number_list(path, f"{where}.rpy_deg", entry.get("rpy_deg")), int(beams),
                               None if vfov is None else float(vfov), float(hfov)))
    return lidars


class MountedSimulator(Simulator):
    """A `Simulator` whose LiDAR sits at T_vehicle_lidar on the path's vehicle, seeing only the
    beams within its horizontal field of view."""

    def __init__(self, options: SimOptions, T_vehicle_lidar: np.ndarray, hfov_deg: float) -> None:
        super().__init__(options)
        keep = in_horizontal_fov(self.dirs_sensor, hfov_deg)
        self.dirs_sensor = self.dirs_sensor[keep]
        self.column_of_ray = self.column_of_ray[keep]
        self.beam_of_ray = self.beam_of_ray[keep]
        self.T_vehicle_lidar = np.asarray(T_vehicle_lidar, dtype=np.float64)

    def gt_poses(self) -> np.ndarray:
        return super().gt_poses() @ self.T_vehicle_lidar

    def poses_at_times(self, time_s: np.ndarray) -> np.ndarray:
        return super().poses_at_times(time_s) @ self.T_vehicle_lidar


def rig_simulators(options: SimOptions, lidars: list[RigLidar]) -> list[MountedSimulator]:
    """One simulator per LiDAR: the shared options with its beams, vertical FoV and noise seed."""
    return [MountedSimulator(replace(options, beams=lidar.beams, vfov_deg=lidar.vfov_deg,
                                     seed=options.seed * MAX_LIDARS + k), lidar.T_vehicle_lidar(), lidar.hfov_deg)
            for k, lidar in enumerate(lidars)]


def simulate_rig(options: SimOptions, rig_path: Path | str, out_dir: Path | str, force: bool = False,
                 progress: Callable[[int, int], None] | None = None) -> dict:
    """Simulate every LiDAR of the rig file along the scene's path and write the rig folder
    (module docstring) atomically; returns the meta dict."""

    lidars = read_rig(rig_path)
    check_simulation(options, out_dir, force)
    sims = rig_simulators(options, lidars)
    out_dir = Path(out_dir)
    n_scans = options.scans
    T_lidar0_vehicle = rigid_inverse(lidars[0].T_vehicle_lidar()[None])[0]
    T_base_lidar = np.stack([T_lidar0_vehicle @ lidar.T_vehicle_lidar() for lidar in lidars])
    with building_dir(out_dir) as tmp:
        n_points = [0] * len(sims)
        for k, sim in enumerate(sims):
            folder = tmp / f"lidar{k}"
            folder.mkdir()
            for i, scan in enumerate(sim.iter_scans()):
                write_pcd(folder / f"{i:06d}.pcd", scan.points_scan, time=scan.time, intensity=scan.intensity)
                n_points[k] += len(scan.points_scan)
                if progress is not None:
                    progress(k * n_scans + i + 1, len(sims) * n_scans)
        T_world_base = sims[0].gt_poses()
        timestamps_s = np.arange(n_scans) * SCAN_PERIOD_S
        (tmp / "gt_poses_kitti.txt").write_text(format_kitti(T_world_base))
        (tmp / "gt_poses_tum.txt").write_text(format_tum(T_world_base, timestamps_s))
        (tmp / "times.txt").write_text("".join(f"{t:.9f}\n" for t in timestamps_s))
        (tmp / "gt_extrinsics.yaml").write_text(format_extrinsics(T_base_lidar))
        (tmp / "rig.yaml").write_text(yaml.safe_dump({"lidars": [asdict(lidar) for lidar in lidars]},
                                                     sort_keys=False, default_flow_style=None))
        meta = {"pa_version": __version__, "scene": sims[0].options.scene,
                "options": [sim.options.record() for sim in sims], "scan_period_s": SCAN_PERIOD_S,
                "n_scans": n_scans, "n_lidars": len(sims), "n_points": n_points,
                "base_frame": "the frame of lidar0; gt poses are T_world_base at each scan's start",
                "extrinsics": "gt_extrinsics.yaml: T_base_lidar per LiDAR (pa calibrate --out format)"}
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return meta
