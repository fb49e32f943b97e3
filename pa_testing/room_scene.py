"""A small synthetic room seen from a moving sensor: the scans of the pipeline and source tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

N_SCANS = 10


def room_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on the six faces of an asymmetric 14 x 9 x 3.5 m room plus two boxes (world frame, m)."""
    size = np.array([14.0, 9.0, 3.5])
    boxes = [(np.array([3.0, 2.0, 0.0]), np.array([1.5, 0.8, 1.2])),
             (np.array([9.0, 6.0, 0.0]), np.array([0.6, 2.0, 2.0]))]
    parts = []
    for origin, extent, share in [(np.zeros(3), size, 0.7)] + [(o, e, 0.15) for o, e in boxes]:
        m = int(n * share)
        face = rng.integers(0, 6, m)
        axis = face // 2
        p = origin + rng.random((m, 3)) * extent
        p[np.arange(m), axis] = origin[axis] + np.where(face % 2 == 0, 0.0, extent[axis])
        parts.append(p)
    return np.vstack(parts)


def ground_truth_poses() -> np.ndarray:
    from scipy.spatial.transform import Rotation

    k = np.arange(N_SCANS)
    T = np.tile(np.eye(4), (N_SCANS, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", (0.03 * k)[:, None]).as_matrix()
    T[:, :3, 3] = np.column_stack([5 + 0.25 * k, 4 + 0.05 * k, 1.6 + 0.01 * np.sin(k)])
    return T


def room_scans_scan_frame(seed: int = 7, n_points: int = 8000) -> list[np.ndarray]:
    """N_SCANS scans of the room (1 cm range noise) in their sensor frames, under `ground_truth_poses()`."""
    rng = np.random.default_rng(seed)
    scans = []
    for T_world_scan in ground_truth_poses():
        T_scan_world = np.linalg.inv(T_world_scan)
        points_world = room_points(rng, n_points)
        points_scan = points_world @ T_scan_world[:3, :3].T + T_scan_world[:3, 3]
        scans.append(points_scan + rng.normal(scale=0.01, size=points_scan.shape))
    return scans


def write_room_folder(root: Path) -> Path:
    """`root/scans/000000.pcd ...`, GT poses `root/gt_kitti.txt` and `root/gt_tum.txt`, and `root/times.txt`."""
    from pa_cli.io.scans import write_pcd
    from pa_cli.io.trajectory import write_kitti, write_tum

    scans = root / "scans"
    scans.mkdir()
    for k, points_scan in enumerate(room_scans_scan_frame()):
        write_pcd(scans / f"{k:06d}.pcd", points_scan)
    T_world_scan = ground_truth_poses()
    write_kitti(root / "gt_kitti.txt", T_world_scan)
    stamps = 100.0 + 0.1 * np.arange(N_SCANS)
    write_tum(root / "gt_tum.txt", T_world_scan, stamps)
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    return root
