"""`pa refine`: scans (folder or ROS bag) -> refined poses and a merged map."""

from __future__ import annotations

import contextlib
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
    warning_folder,
)


@app.command("refine")
def refine_command(
    scans: Annotated[Path | None, typer.Argument(
        metavar="SCANS", help="Folder of scans (PCD/PLY/BIN, sensor frame, metres, sorted naturally), a ROS bag "
        "(ROS1 .bag, ROS2 .db3/.mcap file or bag folder) with --topic, or a dataset's sequence folder (KITTI "
        "odometry, MulRan, Newer College, NCLT) or Ouster .pcap (docs/formats.md).", show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Map to write: .ply, .pcd, .las or .laz (by suffix); the other outputs are named after "
        "its stem.", show_default=False)] = None,
    topic: Annotated[str | None, typer.Option(
        "--topic", help="ROS bag: the topic to read (PointCloud2 messages), e.g. /points.")] = None,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial poses T_world_scan (KITTI or TUM, one per scan); skips KISS-ICP.")] = None,
    gt: Annotated[Path | None, typer.Option(
        "--gt", help="Ground-truth poses (KITTI or TUM, or a dataset's own file, converted to the LiDAR: "
        "docs/formats.md): ATE of initial and refined poses in the report.")] = None,
    config_path: Annotated[str | None, typer.Option(
        "--config", "-c", metavar=CONFIG_METAVAR, help=CONFIG_HELP)] = None,
    solver: Annotated[SolverChoice | None, typer.Option(
        "--solver", help="newton (planes eliminated) or lm (PA_LM baseline); overrides the config.")] = None,
    rounds: Annotated[int | None, typer.Option(
        "--rounds", min=1, metavar="N", help="Association + adjustment rounds at most; overrides refine.max_rounds.")] = None,
    loops: Annotated[bool | None, typer.Option(
        "--loops/--no-loops",
        help="Close loops before the rounds (candidates by place descriptors, verified by registration, pose graph) "
        "or not; overrides loops.enabled (on by default).")] = None,
    map_voxel_m: Annotated[float | None, typer.Option(
        "--map-voxel-m", min=0.0, help="Map density: one point per voxel of this edge (m), 0 keeps every point; "
        "overrides map.voxel_m.")] = None,
    save_problem: Annotated[Path | None, typer.Option(
        "--save-problem", help="Also write the last round's plane problem (.npz, for pa adjust).")] = None,
    glob: Annotated[str | None, typer.Option(
        "--glob", help="Only scans whose file name matches this pattern, e.g. '*.pcd'.")] = None,
    first: Annotated[int, typer.Option(
        "--first", min=0, metavar="N", help="First scan to use (0-based index, kept).")] = 0,
    last: Annotated[int | None, typer.Option(
        "--last", min=0, metavar="M", help="Last scan to use (0-based index, kept); default: the last.")] = None,
    every: Annotated[int, typer.Option(
        "--every", min=1, metavar="K", help="Use every K-th scan from --first; --gt and --poses with one pose per "
        "scan follow.")] = 1,
    force: Annotated[bool, typer.Option(
        "--force", help="Overwrite existing outputs; without --resume, also start over from an earlier run's work "
        "folder.")] = False,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue a stopped run (crash, kill, Ctrl-C) from the last finished stage kept in its work "
        "folder MAP.work; the result equals an uninterrupted run's. Refused when the inputs or the config "
        "changed.")] = False,
    keep_work: Annotated[bool, typer.Option(
        "--keep-work", help="Keep the work folder MAP.work (each finished stage's result) after a successful run.")
    ] = False,
    quiet: Annotated[bool, typer.Option(
        "--quiet", "-q", help="No progress bars or table: warnings and the verdict line only.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug messages.")] = False,
    workers: Annotated[int | None, typer.Option("--workers", min=0, metavar="N", help=WORKERS_HELP)] = None,
    scheduler: Annotated[str | None, typer.Option("--scheduler", help=SCHEDULER_HELP)] = None,
    print_config: Annotated[bool, typer.Option(
        "--print-config", help="Print the effective config (defaults < --config < flags) as YAML and exit; "
        "`pa config show` prints a preset's or a file's.")] = False,
    strict: Annotated[bool, typer.Option(
        "--strict", help="Exit 1 when the quality verdict is not 'improved' (outputs are still written).")] = False,
) -> None:
    """Refine LiDAR scan poses by plane adjustment and write a merged map.

    Stages (each with a progress bar on stderr): load the scans (every scan's header is checked first); initial poses by KISS-ICP (or --poses); loop closure unless loops.enabled is false or --no-loops (candidates by place descriptors, verified by registration, pose graph); motion compensation when the scans have per-point times; rounds of plane association at the current poses and second-order plane adjustment with odometry factors, until no pose moves more than refine.pose_change_tolerance_m/_deg (settled) or --rounds is reached; degeneracy and the quality verdict (improved / uncertain / degraded, a warning when not improved; --strict exits 1); write.

    The map (world frame) keeps each scan's points within the sensor range (sensor.min_range_m .. max_range_m from the sensor) and then one point per map.voxel_m voxel (--map-voxel-m; 0: every point), with the scan index, the intensity when the scans have one and the time when the scans have timestamps: MAP.ply (x y z float32, scan_index int, intensity float, time double), MAP.pcd (the same fields, binary PCD) or MAP.las/.laz (x y z, extra dimension scan_index, gps_time, intensity as uint16: see docs/pictures.md for its scale).

    While it runs, the work folder MAP.work next to the map keeps each finished stage (initial poses, loop closures, each round's poses and association); after a crash, a kill or Ctrl-C (exit 130), the same command with --resume continues from the last finished stage. It is removed when the outputs are written (--keep-work keeps it); an existing one is refused without --resume or --force.

    Outputs next to the map: MAP_poses_kitti.txt, MAP_poses_tum.txt, MAP_initial_poses_kitti.txt, MAP_report.json, MAP_config.yaml, MAP_overview.png (a slice of the map before and after, the correction per scan, the error against --gt over time). Existing outputs are refused without --force.

    Poses are T_world_scan; with KISS-ICP the world frame is the frame of scan 0.

    Scans from a ROS bag: each sensor_msgs/PointCloud2 message of --topic is one scan, its header stamp the scan's timestamp.

    Scans from a dataset: a KITTI odometry sequence folder (or its velodyne/), a MulRan, Newer College or NCLT sequence folder, or an Ouster .pcap with its metadata .json (docs/formats.md); the layout found is logged, with its ground-truth file for --gt.

    --first N --last M --every K: scans N to M (0-based indices, both kept), every K-th.

    Example:

        pa refine run.bag --topic /points --out map.las

        pa refine sample_data/office/scans --out office_map.ply --config indoor --gt sample_data/office/gt_poses_tum.txt

        pa config show outdoor > my.yaml  (then edit my.yaml)

        pa refine scans/ --out map.ply --config my.yaml

        pa refine scans/ --out map.ply --workers 2

        pa refine kitti/sequences/00 --out map.ply --gt kitti/poses/00.txt --first 0 --last 499 --every 2

        pa refine scans/ --out map.ply --resume  (after a crash, a kill or Ctrl-C)
    """
    from pa_cli.config import dump_config, load_config
    from pa_cli.sources.subset import ScanSubset

    subset = ScanSubset(first, last, every)
    config_source = str(config_path) if config_path else "defaults"
    if config_path is None and scans is not None and not print_config:
        from pa_cli.refine.auto_preset import choose_preset
        from pa_cli.sources import open_source

        with contextlib.closing(open_source(scans, topic=topic, glob=glob, subset=subset)) as source:
            choice = choose_preset(source)
        log.info("%s", choice.reason())
        config_path, config_source = choice.name, f"{choice.name} (chosen from the scans)"
    config = load_config(config_path)
    if solver is not None:
        config.advanced.solver.solver = solver.value
    if rounds is not None:
        config.refine.max_rounds = rounds
    if map_voxel_m is not None:
        config.map.voxel_m = map_voxel_m
    config.execution = execution_config(config.execution, workers, scheduler)
    if loops is not None:
        config.loops.enabled = loops
    if print_config:
        typer.echo(dump_config(config, advanced=False), nl=False)
        return
    require(scans, "SCANS is required (a folder of scans or a ROS bag).", "SCANS")
    require(out, "--out MAP.ply (or .pcd, .las, .laz) is required.", "--out")
    from pa_cli.io.maps import MAP_SUFFIXES

    if out.suffix.lower() not in MAP_SUFFIXES:
        raise typer.BadParameter(f"expected a map path ending in {' '.join(MAP_SUFFIXES)}, got '{out}'.",
                                 param_hint="--out")
    set_verbosity(quiet, verbose)

    from pa_cli.planes.warm_up import compile_in_background

    compile_in_background()  # a first run: the plane kernels compile beside the start of the run
    from pa_cli.cli.tables import print_refine_summary, refine_verdict_line
    from pa_cli.refine.pipeline import RefinePipeline

    pipeline = RefinePipeline(scans, out, config, topic=topic, poses=poses, gt=gt, save_problem=save_problem,
                              glob=glob, subset=subset, force=force, show_progress=not quiet,
                              config_source=config_source, resume=resume, keep_work=keep_work)
    try:
        report = pipeline.run()
    except KeyboardInterrupt:
        if pipeline.work is not None and pipeline.work.path.exists():
            err_console.print(f"the finished stages are kept in {pipeline.work.path}; run the same command with "
                              "--resume to continue from the last one.", highlight=False, soft_wrap=True)
        raise
    warning_folder.flush()  # the run's repeated warnings, before its result
    if quiet:
        err_console.print(refine_verdict_line(report), highlight=False, soft_wrap=True)
    else:
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
