"""Human-readable summaries (rich tables on stderr); machine-readable results go to JSON files."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table


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
