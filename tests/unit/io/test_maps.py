"""Merged map: voxel downsampling against brute force, PLY/LAS round trips, chunked streaming writes."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.errors import OutputError
from pa_cli.io.maps import (
    MapCloud,
    MapVoxelFilter,
    chunked,
    read_map,
    read_map_ply,
    voxel_downsample,
    write_map,
    write_map_ply,
)


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


def _overlapping_scans(n_scans: int = 6, n_points: int = 500) -> tuple[list[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(2)
    scans = [rng.uniform(0, 4, size=(n_points, 3)) for _ in range(n_scans)]
    T = np.tile(np.eye(4), (n_scans, 1, 1))
    T[:, 0, 3] = np.arange(n_scans) * 1.0  # scans shifted 1 m apart in x, overlapping
    return scans, T


@pytest.mark.parametrize("merge_chunks", [1, 2, 64])
def test_voxel_filter_keeps_first_point_per_voxel_in_scan_order(monkeypatch, merge_chunks):
    from pa_cli.io import maps

    monkeypatch.setattr(maps._SortedKeySet, "MERGE_CHUNKS", merge_chunks)  # merged every scan .. never
    voxel = 0.25
    scans, T = _overlapping_scans()
    voxel_filter = MapVoxelFilter(voxel)
    cloud = maps.concatenate_clouds([voxel_filter.add(pts, T[k], k) for k, pts in enumerate(scans)])
    all_world = np.vstack([s + T[k, :3, 3] for k, s in enumerate(scans)])
    all_scan = np.repeat(np.arange(len(scans)), 500)
    expected = _brute_force_voxels(all_world, voxel)
    assert len(cloud.points_world) == len(expected)
    got = {tuple(int(c) for c in np.floor(p / voxel)): s
           for p, s in zip(cloud.points_world, cloud.scan_index, strict=True)}
    # each voxel keeps the first point in scan order, so its scan index matches brute force
    assert got == {k: all_scan[i] for k, i in expected.items()}
    kept = np.sort(list(expected.values()))
    assert np.allclose(np.sort(cloud.points_world, axis=0), np.sort(all_world[kept], axis=0))


@pytest.mark.parametrize(("suffix", "with_time"), [(".ply", False), (".las", True), (".laz", False)])
def test_streamed_map_equals_the_map_written_whole(tmp_path, suffix, with_time):
    scans, T = _overlapping_scans(8, 300)
    rng = np.random.default_rng(5)
    times = [rng.random(300) if with_time else None for _ in scans]
    voxel_filter = MapVoxelFilter(0.3)
    parts = [voxel_filter.add(pts, T[k], k, times[k]) for k, pts in enumerate(scans)]
    whole = MapCloud(np.vstack([p.points_world for p in parts]), np.concatenate([p.scan_index for p in parts]),
                     np.concatenate([p.time_s for p in parts]) if with_time else None)
    streamed = tmp_path / f"streamed{suffix}"
    written = write_map(streamed, chunked(iter(parts), chunk_points=100))
    write_map(tmp_path / f"whole{suffix}", whole)
    assert written == len(whole.points_world)
    a, b = read_map(streamed), read_map(tmp_path / f"whole{suffix}")
    assert np.array_equal(a.scan_index, b.scan_index) and np.array_equal(a.scan_index, whole.scan_index)
    if suffix == ".ply":  # float32, as the whole map
        assert np.array_equal(a.points_world, b.points_world)
        assert np.array_equal(a.points_world, whole.points_world.astype(np.float32))
    else:  # the grid's offset is the first chunk's minimum: each point rounded to LAS_SCALE_M
        from pa_cli.io.maps import LAS_SCALE_M

        assert np.abs(a.points_world - whole.points_world).max() <= LAS_SCALE_M / 2 + 1e-9
    assert (a.time_s is None) == (not with_time)
    if with_time:
        assert np.array_equal(a.time_s, whole.time_s)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([streamed.name, f"whole{suffix}"])


def test_chunks_regroup_in_order():
    clouds = [MapCloud(np.full((n, 3), float(k)), np.full(n, k, dtype=np.int32)) for k, n in enumerate([3, 0, 5, 1, 4])]
    chunks = list(chunked(clouds, chunk_points=4))
    assert [len(c.points_world) for c in chunks] == [8, 5]
    assert np.concatenate([c.scan_index for c in chunks]).tolist() == [0] * 3 + [2] * 5 + [3] + [4] * 4


def test_empty_streamed_map(tmp_path):
    for suffix in (".ply", ".las"):
        assert write_map(tmp_path / f"m{suffix}", iter([])) == 0
        assert len(read_map(tmp_path / f"m{suffix}").points_world) == 0


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
