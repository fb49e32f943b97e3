"""Reports: plots (files) and rich summary tables (stderr); nothing here prints errors."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from pa_cli.io.atomic import atomic_path


def plot_trajectories_top_view(path: Path | str, trajectories: Sequence[tuple[str, np.ndarray]],
                               title: str = "", force: bool = False) -> None:
    """Write a top view (world x-y, metres) of trajectories to a PNG, atomically.

    `trajectories`: (label, T_world_scan (N, 4, 4)) pairs, drawn in order; the start of each is
    marked. Uses matplotlib's Agg backend, so it works without a display.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6), dpi=120)
    ax = fig.add_subplot(1, 1, 1)
    for label, T_world_scan in trajectories:
        xy = np.asarray(T_world_scan)[:, :2, 3]
        line = ax.plot(xy[:, 0], xy[:, 1], label=label, linewidth=1.2)[0]
        ax.plot(xy[:1, 0], xy[:1, 1], marker="o", color=line.get_color())
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    with atomic_path(path, force) as tmp:
        fig.savefig(tmp, format="png")



def refine_summary_table(report: dict[str, Any]) -> Table:
    """The closing table of `pa refine`: sizes, cost and RMS point-to-plane before/after, time."""
    summary = report["summary"]
    table = Table(title="pa refine", show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("initial", justify="right")
    table.add_column("refined", justify="right")
    table.add_row("scans", str(summary["n_scans"]), "")
    table.add_row("points (input)", f"{report['input'].get('n_points', 0):,}", "")
    table.add_row("points on planes", f"{summary['n_points_on_planes']:,}", "")
    table.add_row("landmarks (planes)", str(summary["n_landmarks"]), "")
    table.add_row("cost (m^2)", f"{summary['cost_initial_m2']:.6g}", f"{summary['cost_final_m2']:.6g}")
    table.add_row("RMS point-to-plane (m)", f"{summary['rms_point_to_plane_initial_m']:.4f}",
                  f"{summary['rms_point_to_plane_final_m']:.4f}")
    gt = report.get("gt")
    if gt:
        table.add_row("ATE vs --gt (m)", f"{gt['initial']['ate_rmse_m']:.4f}", f"{gt['refined']['ate_rmse_m']:.4f}")
        if "rms_point_to_plane_at_gt_m" in gt:
            table.add_row("RMS at --gt poses (m)", f"{gt['rms_point_to_plane_at_gt_m']:.4f}", "")
    table.add_row("rounds / iterations", "", f"{summary['n_rounds']} / {summary['iterations']}")
    times = report["stage_times_s"]
    table.add_row("time (s)", ", ".join(f"{k} {v:.1f}" for k, v in times.items()), f"{sum(times.values()):.1f}")
    flagged = report.get("poorly_constrained_scans") or []
    if flagged:
        table.add_row("poorly constrained scans", str(len(flagged)), "")
    return table


def print_refine_summary(report: dict[str, Any], console: Console | None = None) -> None:
    """Print the closing table of `pa refine` (stderr unless a console is given)."""
    (console or Console(stderr=True)).print(refine_summary_table(report))
