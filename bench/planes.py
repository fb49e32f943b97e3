"""Benchmark of plane detection + association (issue 6, item 5).

Synthetic outdoor-like scene: 100 scans x 30k points (default) on a street of planar facades,
ground and boxes, with 2 cm noise and 20 % clutter. Each configuration runs in a fresh
subprocess so that peak memory (ru_maxrss) belongs to it alone. Prints a table:

    PYTHONPATH=. python bench/planes.py [--scans 100] [--points 30000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np


def make_street(n_scans: int, n_points: int, seed: int = 0):
    """Lazy-free synthetic street: list of (n_points, 3) scan-frame arrays and T_world_scan."""
    rng = np.random.default_rng(seed)
    # planes: ground, two facades along x, 20 box faces (vertical) and 10 roof planes
    rects = [((-20, -15, 0), (1, 0, 0), (0, 1, 0), 240, 30),
             ((-20, -12, 0), (1, 0, 0), (0, 0, 1), 240, 12),
             ((-20, 12, 0), (1, 0, 0), (0, 0, 1), 240, 12)]
    for b in range(20):
        x0, y0 = 10 * b - 10, rng.choice([-9, 6])
        rects += [((x0, y0, 0), (1, 0, 0), (0, 0, 1), 3, 2), ((x0, y0, 0), (0, 1, 0), (0, 0, 1), 3, 2),
                  ((x0, y0 + 3, 0), (1, 0, 0), (0, 0, 1), 3, 2)]
    rects = [(np.array(o, float), np.array(u, float), np.array(v, float), a, b)
             for o, u, v, a, b in rects]
    area = np.array([a * b for *_, a, b in rects])
    T = np.repeat(np.eye(4)[None], n_scans, axis=0)
    scans = []
    for j in range(n_scans):
        yaw = rng.normal(0, 0.05)
        c, s = np.cos(yaw), np.sin(yaw)
        T[j, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        T[j, :3, 3] = [2.0 * j, rng.normal(0, 0.3), 1.8]
        n_plane = int(0.8 * n_points)
        k = rng.choice(len(rects), n_plane, p=area / area.sum())
        st = rng.uniform(0, 1, (n_plane, 2))
        o = np.array([r[0] for r in rects])[k]
        u = np.array([r[1] for r in rects])[k]
        v = np.array([r[2] for r in rects])[k]
        ab = np.array([[r[3], r[4]] for r in rects])[k]
        p = o + st[:, :1] * ab[:, :1] * u + st[:, 1:] * ab[:, 1:] * v
        p += rng.normal(0, 0.02, p.shape)
        clutter = T[j, :3, 3] + rng.uniform(-30, 30, (n_points - n_plane, 3)) * [1, 0.4, 0.1]
        p_world = np.vstack([p, clutter])
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scans", type=int, default=100)
    ap.add_argument("--points", type=int, default=30000)
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
