"""Benchmarks of `pa refine` (prints tables; never a timed assertion).

    python bench/refine.py sims     # ATE of KISS-ICP alone vs pa refine on fresh office/street sequences
    python bench/refine.py real     # balm-campus-30, kaist03-21: RMS point-to-plane, refined vs reference
    python bench/refine.py speed    # planes+adjustment vs KISS-ICP: streets of 30k and 100k points/scan, real data
    python bench/refine.py memory   # peak RSS of `pa refine` on 1000 scans of ~30k points (subprocess)

Options: --scans N, --keep DIR (keep the simulated data there), --solver newton|lm, --repeat N (speed).
Data are simulated with `pa simulate` into a temporary folder. Real data: ../shared/data
(or $PA_SHARED_DATA).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import print_table, run_pa, shared_sequences  # noqa: E402


def _report(map_ply: Path) -> dict:
    return json.loads(map_ply.with_name(map_ply.stem + "_report.json").read_text())


def bench_sims(work: Path, scans: int, solver: str) -> None:
    rows = []
    for scene, beams, config in (("office", 16, ["--config", "indoor"]), ("street", 32, [])):
        data = work / scene
        run_pa("simulate", scene, data, "--scans", scans, "--beams", beams, "--seed", 3, "--force")
        out = work / f"{scene}.ply"
        run_pa("refine", data / "scans", "--out", out, "--gt", data / "gt_poses_tum.txt", "--solver", solver,
               *config, "--force", "-q")
        r = _report(out)
        ate0, ate1 = r["gt"]["initial"]["ate_rmse_m"], r["gt"]["refined"]["ate_rmse_m"]
        s = r["summary"]
        rows.append([scene, config[-1] if config else "defaults", scans, f"{r['input']['n_points'] / scans:.0f}",
                     f"{ate0:.4f}", f"{ate1:.4f}", f"{ate1 / ate0:.3f}", f"{s['rms_point_to_plane_initial_m']:.4f}",
                     f"{s['rms_point_to_plane_final_m']:.4f}", f"{r['gt']['rms_point_to_plane_at_gt_m']:.4f}",
                     s["n_rounds"], s["iterations"], f"{r['total_time_s']:.1f}"])
    print_table(f"ATE (m, SE(3)-aligned) of KISS-ICP alone vs pa refine ({solver}); acceptance: ratio <= 0.5",
                ["scene", "config", "scans", "pts/scan", "ATE KISS", "ATE refine", "ratio", "RMS init", "RMS refined",
                 "RMS at GT", "rounds", "iters", "time s"], rows)


def bench_real(work: Path, solver: str) -> None:
    from pa_cli.adjust import plane_cost
    from pa_cli.config import PaConfig
    from pa_cli.io.scans import ScanFolder
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.planes.associate import build_plane_problem

    rows = []
    for name, folder in shared_sequences(("balm-campus-30", "kaist03-21")):
        out = work / f"{name}.ply"
        ref = folder / "poses_kitti.txt"
        run_pa("refine", folder / "scans", "--out", out, "--gt", ref, "--solver", solver, "--force", "-q")
        r = _report(out)
        T_ref = read_trajectory(ref).T_world_scan
        T_refined = read_trajectory(out.with_name(out.stem + "_poses_kitti.txt")).T_world_scan
        # the same plane problem, built at the reference poses, scored at both pose sets
        problem, _ = build_plane_problem(ScanFolder(folder / "scans").points, T_ref, PaConfig().planes_config())
        n = problem.n_points
        rms_ref = np.sqrt(plane_cost(problem, T_ref) / n)
        rms_refined = np.sqrt(plane_cost(problem, T_refined) / n)
        rows.append([name, problem.n_planes, n, f"{rms_ref:.4f}", f"{rms_refined:.4f}",
                     f"{r['gt']['initial']['ate_rmse_m']:.4f}", f"{r['gt']['refined']['ate_rmse_m']:.4f}",
                     f"{r['total_time_s']:.1f}"])
    print_table("Real data: RMS point-to-plane (m) on the plane problem built at the reference poses; "
                "acceptance: refined < reference",
                ["data", "planes", "points", "RMS reference", "RMS refined", "ATE KISS vs ref",
                 "ATE refined vs ref", "time s"], rows)


def _speed_times(out: Path) -> dict:
    """Wall and process CPU times (s) of KISS-ICP and of plane association + adjustment in one report."""
    r = _report(out)
    times = {"n_scans": r["input"]["n_scans"], "pts": r["input"]["n_points"] / r["input"]["n_scans"],
             "rounds": r["summary"]["n_rounds"], "total_wall": r["total_time_s"]}
    for kind, t in (("wall", r["stage_times_s"]), ("cpu", r["stage_cpu_s"])):
        times[f"kiss_{kind}"] = t["odometry"]
        times[f"planes_{kind}"] = sum(v for k, v in t.items() if k.startswith("planes"))
        times[f"adjust_{kind}"] = sum(v for k, v in t.items() if k.startswith("adjust"))
        times[f"ratio_{kind}"] = (times[f"planes_{kind}"] + times[f"adjust_{kind}"]) / t["odometry"]
    for what in ("kiss", "planes"):  # cores used: process CPU / wall
        times[f"{what}_cores"] = times[f"{what}_cpu"] / times[f"{what}_wall"]
    return times


def bench_speed(work: Path, scans: int, solver: str, repeat: int) -> None:
    """(planes + adjust) / KISS-ICP time of `pa refine` (same process, same machine), `repeat` runs
    each: a 32-beam street of ~30k points per scan, a 64-beam street of ~100k points per scan, and
    the real sequences of ../shared/data. Medians over the runs, the range of the wall ratio,
    the cores used (process CPU / wall) by KISS-ICP and by plane finding, the wall time of all
    stages of `pa refine` (the plane kernels load on a thread beside the odometry, whose stage time
    includes any slowdown that causes), and the 1-minute load average before each run."""
    inputs = []
    for name, beams, azimuth, n in (("street 32 beams", 32, 1024, scans), ("street 64 beams", 64, 2048, 30)):
        data = work / f"street_speed_{beams}"
        run_pa("simulate", "street", data, "--scans", n, "--beams", beams, "--azimuth-steps", azimuth, "--seed", 5,
               "--force")
        inputs.append((name, data / "scans", ("--gt", data / "gt_poses_tum.txt")))
    inputs += [(name, folder / "scans", ()) for name, folder in shared_sequences(("balm-campus-30", "kaist03-21"))]
    rows = []
    for name, folder, extra in inputs:
        runs, loads = [], []
        for k in range(repeat):
            out = work / f"speed_{name.replace(' ', '_')}_{k}.ply"
            loads.append(os.getloadavg()[0])
            run_pa("refine", folder, "--out", out, *extra, "--solver", solver, "--force", "-q")
            runs.append(_speed_times(out))
        med = {key: float(np.median([r[key] for r in runs])) for key in runs[0]}
        walls = [r["ratio_wall"] for r in runs]
        stages = ("wall", "cpu")
        rows.append([name, runs[0]["n_scans"], f"{med['pts']:.0f}"] +
                    [f"{med[f'{what}_{kind}']:.1f}" for kind in stages for what in ("kiss", "planes", "adjust")] +
                    [f"{med['kiss_cores']:.2f}", f"{med['planes_cores']:.2f}",
                     f"{med['ratio_wall']:.2f} ({min(walls):.2f}-{max(walls):.2f})", f"{med['ratio_cpu']:.2f}",
                     f"{runs[0]['rounds']}", f"{med['total_wall']:.1f}", " ".join(f"{x:.1f}" for x in loads)])
    print_table(f"Time (s): KISS-ICP vs plane association + adjustment ({solver}), medians of {repeat} run(s), "
                "wall and process CPU (all threads); acceptance: wall ratio (planes + adjust) / KISS-ICP <= 1",
                ["data", "scans", "pts/scan", "KISS-ICP wall", "planes wall", "adjust wall", "KISS-ICP CPU",
                 "planes CPU", "adjust CPU", "KISS-ICP cores", "planes cores", "ratio wall (range)", "ratio CPU",
                 "rounds", "refine stages wall", "load avg"], rows)


def bench_memory(work: Path, scans: int, solver: str) -> None:
    data = work / "street_memory"
    t0 = time.perf_counter()
    run_pa("simulate", "street", data, "--scans", scans, "--beams", 32, "--step-m", 0.5, "--seed", 6, "--force")
    sim_s = time.perf_counter() - t0
    out = work / "memory.ply"
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    run_pa("refine", data / "scans", "--out", out, "--solver", solver, "--force", "-q")
    wall = time.perf_counter() - t0
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    r = _report(out)
    note = "" if peak_kib > before else " (peak of an earlier child; lower bound)"
    rows = [[scans, f"{r['input']['n_points'] / scans:.0f}", f"{r['input']['n_points']:,}",
             f"{peak_kib / 1024 / 1024:.2f}{note}", f"{wall:.0f}", f"{sim_s:.0f}",
             {k: round(v, 1) for k, v in r["stage_times_s"].items() if not k[-1].isdigit() or k.endswith("1")}]]
    print_table("Peak memory of `pa refine` (subprocess, ru_maxrss); acceptance: <= 4 GB",
                ["scans", "pts/scan", "points", "peak GiB", "wall s", "simulate s", "stage s (round 1)"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["sims", "real", "speed", "memory", "all"])
    parser.add_argument("--scans", type=int, default=None)
    parser.add_argument("--solver", default="newton", choices=["newton", "lm"])
    parser.add_argument("--repeat", type=int, default=1, help="Runs per input of `speed` (medians).")
    parser.add_argument("--keep", type=Path, default=None, help="Folder for the simulated data (kept).")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="pa_bench_") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        if args.what in ("sims", "all"):
            bench_sims(work, args.scans or 60, args.solver)
        if args.what in ("real", "all"):
            bench_real(work, args.solver)
        if args.what in ("speed", "all"):
            bench_speed(work, args.scans or 100, args.solver, args.repeat)
        if args.what in ("memory", "all"):
            bench_memory(work, args.scans or 1000, args.solver)


if __name__ == "__main__":
    main()
