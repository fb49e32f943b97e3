"""Scans: folders of PCD / PLY / KITTI BIN point clouds, in the sensor (scan) frame, metres."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pa_cli.io.atomic import atomic_path


def write_pcd(path: Path | str, points_scan: np.ndarray, time: np.ndarray | None = None,
              intensity: np.ndarray | None = None, force: bool = False) -> None:
    """Write a binary PCD with float32 x y z [intensity] [time] fields, atomically.

    `time` is the per-point time in seconds relative to the scan's timestamp.
    """
    from pypcd4 import PointCloud

    columns = [np.asarray(points_scan, dtype=np.float32)]
    fields = ["x", "y", "z"]
    for name, values in (("intensity", intensity), ("time", time)):
        if values is not None:
            columns.append(np.asarray(values, dtype=np.float32).reshape(-1, 1))
            fields.append(name)
    data = np.hstack(columns)
    cloud = PointCloud.from_points(data, fields, [np.float32] * len(fields))
    with atomic_path(path, force) as tmp:
        cloud.save(tmp)
