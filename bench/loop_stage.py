"""The loop stage alone on fixed odometry poses: its CPU time, local-map preparations and outcome (prints a table).

    python bench/loop_stage.py --keep /tmp/loops                        # 1,000 scans of the 16-beam circuit
    python bench/loop_stage.py --scans 5000 --odometry drift --keep /tmp/loops
    python bench/loop_stage.py --keep /tmp/loops --workers 2 --profile /tmp/loops/stage.prof

Per sequence: `pa simulate town --path circuit --seed S --beams B` (kept with --keep and reused),
then the odometry, computed once and kept beside it: KISS-ICP with the outdoor preset
(`--odometry kiss`), or the true poses given a drift of DRIFT_YAW_DEG of heading and DRIFT_STEP_M
sideways per scan (`--odometry drift`, a stand-in for KISS-ICP on sequences too long to run it
for). Then `close_loops` with the outdoor preset in this process, on its execution.threads as `pa refine` runs
it (`--workers N`: registrations on a local dask cluster of N workers). The script runs the checkout it lies
in (column `code`): the copies of it in two checkouts, on the same kept poses, compare their loop stages alone.
Columns: the stage's CPU seconds (this process; with --workers, plus its worker
processes'), wall seconds, local maps, preparations of a local map for registration (calls of
`prepare_local_map`, counted in this process), candidates, closures, false closures (anchor scans
truly more than bench/loops.py's FALSE_CLOSURE_M apart), the ATE (SE(3)-aligned RMSE) of the
odometry and of the loop-closed poses, this process's resident memory before the stage and its peak
(ru_maxrss: the stage's peak, the process holding little else), and the load average before / after.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import print_table, run_pa  # noqa: E402
from bench.loops import false_closures  # noqa: E402

DRIFT_YAW_DEG = 0.004  # heading drift per scan of the stand-in odometry (deg)
DRIFT_STEP_M = 0.003  # sideways drift per scan of the stand-in odometry (m)


def drifted(T_true: np.ndarray) -> np.ndarray:
    """The true poses with a steady heading drift and a lateral drift per scan compounded along the path."""
    steps = np.linalg.inv(T_true[:-1]) @ T_true[1:]
    c, s = np.cos(np.deg2rad(DRIFT_YAW_DEG)), np.sin(np.deg2rad(DRIFT_YAW_DEG))
    error = np.eye(4)
    error[:2, :2] = [[c, -s], [s, c]]
    error[1, 3] = DRIFT_STEP_M
    out = [T_true[0]]
    for step in steps:
        out.append(out[-1] @ step @ error)
    return np.array(out)


def odometry(data: Path, kind: str) -> np.ndarray:
    """The kept odometry of `data` (computed and kept on the first call)."""
    from pa_cli.config import load_config
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.refine.odometry import run_kiss_icp
    from pa_cli.sources import open_source

    kept = data.parent / f"{data.name}_{kind}_odometry.npy"
    if kept.is_file():
        return np.load(kept)
    if kind == "kiss":
        config = load_config("outdoor")
        T = run_kiss_icp(open_source(data / "scans"), config.sensor, config.advanced.kiss_icp)
    else:
        T = drifted(read_trajectory(data / "gt_poses_kitti.txt").T_world_scan)
    np.save(kept, T)
    return T


def ate_m(T_true: np.ndarray, T_est: np.ndarray) -> float:
    """ATE (m, SE(3)-aligned RMSE; `pa_cli.evaluation.evaluate`) of `T_est` against `T_true`."""
    from pa_cli.evaluation import evaluate
    from pa_cli.io.trajectory import Trajectory

    return float(evaluate(Trajectory(T_true), Trajectory(T_est), align="se3")["ate_rmse_m"])


def _count_preparations() -> list[int]:
    """Count the calls of `prepare_local_map` wherever the loop modules name it; the counter (one element)."""
    import importlib
    import pkgutil

    import pa_cli.loops
    from pa_cli.loops import verification

    count = [0]
    original = verification.prepare_local_map

    def counted(*args, **kwargs):
        count[0] += 1
        return original(*args, **kwargs)

    for info in pkgutil.iter_modules(pa_cli.loops.__path__):
        module = importlib.import_module(f"pa_cli.loops.{info.name}")
        if getattr(module, "prepare_local_map", None) is original:
            module.prepare_local_map = counted
    return count


def _cpu_s() -> float:
    import psutil

    process = psutil.Process()
    total = sum(process.cpu_times()[:2])
    for child in process.children(recursive=True):
        try:
            total += sum(child.cpu_times()[:2])
        except psutil.Error:
            continue
    return total


def run_stage(data: Path, T_odometry: np.ndarray, workers: int, profile: Path | None) -> dict:
    """Run the loop stage on `data`'s scans from `T_odometry`; its figures."""
    import psutil

    import pa_cli
    from pa_cli.config import load_config
    from pa_cli.config.model import ExecutionConfig
    from pa_cli.io.trajectory import read_trajectory
    from pa_cli.loops import close_loops
    from pa_cli.runtime.distributed import execution
    from pa_cli.sources import PointsView, open_source

    config = load_config("outdoor")
    count = _count_preparations()
    rss_before_gb = psutil.Process().memory_info().rss / 1e9
    points = PointsView(open_source(data / "scans"))
    load_before = os.getloadavg()[0]
    with execution(ExecutionConfig(workers=workers)):
        cpu0, wall0 = _cpu_s(), time.perf_counter()
        profiler = cProfile.Profile() if profile else None
        if profiler:
            profiler.enable()
        result = close_loops(points, T_odometry, config.advanced.loops, config.loops.min_separation_m,
                             threads=config.execution.threads)
        if profiler:
            profiler.disable()
            profiler.dump_stats(profile)
        cpu_s, wall_s = _cpu_s() - cpu0, time.perf_counter() - wall0
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    T_true = read_trajectory(data / "gt_poses_kitti.txt").T_world_scan
    report = result.report()
    return {"code": str(Path(pa_cli.__file__).parents[1]), "cpu_s": cpu_s, "wall_s": wall_s,
            "maps": report["n_local_maps"], "preparations": count[0], "candidates": report["n_candidates"],
            "closures": report["n_closures"], "false": false_closures(report["closures"], T_true),
            "ate": f"{ate_m(T_true, T_odometry):.3f} -> {ate_m(T_true, result.T_world_scan):.3f}",
            "RSS before / peak GB": f"{rss_before_gb:.2f} / {peak_gb:.2f}",
            "load": f"{load_before:.1f} / {os.getloadavg()[0]:.1f}"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=1000)
    parser.add_argument("--beams", type=int, default=16)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--odometry", choices=["kiss", "drift"], default="kiss")
    parser.add_argument("--workers", type=int, default=0, help="dask worker processes (0: in-process)")
    parser.add_argument("--keep", type=Path, required=True, help="keep (and reuse) the data and odometry here")
    parser.add_argument("--profile", type=Path, default=None, help="write the stage's cProfile stats here")
    args = parser.parse_args()
    args.keep.mkdir(parents=True, exist_ok=True)
    data = args.keep / f"town_circuit_{args.scans}_b{args.beams}_seed{args.seed}"
    if not (data / "meta.json").is_file():
        run_pa("simulate", "town", data, "--path", "circuit", "--scans", args.scans, "--beams", args.beams,
               "--seed", args.seed, "--force")
    T_odometry = odometry(data, args.odometry)
    row = run_stage(data, T_odometry, args.workers, args.profile)
    header = list(row)
    print_table(f"loop stage, {args.scans} scans, {args.beams} beams, {args.odometry} odometry, --workers "
                f"{args.workers}", header, [[f"{v:.1f}" if isinstance(v, float) else v for v in row.values()]])


if __name__ == "__main__":
    main()
