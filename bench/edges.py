"""Benchmark of edge features (prints tables; never a timed assertion).

    python bench/edges.py street   # `pa refine` planes only vs planes + edges on a simulated street
    python bench/edges.py real     # edges found and RMS point-to-line on ../shared/data sequences

street: `pa simulate street` (16 beams; poles every 12 m on both sides), initial poses from
KISS-ICP (--init kiss-icp) or the ground truth perturbed (--init perturbed: --rot-deg, --trans-m
per scan, seeded), then `pa refine` with `edges.enabled` false and true. Reported: ATE
(SE(3)-aligned, m) and its along-street part (the RMS of the aligned position error along each
scan's direction of travel), and the number of weakly constrained scans: scans whose per-scan
information (the diagonal Gauss-Newton block of all features, `FeatureCost.scan_information`,
at the refined poses) gives its weakest translation direction less than --min-points points'
worth (eigenvalue / 2 of the translation block, m^2/m^2), each run on its own last-round problem.

real: the scans and reference poses of each sequence in ../shared/data (or $PA_SHARED_DATA):
edges found at the reference poses, observations, and RMS point-to-line (m).
Options: --scans N, --seed S, --keep DIR.
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
SHARED = Path(os.environ.get("PA_SHARED_DATA", REPO.parent / "shared" / "data"))


def _pa(*args: object) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "pa_cli", *map(str, args)], env=env, capture_output=True,
                          text=True)
    if proc.returncode != 0:
        raise SystemExit(f"pa {' '.join(map(str, args))} failed:\n{proc.stderr}")


def _table(title: str, header: list[str], rows: list[list]) -> None:
    print(f"\n{title}")
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]
    print("| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        print("| " + " | ".join(str(x).ljust(w) for x, w in zip(row, widths, strict=True)) + " |")


def travel_directions(T_world_scan: np.ndarray) -> np.ndarray:
    """(N, 3) unit horizontal directions of travel from the neighbouring positions."""
    t = T_world_scan[:, :3, 3]
    idx = np.arange(len(t))
    d = t[np.minimum(idx + 1, len(t) - 1)] - t[np.maximum(idx - 1, 0)]
    d[:, 2] = 0.0
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def position_errors(T_gt: np.ndarray, T_est: np.ndarray) -> tuple[float, float]:
    """ATE RMS (m) after SE(3) alignment and the RMS of its component along the direction of travel."""
    from pa_cli.evaluation.alignment import alignment_transform, apply_alignment

    A, s = alignment_transform(T_gt, T_est, "se3")
    err = apply_alignment(T_est, A, s)[:, :3, 3] - T_gt[:, :3, 3]
    along = np.einsum("ki,ki->k", err, travel_directions(T_gt))
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), float(np.sqrt(np.mean(along**2)))


def weak_scans(problem, T_world_scan: np.ndarray, min_points: float) -> int:  # noqa: ANN001
    """Scans whose weakest translation direction holds fewer than `min_points` points' worth."""
    from pa_cli.adjust.newton import FeatureCost

    info = FeatureCost(problem).scan_information(T_world_scan)[:, 3:, 3:]
    return int(np.count_nonzero(np.linalg.eigvalsh(info)[:, 0] / 2.0 < min_points))


def bench_street(work: Path, args: argparse.Namespace) -> None:
    from pa_cli.evaluation.perturbation import perturb_poses
    from pa_cli.io.problem import load_problem
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

    data = work / "street"
    _pa("simulate", "street", data, "--scans", args.scans, "--beams", 16, "--seed", args.seed, "--force")
    gt = read_trajectory(data / "gt_poses_tum.txt")
    poses = []
    if args.init == "perturbed":
        T0 = perturb_poses(gt.T_world_scan, np.deg2rad(args.rot_deg), args.trans_m,
                           np.random.default_rng(args.seed))
        write_trajectory(work / "init_tum.txt", Trajectory(T0, gt.timestamps), "tum", force=True)
        poses = ["--poses", work / "init_tum.txt"]
    rows, problems, refined = [], {}, {}
    for label, enabled in (("planes only", "false"), ("planes + edges", "true")):
        cfg = work / f"edges_{enabled}.yaml"
        cfg.write_text(f"edges:\n  enabled: {enabled}\n")
        out = work / f"map_{enabled}.ply"
        _pa("refine", data / "scans", "--out", out, *poses, "--config", cfg,
            "--save-problem", work / f"problem_{enabled}.npz", "--force", "-q")
        T0 = read_trajectory(out.with_name(out.stem + "_initial_poses_kitti.txt")).T_world_scan
        refined[label] = read_trajectory(out.with_name(out.stem + "_poses_tum.txt")).T_world_scan
        problems[label] = load_problem(work / f"problem_{enabled}.npz")
        report = json.loads(out.with_name(out.stem + "_report.json").read_text())
        edges = report["rounds"][-1]["planes"].get("edges", {})
        rows.append([label, edges.get("n_edges", 0), edges.get("n_edge_observations", 0),
                     f"{edges.get('edge_rms_point_to_line_m', float('nan')):.4f}"])
    ate0, along0 = position_errors(gt.T_world_scan, T0)
    table = [["initial", f"{ate0:.4f}", f"{along0:.4f}", ""]]
    for label, T in refined.items():
        ate, along = position_errors(gt.T_world_scan, T)
        table.append([label, f"{ate:.4f}", f"{along:.4f}", weak_scans(problems[label], T, args.min_points)])
    init = "KISS-ICP" if args.init == "kiss-icp" else f"GT perturbed by {args.rot_deg} deg / {args.trans_m} m"
    _table(f"street, 16 beams, {args.scans} scans, seed {args.seed}, initial = {init}",
           ["poses", "ATE m", "along-street m", f"weak scans (< {args.min_points:g} pts)"], table)
    _table("edges found (last round)", ["run", "edges", "observations", "RMS point-to-line m"], rows)


def bench_real(args: argparse.Namespace) -> None:
    from pa_cli.config import EdgesConfig
    from pa_cli.io.scans import ScanFolder
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.planes.edges import build_edge_problem

    rows = []
    for folder in sorted(p for p in SHARED.iterdir() if p.is_dir()):
        scans = folder / "scans"
        poses = sorted(folder.glob("*pose*.txt"))
        if not scans.is_dir() or not poses:
            continue
        T = read_trajectory(poses[0]).T_world_scan
        points = ScanFolder(scans).points
        n = min(len(points), len(T), args.scans)
        _, diag = build_edge_problem([points[k] for k in range(n)], T[:n], EdgesConfig())
        rows.append([folder.name, n, poses[0].name, diag["n_edges_detected"], diag["n_edges"],
                     diag["n_edge_observations"], f"{diag['edge_rms_point_to_line_m']:.4f}"])
    _table("real data: edges at the reference poses (default edges config)",
           ["sequence", "scans", "poses", "detected", "edges (>= 2 scans)", "observations", "RMS point-to-line m"],
           rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["street", "real"])
    parser.add_argument("--scans", type=int, default=80)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--init", choices=["perturbed", "kiss-icp"], default="kiss-icp")
    parser.add_argument("--rot-deg", type=float, default=0.3)
    parser.add_argument("--trans-m", type=float, default=0.15)
    parser.add_argument("--min-points", type=float, default=20.0)
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    if args.what == "real":
        bench_real(args)
        return
    if args.keep is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        bench_street(args.keep, args)
        return
    with tempfile.TemporaryDirectory() as tmp:
        bench_street(Path(tmp), args)


if __name__ == "__main__":
    main()
