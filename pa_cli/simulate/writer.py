"""Writing a simulated sequence to a folder, atomically (the `pa simulate` output layout).

The folder is built beside OUT_DIR under a temporary name and renamed into place, so a
failure never leaves a half-written sequence; an existing OUT_DIR (only with `force`) is
moved aside first and removed after the rename.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from pa_cli import __version__
from pa_cli.errors import OutputError
from pa_cli.io.atomic import apply_umask
from pa_cli.io.scans import write_pcd
from pa_cli.io.trajectory import write_kitti, write_tum
from pa_cli.simulate.raycast import Simulator
from pa_cli.simulate.sensor import SCAN_PERIOD_S, SimOptions


def check_simulation(options: SimOptions, out_dir: Path | str, force: bool = False) -> None:
    """Refuse bad options (`UsageError`) or an unusable OUT_DIR (`OutputError`) before any work."""
    options.validate()
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: not a folder (a file of that name exists); choose another OUT_DIR.")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OutputError(f"{out_dir}: the folder is not empty; pass --force to replace its contents, "
                          "or choose another OUT_DIR.")
    parent = out_dir.parent
    if not parent.is_dir():
        raise OutputError(f"{out_dir}: the folder {parent} does not exist; create it first.")


def simulate(options: SimOptions, out_dir: Path | str, force: bool = False,
             progress: Callable[[int, int], None] | None = None) -> dict:
    """Simulate a sequence and write it to `out_dir` atomically; returns the meta dict.

    Layout: `scans/%06d.pcd` (binary, float32 x y z intensity [time], sensor frame),
    `labels/%06d.npy` (int32 per point), `gt_poses_kitti.txt`, `gt_poses_tum.txt`, `times.txt`
    (timestamps k * 0.1 s), `planes.npy` ((P, 4) float64 rows n_x n_y n_z d, world frame,
    row = label), `meta.json`. The folder is built beside `out_dir` and renamed into place.
    `check_simulation` runs first, so a refused call leaves nothing behind.
    """

    check_simulation(options, out_dir, force)
    out_dir = Path(out_dir)
    sim = Simulator(options)
    opt = sim.options
    with building_dir(out_dir) as tmp:
        (tmp / "scans").mkdir()
        (tmp / "labels").mkdir()
        n_points = 0
        for k, scan in enumerate(sim.iter_scans()):
            write_pcd(tmp / "scans" / f"{k:06d}.pcd", scan.points_scan, time=scan.time,
                      intensity=scan.intensity)
            np.save(tmp / "labels" / f"{k:06d}.npy", scan.labels.astype(np.int32))
            n_points += len(scan.labels)
            if progress is not None:
                progress(k + 1, opt.scans)
        T = sim.gt_poses()
        write_kitti(tmp / "gt_poses_kitti.txt", T)
        timestamps_s = np.arange(opt.scans) * SCAN_PERIOD_S
        write_tum(tmp / "gt_poses_tum.txt", T, timestamps_s)
        # one scan start time per line: `pa refine OUT_DIR/scans` finds it and writes real TUM times
        (tmp / "times.txt").write_text("".join(f"{t:.9f}\n" for t in timestamps_s))
        np.save(tmp / "planes.npy", sim.planes_world.astype(np.float64))
        meta = {
            "pa_version": __version__,
            "scene": opt.scene,
            "options": opt.record(),
            "scan_period_s": SCAN_PERIOD_S,
            "n_scans": opt.scans,
            "n_points": n_points,
            "n_planes": len(sim.planes_world),
            "path_length_m": sim.path.length_m,
            "sensor_frame": "x forward, y left, z up; points are in the sensor frame",
            "gt_pose": "T_world_scan at the scan's start time (timestamp k * scan_period_s)",
            "point_order": "column by column (azimuth counter-clockwise from +x), beams bottom to top",
            "time_field": "seconds since the scan start (only with motion_distortion)",
            "planes": "planes.npy row i = label i: n_x n_y n_z d with n.x + d = 0 (world frame, m)",
            "labels": "labels/%06d.npy int32 per PCD point: true plane label, -1 = no plane",
        }
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return meta


@contextlib.contextmanager
def building_dir(out_dir: Path) -> Iterator[Path]:
    """A temporary folder beside `out_dir`, renamed onto it when the block succeeds and removed
    otherwise (a failure never leaves a half-written folder)."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=out_dir.parent))
    apply_umask(tmp)  # mkdtemp makes 0700; give the folder the usual permissions
    try:
        yield tmp
        replace_dir(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def replace_dir(new: Path, out_dir: Path) -> None:
    """Rename `new` onto `out_dir`; an existing `out_dir` is moved aside first, then removed."""
    old = None
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".old", dir=out_dir.parent))
        os.replace(out_dir, old / "x")
    try:
        os.replace(new, out_dir)
    except OSError:
        if old is not None:
            os.replace(old / "x", out_dir)
        raise
    if old is not None:
        shutil.rmtree(old)

