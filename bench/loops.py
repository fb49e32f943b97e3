"""Benchmark of the loop stage on simulated sequences that revisit places (prints a table).

    python bench/loops.py                         # town circuit, 1,000 scans, 32 beams
    python bench/loops.py --scans 1000 3000 --path figure8 --seed 7 --keep /tmp/loops

Per sequence: `pa simulate town` (kept with --keep and reused when present), then one
`pa refine --config outdoor --gt ... --loops` in a subprocess (the backend is the
one `pa refine` picks: hierarchical from advanced.solver.hierarchical_min_scans scans). The table holds
the ATE (SE(3)-aligned RMSE) of KISS-ICP alone (`gt.odometry`), after the loop stage
(`gt.initial`) and after the rounds (`gt.refined`); wall and CPU time of the odometry, the loop
stage and the rounds (planes + adjust); the closures, and how many join anchor scans truly more
than FALSE_CLOSURE_M apart (false); the peak RSS after each of those stages and of the whole
run; and the wall thickness (see `wall_thickness`) of walls seen on two passes
against the same walls seen on one, under the refined poses. Acceptance: refined ATE <= 0.3 m
and <= 1/20 of KISS-ICP's; loop stage time <= odometry time; thickness ratio <= 2; no false closure.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import run_pa, run_pa_measured  # noqa: E402

WALL_MAX_NORMAL_Z = 0.5  # a true plane is a wall when its normal is within 60 deg of horizontal
WALL_TILE_M = 20.0  # walls are cut into tiles of this size (true world x-y): one tile is one physical place
MIN_VISIT_POINTS = 200  # points one visit of a tile needs for a thickness (a 20 m tile gets thousands)
REVISIT_GAP_M = 100.0  # true path since a tile was last seen after which a sighting is a new pass
# A closure is false when its two anchor scans are truly farther apart than this: a true revisit's anchors lie within
# about a local map's length (10 m) of each other, a look-alike place is a block (56 m or more) away.
FALSE_CLOSURE_M = 30.0


def _thickness_m(count: np.ndarray, total: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """RMS distance (m) of points to their own best-fit plane, from count, sum and sum of outer products."""
    mean = total / count[:, None]
    scatter = outer / count[:, None, None] - np.einsum("ni,nj->nij", mean, mean)
    return np.sqrt(np.maximum(np.linalg.eigvalsh(scatter)[:, 0], 0.0))


def wall_thickness(frames: Iterable[tuple[np.ndarray, np.ndarray]], planes: np.ndarray, T_true: np.ndarray,
                   estimates: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Plane thickness of the walls seen on two passes against the same walls seen on one, per estimate.

    `frames` yields, per scan, its points (sensor frame, m) and their true plane labels (-1 none);
    `planes` (L, 4) are the true planes; `T_true` and each estimate are T_world_scan (N, 4, 4).
    A wall tile is a true vertical plane cut into WALL_TILE_M x-y tiles (by the points' true
    positions); its sightings split into passes where the true path since the previous sighting
    exceeds REVISIT_GAP_M. The thickness of a set of points is their RMS distance to their own
    best-fit plane (sqrt of the smallest scatter eigenvalue), so it measures how well the estimate
    stacks the scans on one surface, free of the alignment to the truth. Per estimate: over the
    tiles with two or more passes of MIN_VISIT_POINTS points, the median thickness of all their
    points (`revisited_m`), the median of the mean single-pass thickness (`once_m`), and the median
    and 90th percentile of the per-tile ratio of the two; `n_tiles` counts the tiles.
    """
    is_wall = np.abs(planes[:, 2]) < WALL_MAX_NORMAL_Z
    tiles: dict[tuple[int, int, int], int] = {}
    rows_tile, rows_scan, rows_count = [], [], []
    rows_sums: dict[str, list[np.ndarray]] = {name: [] for name in estimates}
    rows_outer: dict[str, list[np.ndarray]] = {name: [] for name in estimates}
    for k, (points, labels) in enumerate(frames):
        keep = labels >= 0
        keep[keep] = is_wall[labels[keep]]
        points, labels = np.asarray(points, dtype=np.float64)[keep], labels[keep]
        if len(points) == 0:
            continue
        true_world = points @ T_true[k, :3, :3].T + T_true[k, :3, 3]
        keys = np.column_stack([labels, np.floor(true_world[:, :2] / WALL_TILE_M).astype(np.int64)])
        unique_keys, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        ids = np.array([tiles.setdefault(tuple(int(v) for v in key), len(tiles)) for key in unique_keys])
        # Coordinates relative to the tile's centre keep the sums of squares well conditioned.
        origin = np.column_stack([(unique_keys[:, 1:] + 0.5) * WALL_TILE_M, np.zeros(len(unique_keys))])
        rows_tile.append(ids)
        rows_scan.append(np.full(len(ids), k))
        rows_count.append(np.bincount(inverse, minlength=len(ids)).astype(np.float64))
        for name, T in estimates.items():
            local = points @ T[k, :3, :3].T + T[k, :3, 3] - origin[inverse]
            sums = np.zeros((len(ids), 3))
            outer = np.zeros((len(ids), 3, 3))
            np.add.at(sums, inverse, local)
            np.add.at(outer, inverse, np.einsum("ni,nj->nij", local, local))
            rows_sums[name].append(sums)
            rows_outer[name].append(outer)
    tile, scan, count = (np.concatenate(rows) for rows in (rows_tile, rows_scan, rows_count))
    path_m = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(T_true[:, :3, 3], axis=0), axis=1))]
    # Rows are in scan order; sorted by tile (stable) each tile's sightings stay in scan order.
    order = np.argsort(tile, kind="stable")
    tile, scan, count = tile[order], scan[order], count[order]
    new_tile = np.r_[True, tile[1:] != tile[:-1]]
    new_pass = new_tile | np.r_[True, np.diff(path_m[scan]) > REVISIT_GAP_M]
    pass_id = np.cumsum(new_pass) - 1
    pass_tile = tile[new_pass]
    pass_count = np.bincount(pass_id, weights=count)
    out = {}
    for name in estimates:
        sums = np.concatenate(rows_sums[name])[order]
        outer = np.concatenate(rows_outer[name])[order]
        pass_sums = np.zeros((len(pass_tile), 3))
        pass_outer = np.zeros((len(pass_tile), 3, 3))
        np.add.at(pass_sums, pass_id, sums)
        np.add.at(pass_outer, pass_id, outer)
        good = pass_count >= MIN_VISIT_POINTS
        n_good = np.bincount(pass_tile[good], minlength=len(tiles))
        revisited = np.flatnonzero(n_good >= 2)
        chosen = good & np.isin(pass_tile, revisited)
        once = _thickness_m(pass_count[chosen], pass_sums[chosen], pass_outer[chosen])
        once_mean = np.bincount(pass_tile[chosen], weights=once, minlength=len(tiles))[revisited] / n_good[revisited]
        tile_count = np.bincount(pass_tile[chosen], weights=pass_count[chosen], minlength=len(tiles))[revisited]
        tile_sums = np.zeros((len(tiles), 3))
        tile_outer = np.zeros((len(tiles), 3, 3))
        np.add.at(tile_sums, pass_tile[chosen], pass_sums[chosen])
        np.add.at(tile_outer, pass_tile[chosen], pass_outer[chosen])
        together = _thickness_m(tile_count, tile_sums[revisited], tile_outer[revisited])
        ratio = together / np.maximum(once_mean, np.finfo(float).tiny)
        out[name] = {"n_tiles": len(revisited), "revisited_m": float(np.median(together)) if len(ratio) else np.nan,
                     "once_m": float(np.median(once_mean)) if len(ratio) else np.nan,
                     "ratio_median": float(np.median(ratio)) if len(ratio) else np.nan,
                     "ratio_p90": float(np.percentile(ratio, 90)) if len(ratio) else np.nan}
    return out


def _frames(data: Path) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Points and true plane labels of each simulated scan, in order."""
    from pa_cli.io.scans import ScanFolder

    scans = ScanFolder(data / "scans")
    for k in range(len(scans)):
        yield np.asarray(scans.points[k]), np.load(data / "labels" / f"{k:06d}.npy")


def _stage_sum(table: dict[str, float], prefixes: tuple[str, ...]) -> float:
    return sum(v for k, v in table.items() if k.startswith(prefixes))


_ROUNDS = ("planes", "adjust")  # the refine stages: association and adjustment rounds


def false_closures(closures: list[list[int]], T_true: np.ndarray) -> int:
    """Accepted closures (ref_scan, query_scan) whose anchor scans are truly more than FALSE_CLOSURE_M apart."""
    pairs = np.array(closures, dtype=np.int64).reshape(-1, 2)
    return int(np.sum(np.linalg.norm(T_true[pairs[:, 0], :3, 3] - T_true[pairs[:, 1], :3, 3], axis=1)
                      > FALSE_CLOSURE_M))


def _row(data: Path, out: Path, scans: int, peak_gb: float, config: str) -> list:
    from pa_cli.adjust.hierarchical import choose_backend
    from pa_cli.config import load_config
    from pa_cli.io.trajectory import read_trajectory

    report = json.loads(out.with_name(out.stem + "_report.json").read_text())
    meta = json.loads((data / "meta.json").read_text())
    gt = report["gt"]
    wall, cpu, rss = (report[key] for key in ("stage_times_s", "stage_cpu_s", "stage_peak_rss_gb"))
    kiss, loops, refined = (gt[key]["ate_rmse_m"] for key in ("odometry", "initial", "refined"))
    estimates = {name: read_trajectory(out.with_name(out.stem + suffix)).T_world_scan
                 for name, suffix in (("loops", "_initial_poses_kitti.txt"), ("refined", "_poses_kitti.txt"))}
    T_true = read_trajectory(data / "gt_poses_kitti.txt").T_world_scan
    thick = wall_thickness(_frames(data), np.load(data / "planes.npy"), T_true, estimates)
    n_false = false_closures(report["loops"]["closures"], T_true)
    rounds_rss = max((v for k, v in rss.items() if k.startswith(_ROUNDS)), default=float("nan"))
    checks = [refined <= 0.3, refined <= kiss / 20, wall["loops"] <= wall["odometry"],
              thick["refined"]["ratio_median"] <= 2, n_false == 0]
    backend = choose_backend(load_config(config).advanced.solver, scans)[0].solver
    return [f"{meta['scene']} {meta['options']['path']}", meta["options"]["seed"], scans,
            f"{kiss:.3f}", f"{loops:.3f}", f"{refined:.3f}",
            f"{wall['odometry']:.0f} / {cpu['odometry']:.0f}", f"{wall['loops']:.0f} / {cpu['loops']:.0f}",
            f"{_stage_sum(wall, _ROUNDS):.0f} / {_stage_sum(cpu, _ROUNDS):.0f}",
            f"{report['loops']['n_closures']}/{report['loops']['n_candidates']} ({n_false})",
            f"{rss['odometry']:.2f} / {rss['loops']:.2f} / {rounds_rss:.2f} ({peak_gb:.2f})",
            f"{1000 * thick['refined']['revisited_m']:.1f} / {1000 * thick['refined']['once_m']:.1f} "
            f"({thick['refined']['n_tiles']})",
            f"{thick['loops']['ratio_median']:.2f} -> {thick['refined']['ratio_median']:.2f} "
            f"(p90 {thick['refined']['ratio_p90']:.2f})", backend,
            " ".join("yes" if c else "NO" for c in checks)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, nargs="+", default=[1000])
    parser.add_argument("--scene", default="town")
    parser.add_argument("--path", default="circuit")
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--seed", type=int, default=3, help="simulator seed (the range noise)")
    parser.add_argument("--keep", type=Path, default=None, help="keep (and reuse) the simulated data here")
    parser.add_argument("--reuse", action="store_true",
                        help="with --keep: tabulate a kept refine run instead of running it again")
    parser.add_argument("--config", default="outdoor", help="a preset or a YAML config file")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="pa_bench_loops_"))
    work.mkdir(parents=True, exist_ok=True)
    header = ["sequence", "seed", "scans", "ATE KISS-ICP (m)", "ATE loops (m)", "ATE refined (m)",
              "odometry wall / CPU (s)", "loops wall / CPU (s)", "rounds wall / CPU (s)", "closures/candidates (false)",
              "peak RSS after odometry / loops / rounds (whole run) (GB)",
              "wall thickness revisited / once, refined (mm) (tiles)", "thickness ratio loops -> refined",
              "backend", "refined<=0.3, <=KISS/20, loops<=odometry, thickness<=2x, no false closure"]
    rows = []
    for scans in args.scans:
        data = work / f"{args.scene}_{args.path}_{scans}_seed{args.seed}"
        if not (data / "meta.json").is_file():
            run_pa("simulate", args.scene, data, "--path", args.path, "--scans", scans, "--beams", args.beams,
                "--seed", args.seed, "--force")
        out = work / f"{data.name}_refined" / "map.ply"
        out.parent.mkdir(exist_ok=True)
        if args.reuse and out.with_name(out.stem + "_report.json").is_file():
            peak_gb = json.loads(out.with_name(out.stem + "_report.json").read_text())["stage_peak_rss_gb"]["write"]
        else:
            peak_gb = run_pa_measured("refine", data / "scans", "--out", out, "--config", args.config,
                                      "--gt", data / "gt_poses_tum.txt", "--loops", "--force", "-q").peak_gb
        rows.append(_row(data, out, scans, peak_gb, args.config))
        print(" | ".join(map(str, rows[-1])), flush=True)
    print(f"\nload average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("\n| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(map(str, row)) + " |")


if __name__ == "__main__":
    main()
