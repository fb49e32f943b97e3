"""Feature adjustment: refine poses T_world_scan against a feature problem of planes and edges.

`solve(problem, T_world_scan_init, config, progress, terms)` runs the backend named by
`config.solver` (`SolverConfig`, the config's `advanced.solver`) and returns a `SolveResult` with
the refined poses (N, 4, 4) and the solver report (REPORT_KEYS; costs in m^2).

Layout:

- `terms.py`: the pose-term protocol (`PoseTerm`: cost, gradient, Hessian blocks, pose pairs);
- `odometry_factors.py`: `OdometryFactors`, a pose term holding consecutive scans to the initial
  trajectory's relative motions;
- `newton.py`: `PlaneCost` (the plane feature cost, planes eliminated), `FeatureCost` (planes and
  edges by `feature_kind`) and the `newton` backend;
- `edges.py`: `EdgeCost` (the edge feature cost, lambda_min + lambda_mid, lines eliminated);
- `normal_terms.py`: the per-observation derivatives both feature costs are built from;
- `joint_lm.py`: the `lm` backend (PA_LM baseline, planes and lines as unknowns);
- `linalg.py`: the sparse Hessian pattern, assembly and the damped factorisation;
- `damped.py`: the damped loop both backends run (stopping rules, damping schedule);
- `hierarchical.py`: the `hierarchical` backend (windows, keyframes, a global layer, a flat
  final pass) for long sequences, its windows run by `pa_cli.runtime.distributed`;
- `backend.py`: the backend interface and registry (`register_backend`).

Adding a cost term on the poses:
write a class with `name`, `cost(T)`, `linearize(T) -> TermLinearization` (cost, gradient (N, 6),
per-pose blocks (N, 6, 6), blocks (K, 6, 6) for its pose pairs) and `pose_pairs() -> (K, 2)`
(see `terms.py`; `odometry_factors.OdometryFactors` is the example), and pass an instance in `solve(...,
terms=[...])`. The `newton` backend adds its pairs to the Hessian pattern and its blocks to the
sparse system, the `lm` backend to its Schur system; the report gains `{name}_cost_initial_m2` and
`{name}_cost_final_m2`. A new feature kind gets its own cost class next to `PlaneCost` and
`EdgeCost` (and a line in `FeatureCost`); a new backend is a function registered with
`register_backend`.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pa_cli.adjust.backend import get_backend, register_backend
from pa_cli.adjust.damped import IterationRecord
from pa_cli.adjust.newton import PlaneCost, plane_cost, solve_newton
from pa_cli.adjust.terms import PoseTerm
from pa_cli.config import SolverConfig
from pa_cli.core.problem import FeatureProblem
from pa_cli.errors import SolverError

__all__ = ["PlaneCost", "PoseTerm", "REPORT_KEYS", "REPORT_VERSION", "SolveResult",
           "plane_cost", "register_backend", "solve"]

REPORT_VERSION = 1  # bump when a key of the solver report changes meaning or name
REPORT_KEYS = ("report_version", "solver", "iterations", "cost_initial_m2", "cost_final_m2", "converged",
               "stop_reason", "rejected_steps", "time_s", "n_planes", "n_scans", "n_observations", "history",
               "warnings")

register_backend("newton", solve_newton)


def _imported_on_use(module: str, name: str) -> Callable[..., Any]:
    """A backend whose module is imported when first used (keeps `pa adjust` start-up short)."""

    def run(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(module), name)(*args, **kwargs)

    return run


register_backend("lm", _imported_on_use("pa_cli.adjust.joint_lm", "solve_lm"))
register_backend("hierarchical", _imported_on_use("pa_cli.adjust.hierarchical", "solve_hierarchical"))


@dataclass
class SolveResult:
    """Refined poses T_world_scan (N, 4, 4), the solver report and the backend's model (`newton`:
    its `NewtonModel`, linearised last at T_world_scan; else None), which `pose_covariance` reuses."""

    T_world_scan: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)
    model: Any = None


def _check_inputs(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig) -> np.ndarray:
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
    if not 0 <= config.fixed_pose < problem.n_scans:
        raise SolverError(f"fixed pose {config.fixed_pose} is out of range 0..{problem.n_scans - 1} "
                          "(--fix).")
    return T


def solve(problem: FeatureProblem, T_world_scan_init: np.ndarray, config: SolverConfig | None = None,
          progress: Callable[[IterationRecord], None] | None = None,
          terms: Sequence[PoseTerm] = ()) -> SolveResult:
    """Refine poses by plane adjustment; the pose `config.fixed_pose` is held fixed (gauge).

    `progress(record)` is called after every iteration. Costs are in m^2 (sum of squared
    point-to-plane distances with every plane at its optimum). With pose `terms` (such as
    `OdometryFactors`) the backends minimise plane cost + terms; the report's `cost_initial_m2` and
    `cost_final_m2` stay the plane cost alone, the history holds the minimised objective and
    `{name}_cost_initial_m2`, `{name}_cost_final_m2` each term's share.
    """
    config = config or SolverConfig()
    T0 = _check_inputs(problem, T_world_scan_init, config)
    backend = get_backend(config.solver)
    t_start = time.perf_counter()
    result = backend(problem, T0, config, terms, progress)
    T, fields, warnings = result.T_world_scan, result.fields, list(result.warnings)
    if not fields["converged"]:
        warnings.append(f"not converged: stopped by {fields['stop_reason']} after {fields['iterations']} "
                        "iterations.")
    cost_initial, cost_final = fields["cost_initial_m2"], fields["cost_final_m2"]
    if terms:
        cost_initial, cost_final = plane_cost(problem, T0), plane_cost(problem, T)
    report = {
        "report_version": REPORT_VERSION,
        "solver": config.solver,
        "iterations": fields["iterations"],
        "cost_initial_m2": cost_initial,
        "cost_final_m2": cost_final,
        "converged": bool(fields["converged"]),
        "stop_reason": fields["stop_reason"],
        "rejected_steps": sum(not record["accepted"] for record in fields["history"]),
        "time_s": time.perf_counter() - t_start,
        "n_planes": problem.n_planes,
        "n_scans": problem.n_scans,
        "n_observations": problem.n_observations,
        "history": fields["history"],
        "warnings": warnings,
    }
    for term in terms:
        report[f"{term.name}_cost_initial_m2"] = term.cost(T0)
        report[f"{term.name}_cost_final_m2"] = term.cost(T)
    return SolveResult(T_world_scan=T, report=report, model=result.model)
