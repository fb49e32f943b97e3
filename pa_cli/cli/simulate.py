"""`pa simulate`: ray-cast LiDAR sequences with exact ground truth."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import app, err_console, log


class SceneName(str, Enum):
    office = "office"
    street = "street"
    town = "town"
    blocks = "blocks"
    avenue = "avenue"
    hall = "hall"


@app.command()
def simulate(
    scene: Annotated[SceneName, typer.Argument(help="Built-in scene: office (indoor floor, 30 x 20 m), "
                                               "street (outdoor, ~150 m), town (a grid of city blocks), "
                                               "blocks (the same grid, every block identical), avenue (a long "
                                               "sparse street, few facades, repeated structure) or hall (an "
                                               "empty 60 x 30 m hall, walls and floor only).")],
    out_dir: Annotated[str, typer.Argument(help="Output folder (must not exist or be empty, "
                                           "unless --force).")],
    scans: Annotated[int, typer.Option(help="Number of scans (one per 0.1 s); more than a lap drives the path again.")] = 50,
    path: Annotated[str | None, typer.Option(
        help="Sensor path: loop (office, street, avenue); circuit (default) or figure8 (town, blocks); "
             "loop (default) or sharp (hall: turns of up to 22.5 deg per scan).")] = None,
    step_m: Annotated[float | None, typer.Option(
        help="Path length per scan (m); default 0.1 (office, walking), 1.0 (street, town, avenue, driving) "
             "or 0.9 (hall).")] = None,
    beams: Annotated[int, typer.Option(help="Number of laser beams: 16, 32 or 64.")] = 16,
    vfov_deg: Annotated[float | None, typer.Option(
        help="Vertical field of view (deg), symmetric about the horizon; default 30 / 40 / 45 "
             "for 16 / 32 / 64 beams.")] = None,
    azimuth_steps: Annotated[int, typer.Option(help="Columns per 360 deg sweep.")] = 1024,
    range_noise_m: Annotated[float, typer.Option(help="Gaussian range noise along the ray, sigma (m).")] = 0.01,
    realistic: Annotated[bool, typer.Option(
        "--realistic", help="Turn on a realistic mix (each can be overridden by its own flag): vegetation 0.4, "
        "curved cars, road camber 0.1 m and undulation 0.03 m, facade relief (street scenes only); "
        "range noise + 0.001 per m, mixed pixels 0.02, dropout 0.05 (every scene).",
        rich_help_panel="Realism")] = False,
    vegetation: Annotated[float | None, typer.Option(
        help="Share of the street's length (0..1) with trees (trunk and scatter crown) and hedges: returns "
             "off any plane that move from scan to scan (street, avenue).", rich_help_panel="Realism")] = None,
    curved_cars: Annotated[bool | None, typer.Option(
        "--curved-cars/--no-curved-cars", help="Parked cars as rounded bodies of small triangles instead of "
        "boxes (street, avenue).", rich_help_panel="Realism")] = None,
    road_camber_m: Annotated[float | None, typer.Option(
        help="Road crown: drop from the centre line to the kerb (m), quadratic across (street, avenue).",
        rich_help_panel="Realism")] = None,
    road_undulation_m: Annotated[float | None, typer.Option(
        help="Amplitude (m) of a slow swell of the road along it (30 m wavelength) (street, avenue).",
        rich_help_panel="Realism")] = None,
    facade_relief: Annotated[bool | None, typer.Option(
        "--facade-relief/--no-facade-relief", help="Facades of pilasters, bays recessed 0.1-0.5 m and "
        "balconies (street, avenue).", rich_help_panel="Realism")] = None,
    facade_gaps: Annotated[bool | None, typer.Option(
        "--facade-gaps/--no-facade-gaps", help="Leave out some buildings (never two in a row): open lots of "
        "10-30 m (street, avenue).", rich_help_panel="Realism")] = None,
    range_noise_per_m: Annotated[float | None, typer.Option(
        help="Range noise grows with range: sigma = --range-noise-m + this * range (0.001 = 0.1 %).",
        rich_help_panel="Realism")] = None,
    point_noise_m: Annotated[float | None, typer.Option(
        help="Isotropic 3D Gaussian noise added to every point, sigma (m).", rich_help_panel="Realism")] = None,
    mixed_pixels: Annotated[float | None, typer.Option(
        help="Share of all returns (0..1) placed between the two surfaces of a depth edge (label -1).",
        rich_help_panel="Realism")] = None,
    dropout: Annotated[float | None, typer.Option(
        help="Share of returns (0..0.99) missing at random.", rich_help_panel="Realism")] = None,
    max_range_m: Annotated[float | None, typer.Option(
        help="Drop returns farther than this (m); default 30 (office) or 100 (street).")] = None,
    min_range_m: Annotated[float, typer.Option(help="Drop returns closer than this (m).")] = 0.5,
    seed: Annotated[int, typer.Option(help="Random seed of the range noise (same seed: identical files).")] = 0,
    motion_distortion: Annotated[bool, typer.Option(
        "--motion-distortion",
        help="Cast each azimuth column from the pose at its firing time and store per-point time.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace the contents of a non-empty OUT_DIR.")] = False,
    rig: Annotated[Path | None, typer.Option(
        "--rig", help="Rig file (YAML) listing several LiDARs (mounting xyz_m + rpy_deg, beams, vfov_deg, "
        "hfov_deg): writes OUT_DIR/lidar0/, lidar1/, ... and gt_extrinsics.yaml for pa calibrate; --beams and "
        "--vfov-deg then come from the rig file.")] = None,
) -> None:
    r"""Ray-cast a LiDAR sequence with exact ground truth (poses, plane labels, plane equations).

    Outputs in OUT_DIR (built beside it, then renamed into place):
    - scans/000000.pcd ...: binary PCD, float32 x y z intensity \[time], points in the sensor frame
    - labels/000000.npy ...: int32 true plane label per point (same order), -1 = no plane
    - planes.npy: (P, 4) rows n_x n_y n_z d with n.x + d = 0 (world frame, m), row = label
    - gt_poses_kitti.txt, gt_poses_tum.txt: T_world_scan at each scan's start, timestamps k * 0.1 s
    - meta.json: scene, options, seed, version

    With --rig: lidar0/ lidar1/ ... (PCD scans of each LiDAR, sensor frame), times.txt, gt_poses_*.txt (T_world_base, base = lidar0), gt_extrinsics.yaml (true T_base_lidar), rig.yaml, meta.json.

    Example:

        pa simulate office out/office --scans 60 --beams 16 --seed 1

        pa simulate office out/rig --rig rig.yaml --scans 30

        pa simulate street out/real --scans 60 --realistic
    """
    from rich.progress import Progress

    from pa_cli.simulate import SimOptions, check_simulation
    from pa_cli.simulate import simulate as run_simulation

    options = SimOptions(scene=scene.value, path=path, scans=scans, step_m=step_m, beams=beams, vfov_deg=vfov_deg,
                         azimuth_steps=azimuth_steps, range_noise_m=range_noise_m,
                         max_range_m=max_range_m, min_range_m=min_range_m, seed=seed,
                         motion_distortion=motion_distortion, realistic=realistic, vegetation=vegetation,
                         curved_cars=curved_cars, road_camber_m=road_camber_m, road_undulation_m=road_undulation_m,
                         facade_relief=facade_relief, facade_gaps=facade_gaps, range_noise_per_m=range_noise_per_m,
                         point_noise_m=point_noise_m, mixed_pixels=mixed_pixels, dropout=dropout)
    check_simulation(options, out_dir, force)  # errors before the progress bar opens
    if rig is not None:
        from pa_cli.simulate.rig import read_rig, simulate_rig

        n_lidars = len(read_rig(rig))  # errors before the progress bar opens
        with Progress(console=err_console, transient=True) as bar:
            task = bar.add_task(f"simulate {scene.value} rig", total=n_lidars * scans)
            meta = simulate_rig(options, rig, out_dir, force=force,
                                progress=lambda done, total: bar.update(task, completed=done))
        log.info("wrote %d LiDARs x %d scans (%d points) to %s", meta["n_lidars"], meta["n_scans"],
                 sum(meta["n_points"]), out_dir)
        return
    with Progress(console=err_console, transient=True) as bar:
        task = bar.add_task(f"simulate {scene.value}", total=scans)
        meta = run_simulation(options, out_dir, force=force,
                              progress=lambda done, total: bar.update(task, completed=done))
    log.info("wrote %d scans, %d points, %d true planes to %s", meta["n_scans"], meta["n_points"],
             meta["n_planes"], out_dir)
