"""A `pa refine` killed with SIGKILL in the middle of its rounds, then `--resume`: the poses against
an uninterrupted run, the times, and what the work folder costs (prints tables; never a timed assertion).

    PYTHONPATH=. python bench/resume.py                                   # 1000 simulated office scans, 50 m
    PYTHONPATH=. python bench/resume.py --scans-dir sample_data/office/scans --config indoor
    PYTHONPATH=. python bench/resume.py --poses-level 1      # from perturbed true poses, no KISS-ICP

Runs, each `pa refine` a subprocess:
1. uninterrupted, with --keep-work (its work folder holds its initial poses and registered motions);
2. a fresh run killed with SIGKILL once its work folder holds the carry of round --kill-after-round,
   then the same command with --resume;
3. a run started from run 1's finished initial stages (its manifest, odometry, motions copied into
   a new work folder and --resume), killed the same way, then resumed.
Run 3 isolates what resuming adds: it shares run 1's stages before the kill, so its poses equal
run 1's to the text output's 1e-9 unless the resume lost something. Run 2 also carries the
run-to-run difference of two fresh runs (KISS-ICP's threads differ in the last bits; the
registration and the association can amplify that).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import REPO, print_table, run_pa  # noqa: E402

POLL_S = 0.05


def refine_command(scans: Path, out: Path, config: str | None, *extra: str) -> list[str]:
    return [sys.executable, "-m", "pa_cli", "refine", str(scans), "--out", str(out), "-q",
            *(["--config", config] if config else []), *extra]


def timed(command: list[str]) -> float:
    """Run `command` to its end; its wall time (s). Exits with its stderr on failure."""
    start = time.perf_counter()
    proc = subprocess.run(command, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{proc.stderr}")
    return time.perf_counter() - start


def killed_after_round(command: list[str], work: Path, after_round: int) -> tuple[float, int]:
    """Start `command`; SIGKILL it once `work`/round.npz carries round `after_round` (or a later
    one). Its wall time until the kill (s) and the rounds it had finished."""
    start = time.perf_counter()
    process = subprocess.Popen(command, env=dict(os.environ, PYTHONPATH=str(REPO)),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    round_file = work / "round.npz"
    finished = 0
    while process.poll() is None:
        if round_file.exists():
            with np.load(round_file) as data:
                finished = int(data["next_round"])
            if finished >= after_round:
                break
        time.sleep(POLL_S)
    if process.poll() is not None:
        raise SystemExit(f"{' '.join(command)} ended (exit {process.returncode}) before round {after_round}'s "
                         "carry was kept; lower --kill-after-round.")
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    return time.perf_counter() - start, finished


def poses(out: Path) -> np.ndarray:
    return np.loadtxt(out.with_name(out.stem + "_poses_kitti.txt"))


def save_cost_s(work: Path, repeats: int = 3) -> float:
    """The least wall time (s) of writing the kept round file again (`WorkFolder.save`)."""
    from pa_cli.refine.work import WorkFolder

    folder = WorkFolder(work)
    arrays, record = folder.load("round")
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        folder.save("round_again", arrays, record)
        best = min(best, time.perf_counter() - start)
    (work / "round_again.npz").unlink()
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=int, default=1000, help="simulated office scans (without --scans-dir)")
    parser.add_argument("--azimuth-steps", type=int, default=256, help="simulated columns per sweep (points/scan / 16)")
    parser.add_argument("--step-m", type=float, default=0.05,
                        help="simulated path per scan (m); 1000 x 0.05 m stays within one lap of the office loop "
                        "(64 m), so no place is revisited (that would need --loops)")
    parser.add_argument("--scans-dir", type=Path, help="refine this scan folder instead of a simulated one")
    parser.add_argument("--config", default="indoor")
    parser.add_argument("--kill-after-round", type=int, default=2)
    parser.add_argument("--poses-level", type=int, choices=[1, 2, 3, 4],
                        help="start from the true poses perturbed at this level (pa perturb --level; --poses) "
                        "instead of KISS-ICP")
    parser.add_argument("--keep", type=Path, help="work here (kept) instead of a temporary folder")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="pa_bench_resume_"))
    root.mkdir(parents=True, exist_ok=True)
    scans = args.scans_dir
    if scans is None:
        data = root / "office"
        if not (data / "scans").is_dir():
            run_pa("simulate", "office", data, "--scans", args.scans, "--azimuth-steps", args.azimuth_steps,
                   "--step-m", args.step_m, "--seed", 1, "--force")
        scans = data / "scans"
    start: list[str] = []
    if args.poses_level:
        noisy = root / f"poses_level{args.poses_level}_kitti.txt"
        run_pa("perturb", scans.parent / "gt_poses_kitti.txt", "--level", args.poses_level, "--keep-first",
               "--seed", 7, "--out", noisy, "--force")
        start = ["--poses", str(noisy)]
    runs = {name: root / name / "m.ply" for name in ("uninterrupted", "fresh", "seeded")}
    for out in runs.values():
        shutil.rmtree(out.parent, ignore_errors=True)
        out.parent.mkdir(parents=True)
    work = {name: out.with_name("m.work") for name, out in runs.items()}

    whole_s = timed(refine_command(scans, runs["uninterrupted"], args.config, *start, "--keep-work"))
    reference = poses(runs["uninterrupted"])
    kept_mb = {p.name: p.stat().st_size / 1e6 for p in sorted(work["uninterrupted"].iterdir())}
    rows = [["uninterrupted (--keep-work)", "-", f"{whole_s:.1f}", "-", "0"]]

    kill_s, finished = killed_after_round(refine_command(scans, runs["fresh"], args.config, *start), work["fresh"],
                                          args.kill_after_round)
    resume_s = timed(refine_command(scans, runs["fresh"], args.config, *start, "--resume"))
    rows.append(["fresh run, SIGKILL, --resume", f"round {finished}", f"{kill_s:.1f}", f"{resume_s:.1f}",
                 f"{np.abs(poses(runs['fresh']) - reference).max():.3g}"])

    work["seeded"].mkdir()
    for name in ("manifest.json", "odometry.npz", "motions.npz", "loops.npz"):
        if (work["uninterrupted"] / name).exists():
            shutil.copy2(work["uninterrupted"] / name, work["seeded"] / name)
    kill_s, finished = killed_after_round(refine_command(scans, runs["seeded"], args.config, *start, "--resume"),
                                          work["seeded"], args.kill_after_round)
    resume_s = timed(refine_command(scans, runs["seeded"], args.config, *start, "--resume"))
    rows.append(["run 1's initial stages, SIGKILL, --resume", f"round {finished}", f"{kill_s:.1f}", f"{resume_s:.1f}",
                 f"{np.abs(poses(runs['seeded']) - reference).max():.3g}"])

    n_scans = len(reference)
    print_table(f"pa refine killed with SIGKILL in its rounds, then --resume ({n_scans} scans of {scans}; "
                f"--config {args.config}{'; ' + ' '.join(start) if start else ''})",
                ["run", "killed after", "wall s (to the kill)", "--resume wall s",
                 "max abs difference of the pose entries"], rows)
    report = json.loads(runs["uninterrupted"].with_name("m_report.json").read_text())
    n_carries = max(report["summary"]["n_rounds"] - 1, 0)
    cost_s = save_cost_s(work["uninterrupted"])
    print_table("the work folder's cost (uninterrupted run)",
                ["file", "MB", "written"], [[name, f"{mb:.2f}", "every round but the last" if name == "round.npz"
                                             else "once"] for name, mb in kept_mb.items()]
                + [["round.npz: one write (s)", f"{cost_s:.3f}", f"x {n_carries} rounds = {cost_s * n_carries:.2f} s "
                    f"of {whole_s:.0f} s ({100 * cost_s * n_carries / whole_s:.2f} %)"]])
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
