"""The files `pa calibrate` writes next to the extrinsics YAML, and the merged rig map.

For `--out EXTRINSICS.yaml`: `EXTRINSICS.yaml`, `EXTRINSICS_base_poses_kitti.txt`,
`EXTRINSICS_base_poses_tum.txt` (refined T_world_base, world = base scan 0 unless --poses),
`EXTRINSICS_map.ply` (binary PLY: float32 x y z world frame, int32 scan_index = base scan,
int32 lidar_index = LiDAR k) and `EXTRINSICS_report.json`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError
from pa_cli.io.atomic import atomic_path
from pa_cli.io.maps import ply_header, ply_vertex_dtype
from pa_cli.runtime.open3d_preload import open3d


@dataclass
class CalibrationOutputs:
    """Paths of every output of one `pa calibrate` run."""

    extrinsics: Path
    base_poses_kitti: Path
    base_poses_tum: Path
    map_ply: Path
    report_json: Path

    @classmethod
    def from_extrinsics_path(cls, path: Path | str) -> CalibrationOutputs:
        path = Path(path)
        stem = path.with_suffix("")
        return cls(path, Path(f"{stem}_base_poses_kitti.txt"), Path(f"{stem}_base_poses_tum.txt"),
                   Path(f"{stem}_map.ply"), Path(f"{stem}_report.json"))

    def all(self) -> list[Path]:
        return [self.extrinsics, self.base_poses_kitti, self.base_poses_tum, self.map_ply, self.report_json]


def write_rig_map(path: Path | str, points_world: np.ndarray, scan_index: np.ndarray, lidar_index: np.ndarray,
                  force: bool = False, float64_coordinates: bool = False) -> None:
    """Binary little-endian PLY with float32 (or, with `float64_coordinates`, double) x y z (world,
    m), int32 scan_index and int32 lidar_index, atomically."""
    vertex = np.empty(len(points_world), dtype=ply_vertex_dtype(float64_coordinates, ("scan_index", "lidar_index")))
    for i, axis in enumerate("xyz"):
        vertex[axis] = points_world[:, i]
    vertex["scan_index"], vertex["lidar_index"] = scan_index, lidar_index
    with atomic_path(path, force) as tmp:
        tmp.write_bytes(ply_header(len(vertex), vertex.dtype) + vertex.tobytes())


def read_rig_map(path: Path | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 3) points, (K,) scan indices and (K,) LiDAR indices of a map written by `write_rig_map`."""
    cloud = open3d().t.io.read_point_cloud(str(path))
    if "lidar_index" not in cloud.point or "scan_index" not in cloud.point:
        raise FormatError(f"{path}: expected 'scan_index' and 'lidar_index' vertex properties (a pa calibrate map).")
    return (cloud.point.positions.numpy(), cloud.point["scan_index"].numpy().ravel(),
            cloud.point["lidar_index"].numpy().ravel())
