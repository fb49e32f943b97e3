"""`pa calibrate`: a rig folder (lidar0/, lidar1/, ...) -> extrinsics, base poses, map, report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import CONFIG_HELP, CONFIG_METAVAR, app, log, require, set_verbosity


@app.command("calibrate")
def calibrate_command(
    rig_dir: Annotated[Path | None, typer.Argument(
        metavar="RIG_DIR", help="Rig folder: one scan folder per LiDAR, lidar0/ (the base), lidar1/, ...; scans "
        "matched by times.txt when every LiDAR has one, else by index.", show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Extrinsics to write (.yaml); the other outputs are named after its stem.",
        show_default=False)] = None,
    init: Annotated[Path | None, typer.Option(
        "--init", help="Initial extrinsics (YAML: per LiDAR T_base_lidar, or xyz_m + rpy_deg); default identity.")
    ] = None,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Initial base poses T_world_base (KITTI or TUM, one per lidar0 scan); skips KISS-ICP.")
    ] = None,
    config_path: Annotated[str | None, typer.Option(
        "--config", "-c", metavar=CONFIG_METAVAR, help=CONFIG_HELP + " Its advanced.calibrate section tunes the "
        "calibration.")] = None,
    first: Annotated[int, typer.Option(
        "--first", min=0, metavar="N", help="First lidar0 scan to use (0-based index, kept).")] = 0,
    last: Annotated[int | None, typer.Option(
        "--last", min=0, metavar="M", help="Last lidar0 scan to use (0-based index, kept); default: the last.")] = None,
    every: Annotated[int, typer.Option(
        "--every", min=1, metavar="K", help="Use every K-th lidar0 scan from --first; the other LiDARs' scans are "
        "matched to the kept ones, --poses with one pose per lidar0 scan follows.")] = 1,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing outputs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Warnings only.")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Debug messages.")] = False,
    print_config: Annotated[bool, typer.Option(
        "--print-config", help="Print the effective config (defaults < --config) as YAML and exit, as `pa config "
        "show` does.")] = False,
) -> None:
    """Calibrate the extrinsics of a multi-LiDAR rig and refine the base poses together.

    Stages: base poses by KISS-ICP on lidar0 (or --poses); initial extrinsics from --init (or identity, with a warning); coarse point-to-plane ICP of each LiDAR against lidar0's map; rounds of plane association and joint second-order adjustment of base poses and extrinsics; observability: extrinsic directions the motion and scene do not determine are named ("lidar1: translation along base z") and held at the --init value; covariance; write.

    Outputs: EXTRINSICS.yaml (T_base_lidar as 4x4 and xyz_m + rpy_deg per LiDAR, with 1-sigma and unobservable directions), EXTRINSICS_base_poses_kitti.txt, EXTRINSICS_base_poses_tum.txt, EXTRINSICS_map.ply (x y z, scan_index, lidar_index), EXTRINSICS_report.json (6x6 covariance per extrinsic). Existing outputs are refused without --force.

    Example:

        pa simulate office rig/ --rig rig.yaml --scans 30

        pa calibrate rig/ --out extrinsics.yaml --init measured.yaml --config indoor
    """
    from pa_cli.config import dump_config, load_config

    config = load_config(config_path)
    if print_config:
        typer.echo(dump_config(config, advanced=False), nl=False)
        return
    require(rig_dir, "RIG_DIR is required (a folder with lidar0/, lidar1/, ...).", "RIG_DIR")
    require(out, "--out EXTRINSICS.yaml is required.", "--out")
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise typer.BadParameter(f"expected a path ending in .yaml or .yml, got '{out}'.", param_hint="--out")
    set_verbosity(quiet, verbose)
    from pa_cli.calibration import CalibrationRun
    from pa_cli.sources import ScanSubset

    report = CalibrationRun(rig_dir, out, config, init=init, poses=poses, subset=ScanSubset(first, last, every),
                            force=force).run()
    for name, entry in report["extrinsics"].items():
        if name == "lidar0":
            continue
        xyz, rpy = entry["xyz_m"], entry["rpy_deg"]
        log.info("%s: xyz %.4f %.4f %.4f m, rpy %.4f %.4f %.4f deg%s", name, *xyz, *rpy,
                 "".join(f"; {w}" for w in entry["unobservable"]))
    log.info("wrote %s", ", ".join(str(p) for p in report["outputs"].values()))
