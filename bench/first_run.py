"""The first run against the warm run of `pa refine`: numba compiles the kernels a run uses once and
caches them (`pa_cli.runtime.numba_cache`); this times a run with an empty cache (cold) and the run
after it (warm, the kernels loaded from the cache) in fresh processes. Prints tables; never a timed
assertion.

Each repeat makes a new temporary cache folder (NUMBA_CACHE_DIR), runs `pa refine` in it (cold),
then again (warm), back to back, so both see about the same load of the machine. Wall time of the
process (imports included) and the report's stage times (`stage_times_s`); medians over the repeats,
the 1-minute load average before and after.

    PYTHONPATH=. python bench/first_run.py                    # sample_data/office, 3 repeats
    PYTHONPATH=. python bench/first_run.py --repeats 5
    PYTHONPATH=. python bench/first_run.py --scans DIR --config outdoor [--gt POSES]   # other data
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import REPO, print_table  # noqa: E402

OFFICE = REPO / "sample_data" / "office"


def run_refine(scans: Path, config: str, gt: Path | None, out: Path, cache_dir: Path) -> tuple[float, dict]:
    """Wall time (s) of `pa refine` in a fresh process with numba's cache in cache_dir, and its report."""
    args = [sys.executable, "-m", "pa_cli", "refine", str(scans), "--out", str(out), "--config", config, "--force"]
    if gt is not None:
        args += ["--gt", str(gt)]
    env = dict(os.environ, PYTHONPATH=str(REPO), NUMBA_CACHE_DIR=str(cache_dir))
    t0 = time.perf_counter()
    proc = subprocess.run(args, env=env, capture_output=True, text=True, cwd=REPO)  # this checkout's pa_cli
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"pa refine failed:\n{proc.stderr}")
    report = json.loads(out.with_name(out.stem + "_report.json").read_text())
    return wall, report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=Path, default=OFFICE / "scans")
    parser.add_argument("--config", default="indoor")
    parser.add_argument("--gt", type=Path, default=None, help="ground truth (default: the office's with its scans)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    gt = args.gt if args.gt is not None or args.scans != OFFICE / "scans" else OFFICE / "gt_poses_tum.txt"

    load_before = os.getloadavg()[0]
    runs: dict[str, list[tuple[float, dict]]] = {"cold": [], "warm": []}
    with tempfile.TemporaryDirectory(prefix="pa-first-run-") as tmp:
        for k in range(args.repeats):
            cache_dir = Path(tmp) / f"numba-{k}"  # empty: every kernel is compiled
            for kind in ("cold", "warm"):
                runs[kind].append(run_refine(args.scans, args.config, gt, Path(tmp) / f"{kind}.ply", cache_dir))
                print(f"repeat {k + 1}/{args.repeats} {kind}: {runs[kind][-1][0]:.1f} s", file=sys.stderr, flush=True)
    load_after = os.getloadavg()[0]

    def median_wall(kind: str) -> float:
        return statistics.median(wall for wall, _ in runs[kind])

    def median_stage(kind: str, stage: str) -> float:
        return statistics.median(report["stage_times_s"].get(stage, 0.0) for _, report in runs[kind])

    cold, warm = median_wall("cold"), median_wall("warm")
    print_table(f"pa refine {args.scans} (config {Path(args.config).name}): first run (empty numba cache) and "
                f"second run, medians of {args.repeats}; load {load_before:.1f} before, {load_after:.1f} after "
                f"({os.cpu_count()} cores)",
                ["run", "cold s", "warm s", "cold / warm"],
                [["wall (process)", f"{cold:.1f}", f"{warm:.1f}", f"{cold / warm:.2f}"],
                 *[[f"per repeat {k + 1}", f"{c[0]:.1f}", f"{w[0]:.1f}", f"{c[0] / w[0]:.2f}"]
                   for k, (c, w) in enumerate(zip(runs["cold"], runs["warm"], strict=True))]])
    stages = list(dict.fromkeys(s for _, report in runs["cold"] + runs["warm"] for s in report["stage_times_s"]))
    print_table("per stage (report stage_times_s, medians)", ["stage", "cold s", "warm s", "cold - warm s"],
                [[s, f"{median_stage('cold', s):.2f}", f"{median_stage('warm', s):.2f}",
                  f"{median_stage('cold', s) - median_stage('warm', s):.2f}"] for s in stages])


if __name__ == "__main__":
    main()
