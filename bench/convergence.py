"""Convergence benchmark of seed 000, section 5: damped Newton (planes eliminated) vs PA_LM.

Protocol, per dataset:
1. the plane association is built once at the reference poses and then held fixed;
2. the optimum is computed by `newton` from the reference poses (tight tolerances);
3. every pose of the optimum is perturbed (`pa_cli.evaluation.perturb_poses`) at the four
   levels (0.1 deg, 0.01 m), (1, 0.1), (2, 0.2), (3, 0.3) with `--seeds` seeds each, pose 0
   (the gauge) kept;
4. the solvers run from the same perturbed poses with the same options (damping schedule,
   stopping rules, gauge), at most `--max-iterations` damped solves: `newton`, `lm` (PA_LM as
   `pa adjust --solver lm`: plane normals turn about the plane centroids) and `lm-origin`
   (PA_LM with the normals turning about the world origin, the naive parametrisation).

Printed per dataset and level: iterations (median, max), iterations until the cost is within
1e-6 relative of the optimum (median, max; '-' if never), wall time (median, s), the final
relative excess cost over the optimum (worst seed; negative: below the reference optimum)
and the newton/lm ratios of median iterations and time.
Plots (PNG, Agg) in --out: relative excess cost vs iteration and vs wall time (summed
iteration times, setup excluded), one panel per level, like figures 5 and 6 of seed 000.

    PYTHONPATH=. python bench/convergence.py --seeds 5 --out bench/out
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pa_cli.config import SolverConfig
from pa_cli.core.problem import FeatureProblem
from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
from pa_testing.synthetic_problems import make_scene

REPO = Path(__file__).resolve().parents[1]


def _find_shared_data() -> Path:
    """../shared/data beside the repository or a parent folder (git worktrees); PA_SHARED_DATA overrides."""
    if os.environ.get("PA_SHARED_DATA"):
        return Path(os.environ["PA_SHARED_DATA"])
    for parent in REPO.parents:
        if (parent / "shared" / "data").is_dir():
            return parent / "shared" / "data"
    return REPO.parent / "shared" / "data"


SHARED_DATA = _find_shared_data()
REL_OPT = 1e-6  # "reached the optimum": cost <= optimum * (1 + REL_OPT)

class Skip(Exception):
    """A dataset that cannot be built yet (module or data missing)."""


# ------------------------------------------------------------------------------------------
# datasets
# ------------------------------------------------------------------------------------------


def dataset_synthetic() -> FeatureProblem:
    """`pa_testing.synthetic_problems`: 100 scans, 400 planes seen by 8 consecutive scans, 30 points, 1 cm noise."""
    return make_scene(n_scans=100, n_planes=400, window=8, points_per_observation=30, noise_m=0.01, seed=0)[0]


def _simulated(scene: str, scans: int) -> FeatureProblem:
    try:
        from pa_cli import simulate as sim
    except ImportError as exc:
        raise Skip(f"pa_cli.simulate not available ({exc})") from None
    if hasattr(sim, "simulate_sequence"):
        return sim.build_problem_from_labels(sim.simulate_sequence(sim.SimOptions(scene=scene, scans=scans)))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "seq"
        sim.simulate(sim.SimOptions(scene=scene, scans=scans), out)
        return sim.build_problem_from_labels(out)


def dataset_sim_office() -> FeatureProblem:
    return _simulated("office", 60)


def dataset_sim_street() -> FeatureProblem:
    return _simulated("street", 60)


def _real(name: str) -> FeatureProblem:
    folder = SHARED_DATA / name
    if not folder.is_dir():
        raise Skip(f"{folder} not present")
    try:
        from pa_cli.config import PlanesConfig
        from pa_cli.io.scans import ScanFolder
        from pa_cli.io.trajectory import read_trajectory
        from pa_cli.planes.associate import build_plane_problem
    except ImportError as exc:
        raise Skip(f"plane association or scan reading not available ({exc})") from None
    scans = ScanFolder(folder / "scans")
    T_ref = read_trajectory(folder / "poses_kitti.txt").T_world_scan

    class _Points:
        def __len__(self) -> int:
            return len(scans)

        def __getitem__(self, i: int) -> np.ndarray:
            return scans[i].points_scan

    problem, _ = build_plane_problem(_Points(), T_ref, PlanesConfig())
    problem.T_world_scan = T_ref
    return problem


DATASETS: dict[str, Callable[[], FeatureProblem]] = {
    "synthetic": dataset_synthetic,
    "sim-office": dataset_sim_office,
    "sim-street": dataset_sim_street,
    "balm-campus-30": lambda: _real("balm-campus-30"),
    "kaist03-21": lambda: _real("kaist03-21"),
}


# ------------------------------------------------------------------------------------------
# runs
# ------------------------------------------------------------------------------------------


SOLVERS = ("newton", "lm", "lm-origin")
LABELS = {"newton": "newton (planes eliminated)", "lm": "PA_LM (normals turn about centroids)",
          "lm-origin": "PA_LM (normals turn about the origin)"}


def run_solver(problem: FeatureProblem, T_init: np.ndarray, solver: str, options: SolverConfig) -> dict:
    """One run; `lm-origin` is PA_LM with the plane normals turning about the world origin."""
    from pa_cli.adjust import solve
    from pa_cli.adjust.joint_lm import solve_lm

    t0 = time.perf_counter()
    if solver == "lm-origin":
        report = solve_lm(problem, T_init, options, anchor_at_centroid=False).fields
    else:
        report = solve(problem, T_init, options.model_copy(update={"solver": solver})).report
    wall_s = time.perf_counter() - t0
    costs = np.array([report["cost_initial_m2"]] + [h["cost_m2"] for h in report["history"]])
    times = np.concatenate([[0.0], np.cumsum([h["time_s"] for h in report["history"]])])
    return {"iterations": report["iterations"], "time_s": wall_s, "cost_final_m2": report["cost_final_m2"],
            "costs": costs, "times": times, "stop_reason": report["stop_reason"]}


def first_within(costs: np.ndarray, optimum: float) -> int | None:
    hit = np.flatnonzero(costs <= optimum * (1.0 + REL_OPT))
    return int(hit[0]) if len(hit) else None


def benchmark(name: str, problem: FeatureProblem, seeds: int, max_iterations: int, out: Path) -> None:
    from pa_cli.adjust import solve

    print(f"\n## {name}: {problem.n_scans} scans, {problem.n_planes} planes, "
          f"{problem.n_observations} observations, {problem.n_points} points")
    tight = SolverConfig(max_iterations=200, cost_tolerance=1e-15, gradient_tolerance=1e-12,
                         step_tolerance=1e-14)
    t0 = time.perf_counter()
    ref = solve(problem, problem.T_world_scan, tight)
    T_opt, cost_opt = ref.T_world_scan, ref.report["cost_final_m2"]
    print(f"optimum (newton from the reference poses): cost {cost_opt:.9g} m^2 "
          f"(reference poses {ref.report['cost_initial_m2']:.9g}), {ref.report['iterations']} iterations, "
          f"{time.perf_counter() - t0:.2f} s")
    options = SolverConfig(max_iterations=max_iterations)
    runs: dict[tuple[int, str], list[dict]] = {}
    for level, (sigma_rot_deg, sigma_trans_m) in PERTURBATION_LEVELS.items():
        for seed in range(seeds):
            rng = np.random.default_rng(1000 * level + seed)
            T_init = perturb_poses(T_opt, np.deg2rad(sigma_rot_deg), sigma_trans_m, rng, keep_first=True)
            for solver in SOLVERS:
                run = run_solver(problem, T_init, solver, options)
                run["reach"] = first_within(run["costs"], cost_opt)
                runs.setdefault((level, solver), []).append(run)
    print_table(runs, cost_opt, max_iterations)
    plot(name, runs, cost_opt, out)


def _med_max(values: list[int | None]) -> str:
    if any(v is None for v in values):
        ok = [v for v in values if v is not None]
        return f"{np.median(ok):.0f}/{max(ok)} ({len(values) - len(ok)} never)" if ok else "never"
    return f"{np.median(values):.0f}/{max(values)}"


def print_table(runs: dict, cost_opt: float, options_max: int) -> None:
    header = ("| level | solver | iters med/max | iters to opt med/max | time med (s) | cost/opt - 1 worst "
              "| stop reasons |")
    print(header)
    print("|---|---|---|---|---|---|---|")
    ratios = []
    for level in PERTURBATION_LEVELS:
        for solver in SOLVERS:
            rs = runs[(level, solver)]
            worst = max(r["cost_final_m2"] for r in rs) / cost_opt - 1.0
            reasons = ",".join(sorted({r["stop_reason"] for r in rs}))
            print(f"| {level} | {solver} | {_med_max([r['iterations'] for r in rs])} | "
                  f"{_med_max([r['reach'] for r in rs])} | {np.median([r['time_s'] for r in rs]):.3f} | "
                  f"{worst:.1e} | {reasons} |")
        nw = runs[(level, "newton")]
        cells = []
        for other in SOLVERS[1:]:
            lm = runs[(level, other)]
            it = np.median([r["iterations"] for r in nw]) / np.median([r["iterations"] for r in lm])
            tm = np.median([r["time_s"] for r in nw]) / np.median([r["time_s"] for r in lm])
            reach_n, reach_l = [r["reach"] for r in nw], [r["reach"] for r in lm]
            # a run that never reached the optimum counts as max-iterations reached
            reach_l = [options_max if v is None else v for v in reach_l]
            rr = "n/a" if None in reach_n else f"{np.median(reach_n) / max(np.median(reach_l), 1):.2f}"
            cells += [f"{it:.2f}", rr, f"{tm:.2f}"]
        ratios.append(f"| {level} | " + " | ".join(cells) + " |")
    print("\nnewton / other solver (ratios of medians; iterations to opt: a run that never got there "
          "counts as the iteration budget):\n")
    print("| level | it. / lm | it. to opt / lm | time / lm | it. / lm-origin | it. to opt / lm-origin "
          "| time / lm-origin |\n|---|---|---|---|---|---|---|")
    print("\n".join(ratios))


def plot(name: str, runs: dict, cost_opt: float, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    floor = 1e-12
    for axis_key, xlabel, fname in (("iteration", "iteration", "iterations"), ("times", "wall time (s)", "time")):
        fig, axes = plt.subplots(1, len(PERTURBATION_LEVELS), figsize=(4 * len(PERTURBATION_LEVELS), 3.4),
                                 sharey=True)
        for ax, (level, (sr, st)) in zip(axes, PERTURBATION_LEVELS.items(), strict=True):
            for solver, color in (("newton", "tab:red"), ("lm", "tab:blue"), ("lm-origin", "tab:gray")):
                for k, r in enumerate(runs[(level, solver)]):
                    x = np.arange(len(r["costs"])) if axis_key == "iteration" else r["times"]
                    y = np.maximum(r["costs"] / cost_opt - 1.0, floor)
                    ax.semilogy(x, y, color=color, alpha=0.6, lw=1,
                                label=LABELS[solver] if k == 0 else None)
            ax.set_title(f"level {level}: {sr} deg, {st} m")
            ax.set_xlabel(xlabel)
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel("cost / optimum - 1")
        axes[0].legend(fontsize=8)
        fig.suptitle(f"{name}: cost vs {xlabel}")
        fig.tight_layout()
        path = out / f"{name}_cost_vs_{fname}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=5, help="perturbation seeds per level (>= 5 for the protocol)")
    parser.add_argument("--max-iterations", type=int, default=500, help="damped solves per run at most")
    parser.add_argument("--datasets", default=",".join(DATASETS), help="comma-separated subset of: "
                        + ", ".join(DATASETS))
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "out", help="folder for the PNG plots")
    args = parser.parse_args()
    try:
        from pa_cli.adjust import solve  # noqa: F401
    except ImportError as exc:
        raise SystemExit(f"pa_cli.adjust.solve is not available yet ({exc}); merge the newton branch.") from None
    for name in args.datasets.split(","):
        try:
            t0 = time.perf_counter()
            problem = DATASETS[name]()
        except Skip as exc:
            print(f"\n## {name}: skipped: {exc}")
            continue
        print(f"(built {name} in {time.perf_counter() - t0:.1f} s)")
        benchmark(name, problem, args.seeds, args.max_iterations, args.out)


if __name__ == "__main__":
    main()
