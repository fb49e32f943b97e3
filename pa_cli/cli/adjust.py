"""`pa adjust`: second-order plane adjustment of a saved plane problem."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import (
    CONFIG_HELP,
    CONFIG_METAVAR,
    SCHEDULER_HELP,
    WORKERS_HELP,
    BackendChoice,
    NoiseModelChoice,
    SolverChoice,
    TrajFormat,
    app,
    err_console,
    execution_config,
    fmt_value,
    log,
    set_verbosity,
)


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
    config: Annotated[str | None, typer.Option(
        "--config", metavar=CONFIG_METAVAR, help=CONFIG_HELP + " Its advanced.solver, advanced.covariance and "
        "execution sections are used.")] = None,
    covariance: Annotated[Path | None, typer.Option(
        "--covariance", help="Write each refined pose's 6x6 covariance (.npz, relative to pose --fix).")] = None,
    point_sigma_m: Annotated[float | None, typer.Option(
        "--point-sigma-m", help="Point-to-plane noise 1-sigma (m) for --covariance; default: estimated from the "
        "residuals (--noise-model).")] = None,
    noise_model: Annotated[NoiseModelChoice, typer.Option(
        "--noise-model", help="Estimated point noise for --covariance: auto (range when the problem has "
        "'range_clusters', else observation), range, observation or plane.")] = NoiseModelChoice.auto,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    verbose: Annotated[bool, typer.Option(
        "--verbose", "-v", help="Debug messages (e.g. the backend the problem's size picked).")] = False,
    backend: Annotated[BackendChoice | None, typer.Option(
        "--backend", help="flat (one system over all poses) or hierarchical (windows, keyframes, a global layer and a "
        "flat final pass; long sequences). Default: hierarchical from 3000 scans on (advanced.solver).")] = None,
    workers: Annotated[int | None, typer.Option("--workers", min=0, metavar="N", help=WORKERS_HELP)] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help=SCHEDULER_HELP)] = None,
) -> None:
    """Refine poses by second-order plane adjustment (damped Newton, planes eliminated).

    Minimises the sum over planes of lambda_min of the world scatter of the plane's points, in m^2: the sum of squared point-to-plane distances with every plane at its optimum. Pose --fix is held fixed (gauge). Initial poses come from --poses, else from the problem's 'poses' array. A summary table goes to stderr; --report writes REPORT.json (solver, iterations, costs, convergence, history, warnings).

    Example:

        pa adjust problem.npz --poses init_kitti.txt --out refined_kitti.txt --report report.json

        pa adjust problem_10000.npz --out refined_kitti.txt --backend hierarchical --workers 2

        pa adjust problem.npz --out refined_kitti.txt --covariance cov.npz --report report.json
    """
    from pa_cli.adjust import solve
    from pa_cli.cli.tables import adjust_table
    from pa_cli.config import load_config
    from pa_cli.core.local_frame import local_origin_m, to_local, to_world
    from pa_cli.errors import InputError
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.problem import load_problem
    from pa_cli.io.report import write_report
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

    set_verbosity(False, verbose)
    if max_iterations is not None and max_iterations < 1:
        raise typer.BadParameter(f"must be at least 1, got {max_iterations}", param_hint="--max-iterations")
    if fix < 0:
        raise typer.BadParameter(f"must be non-negative, got {fix}", param_hint="--fix")
    if point_sigma_m is not None and not point_sigma_m > 0:
        raise typer.BadParameter(f"must be a positive number of metres, got {point_sigma_m}",
                                 param_hint="--point-sigma-m")
    outputs = [out] + [p for p in (report, covariance) if p is not None]
    if len({Path(p).resolve() for p in outputs}) < len(outputs):
        raise typer.BadParameter("--out, --report and --covariance must be different files", param_hint="--report")
    inputs = [problem_path] + ([poses] if poses is not None else []) + ([Path(config)] if config is not None else [])
    check_writable(outputs, force, inputs=inputs)

    full_config = load_config(config)
    cfg = full_config.advanced.solver
    execution_cfg = execution_config(full_config.execution, workers, scheduler)
    updates = {"fixed_pose": fix, "solver": solver.value}
    if max_iterations is not None:
        updates["max_iterations"] = max_iterations
    cfg = cfg.model_copy(update=updates)
    problem = load_problem(problem_path, range_clusters=covariance is not None)
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

    from pa_cli.adjust.hierarchical import choose_backend
    from pa_cli.runtime.distributed import execution

    cfg, message = choose_backend(cfg, problem.n_scans, None if backend is None else backend.value)
    if message:
        log.debug(message)
    origin_world_m = local_origin_m(T_init)  # far from the world origin, clusters need a local frame
    with execution(execution_cfg):
        result = solve(problem, to_local(T_init, origin_world_m), cfg)
    rep = result.report
    if covariance is not None:
        from pa_cli.adjust.covariance import save_covariance, timed_pose_covariance

        cov, rep["covariance"] = timed_pose_covariance(problem, result.T_world_scan, fixed_pose=fix,
                                                       point_sigma_m=point_sigma_m,
                                                       eigen_gap_tolerance=cfg.eigen_gap_tolerance,
                                                       noise_model=noise_model.value,
                                                       memory_budget_gb=execution_cfg.memory_budget_gb,
                                                       max_block_products=full_config.advanced.covariance.max_block_products,
                                                       model=result.model)
        save_covariance(covariance, cov.in_world(origin_world_m), force=force)
    write_trajectory(out, Trajectory(to_world(result.T_world_scan, origin_world_m), timestamps),
                     fmt=fmt_value(fmt) or "kitti", force=force)
    if report is not None:
        write_report(report, rep, force=force)

    err_console.print(adjust_table(rep, problem.n_points))
    for w in rep["warnings"]:
        log.warning(w)
