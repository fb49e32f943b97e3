"""`pa calibrate --first/--last/--every`: a subset of the base LiDAR's scans, the other LiDARs
matched to the kept ones (by times.txt, or by their index in the whole base folder)."""

from __future__ import annotations

import numpy as np

from pa_cli.calibration.rig_scans import open_rig
from pa_cli.io.scans import write_pcd
from pa_cli.sources import ScanSubset


def _rig(tmp_path, counts, times=None):
    for k, n in enumerate(counts):
        folder = tmp_path / f"lidar{k}"
        folder.mkdir()
        for i in range(n):
            write_pcd(folder / f"{i:06d}.pcd", np.full((5, 3), 100.0 * k + i))  # x: which LiDAR and scan
        if times is not None:
            (folder / "times.txt").write_text("".join(f"{t:.6f}\n" for t in times[k]))


def test_by_index_the_other_lidars_follow_the_kept_base_scans(tmp_path):
    _rig(tmp_path, (8, 6))
    rig = open_rig(tmp_path, 0.02, ScanSubset(first=1, every=2))  # base scans 1 3 5 7; lidar1 has 0..5
    assert rig.n_base == 4 and [rig.sources[0].points(t)[0, 0] for t in range(4)] == [1.0, 3.0, 5.0, 7.0]
    assert rig.matches[0].tolist() == [[0, 0], [1, 1], [2, 2], [3, 3]]
    assert rig.matches[1].tolist() == [[0, 1], [1, 3], [2, 5]]  # (kept base scan, lidar1 scan of the same index)
    for t, i in rig.matches[1]:
        assert rig.sources[1].points(int(i))[0, 0] - 100.0 == rig.sources[0].points(int(t))[0, 0]


def test_by_time_the_other_lidars_match_the_kept_base_scans(tmp_path):
    base = np.arange(6) * 0.1
    own = np.arange(12) * 0.05 + 0.001  # twice the rate
    _rig(tmp_path, (6, 12), times=[base, own])
    rig = open_rig(tmp_path, 0.02, ScanSubset(first=2, last=4))
    assert rig.matched_by == "times.txt" and rig.n_base == 3
    np.testing.assert_allclose(rig.base_timestamps, [0.2, 0.3, 0.4], atol=1e-9)
    assert rig.matches[1].tolist() == [[0, 4], [1, 6], [2, 8]]
