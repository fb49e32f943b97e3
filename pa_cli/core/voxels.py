"""Integer voxel keys: three voxel coordinates packed into one non-negative int64.

Each coordinate i (floor(x / voxel_size_m)) is shifted by KEY_OFFSET into [0, 2^KEY_BITS) and the
three are packed as (i_x << 2 KEY_BITS) | (i_y << KEY_BITS) | i_z, so keys sort like (i_x, i_y, i_z)
and bits 60..63 stay free (the plane kernels tag keys with a subdivision level there). The grid
reaches KEY_OFFSET voxels either side of the world origin. `pack_shifted` is the one packing
formula; the numba kernels of `pa_cli.planes.kernels` compile it.
"""

from __future__ import annotations

import numpy as np

from pa_cli.errors import InputError

KEY_BITS = 20  # per axis: +-2^19 voxels, e.g. +-524 km at 1 m, +-26 km at 5 cm
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1


def pack_shifted(sx, sy, sz):  # noqa: ANN001, ANN201 - numpy int64 arrays or scalars (also in numba)
    """Key of shifted coordinates (each in [0, 2^KEY_BITS))."""
    return (sx << (2 * KEY_BITS)) | (sy << KEY_BITS) | sz


def outside_grid_error(voxel_size_m: float, config_key: str) -> InputError:
    """The error for points beyond the key grid, naming the config key that widens it."""
    reach_m = KEY_OFFSET * voxel_size_m
    return InputError(f"points lie more than {reach_m:.0f} m from the world origin, beyond the "
                      f"voxel grid of {voxel_size_m:g} m cells; check the poses or raise "
                      f"{config_key} in the config (--config).")


def encode_keys(coords: np.ndarray, voxel_size_m: float = 1.0,
                config_key: str = "scene.plane_voxel_m") -> np.ndarray:
    """int64 keys of (M, 3) integer voxel coordinates; `voxel_size_m` and `config_key` only word
    the error raised when a coordinate lies outside the grid."""
    shifted = np.asarray(coords).astype(np.int64) + KEY_OFFSET
    if len(shifted) and (shifted.min() < 0 or shifted.max() > KEY_MASK):
        raise outside_grid_error(voxel_size_m, config_key)
    return pack_shifted(shifted[:, 0], shifted[:, 1], shifted[:, 2])


def decode_keys(keys: np.ndarray) -> np.ndarray:
    """(M, 3) int64 voxel coordinates of int64 keys made by `encode_keys`."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.column_stack([(keys >> (2 * KEY_BITS)) & KEY_MASK, (keys >> KEY_BITS) & KEY_MASK,
                            keys & KEY_MASK]) - KEY_OFFSET


def voxel_keys(points: np.ndarray, voxel_size_m: float, config_key: str) -> np.ndarray:
    """Keys (M,) of the voxels of edge `voxel_size_m` (m) holding (M, 3) points."""
    return encode_keys(np.floor(points / voxel_size_m), voxel_size_m, config_key)
