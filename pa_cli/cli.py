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


@app.command("perturb")
def perturb_command(
    poses: Annotated[Path, typer.Argument(help="Input trajectory (KITTI or TUM), T_world_scan.")],
    out: Annotated[Path, typer.Option("--out", help="Output trajectory file.")],
    rot_deg: Annotated[float | None, typer.Option(
        "--rot-deg", min=0.0, help="Rotation noise sigma per axis, degrees (w ~ N(0, sigma^2 I)).")] = None,
    trans_m: Annotated[float | None, typer.Option(
        "--trans-m", min=0.0, help="Translation noise sigma per axis, metres.")] = None,
    level: Annotated[int | None, typer.Option(
        "--level", min=1, max=4, help="Paper preset: 1=(0.1 deg, 0.01 m) 2=(1 deg, 0.1 m) "
        "3=(2 deg, 0.2 m) 4=(3 deg, 0.3 m). Replaces --rot-deg/--trans-m.")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Random seed; the same seed gives the same file.")] = 0,
    keep_first: Annotated[bool, typer.Option("--keep-first", help="Leave pose 0 unperturbed.")] = False,
    fmt: Annotated[TrajFormat | None, typer.Option(
        "--format", help="Format of the input and output (default: detected from the input).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUT if it exists.")] = False,
) -> None:
    """Perturb every pose with Gaussian noise (Zhou, seed 000, section 5.2).

    t <- t + N(0, SIGMA_T^2 I) and R <- Exp(w) R with w ~ N(0, SIGMA_R^2 I), unless --keep-first.

    Give either --level or both sigmas. The output keeps the input format and TUM timestamps.

    Example:

        pa perturb poses_kitti.txt --rot-deg 1 --trans-m 0.1 --seed 7 --out noisy.txt

        pa perturb poses_tum.txt --level 3 --keep-first --out noisy_tum.txt
    """
    import numpy as np

    from pa_cli.evaluation import PERTURBATION_LEVELS, perturb_poses
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory

    if level is not None:
        if rot_deg is not None or trans_m is not None:
            raise typer.BadParameter("give either --level or --rot-deg/--trans-m, not both.",
                                     param_hint="--level")
        rot_deg, trans_m = PERTURBATION_LEVELS[level]
    elif rot_deg is None or trans_m is None:
        raise typer.BadParameter("give both --rot-deg and --trans-m (or a preset --level 1..4).",
                                 param_hint="--rot-deg/--trans-m")
    check_writable([out], force, inputs=[poses])
    trajectory = read_trajectory(poses, _fmt(fmt))
    out_fmt = _fmt(fmt) or ("tum" if trajectory.timestamps is not None else "kitti")
    rng = np.random.default_rng(seed)
    T_noisy = perturb_poses(trajectory.T_world_scan, np.deg2rad(rot_deg), trans_m, rng,
                            keep_first=keep_first)
    write_trajectory(out, Trajectory(T_noisy, trajectory.timestamps), out_fmt, force)
    log.info("Wrote %d perturbed poses to %s (sigma %.4g deg, %.4g m, seed %d%s).", len(T_noisy),
             out, rot_deg, trans_m, seed, ", first pose kept" if keep_first else "")


# --------------------------------------------------------------------------------------------
# pa eval
# --------------------------------------------------------------------------------------------


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
    import json

    from rich.console import Console
    from rich.table import Table

    from pa_cli.evaluation import apply_alignment, evaluate
    from pa_cli.io.atomic import check_writable, write_text_atomic
    from pa_cli.io.trajectory import read_trajectory

    outputs = [p for p in (json_path, plot) if p is not None]
    check_writable(outputs, force, inputs=[gt, est])
    traj_gt = read_trajectory(gt, _fmt(fmt))
    traj_est = read_trajectory(est, _fmt(fmt))
    result = evaluate(traj_gt, traj_est, align=align.value, max_diff_s=max_diff)

    table = Table(title=f"{est.name} vs {gt.name}: {result['n_poses']} poses, align {align.value}"
                  f" (pairing by {result['pairing']})")
    for column in ("metric", "rmse", "mean", "median", "max"):
        table.add_column(column, justify="left" if column == "metric" else "right")
    table.add_row("ATE translation (m)", *(f"{result[f'ate_{k}_m']:.6f}" for k in ("rmse", "mean", "median", "max")))
    table.add_row("ATE rotation (deg)", f"{result['ate_rot_rmse_deg']:.6f}", f"{result['ate_rot_mean_deg']:.6f}",
                  "", f"{result['ate_rot_max_deg']:.6f}")
    table.add_row("RPE translation (m)", f"{result['rpe_trans_rmse_m']:.6f}", f"{result['rpe_trans_mean_m']:.6f}",
                  "", f"{result['rpe_trans_max_m']:.6f}")
    table.add_row("RPE rotation (deg)", f"{result['rpe_rot_rmse_deg']:.6f}", f"{result['rpe_rot_mean_deg']:.6f}",
                  "", f"{result['rpe_rot_max_deg']:.6f}")
    Console(width=110).print(table)
    if align.value == "sim3":
        typer.echo(f"sim3 scale: {result['scale']:.9f}")

    if json_path is not None:
        report = {"gt": str(gt), "est": str(est), **result}
        write_text_atomic(json_path, json.dumps(report, indent=2) + "\n", force)
    if plot is not None:
        import numpy as np

        from pa_cli.report import plot_trajectories_top_view

        A = np.asarray(result["alignment"])
        T_est_aligned = apply_alignment(traj_est.T_world_scan, A, result["scale"])
        plot_trajectories_top_view(plot, [("ground truth", traj_gt.T_world_scan),
                                          (f"estimate ({align.value}-aligned)", T_est_aligned)],
                                   title=f"ATE rmse {result['ate_rmse_m']:.4f} m", force=force)


# --------------------------------------------------------------------------------------------
# pa simulate
# --------------------------------------------------------------------------------------------


class SceneName(str, Enum):
    office = "office"
    street = "street"
    town = "town"
    blocks = "blocks"


@app.command()
def simulate(
    scene: Annotated[SceneName, typer.Argument(help="Built-in scene: office (indoor floor, 30 x 20 m), "
                                               "street (outdoor, ~150 m), town (a grid of city blocks) or "
                                               "blocks (the same grid, every block identical).")],
    out_dir: Annotated[str, typer.Argument(help="Output folder (must not exist or be empty, "
                                           "unless --force).")],
    scans: Annotated[int, typer.Option(help="Number of scans (one per 0.1 s); more than a lap drives the path again.")] = 50,
    path: Annotated[str | None, typer.Option(
        help="Sensor path: loop (office, street); circuit (default) or figure8 (town, blocks).")] = None,
    step_m: Annotated[float | None, typer.Option(
        help="Path length per scan (m); default 0.1 (office, walking) or 1.0 (street, driving).")] = None,
    beams: Annotated[int, typer.Option(help="Number of laser beams: 16, 32 or 64.")] = 16,
    vfov_deg: Annotated[float | None, typer.Option(
        help="Vertical field of view (deg), symmetric about the horizon; default 30 / 40 / 45 "
             "for 16 / 32 / 64 beams.")] = None,
    azimuth_steps: Annotated[int, typer.Option(help="Columns per 360 deg sweep.")] = 1024,
    range_noise_m: Annotated[float, typer.Option(help="Gaussian range noise along the ray, sigma (m).")] = 0.01,
    max_range_m: Annotated[float | None, typer.Option(
        help="Drop returns farther than this (m); default 30 (office) or 100 (street).")] = None,
    min_range_m: Annotated[float, typer.Option(help="Drop returns closer than this (m).")] = 0.5,
    seed: Annotated[int, typer.Option(help="Random seed of the range noise (same seed: identical files).")] = 0,
    motion_distortion: Annotated[bool, typer.Option(
        "--motion-distortion/--no-motion-distortion",
        help="Cast each azimuth column from the pose at its firing time and store per-point time.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace the contents of a non-empty OUT_DIR.")] = False,
) -> None:
    r"""Ray-cast a LiDAR sequence with exact ground truth (poses, plane labels, plane equations).

    Outputs in OUT_DIR (built beside it, then renamed into place):
    - scans/000000.pcd ...: binary PCD, float32 x y z intensity \[time], points in the sensor frame
    - labels/000000.npy ...: int32 true plane label per point (same order), -1 = no plane
    - planes.npy: (P, 4) rows n_x n_y n_z d with n.x + d = 0 (world frame, m), row = label
    - gt_poses_kitti.txt, gt_poses_tum.txt: T_world_scan at each scan's start, timestamps k * 0.1 s
    - meta.json: scene, options, seed, version

    Example:

        pa simulate office out/office --scans 60 --beams 16 --seed 1
    """
    from rich.progress import Progress

    from pa_cli.simulate import SimOptions, check_simulation
    from pa_cli.simulate import simulate as run_simulation

    options = SimOptions(scene=scene.value, path=path, scans=scans, step_m=step_m, beams=beams, vfov_deg=vfov_deg,
                         azimuth_steps=azimuth_steps, range_noise_m=range_noise_m,
                         max_range_m=max_range_m, min_range_m=min_range_m, seed=seed,
                         motion_distortion=motion_distortion)
    check_simulation(options, out_dir, force)  # errors before the progress bar opens
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task(f"simulate {scene.value}", total=scans)
        meta = run_simulation(options, out_dir, force=force,
                              progress=lambda done, total: bar.update(task, completed=done))
    log.info("wrote %d scans, %d points, %d true planes to %s", meta["n_scans"], meta["n_points"],
             meta["n_planes"], out_dir)


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


class SolverChoice(str, Enum):
    newton = "newton"
    lm = "lm"


@app.command("refine")
def refine_command(
    scans_dir: Annotated[Path | None, typer.Argument(
        help="Folder of scans (PCD/PLY/BIN, sensor frame, metres), sorted naturally.",
        show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Map to write (.ply); the other outputs are named after its stem.",
        show_default=False)] = None,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial poses T_world_scan (KITTI or TUM, one per scan); skips KISS-ICP.")] = None,
    gt: Annotated[Path | None, typer.Option(
        "--gt", help="Ground-truth poses (KITTI or TUM): ATE of initial and refined poses in the report.")] = None,
    config_path: Annotated[Path | None, typer.Option(
        "--config", "-c", help="YAML config (see configs/default.yaml); missing keys keep defaults.")] = None,
    solver: Annotated[SolverChoice | None, typer.Option(
        "--solver", help="newton (planes eliminated) or lm (PA_LM baseline); overrides the config.")] = None,
    rounds: Annotated[int | None, typer.Option(
        "--rounds", min=1, help="Association + adjustment rounds at most; overrides refine.rounds.")] = None,
    no_loops: Annotated[bool, typer.Option(
        "--no-loops", help="Skip loop closure (start the rounds from the odometry); sets loops.enabled: false.")] = False,
    save_problem: Annotated[Path | None, typer.Option(
        "--save-problem", help="Also write the last round's plane problem (.npz, for pa adjust).")] = None,
    glob: Annotated[str | None, typer.Option(
        "--glob", help="Only scans whose file name matches this pattern, e.g. '*.pcd'.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars, warnings only.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug messages.")] = False,
    print_config: Annotated[bool, typer.Option(
        "--print-config", help="Print the effective config (defaults < --config < flags) as YAML and exit.")] = False,
) -> None:
    """Refine LiDAR scan poses by plane adjustment and write a merged map.

    Stages (each with a progress bar on stderr): load the scans; initial poses by KISS-ICP (or --poses); loop closure (candidates by place descriptors, verified by registration, pose graph; --no-loops skips it); rounds of plane association at the current poses and second-order plane adjustment, until no pose moves more than refine.pose_change_tolerance_m/_deg or --rounds is reached; write.

    Outputs next to MAP.ply: MAP.ply (map, float32 x y z + int32 scan_index, world frame), MAP_poses_kitti.txt, MAP_poses_tum.txt, MAP_initial_poses_kitti.txt, MAP_report.json, MAP_config.yaml. Existing outputs are refused without --force.

    Poses are T_world_scan; with KISS-ICP the world frame is the frame of scan 0.

    Example:

        pa refine sample_data/office/scans --out office_map.ply --config configs/indoor.yaml --gt sample_data/office/gt_poses_tum.txt

        pa refine --print-config --config configs/indoor.yaml
    """
    from pa_cli.config import dump_config, load_config

    config = load_config(config_path)
    if solver is not None:
        config.solver.solver = solver.value
    if rounds is not None:
        config.refine.rounds = rounds
    if no_loops:
        config.loops.enabled = False
    if print_config:
        typer.echo(dump_config(config), nl=False)
        return
    if scans_dir is None:
        raise typer.BadParameter("SCANS_DIR is required (a folder of scans).", param_hint="SCANS_DIR")
    if out is None:
        raise typer.BadParameter("--out MAP.ply is required.", param_hint="--out")
    if out.suffix.lower() != ".ply":
        raise typer.BadParameter(f"expected a .ply path, got '{out}'.", param_hint="--out")
    if quiet:
        logging.getLogger("pa_cli").setLevel(logging.WARNING)
    elif verbose:
        logging.getLogger("pa_cli").setLevel(logging.DEBUG)

    from pa_cli.pipeline import RefinePipeline
    from pa_cli.report import print_refine_summary

    pipeline = RefinePipeline(scans_dir, out, config, poses=poses, gt=gt, save_problem=save_problem,
                              glob=glob, force=force, show_progress=not quiet,
                              config_source=str(config_path) if config_path else "defaults")
    report = pipeline.run()
    if not quiet:
        print_refine_summary(report, err_console)
    log.info("wrote %s and %s", out, ", ".join(
        str(p) for p in pipeline.outputs.all() if p != out))


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
