"""Initial poses by KISS-ICP, used by composition through its Python API (not a fork).

Frames: KISS-ICP's `last_pose` after registering scan k maps scan-k points (sensor frame)
into the frame of the first scan, so it is T_world_scan(k) with world = scan 0 (identity).
This is the same convention its own pipeline writes to `*_poses_kitti.txt`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from pa_cli.config import KissIcpConfig, SensorConfig
from pa_cli.errors import InputError
from pa_cli.sources.base import ScanSource

log = logging.getLogger(__name__)

# KISS-ICP's own default when no voxel size is given: max_range / 100 (kiss_icp.config.parser).
KISS_VOXEL_PER_RANGE = 100.0
# KISS-ICP thins each (deskewed, range-cropped) frame to this fraction of its map voxel before adding it to its map
# (`KissICP.voxelize`: one point per voxel); `on_frame` hands these frames on.
KISS_FRAME_VOXEL_FRACTION = 0.5


def kiss_config(sensor: SensorConfig, config: KissIcpConfig) -> Any:
    """KISS-ICP's config built from ours (the sensor's max/min range in m; voxel in m, deskew)."""
    from kiss_icp.config import load_config

    kiss = load_config(None)
    kiss.data.max_range = float(sensor.max_range_m)
    kiss.data.min_range = float(sensor.min_range_m)
    kiss.data.deskew = bool(config.deskew)
    voxel_size_m = config.voxel_size_m
    if voxel_size_m is None:
        voxel_size_m = sensor.max_range_m / KISS_VOXEL_PER_RANGE
    kiss.mapping.voxel_size = float(voxel_size_m)
    return kiss


def kiss_frame_voxel_m(sensor: SensorConfig, config: KissIcpConfig) -> float:
    """The voxel (m) KISS-ICP thins each frame to for its map: the frames `run_kiss_icp` hands to `on_frame`."""
    return KISS_FRAME_VOXEL_FRACTION * kiss_config(sensor, config).mapping.voxel_size


def normalized_point_times(time_s: np.ndarray | None) -> np.ndarray:
    """Per-point times mapped to [0, 1] across the scan, as KISS-ICP's deskewing expects.

    Empty array when there are no times or they are all equal (no deskew possible).
    """
    if time_s is None or len(time_s) == 0:
        return np.empty(0)
    time_s = np.asarray(time_s, dtype=np.float64).ravel()
    t_min, t_max = float(time_s.min()), float(time_s.max())
    if not np.isfinite(t_min) or not np.isfinite(t_max) or t_max <= t_min:
        return np.empty(0)
    return (time_s - t_min) / (t_max - t_min)


class ReplayedFrames(Sequence):
    """The frames `run_kiss_icp` hands to `on_frame`, made again from the scans of `source` and the poses it
    returned (T_world_scan (N, 4, 4)): scan k preprocessed (range crop, deskew) with the motion KISS-ICP predicted
    it with, its step from scan k-2 to k-1 (from the identity to scan 0 for scan 1, none for scan 0), then thinned
    by KISS-ICP's own `voxelize`.
    Reads one scan per item."""

    def __init__(self, source: ScanSource, T_world_scan: np.ndarray, sensor: SensorConfig,
                 config: KissIcpConfig) -> None:
        from kiss_icp.kiss_icp import KissICP

        self.source, self.T_world_scan, self.deskew = source, T_world_scan, config.deskew
        self.kiss = KissICP(kiss_config(sensor, config))

    def __len__(self) -> int:
        return len(self.T_world_scan)

    def __getitem__(self, k: int) -> np.ndarray:
        T = self.T_world_scan
        before = np.eye(4) if k < 2 else T[k - 2]  # KISS-ICP's pose before its first scan: the identity
        predicted = np.eye(4) if k == 0 else np.linalg.inv(before) @ T[k - 1]
        times01 = normalized_point_times(self.source.point_times(k)) if self.deskew else np.empty(0)
        frame = self.kiss.preprocessor.preprocess(self.source.points(k), times01, predicted)
        return self.kiss.voxelize(frame)[1]


def run_kiss_icp(source: ScanSource, sensor: SensorConfig, config: KissIcpConfig,
                 progress: Callable[[int, int], None] | None = None,
                 on_frame: Callable[[int, np.ndarray], None] | None = None) -> np.ndarray:
    """Run KISS-ICP over the scans of `source` in order; T_world_scan (N, 4, 4), world = scan 0.

    Points are in the sensor frame (m); per-point times (s) are used for deskewing. Each scan
    is read once. When `config.deskew` is on and a scan has no per-point times, that scan is
    registered without deskewing and a warning is logged once. `on_frame(k, points)` receives
    scan k as KISS-ICP added it to its map: range-cropped, deskewed to its pose when deskewing, one
    point per `kiss_frame_voxel_m` voxel ((M, 3) float64, sensor frame at that pose, m).
    """
    from kiss_icp.kiss_icp import KissICP

    class KissICPKeepingFrames(KissICP):
        """KISS-ICP that keeps the frame it last thinned for its map (`frame_thinned`)."""

        def voxelize(self, iframe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            source, self.frame_thinned = super().voxelize(iframe)
            return source, self.frame_thinned

    n_scans = len(source)
    if n_scans == 0:
        raise InputError("odometry: no scans to register.")
    odometry = KissICPKeepingFrames(kiss_config(sensor, config))
    T_world_scan = np.empty((n_scans, 4, 4))
    warned = False
    for k in range(n_scans):
        points_scan = source.points(k)
        times01 = normalized_point_times(source.point_times(k)) if config.deskew else np.empty(0)
        if config.deskew and len(times01) == 0 and not warned:
            log.warning("advanced.kiss_icp.deskew is on but scan %d has no per-point time field; "
                        "registering without deskewing.", k)
            warned = True
        odometry.register_frame(points_scan, times01)
        T_world_scan[k] = np.array(odometry.last_pose, dtype=np.float64, copy=True)
        if on_frame is not None:
            on_frame(k, odometry.frame_thinned)
        if progress is not None:
            progress(k + 1, n_scans)
    return T_world_scan
