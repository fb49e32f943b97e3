"""`pa adjust`: second-order plane adjustment of a saved plane problem."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import SolverChoice, TrajFormat, app, err_console, fmt_value, log


@app.command("adjust")
def adjust_cmd(
    problem_path: Annotated[Path, typer.Argument(metavar="PROBLEM.npz", help="Plane problem (.npz).")],
    out: Annotated[Path, typer.Option("--out", help="Refined poses T_world_scan (KITTI, or TUM with --format tum).")],
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial poses (KITTI/TUM); default: the problem's 'poses'.")] = None,
    fmt: Annotated[TrajFormat | None, typer.Option("--format", help="Format of --out: kitti (default) or tum.")] = None,
    report: Annotated[Path | None, typer.Option("--report", help="Write the solver report (JSON) here.")] = None,
    solver: Annotated[SolverChoice, typer.Option(
        "--solver", help="newton (planes eliminated) or lm (PA_LM baseline).")] = SolverChoice.newton,
    max_iterations: Annotated[int | None, typer.Option(
        "--max-iterations", help="Damped solves at most (default 100).")] = None,
    fix: Annotated[int, typer.Option("--fix", help="Index of the pose held fixed (gauge).")] = 0,
    config: Annotated[Path | None, typer.Option("--config", help="YAML config; its 'solver' section is used.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
) -> None:
    """Refine poses by second-order plane adjustment (damped Newton, planes eliminated).

    Minimises the sum over planes of lambda_min of the world scatter of the plane's points, in m^2: the sum of squared point-to-plane distances with every plane at its optimum. Pose --fix is held fixed (gauge). Initial poses come from --poses, else from the problem's 'poses' array. A summary table goes to stderr; --report writes REPORT.json (solver, iterations, costs, convergence, history, warnings).

    Example:

        pa adjust problem.npz --poses init_kitti.txt --out refined_kitti.txt --report report.json
    """
    from pa_cli.adjust import solve
    from pa_cli.config import load_config
    from pa_cli.errors import InputError
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.problem import load_problem
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory
    from pa_cli.report import adjust_table, write_report

    if max_iterations is not None and max_iterations < 1:
        raise typer.BadParameter(f"must be at least 1, got {max_iterations}", param_hint="--max-iterations")
    if fix < 0:
        raise typer.BadParameter(f"must be non-negative, got {fix}", param_hint="--fix")
    outputs = [out] + ([report] if report is not None else [])
    if report is not None and Path(report).resolve() == Path(out).resolve():
        raise typer.BadParameter("--report and --out must be different files", param_hint="--report")
    inputs = [problem_path] + ([poses] if poses is not None else []) + ([config] if config is not None else [])
    check_writable(outputs, force, inputs=inputs)

    cfg = load_config(config).solver
    updates = {"fixed_pose": fix, "solver": solver.value}
    if max_iterations is not None:
        updates["max_iterations"] = max_iterations
    cfg = cfg.model_copy(update=updates)
    problem = load_problem(problem_path)
    timestamps = None
    if poses is not None:
        traj = read_trajectory(poses)
        T_init, timestamps = traj.T_world_scan, traj.timestamps
        if len(T_init) != problem.n_scans:
            raise InputError(f"{poses}: {len(T_init)} poses, but {problem_path} has {problem.n_scans} scans; "
                             "give one pose per scan.")
    elif problem.T_world_scan is not None:
        T_init = problem.T_world_scan
    else:
        raise InputError(f"{problem_path}: holds no 'poses' array; pass initial poses with --poses.")
    if fix >= problem.n_scans:
        raise typer.BadParameter(f"pose {fix} does not exist (the problem has {problem.n_scans} scans)",
                                 param_hint="--fix")

    result = solve(problem, T_init, cfg)
    rep = result.report
    write_trajectory(out, Trajectory(result.T_world_scan, timestamps), fmt=fmt_value(fmt) or "kitti", force=force)
    if report is not None:
        write_report(report, rep, force=force)

    err_console.print(adjust_table(rep, problem.n_points))
    for w in rep["warnings"]:
        log.warning(w)
