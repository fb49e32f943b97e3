"""The `pa` command line. The only place where errors become messages and exit codes.

Exit codes: 0 ok, 1 a known error (`PaError`: message on stderr, no traceback unless
`--debug`), 2 a usage error. Heavy imports (open3d, kiss-icp, the solver) happen inside the
commands so that `pa --help` stays fast.
"""

from __future__ import annotations

import logging
import sys
import traceback
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.logging import RichHandler
from typer.exceptions import TyperException

from pa_cli import __version__
from pa_cli.errors import PaError

err_console = Console(stderr=True)
log = logging.getLogger("pa_cli")

app = typer.Typer(
    name="pa",
    help="LiDAR map refinement by second-order plane adjustment.\n\n"
    "Poses are T_world_scan (maps scan-frame points to the world), metres and seconds.",
    rich_markup_mode="rich",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_state = {"debug": False}


def _setup_logging(level: int) -> None:
    root = logging.getLogger("pa_cli")
    root.handlers.clear()
    handler = RichHandler(console=err_console, show_time=False, show_path=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
    root.propagate = False


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"pa {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True,
                           help="Print the version and exit.")
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks of errors.")] = False,
) -> None:
    _state["debug"] = debug
    _setup_logging(logging.DEBUG if debug else logging.INFO)


class TrajFormat(str, Enum):
    kitti = "kitti"
    tum = "tum"


def _fmt(value: TrajFormat | None) -> str | None:
    return None if value is None else value.value


# --------------------------------------------------------------------------------------------
# pa perturb
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa eval
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa simulate
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# pa adjust
# --------------------------------------------------------------------------------------------


class SolverChoice(str, Enum):
    newton = "newton"
    lm = "lm"


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
    import json

    import numpy as np

    from pa_cli.adjust import SolverOptions, solve
    from pa_cli.config import load_config
    from pa_cli.errors import InputError
    from pa_cli.io.atomic import check_writable, write_text_atomic
    from pa_cli.io.problem import load_problem
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

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
    updates = {"fixed_pose": fix}
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

    result = solve(problem, T_init, SolverOptions.from_config(cfg), solver=solver.value)
    rep = result.report
    write_trajectory(out, Trajectory(result.T_world_scan, timestamps), fmt=_fmt(fmt) or "kitti", force=force)
    if report is not None:
        write_text_atomic(report, json.dumps(rep, indent=2) + "\n", force=force)

    from rich.table import Table

    table = Table(title=f"pa adjust ({rep['solver']})", show_header=False)
    rows = [
        ("scans / planes / observations", f"{rep['n_scans']} / {rep['n_planes']} / {rep['n_observations']}"),
        ("iterations", str(rep["iterations"])),
        ("accepted steps", str(sum(h["accepted"] for h in rep["history"]))),
        ("cost initial (m^2)", f"{rep['cost_initial']:.6g}"),
        ("cost final (m^2)", f"{rep['cost_final']:.6g}"),
        ("RMS point-to-plane (m)", f"{np.sqrt(max(rep['cost_final'], 0.0) / max(problem.n_points, 1)):.4g}"),
        ("converged", f"{rep['converged']} ({rep['stop_reason']})"),
        ("time (s)", f"{rep['time_s']:.3f}"),
    ]
    for k, v in rows:
        table.add_row(k, v)
    err_console.print(table)
    for w in rep["warnings"]:
        log.warning(w)


# --------------------------------------------------------------------------------------------
# pa refine
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# entry point: the one place that maps errors to exit codes
# --------------------------------------------------------------------------------------------


def run(argv: list[str] | None = None) -> int:
    """Run the CLI on `argv` and return the exit code (never raises for known errors)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    _state["debug"] = "--debug" in argv
    try:
        app(args=argv, prog_name="pa", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        err_console.print("Aborted.")
        return 130
    except TyperException as exc:  # click's usage errors (typer vendors click): exit 2
        exc.show(file=sys.stderr)
        return exc.exit_code
    except PaError as exc:
        if _state["debug"]:
            traceback.print_exc(file=sys.stderr)
        err_console.print(f"[bold red]error:[/] {exc}", highlight=False, markup=True,
                          soft_wrap=True)
        return exc.exit_code
    except KeyboardInterrupt:
        err_console.print("Interrupted.")
        return 130
    return 0


def main() -> None:
    sys.exit(run())


if __name__ == "__main__":
    main()
