"""Benchmark of the hierarchical backend on long synthetic sequences. Prints a table.

Every run (hierarchical or flat, one sequence length) is its own subprocess, so its peak memory
(ru_maxrss, includes building the synthetic problem) is its own; the runs go one after another.
Scenes come from `pa_testing.synthetic_problems.make_scene`: 4 planes per scan, each seen by 20
consecutive scans, 10 points per observation, 1 cm point noise; initial poses perturbed by 1 deg
and 0.1 m (the papers' level 2).

    PYTHONPATH=. python bench/scale.py                               # 1000 5000 10000 20000 scans
    PYTHONPATH=. python bench/scale.py --scans 1000 --flat-max 1000  # flat only up to 1000 scans
    PYTHONPATH=. python bench/scale.py --workers 2                   # windows on a local dask cluster
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

PLANES_PER_SCAN = 4
SCANS_PER_PLANE = 20
POINTS_PER_OBSERVATION = 10
NOISE_M = 0.01
LEVEL_2 = (1.0, 0.1)  # deg, m


def run_case(kind: str, n_scans: int, workers: int) -> dict:
    from pa_cli.adjust import solve
    from pa_cli.adjust.hierarchical import hierarchical_adjust
    from pa_cli.config import ExecutionConfig, SolverConfig
    from pa_cli.runtime.distributed import execution
    from pa_testing.synthetic_problems import make_scene, perturb

    t0 = time.perf_counter()
    problem, T_gt = make_scene(n_scans, PLANES_PER_SCAN * n_scans, SCANS_PER_PLANE,
                               points_per_observation=POINTS_PER_OBSERVATION, noise_m=NOISE_M, seed=0)
    T0 = perturb(T_gt, np.deg2rad(LEVEL_2[0]), LEVEL_2[1], seed=2)
    out = {"kind": kind, "n_scans": n_scans, "n_obs": problem.n_observations, "build_s": time.perf_counter() - t0,
           "load_before": os.getloadavg()[0]}
    config = SolverConfig()
    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    cpu_before = sum(u.ru_utime + u.ru_stime for u in usage)
    t0 = time.perf_counter()
    if kind == "flat":
        result = solve(problem, T0, config)
        out.update(cost_m2=result.report["cost_final_m2"], iterations=result.report["iterations"],
                   stop=result.report["stop_reason"])
    else:
        with execution(ExecutionConfig(workers=workers)):
            result = hierarchical_adjust(problem, T0, config)
        out.update(cost_m2=result.fields["cost_final_m2"], iterations=result.fields["iterations"],
                   stop=result.fields["stop_reason"], stages=result.stages, warnings=result.warnings)
    out["time_s"] = time.perf_counter() - t0
    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    out["cpu_s"] = sum(u.ru_utime + u.ru_stime for u in usage) - cpu_before
    out["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    out["load_after"] = os.getloadavg()[0]
    return out


def phase_row(h: dict) -> str:
    """One line of the per-phase table: wall (this process's CPU) seconds of every layer, the final
    pass's iterations and its CPU seconds per iteration."""
    cells = [f"{s['time_s']:.1f} ({s['cpu_s']:.1f})" for s in h["stages"]]
    final = [s for s in h["stages"] if s["stage"] == "final flat pass"]
    per_iteration = f"{final[0]['cpu_s'] / h['iterations']:.2f}" if final and h["iterations"] else "-"
    return (f"| {h['n_scans']} | " + " | ".join(cells) + f" | {h['iterations']} ({h['stop']}) | {per_iteration} "
            f"| {h['load_before']:.1f} / {h['load_after']:.1f} |")


def spawn(kind: str, n_scans: int, workers: int) -> dict:
    cmd = [sys.executable, __file__, "--case", kind, str(n_scans), str(workers)]
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(text.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", nargs=3)
    ap.add_argument("--scans", type=int, nargs="+", default=[1000, 5000, 10000, 20000])
    ap.add_argument("--flat-max", type=int, default=5000, help="run the flat solver up to this many scans")
    ap.add_argument("--workers", type=int, default=0, help="dask worker processes (0: in-process)")
    args = ap.parse_args()
    if args.case:
        kind, n, workers = args.case
        print(json.dumps(run_case(kind, int(n), int(workers))))
        return

    print(f"| scans | observations | hierarchical s | CPU s | peak GB | cost after the global layer / flat - 1 "
          f"| final cost m2 | final cost / flat - 1 | flat s | flat CPU s | flat peak GB | flat iterations "
          f"| flat cost m2 | workers {args.workers} |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    phases = []
    for n in args.scans:
        h = spawn("hierarchical", n, args.workers)
        f = spawn("flat", n, 0) if n <= args.flat_max else None
        layers = [s["cost_m2"] for s in h["stages"] if s["stage"].endswith("global")][-1]
        if f:
            gap_layers, gap_final = f"{layers / f['cost_m2'] - 1:.2e}", f"{h['cost_m2'] / f['cost_m2'] - 1:.2e}"
            flat = [f"{f['time_s']:.1f}", f"{f['cpu_s']:.1f}", f"{f['peak_gb']:.2f}", f"{f['iterations']}",
                    f"{f['cost_m2']:.10g}"]
        else:
            gap_layers = gap_final = "flat not run"
            flat = ["-"] * 5
        print(f"| {n} | {h['n_obs']} | {h['time_s']:.1f} | {h['cpu_s']:.1f} | {h['peak_gb']:.2f} | {gap_layers} "
              f"| {h['cost_m2']:.10g} | {gap_final} | " + " | ".join(flat) + " | |")
        print(f"  global-layer cost {layers:.10g} m2; warnings {h['warnings']}", file=sys.stderr)
        phases.append(h)
        sys.stdout.flush()
    print("\nPer phase, wall s (CPU s of the driver process):\n")
    print("| scans | " + " | ".join(s["stage"] for s in phases[0]["stages"])
          + " | final pass iterations | final pass CPU s / iteration | load average before / after |")
    print("|---" * (len(phases[0]["stages"]) + 4) + "|")
    for h in phases:
        print(phase_row(h))


if __name__ == "__main__":
    main()
