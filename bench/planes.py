"""Benchmark of plane detection + association (issue 6, item 5).

Synthetic outdoor-like scene: 100 scans x 30k points (default) on a street of planar facades,
ground and boxes within 35 m of each scan, with 2 cm noise and 20 % clutter. Each configuration runs in a fresh
subprocess so that peak memory (ru_maxrss) belongs to it alone. Prints a table:

    PYTHONPATH=. python bench/planes.py [--scans 100] [--points 30000] [--real-only]

A second table: the real sequences of ../shared/data at their reference poses (default
config; skipped when absent).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REAL_SEQUENCES = ("balm-campus-30", "kaist03-21")

RANGE_M = 35.0  # sensor range: each scan samples only the surfaces within this distance
SCENE_YAW_DEG = 7.0  # the street is turned and shifted off the voxel grid: planes at voxel
SCENE_SHIFT_M = (0.13, 0.29, 0.37)  # boundaries or aligned with it would flatter the detector


def make_street(n_scans: int, n_points: int, seed: int = 0):
    """Synthetic street: list of (n_points, 3) scan-frame arrays and T_world_scan (N, 4, 4).

    Ground, two facades and 20 boxes (2 m s apart); each scan samples the surfaces within
    RANGE_M of its position (80 % of its points, 2 cm noise) plus 20 % clutter. The whole
    scene is rotated by SCENE_YAW_DEG and shifted by SCENE_SHIFT_M so that no plane lies on a
    voxel boundary.
    """
    rng = np.random.default_rng(seed)
    # planes: ground, two facades along x, 20 boxes of three vertical faces
    rects = [((-20, -15, 0), (1, 0, 0), (0, 1, 0), 240, 30),
             ((-20, -12, 0), (1, 0, 0), (0, 0, 1), 240, 12),
             ((-20, 12, 0), (1, 0, 0), (0, 0, 1), 240, 12)]
    for b in range(20):
        x0, y0 = 10 * b - 10, rng.choice([-9, 6])
        rects += [((x0, y0, 0), (1, 0, 0), (0, 0, 1), 3, 2), ((x0, y0, 0), (0, 1, 0), (0, 0, 1), 3, 2),
                  ((x0, y0 + 3, 0), (1, 0, 0), (0, 0, 1), 3, 2)]
    o_all = np.array([r[0] for r in rects], float)
    u_all = np.array([r[1] for r in rects], float)
    v_all = np.array([r[2] for r in rects], float)
    ab_all = np.array([[r[3], r[4]] for r in rects], float)
    area = ab_all.prod(axis=1)
    c, s = np.cos(np.deg2rad(SCENE_YAW_DEG)), np.sin(np.deg2rad(SCENE_YAW_DEG))
    R_world_street = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    t_world_street = np.array(SCENE_SHIFT_M)
    T = np.repeat(np.eye(4)[None], n_scans, axis=0)
    scans = []
    for j in range(n_scans):
        yaw = rng.normal(0, 0.05)
        c, s = np.cos(yaw), np.sin(yaw)
        pos_street = np.array([2.0 * j, rng.normal(0, 0.3), 1.8])
        T[j, :3, :3] = R_world_street @ [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[j, :3, 3] = R_world_street @ pos_street + t_world_street
        n_plane = int(0.8 * n_points)
        pts = np.empty((0, 3))
        while len(pts) < n_plane:  # rejection sampling of the surfaces within range
            k = rng.choice(len(rects), 4 * n_plane, p=area / area.sum())
            st = rng.uniform(0, 1, (len(k), 2)) * ab_all[k]
            p = o_all[k] + st[:, :1] * u_all[k] + st[:, 1:] * v_all[k]
            pts = np.vstack([pts, p[np.linalg.norm(p - pos_street, axis=1) <= RANGE_M]])
        p = pts[:n_plane] + rng.normal(0, 0.02, (n_plane, 3))
        clutter = pos_street + rng.uniform(-30, 30, (n_points - n_plane, 3)) * [1, 0.4, 0.1]
        p_world = np.vstack([p, clutter]) @ R_world_street.T + t_world_street
        scans.append((p_world - T[j, :3, 3]) @ T[j, :3, :3])
    return scans, T


def _child(n_scans: int, n_points: int, voxel: float, levels: int) -> None:
    import resource

    from pa_cli.config import PlanesConfig
    from pa_cli.planes.associate import build_plane_problem

    t0 = time.perf_counter()
    scans, T = make_street(n_scans, n_points)
    t_gen = time.perf_counter() - t0
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    config = PlanesConfig(voxel_size_m=voxel, max_subdivision_levels=levels)
    t0 = time.perf_counter()
    problem, diag = build_plane_problem(scans, T, config)
    total = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    scans_mb = sum(s.nbytes for s in scans) / 2**20
    print(json.dumps({"gen_s": t_gen, "total_s": total, **diag["timings_s"], "peak_mb": rss,
                      "peak_before_mb": rss_before, "scans_mb": scans_mb,
                      "landmarks": diag["n_landmarks"], "detected": diag["n_landmarks_detected"],
                      "obs": diag["n_observations"], "covered": diag["covered_fraction"],
                      "thick_med_m": diag["thickness_rms_m"]["median"]}))


def _real_child(name: str) -> None:
    import resource

    from pa_cli.config import PlanesConfig
    from pa_cli.io.scans import ScanFolder
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.planes.associate import build_plane_problem

    folder = _shared_data() / name
    scans = ScanFolder(folder / "scans").points  # lazy: read once per pass
    T = read_trajectory(folder / "poses_kitti.txt").T_world_scan
    t0 = time.perf_counter()
    _, diag = build_plane_problem(scans, T, PlanesConfig())
    total = time.perf_counter() - t0
    print(json.dumps({"total_s": total, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "scans": len(T), "landmarks": diag["n_landmarks"],
                      "detected": diag["n_landmarks_detected"], "obs": diag["n_observations"],
                      "covered": diag["covered_fraction"],
                      "thick_med_m": diag["thickness_rms_m"]["median"],
                      "thick_p90_m": diag["thickness_rms_m"]["p90"],
                      "poor": len(diag["poorly_constrained_scans"]),
                      "failed_verification": diag["n_landmarks_failed_verification"],
                      "refit": diag["n_landmarks_refit"]}))


def _shared_data() -> Path:
    """../shared/data beside the repository or one of its parents (PA_SHARED_DATA overrides)."""
    if os.environ.get("PA_SHARED_DATA"):
        return Path(os.environ["PA_SHARED_DATA"])
    for parent in Path(__file__).resolve().parents:
        if (parent / "shared" / "data").is_dir():
            return parent / "shared" / "data"
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def real_table() -> None:
    """Plane problems of the real sequences at their reference poses (default config)."""
    rows = []
    for name in REAL_SEQUENCES:
        if not (_shared_data() / name / "scans").is_dir():
            print(f"{name}: not present under {_shared_data()}, skipped")
            continue
        out = subprocess.run([sys.executable, __file__, "--real-child", name], capture_output=True,
                             text=True, check=True)
        rows.append((name, json.loads(out.stdout.strip().splitlines()[-1])))
    if not rows:
        return
    head = (f"{'sequence':>15} {'scans':>5} {'landmarks':>9} {'detected':>8} {'obs':>5} {'covered':>7} "
            f"{'thick_med_m':>11} {'thick_p90_m':>11} {'poor_scans':>10} {'failed_verif':>12} {'refit':>5} "
            f"{'total_s':>7} {'peak_MB':>7}")
    print(head)
    print("-" * len(head))
    for name, r in rows:
        print(f"{name:>15} {r['scans']:>5} {r['landmarks']:>9} {r['detected']:>8} {r['obs']:>5} "
              f"{r['covered']:>7.3f} {r['thick_med_m']:>11.4f} {r['thick_p90_m']:>11.4f} {r['poor']:>10} "
              f"{r['failed_verification']:>12} {r['refit']:>5} {r['total_s']:>7.2f} {r['peak_mb']:>7.0f}")
    print("poor_scans: smallest eigenvalue of sum n n^T below advanced.planes.min_constraint_eigenvalue; "
          "refit: tilted detections refit on their kept points (a third read of the scans).")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scans", type=int, default=100)
    ap.add_argument("--points", type=int, default=30000)
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--real-child", help=argparse.SUPPRESS)
    ap.add_argument("--real-only", action="store_true", help="only the real-data table")
    args = ap.parse_args()
    if args.real_child:
        _real_child(args.real_child)
        return
    if args.real_only:
        real_table()
        return
    if args.child:
        n, m, voxel, levels = args.child
        _child(int(n), int(m), float(voxel), int(levels))
        return
    rows = []
    for n_scans, voxel, levels in [(args.scans // 4, 1.0, 2), (args.scans // 2, 1.0, 2),
                                   (args.scans, 1.0, 0), (args.scans, 1.0, 2), (args.scans, 0.5, 2)]:
        out = subprocess.run([sys.executable, __file__, "--child", str(n_scans), str(args.points),
                              str(voxel), str(levels)], capture_output=True, text=True, check=True)
        rows.append((n_scans, voxel, levels, json.loads(out.stdout.strip().splitlines()[-1])))
    head = (f"{'scans':>5} {'pts/scan':>8} {'voxel_m':>7} {'levels':>6} {'detect_s':>8} {'assoc_s':>7} "
            f"{'total_s':>7} {'peak_MB':>7} {'scans_MB':>8} {'landmarks':>9} {'detected':>8} "
            f"{'obs':>6} {'covered':>7} {'thick_med_m':>11}")
    print(head)
    print("-" * len(head))
    for n_scans, voxel, levels, r in rows:
        print(f"{n_scans:>5} {args.points:>8} {voxel:>7.2f} {levels:>6} {r['detect']:>8.2f} "
              f"{r['associate']:>7.2f} {r['total_s']:>7.2f} {r['peak_mb']:>7.0f} {r['scans_mb']:>8.0f} "
              f"{r['landmarks']:>9} {r['detected']:>8} {r['obs']:>6} {r['covered']:>7.2f} "
              f"{r['thick_med_m']:>11.4f}")
    print("peak_MB: ru_maxrss of a fresh subprocess, including the in-memory synthetic scans "
          "(scans_MB) and Python/numpy/scipy.")
    print()
    real_table()


if __name__ == "__main__":
    main()
