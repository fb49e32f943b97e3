"""Big inputs: the start of a run on a folder of many scan files, and the peak memory of reading one
very large scan. Prints tables; never a timed assertion.

- `folder`: writes N tiny scan files (one point each) per format into a temporary folder, then times,
  each in a fresh process (cold imports included): opening the source (`open_source`: listing,
  natural sort, the skip of pa's own maps), the header check of every file (`check()`, the
  `load` step's first half) and reading every scan once (the screen of `pa_cli.sources.screen`,
  the `load` step's second half).
- `scan`: writes one scan of P points (a PCD), then runs `pa refine` on a folder of S copies of it
  (shifted) and reports the process's peak RSS and the report's per-stage peak RSS.

    PYTHONPATH=. python bench/big_inputs.py folder --n 100000
    PYTHONPATH=. python bench/big_inputs.py scan --points 2000000 --scans 3
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import REPO, print_table  # noqa: E402

TIMED = """
import sys, time
t0 = time.perf_counter()
from pa_cli.sources import open_source
t1 = time.perf_counter()
source = open_source(sys.argv[1])
t2 = time.perf_counter()
source.check()
t3 = time.perf_counter()
for k in range(len(source)):
    source.points(k)
t4 = time.perf_counter()
print(len(source), t1 - t0, t2 - t1, t3 - t2, t4 - t3)
"""


def write_tiny_scans(folder: Path, n: int, suffix: str) -> None:
    """N one-point scans named 0..N-1 (unsorted on disk: written in a shuffled order)."""
    from pa_cli.io.scans import write_pcd

    folder.mkdir()
    point = np.array([[1.0, 2.0, 3.0]], dtype=np.float32)
    template = folder / f"template{suffix}"
    if suffix == ".pcd":
        write_pcd(template, point)
    else:
        np.column_stack([point, np.zeros(1, np.float32)]).tofile(template)
    data = template.read_bytes()
    template.unlink()
    for k in np.random.default_rng(0).permutation(n):
        (folder / f"{k}{suffix}").write_bytes(data)


def bench_folder(n: int) -> None:
    rows = []
    for suffix in (".bin", ".pcd"):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "scans"
            write_tiny_scans(folder, n, suffix)
            env = dict(os.environ, PYTHONPATH=str(REPO))
            out = subprocess.run([sys.executable, "-c", TIMED, str(folder)], env=env, capture_output=True, text=True,
                                 check=True).stdout.split()
            count, imports_s, open_s, check_s, read_s = int(out[0]), *map(float, out[1:])
            rows.append([f"{count:,}", suffix, f"{imports_s:.2f}", f"{open_s:.2f}", f"{check_s:.2f}", f"{read_s:.2f}"])
    print_table(f"A folder of {n:,} one-point scan files (s, one process each, page cache warm)",
                ["files", "format", "imports", "open_source (list, sort)", "check (headers)", "read every scan"],
                rows)


def bench_scan(n_points: int, n_scans: int) -> None:
    from pa_cli.io.scans import write_pcd

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "scans"
        folder.mkdir()
        # a room-sized box of points on its six walls: planes for the rounds, structure for the odometry
        base = rng.uniform(-10, 10, size=(n_points, 3))
        axis = rng.integers(0, 3, n_points)
        base[np.arange(n_points), axis] = np.where(rng.random(n_points) < 0.5, -10.0, 10.0)
        base[:, 2] *= 0.3
        for k in range(n_scans):
            write_pcd(folder / f"{k:03d}.pcd", base - [0.05 * k, 0.0, 0.0] + rng.normal(scale=0.01, size=base.shape))
        out = Path(tmp) / "out" / "map.ply"
        out.parent.mkdir()
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pa_cli", "refine", str(folder), "--out", str(out),
                               "--config", "indoor", "--rounds", "2", "-q"],
                              env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
        wall_s = time.perf_counter() - start
        peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6
        if proc.returncode != 0:
            print(proc.stderr)
            raise SystemExit(f"pa refine failed with exit code {proc.returncode}")
        report = json.loads((out.parent / "map_report.json").read_text())
    rows = [[stage, f"{gb:.2f}"] for stage, gb in report["stage_peak_rss_gb"].items()]
    print_table(f"pa refine on {n_scans} scans of {n_points:,} points: {wall_s:.0f} s, peak RSS {peak_gb:.2f} GB",
                ["stage", "peak RSS after the stage (GB)"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    folder = sub.add_parser("folder")
    folder.add_argument("--n", type=int, default=100_000)
    scan = sub.add_parser("scan")
    scan.add_argument("--points", type=int, default=2_000_000)
    scan.add_argument("--scans", type=int, default=3)
    args = parser.parse_args()
    if args.what == "folder":
        bench_folder(args.n)
    else:
        bench_scan(args.points, args.scans)


if __name__ == "__main__":
    main()
