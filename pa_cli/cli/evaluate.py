"""`pa eval`: ATE and RPE of a trajectory against ground truth."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import TrajFormat, app, fmt_value


class AlignChoice(str, Enum):
    se3 = "se3"
    sim3 = "sim3"
    origin = "origin"
    none = "none"


@app.command("eval")
def eval_command(
    gt: Annotated[Path, typer.Argument(help="Ground-truth trajectory (KITTI or TUM), T_world_scan.")],
    est: Annotated[Path, typer.Argument(help="Estimated trajectory (KITTI or TUM), T_world_scan.")],
    align: Annotated[AlignChoice, typer.Option(
        "--align", help="Alignment of EST onto GT before the errors: se3 (Umeyama), sim3 (with "
        "scale), origin (first poses equal) or none.")] = AlignChoice.se3,
    json_path: Annotated[Path | None, typer.Option("--json", help="Write all metrics to this JSON file.")] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write a top-view (x-y) plot PNG.")] = None,
    fmt: Annotated[TrajFormat | None, typer.Option(
        "--format", help="Format of both files (default: detected by column count).")] = None,
    max_diff: Annotated[float, typer.Option(
        "--max-diff", min=0.0, help="TUM: max time difference (seconds) to pair poses by timestamp.")] = 0.01,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --json/--plot outputs.")] = False,
) -> None:
    """Compare a trajectory with ground truth: ATE (translation, rotation) and RPE.

    KITTI files pair poses by index (equal lengths needed).

    TUM files pair poses by timestamp (nearest within --max-diff seconds).

    The numbers equal evo's (evo_ape kitti GT EST -a; evo_rpe with --delta 1).

    Example:

        pa eval gt_poses_kitti.txt refined_kitti.txt --align se3 --json eval.json --plot top.png
    """
    from rich.console import Console

    from pa_cli.cli.tables import eval_table
    from pa_cli.evaluation import apply_alignment, evaluate
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.report import write_report
    from pa_cli.io.trajectory import read_trajectory

    outputs = [p for p in (json_path, plot) if p is not None]
    check_writable(outputs, force, inputs=[gt, est])
    traj_gt = read_trajectory(gt, fmt_value(fmt))
    traj_est = read_trajectory(est, fmt_value(fmt))
    result = evaluate(traj_gt, traj_est, align=align.value, max_diff_s=max_diff)

    table = eval_table(result, f"{est.name} vs {gt.name}: {result['n_poses']} poses, align {align.value}"
                       f" (pairing by {result['pairing']})")
    Console(width=110).print(table)
    if align.value == "sim3":
        typer.echo(f"sim3 scale: {result['scale']:.9f}")

    if json_path is not None:
        report = {"gt": str(gt), "est": str(est), **result}
        write_report(json_path, report, force)
    if plot is not None:
        import numpy as np

        from pa_cli.io.plots import plot_trajectories_top_view

        A = np.asarray(result["alignment"])
        T_est_aligned = apply_alignment(traj_est.T_world_scan, A, result["scale"])
        plot_trajectories_top_view(plot, [("ground truth", traj_gt.T_world_scan),
                                          (f"estimate ({align.value}-aligned)", T_est_aligned)],
                                   title=f"ATE rmse {result['ate_rmse_m']:.4f} m", force=force)
