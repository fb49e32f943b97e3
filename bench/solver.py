"""Benchmark of the second-order plane adjustment (`pa adjust --solver newton`). Prints tables.

Every case runs in its own subprocess so that its peak memory (ru_maxrss, includes building the
synthetic problem) is its own. Scenes come from `tests.synthetic_problems.make_scene`: planes seen
by a window of consecutive scans, 1 cm point noise (so the optimum has a non-zero cost).

    PYTHONPATH=. python bench/solver.py            # all tables (~5 min on 2 cores)
    PYTHONPATH=. python bench/solver.py --quick    # smaller cases only
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

LEVELS = {1: (0.1, 0.01), 2: (1.0, 0.1), 3: (2.0, 0.2), 4: (3.0, 0.3)}


def run_case(kind: str, n_scans: int, n_planes: int, window: int, points: int, level: int, iters: int) -> dict:
    from pa_cli.adjust import solve
    from pa_cli.adjust.newton import NewtonModel
    from pa_cli.config import SolverConfig
    from tests.synthetic_problems import make_scene, perturb

    t0 = time.perf_counter()
    problem, T_gt = make_scene(n_scans, n_planes, window, points_per_observation=points, noise_m=0.01, seed=0)
    t_build = time.perf_counter() - t0
    r_rot, r_trans = LEVELS[level]
    T0 = perturb(T_gt, np.deg2rad(r_rot), r_trans, seed=level)
    out = {"n_scans": n_scans, "n_planes": problem.n_planes, "n_obs": problem.n_observations,
           "points": points, "level": level, "build_s": t_build}
    if kind == "levels":
        tight = SolverConfig(cost_tolerance=0.0, gradient_tolerance=0.0, step_tolerance=1e-12, max_iterations=50)
        cost_opt = solve(problem, T_gt, tight).report["cost_final_m2"]
        res = solve(problem, T0, SolverConfig())
        hist = res.report["history"]
        reached = [h["iteration"] for h in hist if h["cost_m2"] <= cost_opt * (1 + 1e-6)]
        out.update(iterations=res.report["iterations"], reached=reached[0] if reached else None,
                   rejected=sum(not h["accepted"] for h in hist), cost_opt=cost_opt,
                   rel_gap=(res.report["cost_final_m2"] - cost_opt) / cost_opt, time_s=res.report["time_s"],
                   s_per_iter=float(np.mean([h["time_s"] for h in hist])), stop=res.report["stop_reason"])
    else:
        t0 = time.perf_counter()
        model = NewtonModel(problem)
        t_setup = time.perf_counter() - t0
        res = solve(problem, T0, SolverConfig(max_iterations=iters))
        hist = res.report["history"]
        # an accepted iteration = solve + cost + new linearisation; the first linearisation is in time_s only
        out.update(setup_s=t_setup, iterations=res.report["iterations"], time_s=res.report["time_s"],
                   s_per_iter=float(np.mean([h["time_s"] for h in hist])),
                   s_per_accepted=float(np.mean([h["time_s"] for h in hist if h["accepted"]] or [np.nan])),
                   n_blocks=model.pattern.n_blocks)
    out["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return out


def spawn(*args) -> dict:
    cmd = [sys.executable, __file__, "--case", *[str(a) for a in args]]
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(text.strip().splitlines()[-1])


def table(title: str, cols: list[str], rows: list[list]) -> None:
    print(f"\n### {title}\n")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r) + " |")
    sys.stdout.flush()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", nargs=7)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if args.case:
        kind, *nums = args.case
        print(json.dumps(run_case(kind, *[int(x) for x in nums])))
        return

    rows = []
    for n in ([100] if args.quick else [100, 200, 300]):
        for level in LEVELS:
            r = spawn("levels", n, 4 * n, 20, 20, level, 0)
            rows.append([n, r["n_planes"], r["n_obs"], level, r["iterations"], r["rejected"], r["reached"],
                         r["stop"], r["rel_gap"], r["s_per_iter"]])
    table("Levels 1-4: iterations to the optimum (noise 1 cm, window 20, 20 points/observation)",
          ["scans", "planes", "obs", "level", "iterations", "rejected", "first iter within 1e-6 of optimum",
           "stop", "final rel. gap", "s/iter"], rows)

    rows = []
    scans = [100, 500, 1000] if args.quick else [100, 500, 1000, 2000]
    for n in scans:
        r = spawn("time", n, 5 * n, 40, 10, 2, 5)
        rows.append([n, r["n_planes"], r["n_obs"], r["n_blocks"], r["setup_s"], r["s_per_iter"],
                     r["s_per_accepted"], r["peak_gb"]])
    table("Time per iteration vs scans (planes = 5 x scans, window 40, level 2, 5 iterations)",
          ["scans", "planes", "obs", "pose-pair blocks", "setup s", "s/iter", "s/accepted iter", "peak GB"], rows)

    rows = []
    for p in [1000, 2000, 4000]:
        r = spawn("time", 400, p, 40, 10, 2, 5)
        rows.append([400, r["n_planes"], r["n_obs"], r["s_per_iter"], r["s_per_accepted"], r["peak_gb"]])
    table("Time per iteration vs planes (400 scans, window 40)",
          ["scans", "planes", "obs", "s/iter", "s/accepted iter", "peak GB"], rows)

    rows = []
    for pts in [10, 100, 1000]:
        r = spawn("time", 200, 1000, 20, pts, 2, 5)
        rows.append([pts, r["n_obs"], r["build_s"], r["s_per_iter"], r["s_per_accepted"]])
    table("Time per iteration vs points per observation (200 scans, 1000 planes): must stay flat",
          ["points/obs", "obs", "build problem s", "s/iter", "s/accepted iter"], rows)

    if not args.quick:
        r = spawn("time", 1000, 5000, 40, 10, 2, 5)
        table("Target: 1000 poses x 5000 planes x 40 observations/plane (target <= 2 s/iter, <= 4 GB)",
              ["obs", "setup s", "s/iter", "s/accepted iter", "peak GB"],
              [[r["n_obs"], r["setup_s"], r["s_per_iter"], r["s_per_accepted"], r["peak_gb"]]])


if __name__ == "__main__":
    main()
