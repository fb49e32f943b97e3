"""Benchmark `pa simulate`: scans per second for 32 beams x 1024 azimuth steps on both scenes.

Run: PYTHONPATH=. python bench/simulate.py [--runs 5] [--scans 40]
"cast" times `Simulator.scan` (ray casting, labels, noise, intensity); "end-to-end" times
`simulate()` writing the whole output folder (PCD + labels + poses). Medians over runs.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from pa_cli.simulate import SimOptions, Simulator, simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--scans", type=int, default=40)
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}, rays per scan: 32 x 1024 = 32768, {args.scans} scans per run, "
          f"median of {args.runs} runs")
    header = f"| {'scene':7} | {'distortion':10} | {'triangles':9} | {'points/scan':11} | " \
             f"{'cast scans/s':12} | {'end-to-end scans/s':18} |"
    print(header)
    print("|---------|------------|-----------|-------------|--------------|--------------------|")
    for scene in ("office", "street"):
        for distortion in (False, True):
            opts = SimOptions(scene=scene, scans=args.scans, beams=32, azimuth_steps=1024,
                              motion_distortion=distortion)
            sim = Simulator(opts)
            sim.scan(0)  # warm up
            cast_rates, e2e_rates, n_points = [], [], []
            for _ in range(args.runs):
                t0 = time.perf_counter()
                for k in range(args.scans):
                    n_points.append(len(sim.scan(k).labels))
                cast_rates.append(args.scans / (time.perf_counter() - t0))
                with tempfile.TemporaryDirectory() as tmp:
                    t0 = time.perf_counter()
                    simulate(opts, Path(tmp) / "out")
                    e2e_rates.append(args.scans / (time.perf_counter() - t0))
            print(f"| {scene:7} | {'on' if distortion else 'off':10} | {len(sim.scene.mesh.triangles):9d} | "
                  f"{int(np.mean(n_points)):11d} | {np.median(cast_rates):12.1f} | {np.median(e2e_rates):18.1f} |")


if __name__ == "__main__":
    main()
