"""Inputs that break (issue 37, item 4): a topic of another type, messages out of order or with
duplicated stamps, scans without valid points, a damaged or truncated bag, a folder of many
files. Each gets a clear message or a skip that is named and counted; the bags and folders are
written here."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from pa_cli.errors import FormatError, InputError
from pa_cli.io.scans import write_pcd
from pa_cli.sources import ScanSubset, open_source
from pa_cli.sources.base import read_issues
from pa_cli.sources.cache import CachedSource
from pa_cli.sources.folder import FolderSource
from pa_cli.sources.screen import MIN_VALID_POINTS, ScreenedSource, kept_indices
from pa_testing.bags import bag_writer
from tests.unit.sources.test_sources import TOPIC, _cloud_message

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
STAMP0_S = 1_700_000_000.0


def _scans(n: int, n_points: int = 300, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(-10, 10, size=(n_points, 3)) for _ in range(n)]


def _write_clouds(path, clouds: list[tuple[float, np.ndarray]], ros: int = 1, storage: str = "sqlite3",
                  extra_topics: bool = False, chunk_bytes: int | None = None) -> None:
    """A bag with one PointCloud2 per (header stamp, points) on TOPIC, in the order given (bag time
    increasing); with `extra_topics` also an Imu and a String message."""
    writer, serialize, typestore = bag_writer(path, ros, storage)
    if chunk_bytes is not None:
        writer.chunk_threshold = chunk_bytes
    types = typestore.types
    with writer:
        connection = writer.add_connection(TOPIC, POINTCLOUD2, typestore=typestore)
        for k, (stamp_s, points) in enumerate(clouds):
            message = _cloud_message(typestore, points, stamp_s, "time")
            writer.write(connection, int(STAMP0_S * 1e9) + k * 100_000_000, serialize(message, POINTCLOUD2))
        if extra_topics:
            imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=typestore)
            text = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=typestore)
            header = message.header
            zero3 = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            q = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
            cov = np.zeros(9)
            writer.write(imu, int(STAMP0_S * 1e9), serialize(types["sensor_msgs/msg/Imu"](
                header=header, orientation=q, orientation_covariance=cov, angular_velocity=zero3,
                angular_velocity_covariance=cov, linear_acceleration=zero3, linear_acceleration_covariance=cov),
                "sensor_msgs/msg/Imu"))
            writer.write(text, int(STAMP0_S * 1e9), serialize(types["std_msgs/msg/String"](data="hi"),
                                                              "std_msgs/msg/String"))


def _as_read(points: np.ndarray) -> np.ndarray:
    """Points as a bag gives them back: float32 in the message, without points at the origin."""
    points = points.astype(np.float32).astype(np.float64)
    return points[points.any(axis=1)]


# ---------------------------------------------------------------- 1. a topic of another type


def test_a_topic_of_another_type_names_its_type_and_the_topics_that_fit(tmp_path, run_pa):
    path = tmp_path / "run.bag"
    _write_clouds(path, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(_scans(3))], extra_topics=True)
    with pytest.raises(InputError) as info:
        open_source(path, topic="/imu")
    message = str(info.value)
    assert message.startswith(f"{path}: topic '/imu' is of type sensor_msgs/msg/Imu; pa reads "
                              f"{POINTCLOUD2}, livox_ros_driver/msg/CustomMsg or livox_ros_driver2/msg/CustomMsg")
    assert f"the point cloud topics in the bag: {TOPIC} ({POINTCLOUD2}, 3 messages). Choose one with --topic." \
        in message
    code, _, err = run_pa("refine", path, "--topic", "/chatter", "--out", tmp_path / "m.ply")
    assert code == 1 and "Traceback" not in err
    assert "topic '/chatter' is of type std_msgs/msg/String" in " ".join(err.split())
    assert not (tmp_path / "m.ply").exists()


def test_without_topic_the_point_cloud_topics_are_listed_and_none_is_guessed(tmp_path):
    one = tmp_path / "one.bag"
    _write_clouds(one, [(STAMP0_S, _scans(1)[0])], extra_topics=True)
    with pytest.raises(InputError, match=r"no --topic given \(pa never guesses the topic\); the point cloud "
                                         rf"topics in the bag: {TOPIC} \({POINTCLOUD2}, 1 messages\)\."):
        open_source(one)
    none = tmp_path / "none.bag"
    writer, serialize, typestore = bag_writer(none, 1)
    with writer:
        text = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=typestore)
        writer.write(text, 1, serialize(typestore.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    with pytest.raises(InputError, match=r"the bag has no point cloud topic \(its topics: /chatter\)"):
        open_source(none, topic="/chatter")


# ---------------------------------------------------------------- 2. order and duplicated stamps


@pytest.mark.parametrize(("ros", "storage"), [(1, "sqlite3"), (2, "mcap")])
def test_messages_are_read_in_stamp_order_and_a_duplicated_stamp_once(tmp_path, caplog, ros, storage):
    scans = _scans(6)
    offsets_s = [0.0, 0.2, 0.1, 0.3, 0.3, 0.4]  # message 2 is stored late, message 4 repeats 3's stamp
    path = tmp_path / ("run.bag" if ros == 1 else "run2")
    _write_clouds(path, [(STAMP0_S + o, p) for o, p in zip(offsets_s, scans, strict=True)], ros, storage)
    source = open_source(path, topic=TOPIC)
    with caplog.at_level(logging.WARNING):
        source.check()
    expected = [0, 2, 1, 3, 5]  # messages in stamp order, the duplicate left out
    assert len(source) == len(expected)
    assert np.allclose(source.timestamps().stamps_s - STAMP0_S, [offsets_s[m] for m in expected], atol=1e-6)
    for k, m in enumerate(expected):
        assert np.array_equal(source.points(k), _as_read(scans[m])), k
    issues = read_issues(source)
    assert issues.n_reordered == 1 and issues.stopped is None
    assert [(s.scan, s.reason) for s in issues.skipped] == [
        (f"{source.name} message 4 (header stamp {STAMP0_S + 0.3:.6f} s)", "duplicated header stamp")]
    assert issues.report()["skipped_by_reason"] == {"duplicated header stamp": 1}
    text = caplog.text
    assert "1 message(s) are stored out of the order of their header stamps" in text
    assert f"1 message(s) repeat the header stamp of an earlier message; the first is read, the others skipped: " \
           f"{source.name} message 4" in text
    assert source.scan_name(1) == f"{source.name} message 2 (header stamp {STAMP0_S + 0.1:.6f} s)"
    source.close()


def test_header_stamps_that_order_nothing_keep_the_bag_order(tmp_path, caplog):
    scans = _scans(4)
    path = tmp_path / "zero.bag"
    _write_clouds(path, [(0.0, p) for p in scans])  # a driver that never sets the stamp
    source = open_source(path, topic=TOPIC)
    with caplog.at_level(logging.WARNING):
        source.check()
    assert len(source) == 4 and read_issues(source).skipped == ()
    assert all(np.array_equal(source.points(k), _as_read(p)) for k, p in enumerate(scans))
    assert "1 distinct header stamps for 4 messages; the messages are read in the bag's order" in caplog.text
    source.close()


# ---------------------------------------------------------------- 3. scans without valid points


def _bad_scans() -> tuple[list[np.ndarray], list[int]]:
    """Six scans: 1 all at the origin, 3 all NaN, 4 with MIN_VALID_POINTS - 1 valid points; the others fine."""
    scans = _scans(6)
    scans[1] = np.zeros_like(scans[1])
    scans[3] = np.full_like(scans[3], np.nan)
    scans[4][MIN_VALID_POINTS - 1:] = 0.0
    return scans, [0, 2, 5]


def test_scans_without_enough_valid_points_are_skipped_named_and_counted(tmp_path, caplog):
    scans, kept = _bad_scans()
    folder = tmp_path / "scans"
    folder.mkdir()
    for k, points in enumerate(scans):
        write_pcd(folder / f"{k:03d}.pcd", points)
    (folder / "times.txt").write_text("".join(f"{10 + k}.5\n" for k in range(len(scans))))
    source = ScreenedSource(CachedSource(FolderSource(folder)))
    with caplog.at_level(logging.WARNING):
        source.check()
    assert len(source) == 3 and source.kept.tolist() == kept
    for k, m in enumerate(kept):
        assert np.allclose(source.points(k), scans[m], atol=1e-5)
    assert np.array_equal(source.timestamps().stamps_s, [10.5 + m for m in kept])
    issues = read_issues(source)
    assert [(s.scan, s.reason) for s in issues.skipped] == [
        (str(folder / "001.pcd"), "no valid point"), (str(folder / "003.pcd"), "no valid point"),
        (str(folder / "004.pcd"), f"fewer than {MIN_VALID_POINTS} valid points")]
    assert issues.report()["n_skipped"] == 3
    assert f"3 of 6 scans hold fewer than {MIN_VALID_POINTS} valid points" in caplog.text
    assert str(folder / "004.pcd") in caplog.text
    # a worker that opens the folder again reads the same scans by the skipped indices
    assert source.skipped_indices() == (1, 3, 4)
    assert kept_indices(source.skipped_indices(), 0, 3).tolist() == kept
    assert kept_indices(source.skipped_indices(), 1, 3).tolist() == kept[1:]


def test_a_worker_reads_the_scans_kept(tmp_path):
    from pa_cli.config import PaConfig
    from pa_cli.planes.windowed import ScanRef, _WindowCache, _WindowTask

    scans, kept = _bad_scans()
    folder = tmp_path / "scans"
    folder.mkdir()
    for k, points in enumerate(scans):
        write_pcd(folder / f"{k:03d}.pcd", points)
    source = ScreenedSource(FolderSource(folder))
    source.check()
    ref = ScanRef(str(folder), skipped=source.skipped_indices())
    task = _WindowTask(ref, 1, 3, np.tile(np.eye(4), (2, 1, 1)), PaConfig().advanced.planes, 0.0)
    read = _WindowCache().points(task)
    assert len(read) == 2 and all(np.array_equal(p, source.points(k)) for p, k in zip(read, (1, 2), strict=True))


def test_a_subset_screens_and_names_the_source_scans_it_keeps(tmp_path):
    """--first/--every then the screen: scan k of the run is the folder's scan at the subset's index,
    and a scan left out is named by its own file."""
    scans, _ = _bad_scans()
    folder = tmp_path / "scans"
    folder.mkdir()
    for k, points in enumerate(scans):
        write_pcd(folder / f"{k:03d}.pcd", points)
    source = ScreenedSource(CachedSource(open_source(folder, subset=ScanSubset(first=1, every=2))))
    source.check()  # the subset holds files 001, 003, 005; 001 and 003 have too few valid points
    assert len(source) == 1 and np.allclose(source.points(0), scans[5], atol=1e-5)
    assert [s.scan for s in read_issues(source).skipped] == [str(folder / "001.pcd"), str(folder / "003.pcd")]


def test_a_bag_message_without_valid_points_is_skipped_by_its_name(tmp_path):
    scans, kept = _bad_scans()
    path = tmp_path / "run.bag"
    _write_clouds(path, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(scans)])
    source = ScreenedSource(open_source(path, topic=TOPIC))
    source.check()
    assert source.kept.tolist() == kept
    assert [s.scan for s in read_issues(source).skipped] == [
        f"{path} {TOPIC} message {m} (header stamp {STAMP0_S + 0.1 * m:.6f} s)" for m in (1, 3, 4)]
    assert all(np.array_equal(source.points(k), _as_read(scans[m])) for k, m in enumerate(kept))
    source.close()


def test_a_run_where_no_scan_has_valid_points_is_a_clear_error(tmp_path, run_pa):
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        write_pcd(folder / f"{k}.pcd", np.zeros((500, 3)))
    code, _, err = run_pa("refine", folder, "--out", tmp_path / "m.ply")
    text = " ".join(err.split())
    assert code == 1 and "Traceback" not in err
    assert f"{folder}: none of the 3 scans holds {MIN_VALID_POINTS} or more valid points" in text
    assert not (tmp_path / "m.ply").exists()


# ---------------------------------------------------------------- 6. damaged and truncated bags


def test_a_bag_damaged_midway_gives_the_messages_before_the_damage(tmp_path, caplog):
    scans = _scans(8, n_points=2000)
    path = tmp_path / "run.bag"
    _write_clouds(path, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(scans)], chunk_bytes=1)  # a chunk per message
    data = bytearray(path.read_bytes())
    fifth = data.rindex(b"op=\x02", 0, data.index(scans[5][0].astype(np.float32).tobytes()))
    data[fifth - 4:fifth] = b"\xff\xff\xff\x7f"  # message 5's record header: a field longer than the bag
    path.write_bytes(bytes(data))
    source = open_source(path, topic=TOPIC)
    with caplog.at_level(logging.WARNING):
        source.check()
    n_read = len(source)
    assert 1 <= n_read <= 5
    assert all(np.array_equal(source.points(k), _as_read(scans[k])) for k in range(n_read))
    stopped = read_issues(source).stopped
    assert stopped.startswith(f"{source.name}: unreadable after message {n_read - 1}") and f"{n_read} of 8" in stopped
    assert f"{n_read} of 8 messages read" in caplog.text
    source.close()


def test_a_ros1_bag_cut_off_gives_the_messages_of_its_complete_chunks(tmp_path, run_pa, caplog):
    scans = _scans(10, n_points=3000)  # 48 kB per message: three to a chunk of 100 kB
    whole = tmp_path / "whole.bag"
    _write_clouds(whole, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(scans)], chunk_bytes=100_000)
    data = whole.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[:len(data) * 6 // 10])  # no index, the second chunk cut in two
    with caplog.at_level(logging.WARNING):
        source = open_source(cut, topic=TOPIC)
        source.check()
    assert len(source) == 3
    assert all(np.array_equal(source.points(k), _as_read(scans[k])) for k in range(3))
    stopped = read_issues(source).stopped
    assert stopped.startswith(f"{cut}: no index; chunks read up to byte ") and "Got only" in stopped
    assert "the bag has no index (a recording cut off?); read its 3 complete messages chunk by chunk" in caplog.text
    source.close()
    early = tmp_path / "early.bag"
    early.write_bytes(data[:len(data) // 10])  # inside the first chunk
    code, _, err = run_pa("refine", early, "--topic", TOPIC, "--out", tmp_path / "m.ply")
    text = " ".join(err.split())
    assert code == 1 and "Traceback" not in err
    assert f"{early}: cannot open the ROS bag" in text and "Its chunks hold no complete message" in text
    assert "rosbag reindex" in text


@pytest.mark.parametrize(("storage", "hint"), [("mcap", "mcap recover"), ("sqlite3", ".recover")])
def test_a_truncated_ros2_bag_is_a_clear_error_with_the_repair(tmp_path, run_pa, storage, hint):
    whole = tmp_path / "whole"
    _write_clouds(whole, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(_scans(5))], 2, storage)
    (stored,) = [p for p in whole.iterdir() if p.suffix in (".db3", ".mcap")]
    cut = tmp_path / f"cut{stored.suffix}"
    cut.write_bytes(stored.read_bytes()[:stored.stat().st_size * 2 // 3])
    code, _, err = run_pa("refine", cut, "--topic", TOPIC, "--out", tmp_path / "m.ply")
    text = " ".join(err.split())
    assert code == 1 and "Traceback" not in err
    assert f"{cut}: cannot open the ROS bag" in text and hint in text
    with pytest.raises(FormatError):
        open_source(cut, topic=TOPIC)


# ---------------------------------------------------------------- 4. a 2-million-point scan

# Bytes traced per point of one message while the load step reads it: its raw bytes (16 per point
# here) and a few float64 copies of x y z (24 each), never a Python object per point.
LOAD_BYTES_PER_POINT = 250


@pytest.mark.slow
def test_a_two_million_point_scan_is_read_in_bounded_memory(tmp_path):
    import tracemalloc

    n_points = 2_000_000
    rng = np.random.default_rng(2)
    scans = [rng.uniform(-50, 50, (n_points, 3)) for _ in range(2)]
    path = tmp_path / "big.bag"
    _write_clouds(path, [(STAMP0_S + 0.1 * k, p) for k, p in enumerate(scans)])
    tracemalloc.start()
    try:
        source = ScreenedSource(CachedSource(open_source(path, topic=TOPIC)))
        source.check()
        _, peak_bytes = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak_bytes <= LOAD_BYTES_PER_POINT * n_points
    assert source.source.n_bytes == 2 * n_points * 16  # the cache: float32 x y z and time offsets
    assert np.array_equal(source.points(1), scans[1].astype(np.float32).astype(np.float64))
    source.close()


# ---------------------------------------------------------------- 5. a folder of many files


@pytest.mark.parametrize("n_files", [5_000, pytest.param(100_000, marks=pytest.mark.slow)])
def test_a_folder_of_many_files_is_listed_in_natural_order_without_opening_them(tmp_path, monkeypatch, caplog,
                                                                                 n_files):
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in np.random.default_rng(1).permutation(n_files):
        (folder / f"{k}.bin").touch()
    (folder / "times.txt").touch()
    (folder / "notes").touch()
    opened = []
    real_open = open

    def counting_open(file, *args, **kwargs):
        opened.append(file)
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", counting_open)
    monkeypatch.setattr("io.open", counting_open)  # Path.open
    with caplog.at_level(logging.INFO):
        source = open_source(folder)
    assert not opened  # no header read to list the files
    assert len(source) == n_files
    assert [int(p.stem) for p in source.files] == list(range(n_files))  # 2.bin before 10.bin
    assert f"{folder}: 1 file(s) that are not scans ((no extension)) are not read: notes" in caplog.text


# ---------------------------------------------------------------- the report counts what was left out


@pytest.mark.slow
def test_refine_reports_the_messages_left_out_and_reordered(run_pa, tmp_path):
    import json

    from pa_cli.io.trajectory import read_trajectory
    from pa_testing.room_scene import N_SCANS, room_scans_scan_frame

    room = room_scans_scan_frame(seed=3, n_points=4000)
    stamps_s = [STAMP0_S + 0.1 * k for k in range(N_SCANS)]
    clouds = [(stamps_s[k], room[k]) for k in range(N_SCANS)]
    clouds[2], clouds[3] = clouds[3], clouds[2]  # stored out of order
    clouds.insert(5, (stamps_s[4], room[4] + 1.0))  # a second message with scan 4's stamp
    clouds.insert(7, (stamps_s[5] + 0.05, np.zeros((500, 3))))  # a message without valid points
    bag = tmp_path / "run.bag"
    _write_clouds(bag, clouds)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("sensor: {max_range_m: 30.0, min_range_m: 0.2, deskew: 'off'}\nscene: {plane_voxel_m: 1.0}\n"
                   "refine: {max_rounds: 2}\nmap: {voxel_m: 0.1}\nadvanced: {kiss_icp: {voxel_size_m: 0.1}}\n")
    code, _, err = run_pa("refine", bag, "--topic", TOPIC, "--out", tmp_path / "map.ply", "--config", cfg, "-q")
    assert code == 0, err
    report = json.loads((tmp_path / "map_report.json").read_text())
    assert report["input"]["n_scans"] == N_SCANS
    issues = report["input"]["read_issues"]
    assert issues["n_reordered"] == 1 and issues["n_skipped"] == 2 and issues["stopped"] is None
    assert issues["skipped_by_reason"] == {"duplicated header stamp": 1, "no valid point": 1}
    assert [s["scan"] for s in issues["skipped"]] == [
        f"{bag} {TOPIC} message 5 (header stamp {stamps_s[4]:.6f} s)",
        f"{bag} {TOPIC} message 7 (header stamp {stamps_s[5] + 0.05:.6f} s)"]
    tum = read_trajectory(tmp_path / "map_poses_tum.txt")
    assert np.allclose(tum.timestamps, stamps_s, atol=1e-6, rtol=0)
