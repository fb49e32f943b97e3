"""Ground truth in the public datasets' own files, converted to pa's convention (T_world_scan of the LiDAR).

`read_ground_truth(path)` recognises the file by its name and place and logs the convention it
applied; any other file is a KITTI or TUM trajectory (`read_trajectory`):

- KITTI odometry `poses/NN.txt` (with `sequences/NN/calib.txt`) or `poses.txt` (with `calib.txt`
  beside it): left camera poses T_cam0_cam(k), one per scan; with `Tr` = T_cam_velo of calib.txt
  (read by KISS-ICP's `KITTIOdometryDataset.read_calib_file`) the LiDAR poses are
  Tr^-1 T_cam0_cam(k) Tr, in the frame of the first LiDAR pose (as KISS-ICP's `load_poses`). No
  timestamps: paired with the scans by index.
- MulRan `global_pose.csv`: `t_ns, r11 r12 r13 tx r21 ... tz` (the top 3x4 of T_world_base, row
  by row); the LiDAR poses are T_world_base T_base_ouster with MulRan's base-to-Ouster
  calibration (the matrix of KISS-ICP's `MulranDataset`); timestamps t_ns / 1e9.
- Newer College `registered_poses.csv`: `sec, nsec, x y z, qx qy qz qw` of the base; the LiDAR poses
  by KISS-ICP's `NewerCollegeDataset.load_gt_poses` (the base-to-Ouster transform, in the frame of
  the first pose); timestamps sec + nsec / 1e9.
- NCLT `groundtruth_DATE.csv`: `utime, x y z, roll pitch yaw` (body frame, z down, R = Rz(yaw)
  Ry(pitch) Rx(roll)); turned z-up as KISS-ICP's `NCLTDataset` does (F T F, F = diag(1, -1, -1)),
  matching the scans of `pa_cli.sources.datasets`; rows with NaN are dropped; timestamps utime / 1e6.

KISS-ICP's own readers of MulRan and NCLT need the scans' timestamps (they keep the pose nearest
each scan) and NCLT's returns float32, so those two files are read here with numpy; the pairing
with the scans is left to the timestamps (`pa_cli.evaluation`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from pa_cli.errors import FormatError
from pa_cli.io.trajectory import Trajectory, TrajectoryFormat, read_trajectory, rigid_rotations

log = logging.getLogger(__name__)

KITTI_POSES = re.compile(r"^\d+\.txt$")
MULRAN_GT, NCD_GT = "global_pose.csv", "registered_poses.csv"
NCLT_GT = re.compile(r"^groundtruth_.+\.csv$")
MULRAN_COLUMNS, NCD_COLUMNS, NCLT_COLUMNS = 13, 9, 7
Z_UP = np.diag([1.0, -1.0, -1.0, 1.0])  # NCLT's z-down body frame turned z-up (a rotation of pi about x)


def kitti_calibration_for(path: Path) -> Path | None:
    """The calib.txt of a KITTI ground-truth file `path` (ROOT/poses/NN.txt or SEQ/poses.txt), or None."""
    if KITTI_POSES.match(path.name) and path.parent.name == "poses":
        calib = path.parent.parent / "sequences" / path.stem / "calib.txt"
        return calib if calib.is_file() else None
    if path.name == "poses.txt" and (path.parent / "calib.txt").is_file():
        return path.parent / "calib.txt"
    return None


def read_ground_truth(path: Path | str, fmt: TrajectoryFormat | None = None) -> Trajectory:
    """Ground-truth poses of the LiDAR (T_world_scan) from a dataset's own file or a KITTI/TUM
    trajectory (`fmt`, else detected); the convention applied is logged for a dataset's file."""
    path = Path(path)
    calib = kitti_calibration_for(path)
    if calib is not None:
        trajectory, convention = _kitti(path, calib), f"KITTI camera poses moved to the LiDAR with Tr of {calib}"
    elif path.name == MULRAN_GT:
        trajectory, convention = _mulran(path), "MulRan base poses moved to the Ouster (MulRan's calibration)"
    elif path.name == NCD_GT:
        trajectory, convention = _newer_college(path), "Newer College base poses moved to the Ouster"
    elif NCLT_GT.match(path.name):
        trajectory, convention = _nclt(path), "NCLT body poses (z down) turned z-up as the NCLT scans"
    else:
        return read_trajectory(path, fmt)
    log.info("%s: %s, %d poses.", path, convention, len(trajectory))
    return trajectory


def _kitti(path: Path, calib: Path) -> Trajectory:
    from kiss_icp.datasets.kitti import KITTIOdometryDataset

    try:
        calibration = KITTIOdometryDataset.read_calib_file(str(calib))
    except (OSError, ValueError) as exc:
        raise FormatError(f"{calib}: cannot read the KITTI calibration ({exc}); expected lines 'KEY: numbers', "
                          "among them 'Tr:' with 12 numbers.") from None
    if "Tr" not in calibration or calibration["Tr"].size != 12:
        raise FormatError(f"{calib}: no 'Tr:' line with 12 numbers (the LiDAR-to-camera transform); the "
                          f"ground truth {path} is in the camera frame and needs it.")
    Tr = np.eye(4)
    Tr[:3, :4] = calibration["Tr"].astype(np.float64).reshape(3, 4)
    T_cam = read_trajectory(path, "kitti").T_world_scan
    return Trajectory(np.linalg.inv(Tr) @ T_cam @ Tr, None, str(path))


def _load_csv(path: Path, n_columns: int, layout: str) -> np.ndarray:
    """The numeric rows of a dataset's csv (a header line starting with a letter or '#' skipped)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise FormatError(f"{path}: cannot read the ground truth ({exc.strerror or exc}).") from None
    rows = [line for line in text.splitlines() if line.strip() and not line.lstrip()[:1].isalpha()
            and not line.lstrip().startswith("#")]
    try:
        data = np.array([[float(v) for v in line.split(",")] for line in rows], dtype=np.float64)
    except ValueError:
        data = np.empty((0, 0))
    if data.ndim != 2 or data.shape[1] != n_columns or not len(data):
        raise FormatError(f"{path}: expected comma-separated rows of {n_columns} numbers ({layout}).")
    return data


def _mulran(path: Path) -> Trajectory:
    from kiss_icp.datasets.mulran import MulranDataset

    data = _load_csv(path, MULRAN_COLUMNS, "MulRan global_pose.csv: t_ns and the top 3x4 of the base pose")
    T_world_base = np.tile(np.eye(4), (len(data), 1, 1))
    T_world_base[:, :3, :4] = data[:, 1:].reshape(-1, 3, 4)
    T_world_base[:, :3, :3] = rigid_rotations(path, T_world_base[:, :3, :3], "check the file's format")
    T_base_ouster = MulranDataset._get_calibration(None)[0]  # KISS-ICP's copy of MulRan's calib_base2ouster
    return Trajectory(T_world_base @ T_base_ouster, data[:, 0] / 1e9, str(path))


def _newer_college(path: Path) -> Trajectory:
    from kiss_icp.datasets.ncd import NewerCollegeDataset

    data = _load_csv(path, NCD_COLUMNS, "Newer College: sec, nsec, x, y, z, qx, qy, qz, qw")
    T = NewerCollegeDataset.load_gt_poses(str(path))
    if len(T) != len(data) or not np.all(np.isfinite(T)):
        raise FormatError(f"{path}: {len(data)} rows but {len(T)} readable poses; expected comma-separated rows "
                          "sec, nsec, x, y, z, qx, qy, qz, qw (a header line starting with '#').")
    T[:, :3, :3] = rigid_rotations(path, T[:, :3, :3], "check the quaternions")
    return Trajectory(T, data[:, 0] + data[:, 1] * 1e-9, str(path))


def _nclt(path: Path) -> Trajectory:
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    data = _load_csv(path, NCLT_COLUMNS, "NCLT: utime, x, y, z, roll, pitch, yaw")
    finite = np.all(np.isfinite(data), axis=1)
    if not finite.all():
        log.warning("%s: %d rows with NaN dropped.", path, int((~finite).sum()))
        data = data[finite]
    if not len(data):
        raise FormatError(f"{path}: no row without NaN.")
    T_body = np.tile(np.eye(4), (len(data), 1, 1))
    T_body[:, :3, :3] = Rotation.from_euler("ZYX", data[:, [6, 5, 4]]).as_matrix()
    T_body[:, :3, 3] = data[:, 1:4]
    return Trajectory(Z_UP @ T_body @ Z_UP, data[:, 0] / 1e6, str(path))
