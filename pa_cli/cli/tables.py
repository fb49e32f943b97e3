"""The rich tables the commands print on stderr (refine summary, adjust, eval)."""

from __future__ import annotations

from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

# The rows of the cross-scored RMS (report `quality.rms_point_to_plane_m`), by association.
RMS_ROWS = {"planes_at_initial_poses": "point-to-plane RMS (m), planes found at the start",
            "planes_at_refined_poses": "point-to-plane RMS (m), planes found at the end"}


def refine_summary_table(report: dict[str, Any]) -> Table:
    """The closing table of `pa refine`: sizes, the point-to-plane RMS of the initial and the refined
    poses on the planes found at the start and on those found at the end, ATE, verdict, time."""
    summary = report["summary"]
    table = Table(title="pa refine", show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("initial poses", justify="right")
    table.add_column("refined poses", justify="right")
    table.add_row("scans", str(summary["n_scans"]), "")
    table.add_row("points (input)", f"{report['input'].get('n_points', 0):,}", "")
    table.add_row("points on planes, last round", f"{summary['n_points_on_planes']:,}", "")
    table.add_row("planes, last round", str(summary["n_landmarks"]), "")
    table.add_row("solver cost, last round (m^2)", f"{summary['cost_initial_m2']:.6g}", f"{summary['cost_final_m2']:.6g}")
    quality, gt = report["quality"], report.get("gt")
    for association, rms in quality["rms_point_to_plane_m"].items():
        table.add_row(RMS_ROWS[association], f"{rms['initial']:.4f}", f"{rms['refined']:.4f}")
    if gt:
        if "rms_point_to_plane_at_gt_m" in gt:  # under the refined poses' value it is to be compared with
            table.add_row("point-to-plane RMS (m), planes found at the end, at the --gt poses", "",
                          f"{gt['rms_point_to_plane_at_gt_m']:.4f}")
        table.add_row("ATE vs --gt (m)", f"{gt['initial']['ate_rmse_m']:.4f}", f"{gt['refined']['ate_rmse_m']:.4f}")
    entropy = quality.get("map_entropy")
    if entropy and entropy["mme_nats"]["initial"] is not None:
        table.add_row(f"mean map entropy, {entropy['radius_m']:g} m (nats)",
                      f"{entropy['mme_nats']['initial']:.4f}", f"{entropy['mme_nats']['refined']:.4f}")
    table.add_row("quality verdict", "", quality["verdict"])
    settled = "settled" if summary["settled"] else "not settled"
    table.add_row("rounds / iterations", "", f"{summary['n_rounds']} / {summary['iterations']}, {settled}")
    written = report.get("map")
    if written:
        density = f"one per {written['voxel_m']:g} m voxel" if written["voxel_m"] else "every point"
        low_m, high_m = written["range_m"]
        table.add_row(f"map points ({density})", f"{written['n_out_of_range']:,} outside range {low_m:g}-{high_m:g} m",
                      f"{written['n_points']:,}")
        table.add_row("map fields", "", ", ".join(["scan"] + [name for name in ("intensity", "time") if written[name]]))
    times, total_s = report["stage_times_s"], report["total_time_s"]
    between_s = total_s - sum(times.values())  # the work between the stages (outside every bar)
    parts = [f"{k} {v:.1f}" for k, v in times.items()] + ([f"between stages {between_s:.1f}"] if between_s >= 0.05
                                                           else [])
    table.add_row("time (s)", ", ".join(parts), f"{total_s:.1f}")
    flagged = report.get("poorly_constrained_scans") or []
    if flagged:
        table.add_row("poorly constrained scans", str(len(flagged)), "")
    return table


def refine_verdict_line(report: dict[str, Any]) -> str:
    """The result of `pa refine` in one line (what `-q` prints): the verdict, whether the rounds
    settled, and the ATE when --gt was given."""
    summary = report["summary"]
    rounds = f"{summary['n_rounds']} round{'s' if summary['n_rounds'] != 1 else ''}"
    parts = [f"verdict {report['quality']['verdict']}",
             f"settled after {rounds}" if summary["settled"] else f"not settled after {rounds}"]
    gt = report.get("gt")
    if gt:
        parts.append(f"ATE vs --gt {gt['initial']['ate_rmse_m']:.4f} m -> {gt['refined']['ate_rmse_m']:.4f} m")
    return "pa refine: " + ", ".join(parts)


def print_refine_summary(report: dict[str, Any], console: Console | None = None) -> None:
    """Print the closing table of `pa refine` (stderr unless a console is given)."""
    (console or Console(stderr=True)).print(refine_summary_table(report))


def adjust_table(report: dict[str, Any], n_points: int) -> Table:
    """The closing table of `pa adjust`: sizes, iterations, cost before/after, RMS, convergence."""
    rms_m = np.sqrt(max(report["cost_final_m2"], 0.0) / max(n_points, 1))
    table = Table(title=f"pa adjust ({report['solver']})", show_header=False)
    rows = [
        ("scans / planes / observations",
         f"{report['n_scans']} / {report['n_planes']} / {report['n_observations']}"),
        ("iterations", str(report["iterations"])),
        ("accepted steps", str(sum(h["accepted"] for h in report["history"]))),
        ("cost initial (m^2)", f"{report['cost_initial_m2']:.6g}"),
        ("cost final (m^2)", f"{report['cost_final_m2']:.6g}"),
        ("RMS point-to-plane (m)", f"{rms_m:.4g}"),
        ("converged", f"{report['converged']} ({report['stop_reason']})"),
        ("time (s)", f"{report['time_s']:.3f}"),
    ]
    if "covariance" in report:  # pa adjust --covariance
        cov = report["covariance"]
        rows.append(("pose 1-sigma, median scan", f"{cov['position_sigma_m_median']:.3g} m, "
                     f"{cov['rotation_sigma_deg_median']:.3g} deg (point sigma {cov['point_sigma_m']:.3g} m)"))
        rows += [("least certain scan",
                  f"{w['scan']}: {w['position_sigma_m']:.3g} m, {w['rotation_sigma_deg']:.3g} deg")
                 for w in cov["least_certain_scans"][:1]]
    for key, value in rows:
        table.add_row(key, value)
    return table


def eval_table(names: list[str], results: list[dict[str, Any]], title: str) -> Table:
    """The table of `pa eval`: ATE and RPE (translation m, rotation deg) of `evaluate` results, one
    column per estimate; a rotation ATE the path leaves meaningless (`ate_rot_note`) is marked (!)."""
    table = Table(title=title)
    table.add_column("metric")
    for name in names:
        table.add_column(name, justify="right")
    rows = [(f"ATE translation {stat} (m)", f"ate_{stat}_m") for stat in ("rmse", "mean", "median", "max")]
    rows += [(f"ATE rotation {stat} (deg)", f"ate_rot_{stat}_deg") for stat in ("rmse", "mean", "max")]
    rows += [(f"RPE translation {stat} (m)", f"rpe_trans_{stat}_m") for stat in ("rmse", "mean", "max")]
    rows += [(f"RPE rotation {stat} (deg)", f"rpe_rot_{stat}_deg") for stat in ("rmse", "mean", "max")]
    for label, key in rows:
        marked = key.startswith("ate_rot")
        table.add_row(label, *(f"{r[key]:.6f}" + (" (!)" if marked and r["ate_rot_note"] else "") for r in results))
    table.add_row("poses paired", *(f"{r['n_poses']} of {r['n_est']}" for r in results))
    return table
