"""The extrinsics YAML file: T_base_lidar of every LiDAR of a rig (read, write, roll/pitch/yaw).

Frames and units: `T_base_lidar` maps points of a LiDAR's sensor frame to the base frame, which
is the frame of `lidar0` (so lidar0's extrinsic is the identity); metres. The file gives each
LiDAR's 4x4 matrix and, for people, the same transform as `xyz_m` (metres) and `rpy_deg`
(roll, pitch, yaw in degrees, R = Rz(yaw) Ry(pitch) Rx(roll), the simulator's convention):

    # pa extrinsics ...
    frame: T_base_lidar maps points of the LiDAR's frame to the base (lidar0) frame
    lidars:
      lidar0: {T_base_lidar: [[1, 0, 0, 0], ...], xyz_m: [0, 0, 0], rpy_deg: [0, 0, 0]}
      lidar1: {T_base_lidar: [...], xyz_m: [0.1, -0.4, 0.05], rpy_deg: [0.0, 2.0, -30.0]}

When reading, a LiDAR given by `xyz_m` and `rpy_deg` alone is accepted (a hand-measured
`--init` file); when `T_base_lidar` is present it is used and the others are ignored.
`pa calibrate --out` adds per LiDAR the directions the data did not determine (`unobservable`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from pa_cli.errors import FormatError
from pa_cli.io.atomic import write_text_atomic
from pa_cli.io.files import read_input_bytes
from pa_cli.io.trajectory import rigid_rotations

FRAME_NOTE = "T_base_lidar maps points of the LiDAR's frame to the base (lidar0) frame; metres, degrees"
EXTRINSICS_HINT = ("expected 'lidars: {lidar0: {T_base_lidar: 4x4} , lidar1: {...}}' or per LiDAR "
                   "'xyz_m: [x, y, z]' and 'rpy_deg: [roll, pitch, yaw]'; see README 'Multi-LiDAR calibration'")


def lidar_name(k: int) -> str:
    """The folder and YAML key of LiDAR k: lidar0, lidar1, ..."""
    return f"lidar{k}"


def rpy_to_rotation(rpy_rad: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (3, 3) of (roll, pitch, yaw) in radians."""
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    roll, pitch, yaw = np.asarray(rpy_rad, dtype=np.float64)
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def rotation_to_rpy(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in radians of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    yaw, pitch, roll = Rotation.from_matrix(R).as_euler("ZYX")
    return np.array([roll, pitch, yaw])


def pose_from_xyz_rpy(xyz_m: np.ndarray, rpy_rad: np.ndarray) -> np.ndarray:
    """The 4x4 transform with translation xyz_m (m) and rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = rpy_to_rotation(rpy_rad)
    T[:3, 3] = np.asarray(xyz_m, dtype=np.float64)
    return T


def format_extrinsics(T_base_lidar: np.ndarray, notes: dict[int, dict] | None = None) -> str:
    """The extrinsics YAML text of (K, 4, 4) T_base_lidar; `notes[k]` adds keys to LiDAR k's entry."""
    lidars = {}
    for k, T in enumerate(np.asarray(T_base_lidar, dtype=np.float64)):
        entry = {"T_base_lidar": [[round(float(v), 12) for v in row] for row in T],
                 "xyz_m": [round(float(v), 9) for v in T[:3, 3]],
                 "rpy_deg": [round(float(v), 9) for v in np.rad2deg(rotation_to_rpy(T[:3, :3]))]}
        entry.update((notes or {}).get(k, {}))
        lidars[lidar_name(k)] = entry
    header = ("# pa extrinsics: T_base_lidar of every LiDAR (4x4, and xyz_m + rpy_deg with\n"
              "# R = Rz(yaw) Ry(pitch) Rx(roll)); lidar0 is the base frame.\n")
    return header + yaml.safe_dump({"frame": FRAME_NOTE, "lidars": lidars}, sort_keys=False,
                                   default_flow_style=None, width=1000)


def write_extrinsics(path: Path | str, T_base_lidar: np.ndarray, notes: dict[int, dict] | None = None,
                     force: bool = False) -> None:
    """Write the extrinsics YAML atomically (refused when it exists, unless `force`)."""
    write_text_atomic(path, format_extrinsics(T_base_lidar, notes), force)


def _vector(path: Path, name: str, key: str, value: object, length: int) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.empty(0)
    if array.shape != (length,) or not np.all(np.isfinite(array)):
        raise FormatError(f"{path}: {name}.{key} must be a list of {length} finite numbers, found {value!r}; "
                          f"{EXTRINSICS_HINT}.")
    return array


def _entry_pose(path: Path, name: str, entry: object) -> np.ndarray:
    if not isinstance(entry, dict):
        raise FormatError(f"{path}: {name} must be a mapping, found {entry!r}; {EXTRINSICS_HINT}.")
    if "T_base_lidar" in entry:
        value = entry["T_base_lidar"]
        T = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.empty(0)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise FormatError(f"{path}: {name}.T_base_lidar must be a 4x4 rigid transform (last row 0 0 0 1), "
                              f"found {value!r}.")
        T[:3, :3] = rigid_rotations(path, T[None, :3, :3], f"{name}.T_base_lidar needs a rotation matrix")[0]
        return T
    if "xyz_m" in entry and "rpy_deg" in entry:
        return pose_from_xyz_rpy(_vector(path, name, "xyz_m", entry["xyz_m"], 3),
                                 np.deg2rad(_vector(path, name, "rpy_deg", entry["rpy_deg"], 3)))
    raise FormatError(f"{path}: {name} has neither T_base_lidar nor xyz_m + rpy_deg; {EXTRINSICS_HINT}.")


def read_extrinsics(path: Path | str, n_lidars: int | None = None) -> np.ndarray:
    """(K, 4, 4) T_base_lidar of lidar0..lidarK-1 from an extrinsics YAML.

    With `n_lidars`, the file must list exactly lidar0..lidar{n_lidars-1}. lidar0 may be left out
    (it is the identity); when given it must be the identity.
    """
    path = Path(path)
    raw = read_input_bytes(path, "extrinsics", "a YAML file written by pa calibrate or pa simulate --rig")
    try:
        data = yaml.safe_load(raw.decode("utf-8", errors="replace"))
    except yaml.YAMLError as exc:
        raise FormatError(f"{path}: not valid YAML ({exc}); {EXTRINSICS_HINT}.") from None
    lidars = data.get("lidars") if isinstance(data, dict) else None
    if not isinstance(lidars, dict) or not lidars:
        raise FormatError(f"{path}: no 'lidars' mapping found; {EXTRINSICS_HINT}.")
    names = set(lidars)
    count = n_lidars if n_lidars is not None else 1 + max(
        (int(n[5:]) for n in names if isinstance(n, str) and n.startswith("lidar") and n[5:].isdigit()), default=0)
    expected = {lidar_name(k) for k in range(count)}
    unknown = sorted(str(n) for n in names - expected)
    missing = sorted(expected - names - {lidar_name(0)})
    if unknown or missing:
        raise FormatError(f"{path}: expected the LiDARs {', '.join(sorted(expected))} of the rig; "
                          + (f"unknown: {', '.join(unknown)}; " if unknown else "")
                          + (f"missing: {', '.join(missing)}; " if missing else "")
                          + "list one entry per lidarK folder of the rig.")
    T = np.tile(np.eye(4), (count, 1, 1))
    for k in range(count):
        if lidar_name(k) in lidars:
            T[k] = _entry_pose(path, lidar_name(k), lidars[lidar_name(k)])
    if not np.allclose(T[0], np.eye(4), atol=1e-9):
        raise FormatError(f"{path}: lidar0 is the base frame, so its T_base_lidar must be the identity; found "
                          f"{T[0][:3].tolist()}. Express the other LiDARs relative to lidar0.")
    return T

