"""Pictures written as PNG files (matplotlib's Agg canvas: no display needed).

Every figure is built from plain arrays by a `*_figure` function (so it can be tested and reused)
and written atomically by `save_png`:

- `overview_figure`: what `pa refine` did (`MAP_overview.png`): a top-down slice of the map
  under the poses before and after, on one grid and one grey scale, so the two panels differ only
  where the poses do; the correction of each scan (distance between its poses before and after);
  with ground truth, the error of each pose over time.
- `trajectory_errors_figure`: `pa eval --plot`: the trajectories in a top view, the error of each
  pose over time, and each estimate's path coloured by its error.
- `map_view_figure`: `pa view --png` without Open3D's offscreen renderer: a top view and a
  perspective view of the map's points, coloured by a value per point.

Frames: poses are T_world_scan (N, 4, 4), points of a scan are in its sensor frame, metres; "up"
is the world's z axis (KISS-ICP's world is the frame of scan 0).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from pa_cli.core.geometry import rotation_angles, transform_points
from pa_cli.io.atomic import atomic_path

# The slice of the overview: points between these heights about the sensor that measured them
# (m, world z): the upright surfaces (walls, poles, trunks) the near-horizontal beams see, without
# the ground below a vehicle-mounted sensor or the ceiling of a room.
OVERVIEW_BAND_M = (-0.5, 1.0)
# Points of the slice drawn at most (each scan's points are thinned evenly to its share before the
# transform): enough to show every wall, and the picture takes seconds whatever the run's size.
OVERVIEW_MAX_POINTS = 4_000_000
OVERVIEW_PIXELS = 900  # cells of the slice's raster along its longer side
# Cells at this percentile of the occupied cells' (log) counts and above are black: a wall seen
# from afar (a few points per cell) stays visible beside the dense ground ring around the sensor.
OVERVIEW_BLACK_PERCENTILE = 80.0
# The slice's extent: these percentiles of the points, widened by OVERVIEW_MARGIN on each side, so
# a few far returns do not shrink the map to a dot.
OVERVIEW_EXTENT_PERCENTILES = (0.1, 99.9)
OVERVIEW_MARGIN = 0.05
VIEW_MAX_POINTS = 400_000  # points of `map_view_figure` at most (thinned evenly)

ErrorCurve = tuple[str, np.ndarray, np.ndarray]
"""(label, x (M,) time in s or pose index, error (M,) m) of one trajectory."""


def new_figure(width_in: float, height_in: float, dpi: int = 100) -> Figure:
    """A matplotlib figure on the Agg canvas (no pyplot, no display)."""
    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: Path | str, force: bool = False) -> None:
    """Write `fig` to `path` as a PNG, atomically (refused when it exists, unless `force`)."""
    with atomic_path(path, force) as tmp:
        fig.savefig(tmp, format="png")


def figure_rgba(fig: Figure) -> np.ndarray:
    """The figure drawn to an (H, W, 4) uint8 array."""
    canvas = fig.canvas
    canvas.draw()
    return np.asarray(canvas.buffer_rgba()).copy()


def axes_pixels(fig: Figure, ax: Axes) -> np.ndarray:
    """The pixels of the drawing area of `ax` (its frame's inside) in `figure_rgba(fig)`."""
    image = figure_rgba(fig)
    box = ax.get_window_extent()
    height = image.shape[0]
    rows = slice(int(np.ceil(height - box.y1)) + 1, int(np.floor(height - box.y0)) - 1)
    cols = slice(int(np.ceil(box.x0)) + 1, int(np.floor(box.x1)) - 1)
    return image[rows, cols]


def _axis_of_poses(time_s: np.ndarray | None, n: int) -> tuple[np.ndarray, str]:
    if time_s is None:
        return np.arange(n, dtype=np.float64), "scan"
    time_s = np.asarray(time_s, dtype=np.float64)
    return time_s - time_s[0], "time since the first scan [s]"


def _slice_points(points_scan: Iterable[np.ndarray], n_scans: int,
                  poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The (K, 2) world x-y of each trajectory's slice (`OVERVIEW_BAND_M` about the sensor), from
    every scan's points thinned evenly to OVERVIEW_MAX_POINTS / n_scans."""
    per_scan = max(1, OVERVIEW_MAX_POINTS // max(n_scans, 1))
    found: list[list[np.ndarray]] = [[] for _ in poses]
    for k, points in enumerate(points_scan):
        points = np.asarray(points, dtype=np.float64)
        points = points[::max(1, int(np.ceil(len(points) / per_scan)))]
        for kept, T_world_scan in zip(found, poses, strict=True):
            world = transform_points(T_world_scan[k], points)
            height = world[:, 2] - T_world_scan[k][2, 3]
            band = (height >= OVERVIEW_BAND_M[0]) & (height <= OVERVIEW_BAND_M[1])
            kept.append(world[band, :2].astype(np.float32))
    return [np.concatenate(kept) if kept else np.empty((0, 2), np.float32) for kept in found]


def _raster_grid(points_xy: Sequence[np.ndarray], paths_xy: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Square-cell bin edges in x and y covering the points (robust extent) and the paths."""
    stacked = np.concatenate([*points_xy, *paths_xy])
    low, high = np.percentile(stacked, OVERVIEW_EXTENT_PERCENTILES, axis=0) if len(stacked) else (np.zeros(2),
                                                                                                    np.ones(2))
    paths = np.concatenate(paths_xy)
    low, high = np.minimum(low, paths.min(axis=0)), np.maximum(high, paths.max(axis=0))
    span = np.maximum(high - low, 1.0)
    low, high = low - OVERVIEW_MARGIN * span, high + OVERVIEW_MARGIN * span
    cell_m = float((high - low).max()) / OVERVIEW_PIXELS
    return tuple(np.arange(low[i], high[i] + cell_m, cell_m) for i in range(2))


def overview_figure(points_scan: Iterable[np.ndarray], T_before: np.ndarray, T_after: np.ndarray,
                    time_s: np.ndarray | None = None, gt_errors: Sequence[ErrorCurve] = (),
                    labels: tuple[str, str] = ("initial poses", "refined poses")) -> Figure:
    """The overview of a refinement.

    `points_scan`: each scan's (M_k, 3) points in its sensor frame (a sequence or an iterator,
    read once); `T_before`, `T_after`: (N, 4, 4) T_world_scan; `time_s`: (N,) scan timestamps (s)
    or None (the scan index is the time axis); `gt_errors`: the error of each pose against ground
    truth, one `ErrorCurve` per trajectory (drawn when given).

    Panels (labelled by `Axes.get_label()`): "before" and "after" (the slice `OVERVIEW_BAND_M`
    about each sensor, as counts of points per cell on one grid and one grey scale, with the
    trajectory and its start), "correction" (per scan: distance in m and angle in deg between its
    poses before and after), "gt" (with `gt_errors`).
    """
    T_before, T_after = np.asarray(T_before, np.float64), np.asarray(T_after, np.float64)
    slices = _slice_points(points_scan, len(T_before), (T_before, T_after))
    paths = [T_before[:, :2, 3], T_after[:, :2, 3]]
    edges_x, edges_y = _raster_grid(slices, paths)
    counts = [np.histogram2d(xy[:, 0], xy[:, 1], bins=(edges_x, edges_y))[0].T for xy in slices]
    occupied = np.concatenate([np.log1p(c[c > 0]) for c in counts])
    top = float(np.percentile(occupied, OVERVIEW_BLACK_PERCENTILE)) if len(occupied) else 1.0

    fig = new_figure(15, 12.5)
    grid = fig.add_gridspec(2, 2, height_ratios=(2.2, 1))
    for column, (name, label, count, path) in enumerate(zip(("before", "after"), labels, counts, paths, strict=True)):
        ax = fig.add_subplot(grid[0, column], label=name)
        ax.imshow(np.log1p(count), origin="lower", cmap="Greys", vmin=0.0, vmax=top, interpolation="nearest",
                  extent=(edges_x[0], edges_x[-1], edges_y[0], edges_y[-1]))
        ax.plot(path[:, 0], path[:, 1], color="tab:red", linewidth=1.0, label="trajectory")
        ax.plot(path[:1, 0], path[:1, 1], "o", color="tab:red", markersize=4, label="first scan")
        ax.set_title(f"{label}: slice {OVERVIEW_BAND_M[0]:+g} .. {OVERVIEW_BAND_M[1]:+g} m about the sensor "
                     f"({len(slices[column]):,} points)", fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper right", fontsize=8)
    x, x_label = _axis_of_poses(time_s, len(T_before))
    moved_m = np.linalg.norm(T_after[:, :3, 3] - T_before[:, :3, 3], axis=1)
    turned_deg = np.degrees(rotation_angles(T_before[:, :3, :3].transpose(0, 2, 1) @ T_after[:, :3, :3]))
    ax = fig.add_subplot(grid[1, 0] if gt_errors else grid[1, :], label="correction")
    ax.plot(x, moved_m, color="tab:blue", linewidth=1.0)
    ax.set_xlabel(x_label)
    ax.set_ylabel("moved [m]", color="tab:blue")
    ax.set_title(f"correction per scan: {labels[0]} -> {labels[1]} (max {moved_m.max():.3f} m, "
                 f"{turned_deg.max():.2f} deg)", fontsize=10)
    ax.grid(True, linewidth=0.3)
    twin = ax.twinx()
    twin.plot(x, turned_deg, color="tab:orange", linewidth=1.0)
    twin.set_ylabel("turned [deg]", color="tab:orange")
    if gt_errors:
        ax = fig.add_subplot(grid[1, 1], label="gt")
        _error_curves(ax, gt_errors, x_label)
        ax.set_title("error against the ground truth (ATE per pose, SE(3)-aligned)", fontsize=10)
    fig.tight_layout()
    return fig


def _error_curves(ax: Axes, curves: Sequence[ErrorCurve], x_label: str) -> None:
    for label, x, error_m in curves:
        error_m = np.asarray(error_m)
        ax.plot(x, error_m, linewidth=1.0, label=f"{label} (rmse {np.sqrt(np.mean(error_m ** 2)):.3f} m)")
    ax.set_xlabel(x_label)
    ax.set_ylabel("position error [m]")
    ax.grid(True, linewidth=0.3)
    ax.legend(fontsize=8)


def trajectory_errors_figure(gt_xy: np.ndarray, estimates: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]],
                             x_label: str) -> Figure:
    """`pa eval --plot`: the ground truth and the aligned estimates in a top view ("trajectories"),
    their errors over time ("errors"), and one top view per estimate with its path coloured by
    its error ("colored 0", "colored 1", ...).

    `gt_xy`: (N, 2) ground-truth positions (m); `estimates`: (label, (M, 2) aligned positions,
    (M,) time axis, (M,) position error in m) each; `x_label` names the time axis.
    """
    n = len(estimates)
    fig = new_figure(6.0 * max(2, n), 11.0)
    grid = fig.add_gridspec(2, 2 * max(2, n))
    half = max(2, n)
    ax = fig.add_subplot(grid[0, :half], label="trajectories")
    ax.plot(gt_xy[:, 0], gt_xy[:, 1], color="0.3", linestyle="--", linewidth=1.2, label="ground truth")
    for label, xy, _, _ in estimates:
        ax.plot(xy[:, 0], xy[:, 1], linewidth=1.0, label=label)
    _top_view(ax, "trajectories (top view, aligned)")
    ax.legend(fontsize=8)
    _error_curves(fig.add_subplot(grid[0, half:], label="errors"),
                  [(label, x, error) for label, _, x, error in estimates], x_label)
    fig.axes[-1].set_title("position error over time", fontsize=10)
    top = max(float(np.max(error)) for *_, error in estimates) or 1.0
    for i, (label, xy, _, error) in enumerate(estimates):
        ax = fig.add_subplot(grid[1, 2 * i:2 * i + 2], label=f"colored {i}")
        ax.plot(gt_xy[:, 0], gt_xy[:, 1], color="0.7", linestyle="--", linewidth=1.0)
        segments = np.stack([xy[:-1], xy[1:]], axis=1)
        lines = LineCollection(segments, cmap="plasma", linewidths=2.0)
        lines.set_array(0.5 * (error[:-1] + error[1:]))
        lines.set_clim(0.0, top)
        ax.add_collection(lines)
        ax.autoscale()
        fig.colorbar(lines, ax=ax, label="position error [m]", shrink=0.8)
        _top_view(ax, f"{label}: coloured by error")
    fig.tight_layout()
    return fig


def _top_view(ax: Axes, title: str) -> None:
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, linewidth=0.3)
    ax.set_title(title, fontsize=10)


def map_view_figure(points_world: np.ndarray, values: np.ndarray, value_label: str, cmap: str,
                    path_xyz: np.ndarray | None = None, title: str = "") -> Figure:
    """A top view ("top") and a perspective view ("perspective") of map points coloured by
    `values` (one per point, with `cmap`), with the trajectory `path_xyz` (N, 3) when given;
    points thinned evenly to VIEW_MAX_POINTS."""
    step = max(1, int(np.ceil(len(points_world) / VIEW_MAX_POINTS)))
    points, values = np.asarray(points_world)[::step], np.asarray(values)[::step]
    fig = new_figure(16, 8)
    top = fig.add_subplot(1, 2, 1, label="top")
    scatter = top.scatter(points[:, 0], points[:, 1], c=values, s=0.3, cmap=cmap, linewidths=0, rasterized=True)
    perspective = fig.add_subplot(1, 2, 2, projection="3d", label="perspective")
    perspective.scatter(points[:, 0], points[:, 1], points[:, 2], c=values, s=0.2, cmap=cmap, linewidths=0,
                        depthshade=False, rasterized=True)
    if path_xyz is not None:
        top.plot(path_xyz[:, 0], path_xyz[:, 1], color="tab:red", linewidth=1.2, label="trajectory")
        perspective.plot(path_xyz[:, 0], path_xyz[:, 1], path_xyz[:, 2], color="tab:red", linewidth=1.2)
        top.legend(loc="upper right", fontsize=8)
    _top_view(top, f"top view ({len(points):,} of {len(points_world):,} points)")
    spans = np.ptp(points, axis=0) if len(points) else np.ones(3)
    perspective.set_box_aspect(np.maximum(spans, 1e-3 * spans.max(initial=1.0) + 1e-9))
    perspective.view_init(elev=35, azim=-60)
    perspective.set_xlabel("x [m]")
    perspective.set_ylabel("y [m]")
    perspective.set_zlabel("z [m]")
    perspective.locator_params(axis="z", nbins=3)
    perspective.set_title("perspective", fontsize=10)
    fig.colorbar(scatter, ax=[top, perspective], label=value_label, shrink=0.7)
    if title:
        fig.suptitle(title)
    return fig
