"""`pa eval`: ATE and RPE of one or more trajectories against ground truth, a table and a plot."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from pa_cli.cli.app import TrajFormat, app, fmt_value, log

if TYPE_CHECKING:
    from pa_cli.io.trajectory import Trajectory


class AlignChoice(str, Enum):
    se3 = "se3"
    sim3 = "sim3"
    origin = "origin"
    none = "none"


@app.command("eval")
def eval_command(
    gt: Annotated[Path, typer.Argument(help="Ground-truth trajectory (KITTI or TUM), T_world_scan, or a dataset's own "
        "file (KITTI, MulRan, Newer College, NCLT: docs/formats.md), converted to the LiDAR's poses.")],
    estimates: Annotated[list[Path], typer.Argument(
        metavar="EST...", help="Estimated trajectories (KITTI or TUM), T_world_scan; each is compared with GT.")],
    align: Annotated[AlignChoice, typer.Option(
        "--align", help="Alignment of each EST onto GT before the errors: se3 (Umeyama), sim3 (with "
        "scale), origin (first poses equal) or none.")] = AlignChoice.se3,
    json_path: Annotated[Path | None, typer.Option("--json", help="Write all metrics to this JSON file.")] = None,
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="Write a PNG: the trajectories (top view), the error over time, each path coloured by its "
        "error.")] = None,
    fmt: Annotated[TrajFormat | None, typer.Option(
        "--format", help="Format of all files (default: detected by column count).")] = None,
    max_diff: Annotated[float, typer.Option(
        "--max-diff", min=0.0, help="TUM: max time difference (seconds) to pair poses by timestamp.")] = 0.01,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --json/--plot outputs.")] = False,
) -> None:
    """Compare trajectories with ground truth: ATE (translation, rotation) and RPE, one column per estimate.

    KITTI files pair poses by index (equal lengths needed).

    TUM files pair poses by timestamp (nearest within --max-diff seconds).

    The numbers equal evo's (evo_ape kitti GT EST -a; evo_rpe with --delta 1).

    The rotation ATE after --align se3/sim3 is meaningless on a nearly straight path (the alignment fits positions only, so its turn about the path follows the errors): a warning says so, and --align origin or the RPE rotation then measure the rotations.

    --json: with one EST, {gt, est, metrics...}; with several, {gt, estimates: [{est, metrics...}, ...]}.

    Example:

        pa eval gt_poses_kitti.txt refined_kitti.txt --align se3 --json eval.json --plot eval.png

        pa eval gt.txt map_initial_poses_kitti.txt map_poses_kitti.txt --plot compare.png
    """
    from rich.console import Console

    from pa_cli.cli.tables import eval_table
    from pa_cli.evaluation import evaluate
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.dataset_gt import read_ground_truth
    from pa_cli.io.report import write_report
    from pa_cli.io.trajectory import read_trajectory

    outputs = [p for p in (json_path, plot) if p is not None]
    check_writable(outputs, force, inputs=[gt, *estimates])
    traj_gt = read_ground_truth(gt, fmt_value(fmt))
    trajectories = [read_trajectory(est, fmt_value(fmt)) for est in estimates]
    results = [evaluate(traj_gt, traj, align=align.value, max_diff_s=max_diff) for traj in trajectories]
    names = _labels(estimates)

    pairing = ", ".join(sorted({r["pairing"] for r in results}))
    Console(width=max(110, 30 + 16 * len(names))).print(
        eval_table(names, results, f"vs {gt.name}: align {align.value} (pairing by {pairing})"))
    for name, result in zip(names, results, strict=True):
        if align.value == "sim3":
            typer.echo(f"{name}: sim3 scale {result['scale']:.9f}")
        if result["ate_rot_note"]:
            log.warning("%s: %s", name, result["ate_rot_note"])

    if json_path is not None:
        entries = [{"est": str(est), **result} for est, result in zip(estimates, results, strict=True)]
        report = {"gt": str(gt), **entries[0]} if len(entries) == 1 else {"gt": str(gt), "estimates": entries}
        write_report(json_path, report, force)
    if plot is not None:
        _write_plot(plot, traj_gt, names, trajectories, align.value, max_diff, force)


def _labels(paths: list[Path]) -> list[str]:
    """The file names, or the paths where two estimates share a name."""
    names = [p.name for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


def _write_plot(path: Path, gt: Trajectory, names: list[str], trajectories: list[Trajectory], align: str,
                max_diff_s: float, force: bool) -> None:
    """`--plot`: `pa_cli.io.plots.trajectory_errors_figure` of the aligned estimates."""
    from pa_cli.evaluation import pose_errors
    from pa_cli.io.plots import save_png, trajectory_errors_figure

    curves = []
    for name, traj in zip(names, trajectories, strict=True):
        errors = pose_errors(gt, traj, align, max_diff_s)
        x = errors.i_gt.astype(float) if gt.timestamps is None else gt.timestamps[errors.i_gt] - gt.timestamps.min()
        curves.append((f"{name} ({align}-aligned)", errors.T_aligned[:, :2, 3], x, errors.trans_m))
    x_label = "pose" if gt.timestamps is None else "time since the first ground-truth pose [s]"
    save_png(trajectory_errors_figure(gt.T_world_scan[:, :2, 3], curves, x_label), path, force)
