"""What `pa refine` writes from its final poses besides the pose files: the map's points, scan by
scan (`map_parts`, filtered and written by `pa_cli.io.maps`), and the overview picture
(`write_overview`, drawn by `pa_cli.io.plots.overview_figure`).

Frames: poses T_world_scan (N, 4, 4) in the world frame (`pa_cli.core.local_frame.to_world`);
points in the sensor frame; metres and seconds.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.evaluation import pose_errors
from pa_cli.io.maps import MapPart, point_times_s
from pa_cli.io.plots import overview_figure, save_png
from pa_cli.io.trajectory import Trajectory
from pa_cli.sources.base import ScanSource, point_intensity

# Scans whose intensities are held while the map is written: with motion compensation pose k
# places points of scans k-1, k and k+1, so each scan's intensities are read once when one pose is
# placed at a time; `map_parts` adds the poses placed at once.
INTENSITY_SCANS_HELD = 3


def map_parts(source: ScanSource, deskewed: Any, timestamps_s: np.ndarray | None,
              poses_at_once: int = 1) -> Callable[[int], list[MapPart]]:
    """The `MapPart`s pose k places, for any k (a function of k): the points of the scans that measured
    them, in scan k's frame, with their times and intensities where known. Called from up to
    `poses_at_once` threads at once, on nearby poses (the intensities of the scans around them are held).

    `deskewed`: the scans motion-compensated at the final trajectory (`pa_cli.refine.deskew.DeskewedPoints`)
    or None (each pose places its own scan as read); `timestamps_s`: (N,) scan timestamps or None (no times).
    """
    intensity_of = functools.lru_cache(maxsize=INTENSITY_SCANS_HELD + poses_at_once - 1)(
        functools.partial(point_intensity, source))

    def parts(k: int) -> list[MapPart]:
        if deskewed is None:
            measured = [(k, source.points(k), source.point_times(k), slice(None))]
        else:
            measured = [(j, points, own_s, index) for (j, points, own_s), (_, index)
                        in zip(deskewed.parts(k), deskewed.sources(k), strict=True)]
        placed = []
        for j, points, own_s, index in measured:
            intensity = intensity_of(j)
            stamp_s = None if timestamps_s is None else timestamps_s[j]
            placed.append(MapPart(j, points, point_times_s(stamp_s, own_s, len(points)),
                                  None if intensity is None else np.asarray(intensity)[index]))
        return placed

    return parts


def write_overview(path: Path | str, points_scan: Sequence[np.ndarray], T_initial: np.ndarray, T_refined: np.ndarray,
                   timestamps_s: np.ndarray | None, gt: Trajectory | None, force: bool = False) -> None:
    """`MAP_overview.png`: the map's slice under the initial and the refined poses (world frame), the
    correction of each scan, and with `gt` the SE(3)-aligned position error of each pose over time."""
    curves = []
    if gt is not None:
        stamps = timestamps_s if gt.timestamps is not None else None
        for label, T in (("initial", T_initial), ("refined", T_refined)):
            errors = pose_errors(gt, Trajectory(T, stamps), align="se3")
            x = errors.i_est.astype(float) if timestamps_s is None else timestamps_s[errors.i_est] - timestamps_s[0]
            curves.append((label, x, errors.trans_m))
    save_png(overview_figure(points_scan, T_initial, T_refined, timestamps_s, curves), path, force)
