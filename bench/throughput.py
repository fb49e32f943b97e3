"""Throughput of `pa refine` stage by stage, against the odometry's own time (prints tables).

    python bench/throughput.py                                  # 100 and 1,000 scans, 16 and 32 beams, real data
    python bench/throughput.py --scans 5000 10000 --beams 32 --no-real --keep DIR
    python bench/throughput.py --workers 2 --no-loops

Per simulated sequence: `pa simulate town --path circuit --seed 3` (a 467 m lap of a grid of
blocks at 1 m a scan: 100 scans drive a fifth of it and revisit nothing, 1,000 scans drive it
2.1 times), kept with --keep and reused when present; then one `pa refine --config outdoor --gt
... --loops` in a child process of its own. Per real sequence of ../shared/data
(balm-campus-30, kaist03-21; neither revisits a place): the same refine without --gt.

The stage times come from the run's report (`stage_times_s`: wall; `stage_cpu_s`: CPU of the
refine process, all its threads, and of the processes a stage joined (the pair registrations'
pool), not of dask workers); the stages of the rounds (planes N, adjust N, ...) are summed under
their name. Per stage: wall and CPU seconds, each as a multiple of the odometry's, the scans per
second (scans / wall), and the refine process's peak RSS at the stage's end. The process itself is
measured from outside (`bench.common.run_pa_measured`: wall from its start to its end, CPU of it and
the processes it waited for, its process tree's peak memory): the total row; the row "start-up,
between stages" is what the stages do not hold (the interpreter's start-up and imports, the work
between them); "after the odometry" is the total but the load and the odometry. A second table
holds the loop stage's outcome on the simulated sequences: closures / candidates, false
closures (anchor scans truly more than FALSE_CLOSURE_M apart), and the ATE (SE(3)-aligned) of the
odometry, of the loop-closed poses and of the refined poses. The load average is printed before
and after each run: the machine may be shared.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import Measured, markdown_table, run_pa, run_pa_measured, shared_sequences  # noqa: E402
from bench.loops import false_closures  # noqa: E402

REAL = ("balm-campus-30", "kaist03-21")
STAGE_COLUMNS = ["sequence", "scans", "stage", "wall s", "CPU s", "wall x odometry", "CPU x odometry", "scans/s",
                 "peak RSS GB", "load before / after"]


def stage_totals(report: dict) -> dict[str, tuple[float, float, float]]:
    """(wall s, CPU s, peak RSS GB) per stage name, a stage run in several rounds ("planes 2") summed
    under its name ("planes"), in the order the stages first ran."""
    totals: dict[str, tuple[float, float, float]] = {}
    for name, wall in report["stage_times_s"].items():
        base = re.sub(r" \d+$", "", name)
        before = totals.get(base, (0.0, 0.0, 0.0))
        totals[base] = (before[0] + wall, before[1] + report["stage_cpu_s"][name],
                        max(before[2], report["stage_peak_rss_gb"][name]))
    return totals


def stage_rows(sequence: str, report: dict, run: Measured, loads: str) -> list[list]:
    """The rows of one run in the stage table (STAGE_COLUMNS): its stages; the rest of the process's time (the
    interpreter's start-up and imports, the work between the stages); everything after the odometry (the
    process's time but the load and the odometry); the process's total last."""
    n_scans = report["input"]["n_scans"]
    totals = stage_totals(report)
    odometry_wall, odometry_cpu = totals["odometry"][:2]
    rows = []

    def row(name: str, wall: float, cpu: float, rss: float | str) -> None:
        rows.append([sequence, n_scans, name, wall, cpu, wall / odometry_wall, cpu / odometry_cpu,
                     n_scans / wall if wall > 0 else float("inf"), rss, loads])

    for name, (wall, cpu, rss) in totals.items():
        row(name, wall, cpu, rss)
    staged_wall, staged_cpu = (sum(t[i] for t in totals.values()) for i in (0, 1))
    row("start-up, between stages", run.wall_s - staged_wall, run.cpu_s - staged_cpu, "")
    row("**after the odometry**", run.wall_s - totals["load"][0] - odometry_wall,
        run.cpu_s - totals["load"][1] - odometry_cpu, "")
    row("**total**", run.wall_s, run.cpu_s, run.peak_gb)
    return rows


def _load() -> str:
    return f"{os.getloadavg()[0]:.1f}"


def _refine(scans: Path, out: Path, extra: list[object], loops: bool, workers: int) -> tuple[dict, Measured, str]:
    """Run `pa refine` on `scans`; its report, its process's peak RSS, wall and CPU, and the load average
    before / after."""
    out.parent.mkdir(parents=True, exist_ok=True)
    before = _load()
    run = run_pa_measured("refine", scans, "--out", out, "--config", "outdoor", *extra,
                          "--loops" if loops else "--no-loops", "--workers", workers, "--force", "-q")
    report = json.loads(out.with_name(out.stem + "_report.json").read_text())
    return report, run, f"{before} / {_load()}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--beams", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--workers", type=int, default=0, help="dask worker processes of pa refine (0: in-process)")
    parser.add_argument("--no-loops", dest="loops", action="store_false", help="run pa refine with --no-loops")
    parser.add_argument("--no-real", dest="real", action="store_false", help="skip the sequences of ../shared/data")
    parser.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the simulated data here")
    args = parser.parse_args()
    from pa_cli.io.trajectory import read_trajectory

    work = args.keep or Path(tempfile.mkdtemp(prefix="pa_bench_throughput_"))
    work.mkdir(parents=True, exist_ok=True)
    stage_table, loop_table = [], []
    for beams in args.beams:
        for scans in args.scans:
            data = work / f"town_circuit_{scans}_b{beams}"
            if not (data / "meta.json").is_file():
                run_pa("simulate", "town", data, "--path", "circuit", "--scans", scans, "--beams", beams,
                       "--seed", 3, "--force")
            name = f"town {beams} beams"
            report, run, loads = _refine(data / "scans", work / f"{data.name}_refined" / "map.ply",
                                             ["--gt", data / "gt_poses_tum.txt"], args.loops, args.workers)
            rows = stage_rows(name, report, run, loads)
            markdown_table(f"{name}, {scans} scans", STAGE_COLUMNS, rows)
            stage_table += rows
            if args.loops:
                T_true = read_trajectory(data / "gt_poses_kitti.txt").T_world_scan
                gt, loops = report["gt"], report["loops"]
                loop_table.append([name, scans, f"{loops['n_closures']} / {loops['n_candidates']}",
                                   false_closures(loops["closures"], T_true),
                                   *(gt[key]["ate_rmse_m"] for key in ("odometry", "initial", "refined")), loads])
    if args.real:
        for name, folder in shared_sequences(REAL):
            report, run, loads = _refine(folder / "scans", work / f"{name}_refined" / "map.ply", [],
                                             args.loops, args.workers)
            stage_table += stage_rows(name, report, run, loads)
    markdown_table(f"Stages of pa refine ({'--loops' if args.loops else '--no-loops'}, --workers {args.workers})",
                   STAGE_COLUMNS, stage_table)
    if loop_table:
        markdown_table("Loop stage outcome", ["sequence", "scans", "closures / candidates", "false closures",
                                              "ATE odometry m", "ATE loops m", "ATE refined m", "load before / after"],
                       loop_table)


if __name__ == "__main__":
    main()
