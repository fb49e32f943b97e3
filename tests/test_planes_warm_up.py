"""The background warm-up of the plane kernels: it exercises every detection and association
kernel (its box room yields the six walls as planes) and never raises into the caller."""

from __future__ import annotations

import numpy as np
from numba.core.registry import CPUDispatcher

from pa_cli.planes import _kernels, warm_up
from pa_cli.planes.warm_up import box_room_scan, warm_up_in_background

# the kernels a plane association calls from Python (the others are inlined into these)
ENTRY_KERNELS = ("scan_voxel_sums", "merge_voxel_sums", "parent_sums", "stats_from_sums", "fill_table",
                 "cell_neighbours", "label_points", "moments_by_label")


def test_box_room_lies_on_six_walls():
    points = box_room_scan()
    on_wall = np.isclose(np.abs(points), warm_up.BOX_HALF_WIDTH_M).sum(axis=1)
    assert len(points) == 6 * warm_up.BOX_POINTS_PER_SIDE**2
    np.testing.assert_array_equal(on_wall, 1)  # every point on exactly one wall, none on an edge


def test_warm_up_finds_the_walls_and_loads_every_entry_kernel():
    assert warm_up.warm_up() == 6
    for name in ENTRY_KERNELS:
        kernel = getattr(_kernels, name)
        assert isinstance(kernel, CPUDispatcher) and kernel.signatures, name


def test_warm_up_failure_is_not_raised(monkeypatch, caplog):
    def broken() -> int:
        raise RuntimeError("no kernels")

    monkeypatch.setattr(warm_up, "warm_up", broken)
    with caplog.at_level("DEBUG", logger="pa_cli.planes.warm_up"):
        thread = warm_up_in_background()
        thread.join(timeout=60)
    assert not thread.is_alive() and thread.daemon
    assert "no kernels" in caplog.text
