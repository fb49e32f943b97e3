"""The local frame pa computes in: the world frame moved by whole kilometres towards the poses.

Poses may be given in a georeferenced world frame (UTM: eastings of hundreds of kilometres,
northings of thousands). Two things need coordinates near the origin: the voxel grids
(`pa_cli.core.voxels` reaches 2^19 cells either side of the origin: 524 km at 1 m, 26 km at 5 cm), and
the point clusters, whose scatter about the world origin of points 4,000 km away cancels to
centimetres in float64. So `pa refine`, `pa adjust` and `pa calibrate` work with poses
T_local_scan = T_local_world @ T_world_scan, where T_local_world is the translation by
-origin_world_m and origin_world_m is the first pose's position rounded to whole kilometres, and
write poses, map and problem in the world frame (the pose covariance keeps its tangents about
the local origin and names it: `pa_cli.adjust.covariance`).

Within 500 m of the world origin (KISS-ICP's poses start at the identity; simulated and most
local trajectories) the origin is zero and nothing moves. Further away the grids sit at the
same world positions (a kilometre is a whole number of cells of every voxel size of 2^-k m or
0.1, 0.2, 0.5 m) up to the rounding of the subtraction. The frame's axes are the world's, so
"vertical" stays the world z axis.
"""

from __future__ import annotations

import numpy as np

ORIGIN_ROUNDING_M = 1000.0  # the local origin is a whole multiple of this (m)


def local_origin_m(T_world_scan: np.ndarray) -> np.ndarray:
    """(3,) world position (m) of the local frame's origin: the first pose's position rounded to
    whole multiples of `ORIGIN_ROUNDING_M` (zero within 500 m of the world origin)."""
    first_m = np.asarray(T_world_scan, dtype=np.float64)[0, :3, 3]
    return np.round(first_m / ORIGIN_ROUNDING_M) * ORIGIN_ROUNDING_M + 0.0  # + 0.0: no -0.0


def _translated(T: np.ndarray, offset_m: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses T moved by offset_m (3,) in the frame they are given in (a new array)."""
    moved = np.array(T, dtype=np.float64)
    moved[:, :3, 3] += offset_m
    return moved


def to_local(T_world_scan: np.ndarray, origin_world_m: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses T_local_scan of world poses T_world_scan (a new array)."""
    return _translated(T_world_scan, -np.asarray(origin_world_m, dtype=np.float64))


def to_world(T_local_scan: np.ndarray, origin_world_m: np.ndarray) -> np.ndarray:
    """(N, 4, 4) world poses T_world_scan of local poses T_local_scan (a new array)."""
    return _translated(T_local_scan, np.asarray(origin_world_m, dtype=np.float64))
