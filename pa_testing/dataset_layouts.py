"""Small sequences written in the public datasets' exact layouts, with ground truth in each dataset's own
convention, from LiDAR-frame truth (for the tests of `pa_cli.sources.datasets` and `pa_cli.io.dataset_gt`).

The conventions are written here from each dataset's documentation, independently of the readers:

- KITTI odometry: `poses/NN.txt` holds the left camera's poses T_cam0_cam(k) (the top 3x4, row by
  row); `calib.txt`'s `Tr` is T_cam_velo, so the camera pose is Tr T_velo0_velo(k) Tr^-1.
- MulRan: `global_pose.csv` rows `t_ns, top 3x4 of T_world_base`; the Ouster sits at
  `MULRAN_BASE_OUSTER_XYZ_M`, turned by `MULRAN_BASE_OUSTER_RPY_DEG` (calib_base2ouster).
- Newer College: `registered_poses.csv` rows `sec, nsec, x, y, z, qx, qy, qz, qw` of the base; the
  Ouster is at T_base_os (`NCD_BASE_OS_QUAT_XYZW`, `NCD_BASE_OS_XYZ_M`).
- NCLT: `groundtruth_DATE.csv` rows `utime, x, y, z, roll, pitch, yaw` of the z-down body; the scans
  `velodyne_sync/<utime>.bin` hold uint16 x y z (5 mm steps from -100 m) of the z-down sensor.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

EPOCH_S = 1_566_535_665.0  # scan k at EPOCH_S + k * period
KITTI_TR = np.array([[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.272]])  # velo -> cam
KITTI_CALIB = ("P0: 7.188560000000e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0\n"
               "Tr: " + " ".join(f"{v:.12e}" for v in KITTI_TR.ravel()) + "\n")
MULRAN_BASE_OUSTER_XYZ_M = (1.7042, -0.021, 1.8047)
MULRAN_BASE_OUSTER_RPY_DEG = (0.0001, 0.0003, 179.6654)
NCD_BASE_OS_QUAT_XYZW = (0.0, 0.0, 0.924, 0.383)
NCD_BASE_OS_XYZ_M = (-0.084, -0.025, 0.050)
Z_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])


def transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def mulran_base_ouster() -> np.ndarray:
    return transform(Rotation.from_euler("xyz", MULRAN_BASE_OUSTER_RPY_DEG, degrees=True).as_matrix(),
                     MULRAN_BASE_OUSTER_XYZ_M)


def ncd_base_os() -> np.ndarray:
    return transform(Rotation.from_quat(NCD_BASE_OS_QUAT_XYZW).as_matrix(), NCD_BASE_OS_XYZ_M)


def kitti_tr() -> np.ndarray:
    return np.vstack([KITTI_TR, [0.0, 0.0, 0.0, 1.0]])


def stamps_s(n: int, period_s: float = 0.1) -> np.ndarray:
    return EPOCH_S + np.arange(n) * period_s


def _kitti_rows(T: np.ndarray) -> str:
    return "".join(" ".join(f"{v:.12e}" for v in row) + "\n" for row in T[:, :3, :4].reshape(-1, 12))


def write_kitti_gt(root: Path, T_world_lidar: np.ndarray, sequence: str = "00") -> Path:
    """ROOT/poses/NN.txt (camera frame, from the first camera pose) and ROOT/sequences/NN/calib.txt."""
    T0 = np.linalg.inv(T_world_lidar[0]) @ T_world_lidar
    Tr = kitti_tr()
    (root / "poses").mkdir(parents=True, exist_ok=True)
    (root / "sequences" / sequence).mkdir(parents=True, exist_ok=True)
    (root / "sequences" / sequence / "calib.txt").write_text(KITTI_CALIB)
    path = root / "poses" / f"{sequence}.txt"
    path.write_text(_kitti_rows(Tr @ T0 @ np.linalg.inv(Tr)))
    return path


def write_mulran_gt(seq: Path, T_world_lidar: np.ndarray, stamps: np.ndarray) -> Path:
    T_world_base = T_world_lidar @ np.linalg.inv(mulran_base_ouster())
    seq.mkdir(parents=True, exist_ok=True)
    path = seq / "global_pose.csv"
    rows = [f"{round(t * 1e9)}," + ",".join(f"{v:.12e}" for v in T[:3, :4].ravel())
            for t, T in zip(stamps, T_world_base, strict=True)]
    path.write_text("\n".join(rows) + "\n")
    return path


def write_ncd_gt(seq: Path, T_world_lidar: np.ndarray, stamps: np.ndarray) -> Path:
    T_world_base = T_world_lidar @ np.linalg.inv(ncd_base_os())
    quat = Rotation.from_matrix(T_world_base[:, :3, :3]).as_quat()
    (seq / "ground_truth").mkdir(parents=True, exist_ok=True)
    path = seq / "ground_truth" / "registered_poses.csv"
    rows = ["#sec,nsec,x,y,z,qx,qy,qz,qw"]
    for t, T, q in zip(stamps, T_world_base, quat, strict=True):
        sec, nsec = _sec_nsec(t)
        rows.append(f"{sec},{nsec}," + ",".join(f"{v:.12e}" for v in (*T[:3, 3], *q)))
    path.write_text("\n".join(rows) + "\n")
    return path


def write_nclt_gt(seq: Path, T_world_lidar: np.ndarray, stamps: np.ndarray) -> Path:
    T_body = Z_DOWN @ T_world_lidar @ Z_DOWN
    ypr = Rotation.from_matrix(T_body[:, :3, :3]).as_euler("ZYX")
    (seq.parent / "ground_truth").mkdir(parents=True, exist_ok=True)
    path = seq.parent / "ground_truth" / f"groundtruth_{seq.name}.csv"
    rows = [f"{round(t * 1e6)}," + ",".join(f"{v:.12e}" for v in (*T[:3, 3], *angles[::-1]))
            for t, T, angles in zip(stamps, T_body, ypr, strict=True)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _sec_nsec(t: float) -> tuple[int, int]:
    ns = round(t * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


def write_bin(path: Path, points: np.ndarray) -> None:
    """A KITTI .bin scan: float32 x y z intensity (0) per point."""
    np.column_stack([points, np.zeros(len(points))]).astype("<f4").tofile(path)


def write_kitti_scans(seq: Path, points: list[np.ndarray], stamps: np.ndarray) -> None:
    """SEQ/velodyne/NNNNNN.bin, SEQ/times.txt (from the first scan) and SEQ/calib.txt."""
    (seq / "velodyne").mkdir(parents=True, exist_ok=True)
    for k, p in enumerate(points):
        write_bin(seq / "velodyne" / f"{k:06d}.bin", p)
    (seq / "times.txt").write_text("".join(f"{t - stamps[0]:.6e}\n" for t in stamps))
    (seq / "calib.txt").write_text(KITTI_CALIB)


def write_mulran_scans(seq: Path, points: list[np.ndarray], stamps: np.ndarray) -> None:
    (seq / "Ouster").mkdir(parents=True, exist_ok=True)
    for p, t in zip(points, stamps, strict=True):
        write_bin(seq / "Ouster" / f"{round(t * 1e9)}.bin", p)


def write_ncd_scans(seq: Path, points: list[np.ndarray], times_s: list[np.ndarray], stamps: np.ndarray) -> None:
    """raw_format/ouster_scan/cloud_<s>_<ns>.pcd with x y z intensity (float32) and t (uint32 ns)."""
    from pypcd4 import PointCloud

    folder = seq / "raw_format" / "ouster_scan"
    folder.mkdir(parents=True, exist_ok=True)
    for p, time_s, t in zip(points, times_s, stamps, strict=True):
        sec, nsec = _sec_nsec(t)
        data = np.column_stack([p, np.zeros(len(p)), np.round(time_s * 1e9)])
        cloud = PointCloud.from_points(data, ["x", "y", "z", "intensity", "t"],
                                       [np.float32, np.float32, np.float32, np.float32, np.uint32])
        cloud.save(folder / f"cloud_{sec}_{nsec:09d}.pcd")


def write_nclt_scans(seq: Path, points: list[np.ndarray], stamps: np.ndarray) -> None:
    """velodyne_sync/<utime>.bin: uint16 x y z of the z-down sensor in 5 mm steps from -100 m."""
    dtype = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"), ("laser", "u1")])
    (seq / "velodyne_sync").mkdir(parents=True, exist_ok=True)
    for p, t in zip(points, stamps, strict=True):
        z_down = p * np.array([1.0, -1.0, -1.0])
        raw = np.zeros(len(p), dtype)
        for i, axis in enumerate("xyz"):
            raw[axis] = np.round((z_down[:, i] + 100.0) / 0.005)
        raw.tofile(seq / "velodyne_sync" / f"{round(t * 1e6)}.bin")
