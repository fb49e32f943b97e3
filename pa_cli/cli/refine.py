"""`pa refine`: scans (folder or ROS bag) -> refined poses and a merged map."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import (
    CONFIG_HELP,
    CONFIG_METAVAR,
    SCHEDULER_HELP,
    WORKERS_HELP,
    SolverChoice,
    app,
    err_console,
    execution_config,
    log,
    require,
    set_verbosity,
)


@app.command("refine")
def refine_command(
    scans: Annotated[Path | None, typer.Argument(
        metavar="SCANS", help="Folder of scans (PCD/PLY/BIN, sensor frame, metres, sorted naturally) or a ROS bag "
        "(ROS1 .bag, ROS2 .db3/.mcap file or bag folder) with --topic.", show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Map to write: .ply, .las or .laz (by suffix); the other outputs are named after its "
        "stem.", show_default=False)] = None,
    topic: Annotated[str | None, typer.Option(
        "--topic", help="ROS bag: the sensor_msgs/PointCloud2 topic to read, e.g. /points.")] = None,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial poses T_world_scan (KITTI or TUM, one per scan); skips KISS-ICP.")] = None,
    gt: Annotated[Path | None, typer.Option(
        "--gt", help="Ground-truth poses (KITTI or TUM): ATE of initial and refined poses in the report.")] = None,
    config_path: Annotated[str | None, typer.Option(
        "--config", "-c", metavar=CONFIG_METAVAR, help=CONFIG_HELP)] = None,
    solver: Annotated[SolverChoice | None, typer.Option(
        "--solver", help="newton (planes eliminated) or lm (PA_LM baseline); overrides the config.")] = None,
    rounds: Annotated[int | None, typer.Option(
        "--rounds", min=1, help="Association + adjustment rounds at most; overrides refine.max_rounds.")] = None,
    loops: Annotated[bool | None, typer.Option(
        "--loops/--no-loops",
        help="Close loops before the rounds (candidates by place descriptors, verified by registration, pose graph) "
        "or not; overrides loops.enabled.")] = None,
    save_problem: Annotated[Path | None, typer.Option(
        "--save-problem", help="Also write the last round's plane problem (.npz, for pa adjust).")] = None,
    glob: Annotated[str | None, typer.Option(
        "--glob", help="Only scans whose file name matches this pattern, e.g. '*.pcd'.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars, warnings only.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug messages.")] = False,
    workers: Annotated[int | None, typer.Option("--workers", min=0, help=WORKERS_HELP)] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help=SCHEDULER_HELP)] = None,
    print_config: Annotated[bool, typer.Option(
        "--print-config", help="Print the effective config (defaults < --config < flags) as YAML and exit; "
        "`pa config show` prints a preset's or a file's.")] = False,
    strict: Annotated[bool, typer.Option(
        "--strict", help="Exit 1 when the quality verdict is not 'improved' (outputs are still written).")] = False,
) -> None:
    """Refine LiDAR scan poses by plane adjustment and write a merged map.

    Stages (each with a progress bar on stderr): load the scans (every scan's header is checked first); initial poses by KISS-ICP (or --poses); loop closure when loops.enabled or --loops (candidates by place descriptors, verified by registration, pose graph); motion compensation when the scans have per-point times; rounds of plane association at the current poses and second-order plane adjustment with odometry factors, until no pose moves more than refine.pose_change_tolerance_m/_deg (settled) or --rounds is reached; degeneracy and the quality verdict (improved / uncertain / degraded, a warning when not improved; --strict exits 1); write.

    Outputs next to the map: MAP.ply (float32 x y z + int32 scan_index, world frame) or MAP.las/.laz (x y z, extra dimension scan_index, gps_time when the scans have timestamps), MAP_poses_kitti.txt, MAP_poses_tum.txt, MAP_initial_poses_kitti.txt, MAP_report.json, MAP_config.yaml. Existing outputs are refused without --force.

    Poses are T_world_scan; with KISS-ICP the world frame is the frame of scan 0.

    Scans from a ROS bag: each sensor_msgs/PointCloud2 message of --topic is one scan, its header stamp the scan's timestamp.

    Example:

        pa refine run.bag --topic /points --out map.las

        pa refine sample_data/office/scans --out office_map.ply --config indoor --gt sample_data/office/gt_poses_tum.txt

        pa config show outdoor > my.yaml  (then edit my.yaml)

        pa refine scans/ --out map.ply --config my.yaml

        pa refine scans/ --out map.ply --workers 2
    """
    from pa_cli.config import dump_config, load_config

    config = load_config(config_path)
    if solver is not None:
        config.advanced.solver.solver = solver.value
    if rounds is not None:
        config.refine.max_rounds = rounds
    config.execution = execution_config(config.execution, workers, scheduler)
    if loops is not None:
        config.loops.enabled = loops
    if print_config:
        typer.echo(dump_config(config, advanced=False), nl=False)
        return
    require(scans, "SCANS is required (a folder of scans or a ROS bag).", "SCANS")
    require(out, "--out MAP.ply (or .las, .laz) is required.", "--out")
    from pa_cli.io.maps import MAP_SUFFIXES

    if out.suffix.lower() not in MAP_SUFFIXES:
        raise typer.BadParameter(f"expected a map path ending in {' '.join(MAP_SUFFIXES)}, got '{out}'.",
                                 param_hint="--out")
    set_verbosity(quiet, verbose)

    from pa_cli.cli.tables import print_refine_summary
    from pa_cli.refine.pipeline import RefinePipeline

    pipeline = RefinePipeline(scans, out, config, topic=topic, poses=poses, gt=gt, save_problem=save_problem,
                              glob=glob, force=force, show_progress=not quiet,
                              config_source=str(config_path) if config_path else "defaults")
    report = pipeline.run()
    if not quiet:
        print_refine_summary(report, err_console)
    log.info("wrote %s and %s", out, ", ".join(
        str(p) for p in pipeline.outputs.all() if p != out and p.exists()))  # no covariance file when skipped
    from pa_cli.errors import QualityError
    from pa_cli.evaluation.quality import verdict_warning

    warning = verdict_warning(report.get("quality"))
    if warning is not None:
        err_console.print(warning, style="bold red")
        if strict:
            raise QualityError(f"{out}: quality verdict '{report['quality']['verdict']}' with --strict "
                               "(the outputs were written for inspection).")
