"""Load the plane-finding kernels ahead of their first use, on a thread of their own.

The first call of a numba kernel in a process sets up numba's compiler context and loads the
kernel from numba's on-disk cache (`pa_cli._numba`); for plane finding that is a fixed cost of
a few tenths of a second, paid at the first `build_plane_problem` of the process. `pa refine`
starts `warm_up_in_background` before its odometry, which keeps the cores only partly busy, so
that cost is paid alongside the odometry instead of before the first plane association.
The warm-up builds the plane problem of a small box room (six walls seen by two scans),
which calls every kernel of detection and association with the argument types of real scans
(float64 points); a kernel's first real call then finds it loaded. Kernels are thread-safe
to load concurrently (numba serialises compilation and cache loading with a lock), but
numba's workqueue threading layer (the one every install has) does not let two threads launch
parallel kernels at once: `build_plane_problem` therefore first waits for a running warm-up
(`wait_for_warm_up`), which loses nothing, the kernels being loaded by then.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from pa_cli.errors import PaError

log = logging.getLogger(__name__)

BOX_HALF_WIDTH_M = 3.0  # the warm-up room: a 6 m cube, walls sampled on a grid
BOX_POINTS_PER_SIDE = 24  # grid points along each wall edge (24^2 = 576 points per wall)


def box_room_scan() -> np.ndarray:
    """(M, 3) points (m) on the six walls of a cube of half-width BOX_HALF_WIDTH_M about the origin."""
    grid = np.linspace(-BOX_HALF_WIDTH_M, BOX_HALF_WIDTH_M, BOX_POINTS_PER_SIDE + 2)[1:-1]
    u, v = (a.ravel() for a in np.meshgrid(grid, grid))
    walls = []
    for axis in range(3):
        for side in (-BOX_HALF_WIDTH_M, BOX_HALF_WIDTH_M):
            wall = np.empty((len(u), 3))
            wall[:, axis] = side
            wall[:, [k for k in range(3) if k != axis]] = np.column_stack([u, v])
            walls.append(wall)
    return np.concatenate(walls)


def warm_up() -> int:
    """Build the plane problem of two scans of the box room with the default plane settings
    (every detection and association kernel called once) and its clusters again from the
    per-point labels (`PointLabels`, the kernels of the frozen rounds); returns its number of planes."""
    from pa_cli.config import PlanesConfig
    from pa_cli.planes.associate import build_plane_problem
    from pa_cli.planes.labels import PointLabels

    scans = [box_room_scan(), box_room_scan()]
    found: dict = {}
    problem, _ = build_plane_problem(scans, np.repeat(np.eye(4)[None], 2, axis=0), PlanesConfig(), landmarks_out=found)
    labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks, found["kept"],
                                          problem)
    labels.problem(scans, with_range=True)
    return problem.n_planes


_running: list[threading.Thread] = []  # the warm-up threads started (at most one is alive)


def warm_up_in_background() -> threading.Thread:
    """Start `warm_up` on a daemon thread and return it; a failure is logged (debug), never raised:
    the kernels then load at their first real use as they would without the warm-up."""
    def run() -> None:
        try:
            warm_up()
        except (PaError, ImportError, ValueError, RuntimeError, OSError) as error:
            log.debug("plane kernel warm-up failed (%s); the kernels load at first use.", error)

    wait_for_warm_up()
    thread = threading.Thread(target=run, name="pa-plane-kernel-warm-up", daemon=True)
    _running[:] = [thread]
    thread.start()
    return thread


def wait_for_warm_up() -> None:
    """Return when no warm-up runs (at once on the warm-up's own thread)."""
    for thread in _running:
        if thread is not threading.current_thread():
            thread.join()
