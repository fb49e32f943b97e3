"""Which points the merged map keeps (`pa_cli.io.maps` writes them).

`MapFilter` keeps a scan's points within the odometry's range (sensor frame, `sensor.min_range_m` ..
`max_range_m`: farther returns are the outliers of a long range, nearer ones the vehicle) and then one
point per voxel of edge `voxel_size_m` (`map.voxel_m`, `pa refine --map-voxel-m`; 0 keeps every point):
the first point falling into it (scans in order), so every kept point is a real measurement.

Memory stays bounded: `MapVoxelFilter` returns each scan's points in voxels not yet occupied and holds
only the occupied voxels' keys (a hash set, `pa_cli.io.voxel_key_set`: 16 to 32 bytes per voxel), never
the points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.core.geometry import transform_points
from pa_cli.core.voxels import voxel_keys
from pa_cli.io.maps import MapCloud, MapPart
from pa_cli.io.voxel_key_set import VoxelKeySet


def _take(values: np.ndarray | None, keep: Any, dtype: type) -> np.ndarray | None:
    return None if values is None else np.asarray(values, dtype=dtype)[keep]


class MapVoxelFilter:
    """Scans in the local frame at `origin_world_m` (`pa_cli.core.local_frame`; default the world frame),
    keeping one point per voxel of `voxel_size_m` metres of that frame (0: every point): the first in
    the order the scans are added. `add` returns a scan's new points in the world frame; only the
    occupied voxels' keys are held (`pa_cli.io.voxel_key_set`), never the points. `add` is `place` (any
    thread, any order) then `keep` (in the scans' order)."""

    def __init__(self, voxel_size_m: float, origin_world_m: np.ndarray | None = None) -> None:
        self.voxel_size_m = float(voxel_size_m)
        self.origin_world_m = np.zeros(3) if origin_world_m is None else np.asarray(origin_world_m, dtype=np.float64)
        self._occupied = VoxelKeySet()

    def add(self, points_scan: np.ndarray, T_local_scan: np.ndarray, scan_index: int,
            time_s: np.ndarray | None = None, intensity: np.ndarray | None = None) -> MapCloud:
        """The points of one scan ((M, 3) in its sensor frame, m; its 4x4 pose in the local frame;
        optional (M,) times, s, and intensities) that fall into voxels no earlier point occupies, in
        the world frame (float64 when the origin is not zero)."""
        return self.keep(*self.place(points_scan, T_local_scan), scan_index, time_s, intensity)

    def place(self, points_scan: np.ndarray, T_local_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """A scan's points (M, 3) in the local frame and their voxel keys (M,) (None with `voxel_size_m` 0).
        Reads nothing the filter holds: any number of threads at once."""
        points_local = transform_points(T_local_scan, points_scan)
        if self.voxel_size_m == 0:
            return points_local, None
        keys = voxel_keys(points_local, self.voxel_size_m, "map.voxel_m") if len(points_local) else \
            np.empty(0, dtype=np.int64)
        return points_local, keys

    def keep(self, points_local: np.ndarray, keys: np.ndarray | None, scan_index: int,
             time_s: np.ndarray | None = None, intensity: np.ndarray | None = None) -> MapCloud:
        """Of a scan's points placed by `place`, those in voxels no earlier point occupies, in the world
        frame; their voxels are occupied afterwards. Scans in order, one at a time."""
        keep: Any = slice(None) if keys is None else self._occupied.add_new(keys)
        points_world = points_local[keep] + self.origin_world_m if self.origin_world_m.any() else points_local[keep]
        return MapCloud(points_world, np.full(len(points_world), scan_index, dtype=np.int32),
                        _take(time_s, keep, np.float64), _take(intensity, keep, np.float32))


@dataclass(frozen=True)
class PlacedPart:
    """A `MapPart` placed by its pose (`MapFilter.place`), before the voxel filter: its points within range in
    the local frame (m) with their voxel keys (None: every point kept), times and intensities, and the number
    of its points dropped for range."""

    scan_index: int
    points_local: np.ndarray
    keys: np.ndarray | None
    time_s: np.ndarray | None
    intensity: np.ndarray | None
    n_out_of_range: int


class MapFilter:
    """What the written map keeps of each `MapPart`: its points within `min_range_m` .. `max_range_m`
    of the sensor (the odometry's range), then one per voxel (`MapVoxelFilter`; `voxel_size_m` 0:
    every point). Intensities are kept when the first part has them (a later part without them gets
    0, so every chunk has the same fields). `n_out_of_range` counts the points dropped for range.
    `add` is `place` (any thread, any order: the range, the pose and the voxel keys, the bulk of the
    work) then `keep` (in the parts' order)."""

    def __init__(self, voxel_size_m: float, min_range_m: float, max_range_m: float,
                 origin_world_m: np.ndarray | None = None) -> None:
        self.voxels = MapVoxelFilter(voxel_size_m, origin_world_m)
        self.min_range_m = float(min_range_m)
        self.max_range_m = float(max_range_m)
        self.n_out_of_range = 0
        self.with_intensity: bool | None = None  # decided by the first part

    def add(self, part: MapPart, T_local_scan: np.ndarray) -> MapCloud:
        """The kept points of `part`, placed by the pose `T_local_scan` (4x4, local frame), in the world frame."""
        return self.keep(self.place(part, T_local_scan))

    def place(self, part: MapPart, T_local_scan: np.ndarray) -> PlacedPart:
        """`part`'s points within range, placed by the pose `T_local_scan` (4x4, local frame), with their voxel
        keys. Reads nothing the filter holds: any number of threads at once."""
        points = np.asarray(part.points_scan, dtype=np.float64)
        range_m = np.linalg.norm(points, axis=1)
        inside = (range_m >= self.min_range_m) & (range_m <= self.max_range_m)
        points_local, keys = self.voxels.place(points[inside], T_local_scan)
        return PlacedPart(part.scan_index, points_local, keys, _take(part.time_s, inside, np.float64),
                          _take(part.intensity, inside, np.float32), int(len(points) - inside.sum()))

    def keep(self, placed: PlacedPart) -> MapCloud:
        """The points of a placed part in voxels no earlier point occupies, in the world frame. Parts in
        order, one at a time."""
        if self.with_intensity is None:
            self.with_intensity = placed.intensity is not None
        intensity = None
        if self.with_intensity:
            intensity = np.zeros(len(placed.points_local), np.float32) if placed.intensity is None else placed.intensity
        self.n_out_of_range += placed.n_out_of_range
        return self.voxels.keep(placed.points_local, placed.keys, placed.scan_index, placed.time_s, intensity)
