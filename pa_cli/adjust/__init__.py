"""Plane adjustment solvers: second-order Newton with planes eliminated (default) and PA_LM.

`solve(problem, T_world_scan_init, options)` refines poses T_world_scan (N, 4, 4) against the
plane problem and returns a `SolveResult` with the refined poses and a report dict (the keys of
REPORT.json: solver, iterations, cost_initial, cost_final, converged, stop_reason, time_s,
n_planes, n_scans, n_observations, history, warnings).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pa_cli.adjust.common import IterationRecord, SolverOptions, damped_newton, retract_poses
from pa_cli.adjust.newton import NewtonModel, plane_cost
from pa_cli.adjust.odometry_factors import OdometryFactors
from pa_cli.adjust.prior import PosePrior
from pa_cli.errors import SolverError
from pa_cli.io.problem import PlaneProblem

__all__ = ["PosePrior", "SolveResult", "SolverOptions", "plane_cost", "solve", "REPORT_KEYS"]

REPORT_KEYS = ("solver", "iterations", "cost_initial", "cost_final", "converged", "stop_reason", "time_s",
               "n_planes", "n_scans", "n_observations", "history", "warnings")


@dataclass
class SolveResult:
    """Refined poses T_world_scan (N, 4, 4) and the solver report."""

    T_world_scan: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)


def _check_inputs(problem: PlaneProblem, T_world_scan_init: np.ndarray, options: SolverOptions) -> np.ndarray:
    T = np.asarray(T_world_scan_init, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise SolverError(f"initial poses must have shape (N, 4, 4), found {T.shape}.")
    if len(T) != problem.n_scans:
        raise SolverError(f"{len(T)} initial poses for a problem with {problem.n_scans} scans; "
                          "give one pose per scan.")
    if not np.all(np.isfinite(T)):
        raise SolverError("initial poses contain NaN or inf values.")
    if problem.n_scans < 2 or problem.n_planes == 0:
        raise SolverError(f"nothing to optimise: {problem.n_scans} scans and {problem.n_planes} planes "
                          "seen by at least two scans.")
    if not 0 <= options.fixed_pose < problem.n_scans:
        raise SolverError(f"fixed pose {options.fixed_pose} is out of range 0..{problem.n_scans - 1} "
                          "(--fix).")
    return T


def solve(problem: PlaneProblem, T_world_scan_init: np.ndarray, options: SolverOptions | None = None,
          solver: str = "newton", progress: Callable[[IterationRecord], None] | None = None,
          prior: PosePrior | None = None, odometry: OdometryFactors | None = None) -> SolveResult:
    """Refine poses by plane adjustment; the pose `options.fixed_pose` is held fixed (gauge).

    `progress(record)` is called after every iteration. Costs are in m^2 (sum of squared
    point-to-plane distances with every plane at its optimum). With a `prior` (see
    `pa_cli.adjust.prior`) the solvers minimise plane cost + prior; the report's `cost_initial`
    and `cost_final` stay the plane cost alone, the history holds the minimised objective and
    `prior_cost_final` the prior's share. `odometry` (`pa_cli.adjust.odometry_factors`) adds
    relative-pose factors between consecutive scans the same way (`odometry_cost_initial`,
    `odometry_cost_final`: their share, m^2).
    """
    options = options or SolverOptions()
    T0 = _check_inputs(problem, T_world_scan_init, options)
    t_start = time.perf_counter()
    warnings: list[str] = []
    if solver == "newton":
        model = NewtonModel(problem, options.fixed_pose, options.eigen_gap_tolerance, prior, odometry)
        T, fields = damped_newton(T0, model.linearize, model.cost, retract_poses,
                                  lambda step: float(np.linalg.norm(step)), options, progress)
        if model.max_guarded:
            warnings.append(
                f"eigen-gap guard: up to {model.max_guarded} of {problem.n_planes} planes had lambda_min "
                f"within {options.eigen_gap_tolerance:g} (relative) of another eigenvalue; their coupling "
                "terms were clamped (degenerate, e.g. line-like or point-like, planes).")
    elif solver == "lm":
        try:
            from pa_cli.adjust.joint_lm import solve_lm
        except ImportError:
            raise SolverError("solver 'lm' (PA_LM baseline) is not available yet; use --solver newton.") from None
        T, fields = solve_lm(problem, T0, options, progress, prior=prior, odometry=odometry)
    else:
        raise SolverError(f"unknown solver '{solver}'; expected 'newton' or 'lm'.")
    if not fields["converged"]:
        warnings.append(f"not converged: stopped by {fields['stop_reason']} after {fields['iterations']} "
                        "iterations.")
    if prior is not None or odometry is not None:
        fields = {**fields, "cost_initial": plane_cost(problem, T0), "cost_final": plane_cost(problem, T)}
    report = {
        "solver": solver,
        "iterations": fields["iterations"],
        "cost_initial": fields["cost_initial"],
        "cost_final": fields["cost_final"],
        "converged": bool(fields["converged"]),
        "stop_reason": fields["stop_reason"],
        "time_s": time.perf_counter() - t_start,
        "n_planes": problem.n_planes,
        "n_scans": problem.n_scans,
        "n_observations": problem.n_observations,
        "history": fields["history"],
        "warnings": warnings,
    }
    if prior is not None:
        report["prior_cost_final"] = prior.cost(T)
    if odometry is not None:
        report["odometry_cost_initial"] = odometry.cost(T0)
        report["odometry_cost_final"] = odometry.cost(T)
    return SolveResult(T_world_scan=T, report=report)
