"""Benchmark of the loop stage on simulated sequences that revisit places (prints a table).

    python bench/loops.py                         # town circuit, 1,000 scans, 32 beams
    python bench/loops.py --scans 1000 3000 --path figure8 --keep /tmp/loops

Per sequence: `pa simulate town` (kept with --keep and reused when present), then one
`pa refine --config configs/outdoor.yaml --gt ...` in a subprocess. The table holds the ATE
(SE(3)-aligned RMSE) of KISS-ICP alone (`gt.odometry`), after the loop stage (`gt.initial`)
and after the rounds (`gt.refined`); the stage times (s); the closures; the peak RSS of the
refine process; and the plane thickness (RMS distance of a true plane's points to their own fit,
from the simulator's labels) of walls seen on two or more passes against walls seen on one,
under the refined poses. Acceptance: refined ATE <= 0.3 m and <= 1/20 of KISS-ICP's; loop
stage time <= odometry time; thickness ratio <= 2.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# Runs `pa refine` and prints the child's peak RSS (kB) as the last line.
_MEASURED = ("import resource, subprocess, sys; code = subprocess.call(sys.argv[1:]); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(code)")


def _pa(*args: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _MEASURED, sys.executable, "-m", "pa_cli", *map(str, args)],
                          env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"pa {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc.stdout


def plane_thickness(data: Path, T_world_scan: np.ndarray, lap_scans: float) -> tuple[float, float]:
    """Median RMS thickness (m) of true planes seen on >= 2 passes and on 1 pass, under T_world_scan."""
    from pa_cli.io.scans import ScanFolder

    scans = ScanFolder(data / "scans")
    n_labels = len(np.load(data / "planes.npy"))
    count = np.zeros(n_labels)
    total = np.zeros((n_labels, 3))
    outer = np.zeros((n_labels, 3, 3))
    passes = np.zeros((n_labels, int(np.ceil(len(T_world_scan) / lap_scans)) + 1), dtype=bool)
    for k in range(len(T_world_scan)):
        labels = np.load(data / "labels" / f"{k:06d}.npy")
        keep = labels >= 0
        p = np.asarray(scans.points[k])[keep] @ T_world_scan[k, :3, :3].T + T_world_scan[k, :3, 3]
        lab = labels[keep]
        np.add.at(count, lab, 1.0)
        np.add.at(total, lab, p)
        np.add.at(outer, lab, np.einsum("ni,nj->nij", p, p))
        passes[np.unique(lab), int(k // lap_scans)] = True
    seen = count >= 100  # planes with enough points for a thickness
    mean = total[seen] / count[seen, None]
    scatter = outer[seen] / count[seen, None, None] - np.einsum("ni,nj->nij", mean, mean)
    thickness = np.sqrt(np.maximum(np.linalg.eigvalsh(scatter)[:, 0], 0.0))
    n_passes = passes[seen].sum(axis=1)
    once = thickness[n_passes == 1]
    again = thickness[n_passes >= 2]
    return (float(np.median(again)) if len(again) else float("nan"),
            float(np.median(once)) if len(once) else float("nan"))


def _row(data: Path, out: Path, scans: int, peak_kb: int) -> list:
    from pa_cli.io.trajectory import read_trajectory

    report = json.loads(out.with_name(out.stem + "_report.json").read_text())
    meta = json.loads((data / "meta.json").read_text())
    gt = report["gt"]
    times = report["stage_times_s"]
    rounds_s = sum(v for k, v in times.items() if k.startswith(("planes", "adjust")))
    kiss, loops, refined = (gt[key]["ate_rmse_m"] for key in ("odometry", "initial", "refined"))
    T_refined = read_trajectory(out.with_name(out.stem + "_poses_kitti.txt")).T_world_scan
    lap_scans = meta["path_length_m"] / meta["options"]["step_m"]
    again_m, once_m = plane_thickness(data, T_refined, lap_scans)
    checks = [refined <= 0.3, refined <= kiss / 20, times["loops"] <= times["odometry"], again_m <= 2 * once_m]
    return [f"{meta['scene']} {meta['options']['path']}", scans, f"{kiss:.3f}", f"{loops:.3f}", f"{refined:.4f}",
            f"{times['odometry']:.0f}", f"{times['loops']:.0f}", f"{rounds_s:.0f}",
            f"{report['loops']['n_closures']}/{report['loops']['n_candidates']}", f"{peak_kb / 1024 ** 2:.2f}",
            f"{1000 * again_m:.1f} / {1000 * once_m:.1f}", " ".join("yes" if c else "NO" for c in checks)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, nargs="+", default=[1000])
    parser.add_argument("--scene", default="town")
    parser.add_argument("--path", default="circuit")
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the simulated data here")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="pa_bench_loops_"))
    work.mkdir(parents=True, exist_ok=True)
    header = ["sequence", "scans", "ATE KISS-ICP (m)", "ATE loops (m)", "ATE refined (m)", "odometry (s)",
              "loops (s)", "rounds (s)", "closures/candidates", "peak RSS (GB)", "thickness 2+ / 1 pass (mm)",
              "refined<=0.3, <=KISS/20, loops<=odometry, thickness<=2x"]
    rows = []
    for scans in args.scans:
        data = work / f"{args.scene}_{args.path}_{scans}"
        if not (data / "meta.json").is_file():
            _pa("simulate", args.scene, data, "--path", args.path, "--scans", scans, "--beams", args.beams,
                "--seed", 3, "--force")
        out = work / f"{data.name}_refined" / "map.ply"
        out.parent.mkdir(exist_ok=True)
        peak_kb = int(_pa("refine", data / "scans", "--out", out, "--config", REPO / "configs" / "outdoor.yaml",
                          "--gt", data / "gt_poses_tum.txt", "--loops", "--force", "-q").strip().splitlines()[-1])
        rows.append(_row(data, out, scans, peak_kb))
        print(" | ".join(map(str, rows[-1])), flush=True)
    print("\n| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(map(str, row)) + " |")


if __name__ == "__main__":
    main()
