"""Looking at a map written by `pa refine` (`pa view`): the points coloured by scan, time, height
or intensity, with the trajectory, in an Open3D window or rendered to a PNG.

`render_png` uses Open3D's offscreen renderer where the machine has one (EGL or Vulkan); on a
headless machine without it, the picture is drawn by matplotlib instead
(`pa_cli.io.plots.map_view_figure`: a top view and a perspective view).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.errors import InputError, OutputError
from pa_cli.io.atomic import atomic_path
from pa_cli.io.maps import ColorBy, MapCloud
from pa_cli.io.plots import map_view_figure, save_png
from pa_cli.runtime.open3d_preload import open3d

# Height and intensity colours span these percentiles of the values, so a few outliers (a tall
# pole, a retro-reflector) do not wash out the rest.
COLOR_PERCENTILES = (1.0, 99.0)
RENDER_SIZE_PX = (1600, 1000)  # Open3D offscreen picture, width x height
TRAJECTORY_RGB = (0.85, 0.1, 0.1)


def color_values(cloud: MapCloud, color_by: ColorBy, where: Path | str) -> tuple[np.ndarray, str, str]:
    """(values (K,), their label, a matplotlib colormap) that colour the map's points; `InputError`
    naming the map when it lacks the field."""
    if color_by == ColorBy.scan:
        return cloud.scan_index.astype(np.float64), "scan", "turbo"
    if color_by == ColorBy.height:
        return _clipped(cloud.points_world[:, 2]), "height z [m]", "viridis"
    values = cloud.time_s if color_by == ColorBy.time else cloud.intensity
    if values is None:
        why = "the scans had no timestamps" if color_by == ColorBy.time else "the scans had no intensity field"
        raise InputError(f"{where}: the map holds no per-point {color_by.value} ({why}); use --color scan or "
                         "--color height.")
    if color_by == ColorBy.time:
        return np.asarray(values, np.float64) - float(np.min(values, initial=0.0)), "time since the first point [s]", \
            "turbo"
    return _clipped(values), "intensity (as the scans store it)", "inferno"


def _clipped(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return values
    return np.clip(values, *np.percentile(values, COLOR_PERCENTILES))


def _rgb(values: np.ndarray, cmap: str) -> np.ndarray:
    from matplotlib import colormaps

    low, high = (float(values.min()), float(values.max())) if len(values) else (0.0, 1.0)
    return colormaps[cmap]((values - low) / max(high - low, 1e-12))[:, :3]


def geometries(cloud: MapCloud, values: np.ndarray, cmap: str, path_xyz: np.ndarray | None) -> list[Any]:
    """Open3D geometries: the points coloured by `values` and the trajectory as a red line."""
    o3d = open3d()
    points = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(cloud.points_world, np.float64)))
    points.colors = o3d.utility.Vector3dVector(_rgb(values, cmap))
    found = [points]
    if path_xyz is not None and len(path_xyz) > 1:
        lines = o3d.geometry.LineSet(o3d.utility.Vector3dVector(np.asarray(path_xyz, np.float64)),
                                     o3d.utility.Vector2iVector(np.column_stack([np.arange(len(path_xyz) - 1),
                                                                                 np.arange(1, len(path_xyz))])))
        lines.paint_uniform_color(TRAJECTORY_RGB)
        found.append(lines)
    return found


def show(cloud: MapCloud, values: np.ndarray, cmap: str, path_xyz: np.ndarray | None, title: str) -> None:
    """Open the map in an Open3D window (returns when it is closed); `OutputError` without a display."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise OutputError("no display to open a window on (DISPLAY is not set); render a picture with --png FILE.")
    open3d().visualization.draw_geometries(geometries(cloud, values, cmap, path_xyz), window_name=title)


def render_png(path: Path | str, cloud: MapCloud, values: np.ndarray, value_label: str, cmap: str,
               path_xyz: np.ndarray | None, title: str, force: bool = False) -> str:
    """Write a picture of the map to `path` (PNG, atomically); returns the renderer used: "open3d"
    (offscreen, a perspective view from above) or "matplotlib" where Open3D has no offscreen renderer."""
    o3d = open3d()
    try:
        renderer = o3d.visualization.rendering.OffscreenRenderer(*RENDER_SIZE_PX)
    except RuntimeError:  # no EGL / Vulkan on this machine (headless without GPU drivers)
        save_png(map_view_figure(cloud.points_world, values, value_label, cmap, path_xyz, title), path, force)
        return "matplotlib"
    rendering = o3d.visualization.rendering
    for i, geometry in enumerate(geometries(cloud, values, cmap, path_xyz)):
        material = rendering.MaterialRecord()
        material.shader = "unlitLine" if i else "defaultUnlit"
        material.point_size, material.line_width = 2.0, 3.0
        renderer.scene.add_geometry(f"geometry {i}", geometry, material)
    renderer.scene.set_background([1.0, 1.0, 1.0, 1.0])
    renderer.scene.view.set_post_processing(False)  # the colours as given, no tone mapping
    box = renderer.scene.bounding_box
    center, size_m = box.get_center(), float(box.get_extent().max())
    renderer.setup_camera(50.0, center, center + np.array([-0.5, -0.7, 0.9]) * size_m, [0.0, 0.0, 1.0])
    image = renderer.render_to_image()
    with atomic_path(path, force) as tmp:
        o3d.io.write_image(str(tmp), image)
    return "open3d"
