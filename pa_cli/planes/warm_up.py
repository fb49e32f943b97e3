"""Load the plane-finding kernels ahead of their first use, on a thread of their own, and on a first
run compile them ahead in a process of their own.

The first call of a numba kernel in a process sets up numba's compiler context and loads the
kernel from numba's on-disk cache (`pa_cli.runtime.numba_cache`): a fixed cost of a few tenths of
a second; on the first run (an empty cache) it compiles them, about 4-6 s of one core. Compiling
holds the interpreter lock, so on a thread it would share one interpreter with the start of the
run: `pa refine` calls `compile_in_background` first, which on a first run compiles them in a
separate process (this module run as a script) while the run reads its scans and runs the
odometry; `warm_up_in_background` (started before the odometry) waits for that process and loads
the kernels, so that plane finding finds them loaded. `build_plane_problem` waits for a running
compile process (`pa_cli.runtime.warm_up.wait_for_compile_processes`) rather than compile the
same kernels again.
The warm-up builds the plane problem of a small box room (six walls seen by two scans),
which calls every kernel of detection and association with the argument types of real scans
(float64 points), in the order plane finding calls them; a kernel's first real call then finds
it loaded; then the kernel of the map entropy (`pa_cli.core.neighbourhoods`), which every
refinement runs after its rounds. The kernels are serial and thread-safe to load concurrently (numba
serialises compilation and cache loading with a lock), so `build_plane_problem` does not wait for a
running warm-up thread: it uses what is loaded and waits only for a kernel still being loaded.
"""

from __future__ import annotations

import threading

import numpy as np

from pa_cli.config import PlanesConfig
from pa_cli.core import neighbourhoods
from pa_cli.core.neighbourhoods import neighbourhood_fit
from pa_cli.planes import kernels
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.labels import PointLabels
from pa_cli.runtime.numba_cache import announce_compilation, is_cached
from pa_cli.runtime.warm_up import start_compile_process, start_warm_up, wait_for_compile_processes

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
    per-point labels (`PointLabels`, the kernels of the frozen rounds), and a neighbourhood fit of a
    wall (the map entropy's kernel); returns its number of planes."""
    scans = [box_room_scan(), box_room_scan()]
    found: dict = {}
    problem, _ = build_plane_problem(scans, np.repeat(np.eye(4)[None], 2, axis=0), PlanesConfig(), landmarks_out=found)
    labels = PointLabels.from_association(found["landmark_of_point"], found["landmarks"].n_landmarks, found["kept"],
                                          problem)
    labels.problem(scans, with_range=True)
    neighbourhood_fit(scans[0], scans[0][:8], BOX_HALF_WIDTH_M / 4, 3, 1e-3)  # the map entropy's kernel
    return problem.n_planes


def compile_in_background() -> None:
    """On a first run (the plane and map-entropy kernels not in numba's cache), start compiling them
    in a process of its own (`pa_cli.runtime.warm_up.start_compile_process`, this module run as a
    script), in parallel with the start of the run; nothing when they are cached."""
    if not all(is_cached(kernel) for kernel in WARM_UP_KERNELS):
        announce_compilation(WARM_UP_KERNELS)
        start_compile_process(__name__)


def warm_up_in_background() -> threading.Thread:
    """Start on a daemon thread (`pa_cli.runtime.warm_up.start_warm_up`): the wait for a running
    compile process (`compile_in_background`), then `warm_up`, which loads the kernels from the
    cache (or compiles what is still missing); return the thread."""
    def load() -> None:
        wait_for_compile_processes()
        warm_up()

    return start_warm_up(load, "pa-plane-kernel-warm-up")


WARM_UP_KERNELS = (*kernels.ENTRY_KERNELS, *neighbourhoods.KERNELS)  # what `warm_up` compiles

if __name__ == "__main__":  # the compile process of `compile_in_background`
    warm_up()
