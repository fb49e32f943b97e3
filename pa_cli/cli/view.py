"""`pa view`: look at a map written by `pa refine`, in an Open3D window or as a PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pa_cli.cli.app import app, log
from pa_cli.io.maps import ColorBy  # the map formats only: the pictures load matplotlib and Open3D


@app.command("view")
def view_command(
    map_path: Annotated[Path, typer.Argument(
        metavar="MAP", help="A map written by pa refine (.ply, .pcd, .las or .laz).", show_default=False)],
    color: Annotated[ColorBy, typer.Option(
        "--color", help="Colour the points by scan index, time, height (z) or intensity.")] = ColorBy.scan,
    poses: Annotated[Path | None, typer.Option(
        "--poses", help="Trajectory to draw (KITTI or TUM); default: MAP_poses_kitti.txt next to the map, when "
        "present.", show_default=False)] = None,
    png: Annotated[Path | None, typer.Option(
        "--png", help="Render to this PNG instead of opening a window (works without a display).",
        show_default=False)] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the --png output.")] = False,
) -> None:
    """Show a map coloured by scan, time, height or intensity, with its trajectory.

    Without --png the map opens in an Open3D window (needs a display). With --png the picture is rendered offscreen by Open3D where the machine has a renderer (EGL or Vulkan), else by matplotlib (a top view and a perspective view).

    Example:

        pa view office.ply --color height

        pa view office.ply --color intensity --png office_view.png
    """
    from pa_cli.io.atomic import check_writable
    from pa_cli.io.map_view import color_values, render_png, show
    from pa_cli.io.maps import read_map
    from pa_cli.io.trajectory import read_trajectory

    if png is not None:
        check_writable([png], force, inputs=[map_path])
    cloud = read_map(map_path)
    values, label, cmap = color_values(cloud, color, map_path)
    next_to_map = Path(f"{map_path.with_suffix('')}_poses_kitti.txt")
    if poses is None and next_to_map.is_file():
        poses = next_to_map
    path_xyz = None if poses is None else read_trajectory(poses).T_world_scan[:, :3, 3]
    title = f"{map_path.name}: {len(cloud.points_world):,} points coloured by {color.value}"
    if png is None:
        show(cloud, values, cmap, path_xyz, title)
        return
    renderer = render_png(png, cloud, values, label, cmap, path_xyz, title, force)
    log.info("wrote %s (rendered by %s)", png, renderer)
