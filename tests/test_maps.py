"""Merged map: voxel downsampling against brute force, PLY round trip, streaming compaction."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.errors import OutputError
from pa_cli.io.maps import MapAccumulator, read_map_ply, voxel_downsample, write_map_ply


def _brute_force_voxels(points: np.ndarray, voxel: float) -> dict:
    first = {}
    for i, p in enumerate(points):
        key = tuple(int(c) for c in np.floor(p / voxel))
        first.setdefault(key, i)
    return first


def test_voxel_downsample_matches_brute_force():
    rng = np.random.default_rng(1)
    points = rng.uniform(-3, 3, size=(2000, 3))
    keep = voxel_downsample(points, 0.5)
    expected = sorted(_brute_force_voxels(points, 0.5).values())
    assert keep.tolist() == expected


def test_accumulator_streams_and_keeps_scan_index():
    rng = np.random.default_rng(2)
    voxel = 0.25
    scans = [rng.uniform(0, 4, size=(500, 3)) for _ in range(6)]
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, 0, 3] = np.arange(6) * 1.0  # scans shifted 1 m apart in x, overlapping
    acc = MapAccumulator(voxel, compact_every_points=300)  # force many compactions
    for k, pts in enumerate(scans):
        acc.add(pts, T[k], k)
    cloud = acc.result()
    points_world, scan_index = cloud.points_world, cloud.scan_index
    all_world = np.vstack([s + T[k, :3, 3] for k, s in enumerate(scans)])
    all_scan = np.repeat(np.arange(6), 500)
    expected = _brute_force_voxels(all_world, voxel)
    assert len(points_world) == len(expected)
    got = {tuple(int(c) for c in np.floor(p / voxel)): s for p, s in zip(points_world, scan_index, strict=True)}
    # each voxel keeps the first point in scan order, so its scan index matches brute force
    assert got == {k: all_scan[i] for k, i in expected.items()}


def test_ply_round_trip_and_refuses_overwrite(tmp_path):
    rng = np.random.default_rng(3)
    points = rng.normal(size=(100, 3)) * 10
    scan = rng.integers(0, 50, 100).astype(np.int32)
    path = tmp_path / "map.ply"
    write_map_ply(path, points, scan)
    p_back, s_back = read_map_ply(path)
    assert p_back.dtype == np.float32
    assert np.allclose(p_back, points.astype(np.float32))
    assert np.array_equal(s_back, scan)
    with pytest.raises(OutputError):
        write_map_ply(path, points, scan)
    write_map_ply(path, points[:10], scan[:10], force=True)
    assert len(read_map_ply(path)[0]) == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ply"]  # no temp files left
    header = path.read_bytes()[:400].decode("ascii", "replace")
    assert "property int scan_index" in header and "property float x" in header


@pytest.mark.parametrize(("suffix", "with_time"), [(".las", True), (".las", False), (".laz", True)])
def test_las_round_trip(tmp_path, suffix, with_time):
    from pa_cli.io.maps import LAS_SCALE_M, MapCloud, read_map, write_map

    rng = np.random.default_rng(4)
    points = rng.normal(size=(500, 3)) * 50 + [1000.0, -2000.0, 30.0]
    scan = rng.integers(0, 80, 500).astype(np.int32)
    time_s = 1.7e9 + rng.random(500) * 8.0 if with_time else None
    path = tmp_path / f"map{suffix}"
    write_map(path, MapCloud(points, scan, time_s))
    back = read_map(path)
    assert np.abs(back.points_world - points).max() <= LAS_SCALE_M / 2 + 1e-9  # rounded to the LAS grid
    assert np.array_equal(back.scan_index, scan)
    if with_time:
        assert np.array_equal(back.time_s, time_s)  # gps_time is a float64: exact
    else:
        assert back.time_s is None
    with pytest.raises(OutputError):
        write_map(path, MapCloud(points, scan, time_s))
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
    if suffix == ".laz":
        assert path.stat().st_size < 0.8 * len(points) * 40  # compressed below the raw record size


def test_unknown_map_suffix_is_refused(tmp_path):
    from pa_cli.io.maps import MapCloud, write_map

    with pytest.raises(OutputError, match="unsupported map format '.xyz'"):
        write_map(tmp_path / "m.xyz", MapCloud(np.zeros((1, 3)), np.zeros(1, dtype=np.int32)))
