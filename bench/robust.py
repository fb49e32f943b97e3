"""Trustworthy refinement on realistic scans: the acceptance table (prints tables; no assertions).

    PYTHONPATH=. python bench/robust.py                      # everything (slow: ~25 refine runs)
    PYTHONPATH=. python bench/robust.py sims --seeds 0 1     # a reduced run while developing
    PYTHONPATH=. python bench/robust.py real | broken

- sims: `pa simulate` street 16 beams without and with --motion-distortion, 32 beams with it
  (configs/outdoor.yaml) and office 16 beams with it (configs/indoor.yaml); default step, --scans
  (60) scans, every --seeds. Per run: ATE (SE(3)-aligned) of KISS-ICP and of `pa refine`, their
  ratio (acceptance: <= 0.5 and never above 1), the RMS point-to-plane on the last association at
  the true poses and at the KISS-ICP poses, each with the points deskewed by its own trajectory
  (acceptance with distortion: truth below KISS-ICP), the verdict and whether the rounds settled.
- real: kaist03-21 and balm-campus-30 (../shared/data or $PA_SHARED_DATA) refined from KISS-ICP
  and from the shipped poses (--poses): ATE between the two refined trajectories (acceptance:
  <= 1 cm), the last round's largest pose change, the verdicts (acceptance: improved).
- broken: a street sequence whose true poses get a 30 deg turn about the vertical halfway
  (acceptance: verdict not improved) or 0.1 deg / 1 cm noise per pose (acceptance: improved),
  given with --poses.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.refine import SHARED, _pa, _report, _table  # noqa: E402

SIM_CASES = (  # name, scene, beams, motion distortion, config
    ("street 16", "street", 16, False, "outdoor"),
    ("street 16 distorted", "street", 16, True, "outdoor"),
    ("street 32 distorted", "street", 32, True, "outdoor"),
    ("office 16 distorted", "office", 16, True, "indoor"),
)


def _refine(scans: Path, out: Path, config: str, *extra: object) -> dict:
    _pa("refine", scans, "--out", out, "--config", REPO / "configs" / f"{config}.yaml", "--force", "-q",
        *extra)
    return _report(out)


def bench_sims(work: Path, seeds: list[int], scans: int) -> None:
    rows = []
    for name, scene, beams, distorted, config in SIM_CASES:
        for seed in seeds:
            data = work / f"{scene}{beams}{'d' if distorted else ''}_{seed}"
            _pa("simulate", scene, data, "--scans", scans, "--beams", beams, "--seed", seed, "--force",
                *(["--motion-distortion"] if distorted else []))
            r = _refine(data / "scans", work / f"{data.name}.ply", config, "--gt", data / "gt_poses_tum.txt")
            ate0, ate1 = r["gt"]["initial"]["ate_rmse_m"], r["gt"]["refined"]["ate_rmse_m"]
            q = r["quality"]
            rows.append([name, seed, f"{ate0:.4f}", f"{ate1:.4f}", f"{ate1 / ate0:.2f}",
                         "yes" if ate1 <= 0.5 * ate0 else "NO",
                         f"{r['gt']['rms_point_to_plane_at_gt_m']:.4f}",
                         f"{r['gt']['rms_point_to_plane_at_initial_m']:.4f}", q["verdict"],
                         "yes" if q["settled"] else "no", r["summary"]["n_rounds"], f"{r['total_time_s']:.0f}"])
    _table(f"Simulated sequences, {scans} scans: ATE (m) of KISS-ICP and pa refine; acceptance ratio <= 0.5; "
           "RMS (m) on the last association at the truth and at the KISS-ICP poses",
           ["case", "seed", "ATE KISS", "ATE refined", "ratio", "<= 1/2", "RMS truth", "RMS KISS", "verdict",
            "settled", "rounds", "time s"], rows)


def bench_real(work: Path) -> None:
    from pa_cli.evaluation import evaluate
    from pa_cli.io.trajectory import Trajectory, read_trajectory

    rows = []
    for name in ("kaist03-21", "balm-campus-30"):
        folder = SHARED / name
        if not folder.is_dir():
            print(f"skip {name}: {folder} not present")
            continue
        shipped = folder / "poses_kitti.txt"
        reports, poses = {}, {}
        for start, extra in (("KISS-ICP", ()), ("shipped", ("--poses", shipped))):
            out = work / f"{name}_{start}.ply"
            reports[start] = _refine(folder / "scans", out, "outdoor", "--gt", shipped, *extra)
            poses[start] = read_trajectory(out.with_name(out.stem + "_poses_kitti.txt")).T_world_scan
        agree = evaluate(Trajectory(poses["shipped"]), Trajectory(poses["KISS-ICP"]), align="se3")["ate_rmse_m"]
        for start, r in reports.items():
            last = r["rounds"][-1]
            rows.append([name, start, f"{agree:.4f}", "yes" if agree <= 0.01 else "NO",
                         f"{r['gt']['initial']['ate_rmse_m']:.4f}", f"{r['gt']['refined']['ate_rmse_m']:.4f}",
                         f"{last['max_pose_change_m']:.4f}", "yes" if r["quality"]["settled"] else "no",
                         r["quality"]["verdict"], len(r["rounds"])])
    _table("Real data from KISS-ICP and from the shipped poses: ATE (m) between the two refined trajectories "
           "(acceptance <= 0.01), ATE vs the shipped poses, last round's largest pose change (m)",
           ["data", "start", "agreement", "<= 1 cm", "ATE start", "ATE refined", "last change m", "settled",
            "verdict", "rounds"], rows)


def _wrong_turn(T: np.ndarray, angle_deg: float) -> np.ndarray:
    """Poses from the middle on turned by angle_deg about the vertical through the middle pose."""
    from scipy.spatial.transform import Rotation

    h = len(T) // 2
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("z", angle_deg, degrees=True).as_matrix()
    pivot = np.eye(4)
    pivot[:3, 3] = T[h, :3, 3]
    turn = pivot @ G @ np.linalg.inv(pivot)
    out = T.copy()
    out[h:] = turn @ T[h:]
    return out


def bench_broken(work: Path, seeds: list[int], scans: int) -> None:
    from pa_cli.evaluation import perturb_poses
    from pa_cli.io.trajectory import format_kitti, read_trajectory

    rows = []
    for seed in seeds:
        data = work / f"street16_broken_{seed}"
        _pa("simulate", "street", data, "--scans", scans, "--beams", 16, "--seed", seed, "--force")
        T_gt = read_trajectory(data / "gt_poses_kitti.txt").T_world_scan
        noisy = perturb_poses(T_gt, np.deg2rad(0.1), 0.01, np.random.default_rng(seed))
        for case, T, expect in (("30 deg wrong turn halfway", _wrong_turn(T_gt, 30.0), "not improved"),
                                ("0.1 deg / 1 cm noise", noisy, "improved")):
            poses = work / f"{data.name}_{case[:4].strip()}.txt"
            poses.write_text(format_kitti(T))
            r = _refine(data / "scans", work / f"{poses.stem}.ply", "outdoor", "--poses", poses,
                        "--gt", data / "gt_poses_kitti.txt")
            verdict = r["quality"]["verdict"]
            met = (verdict == "improved") == (expect == "improved")
            rows.append([case, seed, f"{r['gt']['initial']['ate_rmse_m']:.4f}",
                         f"{r['gt']['refined']['ate_rmse_m']:.4f}", verdict, expect, "yes" if met else "NO",
                         r["quality"]["reasons"][0][:90]])
    _table("Initial poses given with --poses (street, 16 beams): the verdict",
           ["initial poses", "seed", "ATE start", "ATE refined", "verdict", "expected", "met", "first reason"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", nargs="*", help="sims, real and/or broken (default: all three)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--scans", type=int, default=60)
    parser.add_argument("--keep", type=Path, default=None, help="keep the data and outputs in this folder")
    args = parser.parse_args()
    what = args.what or ["sims", "real", "broken"]
    if set(what) - {"sims", "real", "broken"}:
        parser.error(f"unknown part(s) {sorted(set(what) - {'sims', 'real', 'broken'})}; choose sims, real, broken")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        if "sims" in what:
            bench_sims(work, args.seeds, args.scans)
        if "real" in what:
            bench_real(work)
        if "broken" in what:
            bench_broken(work, args.seeds[:2], args.scans)


if __name__ == "__main__":
    main()
