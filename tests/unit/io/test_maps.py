"""Merged map: voxel downsampling against brute force, PLY/PCD/LAS round trips (intensity, scan, time),
chunked streaming writes, every point at voxel 0, points beyond the range dropped."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.errors import OutputError
from pa_cli.io.map_filter import MapFilter, MapVoxelFilter
from pa_cli.io.maps import (
    LAS_SCALE_M,
    MapCloud,
    MapPart,
    chunked,
    las_intensity_scale,
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


def test_the_voxel_key_set_matches_a_set_through_its_doublings():
    """The new keys of every batch (repeats within it and keys held before included) are the first
    occurrences a Python set finds, in order, while the table doubles several times."""
    from pa_cli.io.voxel_key_set import INITIAL_SLOTS, VoxelKeySet

    rng = np.random.default_rng(4)
    keys, held = VoxelKeySet(), set()
    for size in rng.integers(0, 20_000, size=40):
        batch = rng.integers(0, 300_000, size=size) * 4_000_000_007  # spread up to 2^60, the keys' bits
        expected = []
        for i, key in enumerate(batch.tolist()):
            if key not in held:
                held.add(key)
                expected.append(i)
        assert keys.add_new(batch).tolist() == expected
        assert keys.n_keys == len(held)
    assert len(keys._table) >= 8 * INITIAL_SLOTS


@pytest.mark.parametrize("n_scans", [1, 6, 40])
def test_voxel_filter_keeps_first_point_per_voxel_in_scan_order(n_scans):
    from pa_cli.io import maps

    voxel = 0.25
    scans, T = _overlapping_scans(n_scans)
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


def test_parts_placed_in_any_order_and_kept_in_order_are_the_parts_added_in_order():
    """`MapFilter.place` (range, pose, voxel keys: on any thread, in any order) then `keep` in the parts' order
    gives the clouds, counts and fields of `add` in order, to the bit."""
    scans, T = _overlapping_scans(7, 400)
    rng = np.random.default_rng(12)
    parts = [MapPart(k, pts * rng.uniform(0.5, 40.0, (len(pts), 1)), rng.random(len(pts)),
                     None if k == 4 else rng.random(len(pts)).astype(np.float32)) for k, pts in enumerate(scans)]
    in_order_filter, placed_filter = (MapFilter(0.2, min_range_m=1.0, max_range_m=60.0) for _ in range(2))
    added = [in_order_filter.add(part, T[k]) for k, part in enumerate(parts)]
    placed = {k: placed_filter.place(parts[k], T[k]) for k in reversed(range(len(parts)))}
    kept = [placed_filter.keep(placed[k]) for k in range(len(parts))]
    assert placed_filter.n_out_of_range == in_order_filter.n_out_of_range > 0
    for a, b in zip(added, kept, strict=True):
        for name in ("points_world", "scan_index", "time_s", "intensity"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(kept[4].intensity, np.zeros(len(kept[4].points_world), np.float32))  # 0 where none


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
    back = read_map_ply(path)
    p_back, s_back = back.points_world, back.scan_index
    assert p_back.dtype == np.float32 and back.intensity is None and back.time_s is None
    assert np.allclose(p_back, points.astype(np.float32))
    assert np.array_equal(s_back, scan)
    with pytest.raises(OutputError):
        write_map_ply(path, points, scan)
    write_map_ply(path, points[:10], scan[:10], force=True)
    assert len(read_map_ply(path).points_world) == 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ply"]  # no temp files left
    header = path.read_bytes()[:400].decode("ascii", "replace")
    assert "property int scan_index" in header and "property float x" in header


@pytest.mark.parametrize(("suffix", "with_time"), [(".las", True), (".las", False), (".laz", True)])
def test_las_round_trip(tmp_path, suffix, with_time):
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
    with pytest.raises(OutputError, match="unsupported map format '.xyz'"):
        write_map(tmp_path / "m.xyz", MapCloud(np.zeros((1, 3)), np.zeros(1, dtype=np.int32)))


def _full_cloud(n: int = 400, intensity_max: float = 255.0) -> MapCloud:
    rng = np.random.default_rng(6)
    return MapCloud(rng.normal(size=(n, 3)) * 20 + [300.0, -40.0, 2.0], rng.integers(0, 90, n).astype(np.int32),
                    1.7e9 + rng.random(n) * 30.0, (rng.random(n) * intensity_max).astype(np.float32))


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".las", ".laz"])
def test_intensity_scan_and_time_round_trip(tmp_path, suffix):
    cloud = _full_cloud(intensity_max=255.0)
    path = tmp_path / f"map{suffix}"
    assert write_map(path, chunked([cloud], chunk_points=150)) == len(cloud.points_world)
    back = read_map(path)
    assert np.array_equal(back.scan_index, cloud.scan_index)
    assert np.array_equal(back.time_s, cloud.time_s)  # double (PLY, PCD) and gps_time (LAS): exact
    if suffix in (".las", ".laz"):  # uint16 counts: 8-bit intensities kept to the nearest count
        assert las_intensity_scale(cloud.intensity) == 1.0
        assert np.abs(back.intensity - cloud.intensity).max() <= 0.5
        assert np.abs(back.points_world - cloud.points_world).max() <= LAS_SCALE_M / 2 + 1e-9
    else:
        assert np.array_equal(back.intensity, cloud.intensity)
        assert np.allclose(back.points_world, cloud.points_world, atol=1e-4)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_pcd_map_is_read_by_the_strict_scan_reader(tmp_path):
    """The PCD map follows PCL's layout: the scan reader (its own parser, not pypcd4) reads it."""
    from pa_cli.io.scans import read_scan

    cloud = _full_cloud(50)
    write_map(tmp_path / "map.pcd", cloud)
    header = (tmp_path / "map.pcd").read_bytes()[:300].decode("ascii", "replace")
    assert "FIELDS x y z scan_index intensity time" in header and "TYPE F F F I F F" in header
    scan = read_scan(tmp_path / "map.pcd")
    assert np.allclose(scan.points_scan, cloud.points_world, atol=1e-4)
    assert np.array_equal(scan.time, cloud.time_s) and np.array_equal(scan.intensity, cloud.intensity)


@pytest.mark.parametrize(("intensity_max", "scale"), [(1.0, 65535.0), (255.0, 1.0), (2.0e5, 65535 / 2.0e5)])
def test_las_intensity_scale_fits_uint16(tmp_path, intensity_max, scale):
    cloud = _full_cloud(300, intensity_max)
    cloud.intensity[0] = intensity_max
    assert las_intensity_scale(cloud.intensity) == pytest.approx(scale)
    write_map(tmp_path / "map.las", cloud)
    import laspy

    stored = laspy.read(str(tmp_path / "map.las")).intensity
    assert stored.dtype == np.uint16 and stored.max() == 65535 * (scale != 1.0) + 255 * (scale == 1.0)
    back = read_map(tmp_path / "map.las").intensity
    assert np.abs(back - cloud.intensity).max() <= 0.5 / scale + 1e-6 * intensity_max


def test_voxel_zero_keeps_every_point():
    scans, T = _overlapping_scans(4, 300)
    voxel_filter = MapVoxelFilter(0.0)
    clouds = [voxel_filter.add(points, T[k], k) for k, points in enumerate(scans)]
    assert [len(c.points_world) for c in clouds] == [300] * 4
    assert np.allclose(clouds[2].points_world, scans[2] + T[2, :3, 3])


def test_map_filter_drops_points_beyond_the_range_and_keeps_fields():
    rng = np.random.default_rng(8)
    directions = rng.normal(size=(500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    range_m = rng.uniform(0.1, 180.0, 500)
    points = directions * range_m[:, None]
    time_s, intensity = rng.random(500), rng.random(500).astype(np.float32)
    map_filter = MapFilter(0.0, min_range_m=0.5, max_range_m=100.0)
    T = np.eye(4)
    T[:3, 3] = [10.0, 0.0, 0.0]
    cloud = map_filter.add(MapPart(3, points, time_s, intensity), T)
    inside = (range_m >= 0.5) & (range_m <= 100.0)
    assert np.allclose(cloud.points_world, points[inside] + [10.0, 0.0, 0.0])
    assert np.array_equal(cloud.time_s, time_s[inside]) and np.array_equal(cloud.intensity, intensity[inside])
    assert map_filter.n_out_of_range == int((~inside).sum()) > 0 and set(cloud.scan_index) == {3}
    # a later scan without intensities gets 0, so every chunk has the same fields
    later = map_filter.add(MapPart(4, points[:5] * 0 + 1.0), np.eye(4))
    assert np.array_equal(later.intensity, np.zeros(5, np.float32)) and later.time_s is None


def test_map_chunks_must_agree_on_fields(tmp_path):
    from pa_cli.errors import FormatError

    with_intensity = _full_cloud(10)
    without = MapCloud(with_intensity.points_world, with_intensity.scan_index, with_intensity.time_s)
    with pytest.raises(FormatError, match="intensity"):
        write_map(tmp_path / "m.ply", iter([with_intensity, without]))
    assert list(tmp_path.iterdir()) == []
