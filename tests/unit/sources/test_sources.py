"""Scan sources: ROS1 and ROS2 bags written here with rosbags and read back, PointCloud2 layouts
against a brute-force decoder, the folder source's timestamps, the point cache, and `pa refine`
end to end on a bag."""

from __future__ import annotations

import json
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import write_pcd
from pa_cli.sources import ScanSource, open_source
from pa_cli.sources.bag import decode_pointcloud2
from pa_cli.sources.cache import CachedSource
from pa_cli.sources.folder import FolderSource
from pa_testing.room_scene import N_SCANS, ground_truth_poses, room_scans_scan_frame

TOPIC = "/points"
STAMP0_S = 1_700_000_000.25
SCAN_PERIOD_S = 0.1
SWEEP_S = 0.09  # per-point times spread over this much of each scan


def _stamp_s(k: int) -> float:
    return STAMP0_S + SCAN_PERIOD_S * k


def _point_times_s(n: int) -> np.ndarray:
    return np.linspace(0.0, SWEEP_S, n)


def _cloud_message(typestore, points: np.ndarray, stamp_s: float, time_field: str | None):
    """A PointCloud2: float32 x y z, then `time` float32 s or `t` uint32 ns, little-endian, unorganised."""
    types = typestore.types
    fields = [types["sensor_msgs/msg/PointField"](name=a, offset=4 * i, datatype=7, count=1)
              for i, a in enumerate("xyz")]
    columns = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if time_field == "time":
        fields.append(types["sensor_msgs/msg/PointField"](name="time", offset=12, datatype=7, count=1))
        columns.append(("time", "<f4"))
    elif time_field == "t":
        fields.append(types["sensor_msgs/msg/PointField"](name="t", offset=12, datatype=6, count=1))
        columns.append(("t", "<u4"))
    record = np.zeros(len(points), dtype=columns)
    for i, a in enumerate("xyz"):
        record[a] = points[:, i]
    if time_field == "time":
        record["time"] = _point_times_s(len(points))
    elif time_field == "t":
        record["t"] = np.round(_point_times_s(len(points)) * 1e9)
    sec = int(np.floor(stamp_s))
    stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((stamp_s - sec) * 1e9)))
    header_type = types["std_msgs/msg/Header"]
    if "seq" in header_type.__dataclass_fields__:  # ROS1 headers carry a sequence number
        header = header_type(seq=0, stamp=stamp, frame_id="lidar")
    else:
        header = header_type(stamp=stamp, frame_id="lidar")
    return types["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(points), fields=fields, is_bigendian=False,
        point_step=record.dtype.itemsize, row_step=record.dtype.itemsize * len(points),
        data=np.frombuffer(record.tobytes(), dtype=np.uint8), is_dense=True)


def write_bag(path, scans: list[np.ndarray], ros: int, time_field: str | None = "time",
              storage: str = "sqlite3") -> None:
    """A ROS1 `.bag` or ROS2 bag folder with one PointCloud2 per scan on TOPIC and one on /other."""
    from pa_testing.bags import bag_writer

    msgtype = "sensor_msgs/msg/PointCloud2"
    writer, serialize, typestore = bag_writer(path, ros, storage)
    with writer:
        connection = writer.add_connection(TOPIC, msgtype, typestore=typestore)
        other = writer.add_connection("/other", msgtype, typestore=typestore)
        for k, points in enumerate(scans):
            t_ns = int(round(_stamp_s(k) * 1e9))
            writer.write(connection, t_ns, serialize(_cloud_message(typestore, points, _stamp_s(k), time_field),
                                                     msgtype))
            if k == 0:
                writer.write(other, t_ns, serialize(_cloud_message(typestore, points[:5], _stamp_s(k), None),
                                                    msgtype))


@pytest.fixture(scope="module")
def room_scans():
    return room_scans_scan_frame(seed=3, n_points=4000)


@pytest.mark.parametrize(("ros", "storage", "time_field"), [(1, None, "time"), (2, "sqlite3", "t"),
                                                            (2, "mcap", None)])
def test_bag_round_trip(tmp_path, room_scans, ros, storage, time_field):
    path = tmp_path / ("run.bag" if ros == 1 else "run2")
    write_bag(path, room_scans, ros, time_field, storage or "sqlite3")
    source = open_source(path, topic=TOPIC)
    assert isinstance(source, ScanSource)
    source.check()
    assert len(source) == N_SCANS
    stamps = source.timestamps()
    assert np.allclose(stamps.stamps_s, [_stamp_s(k) for k in range(N_SCANS)], atol=1e-6, rtol=0)
    for k in (3, 0, 9, 3):  # random access, backwards too
        assert np.array_equal(source.points(k), room_scans[k].astype(np.float32).astype(np.float64))
        times = source.point_times(k)
        if time_field is None:
            assert times is None
        else:
            assert np.allclose(times, _point_times_s(len(room_scans[k])), atol=1e-6, rtol=0)
    source.close()


def test_bare_ros2_storage_file_is_a_bag(tmp_path, room_scans):
    write_bag(tmp_path / "run2", room_scans[:3], 2, storage="mcap")
    (mcap,) = (tmp_path / "run2").glob("*.mcap")
    source = open_source(mcap, topic=TOPIC)
    assert len(source) == 3 and np.array_equal(source.points(2), room_scans[2].astype(np.float32))
    source.close()


def test_topic_missing_or_wrong_lists_pointcloud2_topics(tmp_path, room_scans):
    path = tmp_path / "run.bag"
    write_bag(path, room_scans[:2], 1)
    for topic, said in ((None, "no --topic given"), ("/lidar", "topic '/lidar' is not in the bag")):
        with pytest.raises(InputError) as info:
            open_source(path, topic=topic)
        assert str(path) in str(info.value) and said in str(info.value)
        assert ("/other (sensor_msgs/msg/PointCloud2, 1 messages), /points (sensor_msgs/msg/PointCloud2, "
                "2 messages)") in str(info.value)


def _brute_force_decode(message) -> np.ndarray:
    """x y z of every point read one by one with struct (float32, any endianness, row padding)."""
    offsets = {f.name: f.offset for f in message.fields}
    endian = ">" if message.is_bigendian else "<"
    data = bytes(message.data)
    points = []
    for row in range(message.height):
        for col in range(message.width):
            base = row * message.row_step + col * message.point_step
            points.append([struct.unpack_from(endian + "f", data, base + offsets[a])[0] for a in "xyz"])
    points = np.array(points)
    return points[np.isfinite(points).all(axis=1)]


@pytest.mark.parametrize("big_endian", [False, True])
def test_decode_organised_padded_cloud_against_brute_force(big_endian):
    rng = np.random.default_rng(5)
    height, width, point_step, row_pad = 3, 7, 20, 12  # 8 unused bytes per point, 12 per row
    endian = ">" if big_endian else "<"
    dtype = np.dtype({"names": ["z", "x", "y"], "formats": [endian + "f4"] * 3, "offsets": [0, 8, 16],
                      "itemsize": point_step})
    cloud = np.zeros((height, width), dtype=dtype)
    for a in "xyz":
        cloud[a] = rng.normal(size=(height, width))
    cloud["x"][1, 2] = np.nan  # organised clouds mark missing returns with NaN
    rows = [cloud[r].tobytes() + bytes(row_pad) for r in range(height)]
    fields = [SimpleNamespace(name=n, offset=o, datatype=7, count=1) for n, o in (("z", 0), ("x", 8), ("y", 16))]
    message = SimpleNamespace(fields=fields, is_bigendian=big_endian, point_step=point_step,
                              row_step=width * point_step + row_pad, height=height, width=width,
                              data=np.frombuffer(b"".join(rows), dtype=np.uint8),
                              header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0)))
    cloud = decode_pointcloud2(message, "test")
    assert cloud.raw_time is None and len(cloud.points) == height * width - 1
    assert np.array_equal(cloud.points, _brute_force_decode(message))


def test_truncated_message_is_a_format_error():
    fields = [SimpleNamespace(name=a, offset=4 * i, datatype=7, count=1) for i, a in enumerate("xyz")]
    message = SimpleNamespace(fields=fields, is_bigendian=False, point_step=12, row_step=120, height=1, width=10,
                              data=np.zeros(100, dtype=np.uint8))
    with pytest.raises(FormatError, match="100 data bytes for 1 x 10 points"):
        decode_pointcloud2(message, "bag.bag /points message 4")


def test_folder_timestamps_say_why_a_times_file_is_ignored(tmp_path, room_scans):
    scans = tmp_path / "scans"
    scans.mkdir()
    for k in range(3):
        write_pcd(scans / f"{k}.pcd", room_scans[k])
    source = FolderSource(scans)
    assert source.timestamps().stamps_s is None and "no times.txt" in source.timestamps().origin
    (tmp_path / "times.txt").write_text("1.0\n2.0\n")
    found = source.timestamps()
    assert found.stamps_s is None
    assert found.origin == f"{tmp_path / 'times.txt'} has 2 timestamps for 3 scans (ignored)"
    (scans / "times.txt").write_text("1.0\n2.0\n3.5\n")
    found = source.timestamps()
    assert np.array_equal(found.stamps_s, [1.0, 2.0, 3.5]) and found.origin == str(scans / "times.txt")


def test_cache_reads_each_scan_once(tmp_path, room_scans, monkeypatch):
    import pa_cli.sources.folder

    scans = tmp_path / "scans"
    scans.mkdir()
    for k in range(3):
        write_pcd(scans / f"{k}.pcd", room_scans[k])
    folder = FolderSource(scans)
    reads = []
    original = pa_cli.sources.folder.read_scan
    monkeypatch.setattr(pa_cli.sources.folder, "read_scan", lambda path: reads.append(path.name) or original(path))
    cached = CachedSource(folder)
    for k in (0, 1, 0, 2, 1, 0):
        assert np.array_equal(cached.points(k), room_scans[k].astype(np.float32))
        assert cached.point_times(k) is None
    assert sorted(reads) == ["0.pcd", "1.pcd", "2.pcd"]


def test_cache_keeps_per_point_times(tmp_path, room_scans):
    bag = tmp_path / "run.bag"
    write_bag(bag, room_scans[:2], 1, "time")
    cached = CachedSource(open_source(bag, topic=TOPIC))
    for k in (1, 0, 1):
        assert np.allclose(cached.point_times(k), _point_times_s(len(room_scans[k])), atol=1e-7, rtol=0)
    cached.close()


def test_cache_keeps_absolute_times_to_the_microsecond():
    from pa_cli.sources.memory import ArraySource

    times = [1_700_000_000.25 + np.linspace(0.0, 0.1, 50), 1.7e18 + np.linspace(0.0, 1e8, 50)]  # s, ns
    cached = CachedSource(ArraySource([np.ones((50, 3))] * 2, times))
    for k, scale in ((0, 1.0), (1, 1e-9)):
        for _ in range(2):  # the first read fills the cache, the second reads it
            np.testing.assert_allclose((cached.point_times(k) - times[k][0]) * scale,
                                       (times[k] - times[k][0]) * scale, rtol=0, atol=1e-6)


def test_not_a_bag_is_a_format_error_naming_it(tmp_path):
    junk = tmp_path / "run.bag"
    junk.write_bytes(b"#ROSBAG V1.9\n" + bytes(50))
    with pytest.raises(FormatError, match=f"{junk}: cannot open the ROS bag"):
        open_source(junk, topic=TOPIC)


@pytest.mark.slow
def test_refine_on_a_bag_end_to_end(run_pa, tmp_path, room_scans):
    from pa_cli.io.maps import read_map
    from pa_cli.io.trajectory import read_trajectory, write_kitti

    bag = tmp_path / "run.bag"
    write_bag(bag, room_scans, 1, "time")
    gt = tmp_path / "gt.txt"
    write_kitti(gt, ground_truth_poses())
    cfg = tmp_path / "cfg.yaml"
    # the room's points are cast at one instant per scan: their time field only labels them, and
    # deskewing along the trajectory would distort them (by its speed times up to a sweep)
    cfg.write_text("sensor: {max_range_m: 30.0, min_range_m: 0.2, deskew: 'off'}\nscene: {plane_voxel_m: 1.0}\n"
                   "refine: {max_rounds: 2}\nmap: {voxel_m: 0.1}\nadvanced: {kiss_icp: {voxel_size_m: 0.1}}\n")
    out = tmp_path / "map.las"
    code, _, err = run_pa("refine", bag, "--topic", TOPIC, "--out", out, "--config", cfg, "--gt", gt, "-q")
    assert code == 0, err
    report = json.loads((tmp_path / "map_report.json").read_text())
    assert report["input"]["n_scans"] == N_SCANS and report["input"]["topic"] == TOPIC
    assert report["gt"]["refined"]["ate_rmse_m"] <= report["gt"]["initial"]["ate_rmse_m"] < 0.05
    tum = read_trajectory(tmp_path / "map_poses_tum.txt")
    assert np.allclose(tum.timestamps, [_stamp_s(k) for k in range(N_SCANS)], atol=1e-6, rtol=0)
    cloud = read_map(out)
    assert len(cloud.points_world) > 1000 and set(np.unique(cloud.scan_index)) <= set(range(N_SCANS))
    # gps_time: the scan's header stamp plus the point's own time, within the scan's sweep
    offsets = cloud.time_s - np.array([_stamp_s(k) for k in cloud.scan_index])
    assert offsets.min() >= -1e-6 and offsets.max() <= SWEEP_S + 1e-6 and offsets.max() > SWEEP_S / 2


def test_header_check_accepts_what_read_scan_reads(tmp_path):
    from pa_cli.io.scans import check_scan_header, read_scan

    points = np.random.default_rng(8).normal(size=(20, 3)).astype(np.float32)
    write_pcd(tmp_path / "binary.pcd", points)
    rows = "".join(f"{x} {y} {z}\n" for x, y, z in points)
    (tmp_path / "ascii.pcd").write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                        f"WIDTH 20\nHEIGHT 1\nPOINTS 20\nDATA ascii\n{rows}")
    (tmp_path / "ascii.ply").write_text("ply\nformat ascii 1.0\nelement vertex 20\nproperty float x\n"
                                        f"property float y\nproperty float z\nend_header\n{rows}")
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 20\n" + "".join(
        f"property float {a}\n" for a in "xyz") + "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    (tmp_path / "binary.ply").write_bytes(header.encode() + points.tobytes())
    np.column_stack([points, np.zeros(20, np.float32)]).tofile(tmp_path / "kitti.bin")
    for path in sorted(tmp_path.iterdir()):
        check_scan_header(path)
        assert np.allclose(read_scan(path).points_scan, points, atol=1e-6), path.name
    (tmp_path / "short.bin").write_bytes(bytes(30))
    (tmp_path / "no_data.pcd").write_text("VERSION 0.7\nFIELDS x y z\nPOINTS 3\n")
    for name, said in (("short.bin", "not a multiple of 16"), ("no_data.pcd", "no PCD 'DATA' line")):
        with pytest.raises(FormatError, match=said):
            check_scan_header(tmp_path / name)


def test_corrupt_message_is_a_format_error_naming_it(tmp_path, room_scans):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "sensor_msgs/msg/PointCloud2"
    path = tmp_path / "cut.bag"
    with Writer(path) as writer:
        connection = writer.add_connection(TOPIC, msgtype, typestore=typestore)
        for k in range(2):
            raw = typestore.serialize_ros1(_cloud_message(typestore, room_scans[k], _stamp_s(k), None), msgtype)
            writer.write(connection, int(_stamp_s(k) * 1e9), raw if k == 0 else raw[:40])
    source = open_source(path, topic=TOPIC)
    with pytest.raises(FormatError, match=f"{path} {TOPIC} message 1: "):
        source.check()
    source.close()


def _write_ply_scan(path, points: np.ndarray) -> None:
    """A binary PLY scan: float32 x y z vertices (as other tools write them)."""
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n" + "".join(
        f"property float {a}\n" for a in "xyz") + "end_header\n"
    path.write_bytes(header.encode() + points.astype("<f4").tobytes())


def _scan_folder(folder, scans, suffixes=(".pcd",)):
    folder.mkdir(parents=True)
    for k, points in enumerate(scans):
        for suffix in suffixes:
            if suffix == ".pcd":
                write_pcd(folder / f"{k:06d}.pcd", points)
            else:
                _write_ply_scan(folder / f"{k:06d}{suffix}", points)
    return folder


def test_a_folder_with_two_scan_formats_is_refused_and_glob_picks_one(tmp_path, room_scans):
    scans = _scan_folder(tmp_path / "scans", room_scans[:3], (".pcd", ".ply"))
    for glob in (None, "*"):
        with pytest.raises(InputError) as info:
            open_source(scans, glob=glob)
        message = str(info.value)
        assert message.startswith(f"{scans}: scan files")
        assert "3 .pcd (000000.pcd, 000001.pcd, ...); 3 .ply (000000.ply, 000001.ply, ...)" in message
        assert "--glob '*.pcd' or --glob '*.ply'" in message
    assert [p.name for p in open_source(scans, glob="*.ply").files] == ["000000.ply", "000001.ply", "000002.ply"]
    assert len(open_source(scans, glob="*.pcd")) == 3


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_maps_written_by_pa_are_never_read_as_scans(tmp_path, room_scans, caplog, suffix):
    from pa_cli.io.maps import MapCloud, write_map
    from pa_cli.refine.outputs import RefineOutputs

    scans = _scan_folder(tmp_path / "scans", room_scans[:3], (suffix,))
    outputs = RefineOutputs.from_map_path(scans / f"map{suffix}")
    write_map(outputs.map_path, MapCloud(room_scans[0][:100], np.zeros(100, dtype=np.int32)))
    for side_file in (outputs.poses_kitti, outputs.report_json):
        side_file.write_text("written by pa refine\n")
    with caplog.at_level("INFO", logger="pa_cli"):
        source = open_source(scans)
    assert [p.name for p in source.files] == [f"00000{k}{suffix}" for k in range(3)]
    assert f"{scans}: skipped 1 file(s) written by pa (maps, never read as scans): map{suffix}" in caplog.text
    with pytest.raises(InputError, match=rf"--glob 'map\.\*' with extensions \{suffix} \(1 of them written by pa\)"):
        open_source(scans, glob="map.*")


def test_out_inside_the_scan_folder_is_refused_unless_force(run_pa, tmp_path, room_scans):
    from pa_cli.errors import UsageError
    from pa_cli.sources import check_out_of_scans

    scans = _scan_folder(tmp_path / "scans", room_scans[:3])
    code, _, err = run_pa("refine", scans, "--out", scans / "map.ply")
    message = " ".join(err.split())
    assert code == 2 and "Traceback" not in err
    assert f"{scans / 'map.ply'}: --out is inside the scan folder {scans}" in message
    assert f"--out {tmp_path / 'map.ply'}" in message and "--force" in message
    assert sorted(p.name for p in scans.iterdir()) == ["000000.pcd", "000001.pcd", "000002.pcd"]
    with pytest.raises(UsageError, match="inside the scan folder"):
        check_out_of_scans(scans, scans / "maps" / "map.ply", force=False)
    check_out_of_scans(scans, scans / "map.ply", force=True)
    check_out_of_scans(scans, tmp_path / "map.ply", force=False)


def test_a_dataset_root_suggests_where_its_scans_are(run_pa, tmp_path, room_scans):
    root = tmp_path / "office"
    _scan_folder(root / "scans", room_scans[:3])
    (root / "times.txt").write_text("0.0\n0.1\n0.2\n")
    code, _, err = run_pa("refine", root, "--out", tmp_path / "map.ply")
    message = " ".join(err.split())
    assert code == 1 and "Traceback" not in err and "--glob" not in message
    assert f"{root}: no scan files (.pcd .ply .bin) in the folder itself" in message
    assert f"did you mean {root / 'scans'}?" in message
    kitti = tmp_path / "kitti"
    velodyne = kitti / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True)
    for k in range(2):
        np.zeros((5, 4), dtype="<f4").tofile(velodyne / f"{k:06d}.bin")
    (kitti / "sequences" / "01").mkdir()
    with pytest.raises(InputError, match=f"did you mean {velodyne}\\?"):
        open_source(kitti)
    bags = tmp_path / "bags"
    bags.mkdir()
    for name in ("a.bag", "b.bag"):
        write_bag(bags / name, room_scans[:2], 1)
    with pytest.raises(InputError, match=f"did you mean {bags / 'a.bag'} --topic TOPIC\\? \\(also below it: "
                                         f"{bags / 'b.bag'}\\)"):
        open_source(bags)
