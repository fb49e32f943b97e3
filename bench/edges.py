"""Benchmark of edge features (prints tables; never a timed assertion).

    python bench/edges.py street   # `pa refine` planes only vs planes + edges on simulated sequences
    python bench/edges.py real     # edges found and RMS point-to-line on ../shared/data sequences

street: `pa simulate SCENE` (--scene street (default), town or office; --beams 16; --step-m; poles
every 12 m on both sides of the street, a few per block in the town; columns and door frames in
the office) for each of --seeds, initial poses from KISS-ICP (--init kiss-icp) or the ground truth
perturbed (--init perturbed: --rot-deg, --trans-m per scan, seeded), then `pa refine` with
--config (the preset outdoor; indoor for the office) and `scene.edges` false and
true. Reported per seed: ATE (SE(3)-aligned, m) and its along-street part (the RMS of the aligned
position error along each scan's direction of travel), and the number of weakly constrained
scans: scans whose per-scan information (the diagonal Gauss-Newton block of all features,
`FeatureCost.scan_information`, at the refined poses) gives its weakest translation direction
less than --min-points points' worth (eigenvalue / 2 of the translation block, m^2/m^2), each
run on its own last-round problem.

real: the scans and reference poses of each sequence in ../shared/data (or $PA_SHARED_DATA):
edges found at the reference poses (default edges config), observations, and RMS point-to-line (m).
Options: --scans N, --seeds S..., --keep DIR.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import SHARED, print_table, run_pa  # noqa: E402


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


def _config_with_edges(base: str, enabled: bool, out: Path) -> Path:
    """The config `base` (a preset or a YAML file) with `scene.edges` set, written to `out`."""
    from pa_cli.config import dump_config, load_config

    config = load_config(base)
    config.scene.edges = enabled
    out.write_text(dump_config(config))
    return out


def street_case(work: Path, seed: int, args: argparse.Namespace) -> list:
    """One simulated sequence refined without and with edges: one summary row."""
    from pa_cli.evaluation.perturbation import perturb_poses
    from pa_cli.io.problem import load_problem
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

    data = work / f"{args.scene}_{seed}"
    sim = ["--scans", args.scans, "--beams", args.beams, "--seed", seed, "--force"]
    if args.step_m is not None:
        sim += ["--step-m", args.step_m]
    run_pa("simulate", args.scene, data, *sim)
    gt = read_trajectory(data / "gt_poses_tum.txt")
    poses = []
    if args.init == "perturbed":
        T0 = perturb_poses(gt.T_world_scan, np.deg2rad(args.rot_deg), args.trans_m, np.random.default_rng(seed))
        write_trajectory(data / "init_tum.txt", Trajectory(T0, gt.timestamps), "tum", force=True)
        poses = ["--poses", data / "init_tum.txt"]
    row: list = [seed]
    for enabled in (False, True):
        name = f"edges_{str(enabled).lower()}"
        cfg = _config_with_edges(args.config, enabled, data / f"{name}.yaml")
        out = data / f"map_{name}.ply"
        run_pa("refine", data / "scans", "--out", out, *poses, "--config", cfg,
               "--save-problem", data / f"problem_{name}.npz", "--force", "-q")
        T0 = read_trajectory(out.with_name(out.stem + "_initial_poses_kitti.txt")).T_world_scan
        T = read_trajectory(out.with_name(out.stem + "_poses_tum.txt")).T_world_scan
        report = json.loads(out.with_name(out.stem + "_report.json").read_text())
        if not enabled:
            ate0, along0 = position_errors(gt.T_world_scan, T0)
            row.append(f"{ate0:.3f} / {along0:.3f}")
        ate, along = position_errors(gt.T_world_scan, T)
        weak = weak_scans(load_problem(data / f"problem_{name}.npz"), T, args.min_points)
        row.append(f"{ate:.3f} / {along:.3f} / {weak}")
        if enabled:
            edges = report["rounds"][-1]["planes"].get("edges", {})
            row.append(f"{edges.get('n_edges', 0)} ({edges.get('n_edge_observations', 0)})")
    return row


def bench_street(work: Path, args: argparse.Namespace) -> None:
    rows = [street_case(work, seed, args) for seed in args.seeds]
    init = "KISS-ICP" if args.init == "kiss-icp" else f"GT perturbed by {args.rot_deg} deg / {args.trans_m} m"
    step = "default step" if args.step_m is None else f"step {args.step_m} m"
    print_table(f"{args.scene}, {args.beams} beams, {args.scans} scans, {step}, config {args.config}, "
                f"initial = {init}; weak scans: weakest translation < {args.min_points:g} points' worth",
                ["seed", "initial ATE / along m", "planes only: ATE / along m / weak",
                 "planes + edges: ATE / along m / weak", "edges (obs.)"], rows)


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
    print_table("real data: edges at the reference poses (default edges config)",
                ["sequence", "scans", "poses", "detected", "edges (>= 2 scans)", "observations", "RMS point-to-line m"],
                rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["street", "real"])
    parser.add_argument("--scans", type=int, default=80)
    parser.add_argument("--seeds", type=int, nargs="+", default=[11, 12, 13, 14, 15])
    parser.add_argument("--scene", choices=["street", "town", "office"], default="street")
    parser.add_argument("--beams", type=int, default=16)
    parser.add_argument("--step-m", type=float, default=None)
    parser.add_argument("--config", default=None, help="a preset or a YAML file; default: outdoor (office: indoor)")
    parser.add_argument("--init", choices=["perturbed", "kiss-icp"], default="kiss-icp")
    parser.add_argument("--rot-deg", type=float, default=0.3)
    parser.add_argument("--trans-m", type=float, default=0.15)
    parser.add_argument("--min-points", type=float, default=20.0)
    parser.add_argument("--keep", type=Path, default=None)
    args = parser.parse_args()
    if args.config is None:
        args.config = "indoor" if args.scene == "office" else "outdoor"
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
