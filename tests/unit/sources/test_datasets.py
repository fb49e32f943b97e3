"""Dataset layouts (`pa_cli.sources.datasets`) and scan subsets (`pa_cli.sources.subset`): each
layout written here in the dataset's exact names and formats (`pa_testing.dataset_layouts`) is
recognised from its sequence folder and from its scan folder and gives back the points, times and
timestamps written."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.errors import FormatError, InputError, UsageError
from pa_cli.io.scans import write_pcd
from pa_cli.sources import ScanSubset, SubsetSource, describe_source, open_source, reads_scans_apart
from pa_cli.sources.datasets import KITTI, MULRAN, NCD, NCLT, find_layout
from pa_cli.sources.folder import FolderSource
from pa_cli.sources.screen import MIN_VALID_POINTS
from pa_testing import dataset_layouts as layouts

N_SCANS = 4
PERIOD_S = 0.1


def _scans(n_points: int = 300, seed: int = 0) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Points within 40 m (NCLT's uint16 reaches 227 m) and their times within the sweep (s)."""
    rng = np.random.default_rng(seed)
    points = [rng.uniform(-40.0, 40.0, (n_points, 3)) for _ in range(N_SCANS)]
    times = [np.sort(rng.uniform(0.0, PERIOD_S, n_points)) for _ in range(N_SCANS)]
    return points, times


@pytest.fixture
def scans():
    return _scans()


def _check_points(source, points, atol):
    assert len(source) == len(points)
    for k, p in enumerate(points):
        np.testing.assert_allclose(source.points(k), p, rtol=0, atol=atol)


def test_kitti_sequence_and_its_velodyne_folder(tmp_path, scans):
    points, _ = scans
    seq = tmp_path / "sequences" / "00"
    stamps = layouts.stamps_s(N_SCANS)
    layouts.write_kitti_scans(seq, points, stamps)
    gt = layouts.write_kitti_gt(tmp_path, np.tile(np.eye(4), (N_SCANS, 1, 1)))
    for given in (seq, seq / "velodyne"):
        layout = find_layout(given)
        assert (layout.kind, layout.root, layout.scans, layout.gt) == (KITTI, seq, seq / "velodyne", gt)
        source = open_source(given)
        _check_points(source, points, 1e-5)
        assert source.point_times(0) is None
        np.testing.assert_allclose(source.timestamps().stamps_s, stamps - stamps[0], atol=1e-6)
        line = describe_source(source)
        assert f"{seq}: {KITTI} layout, {N_SCANS} scans" in line and f"ground truth {gt}" in line
        assert "no per-point times" in line


def test_a_folder_named_velodyne_without_kitti_files_is_a_plain_folder(tmp_path, scans):
    folder = tmp_path / "velodyne"
    folder.mkdir()
    for k, p in enumerate(scans[0]):
        np.column_stack([p, np.zeros(len(p))]).astype("<f4").tofile(folder / f"{k}.bin")
    assert find_layout(folder) is None
    assert isinstance(open_source(folder), FolderSource)


def test_mulran_sequence_stamps_from_names(tmp_path, scans):
    points, _ = scans
    seq = tmp_path / "KAIST01"
    stamps = layouts.stamps_s(N_SCANS)
    layouts.write_mulran_scans(seq, points, stamps)
    gt = layouts.write_mulran_gt(seq, np.tile(np.eye(4), (N_SCANS, 1, 1)), stamps)
    for given in (seq, seq / "Ouster"):
        source = open_source(given)
        assert find_layout(given).kind == MULRAN and find_layout(given).gt == gt
        _check_points(source, points, 1e-5)
        np.testing.assert_allclose(source.timestamps().stamps_s, stamps, rtol=0, atol=1e-6)
        assert source.point_times(0) is None  # not the 64 x 1024 returns: the columns are unknown
        assert "no per-point times (scan 0 holds 300 points, not 64 x 1024)" in describe_source(source)


def test_mulran_full_scans_get_times_from_the_point_order(tmp_path):
    """All 64 x 1024 returns, column by column: point i fires at column i // 64 of 1024 in the sweep
    (the sweep: the interval of the scans' timestamps)."""
    seq = tmp_path / "DCC01"
    n_points = 64 * 1024
    points = [np.random.default_rng(k).uniform(-20, 20, (n_points, 3)) for k in range(3)]
    stamps = layouts.stamps_s(3, period_s=0.1)
    layouts.write_mulran_scans(seq, points, stamps)
    source = open_source(seq)
    times = source.point_times(1)
    column = np.arange(n_points) // 64
    np.testing.assert_allclose(times, column / 1024 * 0.1, rtol=0, atol=1e-9)
    assert "per-point times from the point order" in describe_source(source)


def test_newer_college_sequence_reads_the_t_field(tmp_path, scans):
    points, times = scans
    seq = tmp_path / "01_short_experiment"
    stamps = layouts.stamps_s(N_SCANS)
    layouts.write_ncd_scans(seq, points, times, stamps)
    for given in (seq, seq / "raw_format" / "ouster_scan"):
        source = open_source(given)
        assert find_layout(given).kind == NCD and find_layout(given).gt is None
        _check_points(source, points, 1e-5)
        np.testing.assert_allclose(source.point_times(2), np.round(times[2] * 1e9), rtol=0, atol=0.5)  # raw ns
        np.testing.assert_allclose(source.timestamps().stamps_s, stamps, rtol=0, atol=1e-6)
        line = describe_source(source)
        assert "per-point times from the PCD's t field" in line and "no ground truth found" in line


def test_newer_college_scan_names_carry_the_time(tmp_path, scans):
    seq = tmp_path / "ncd"
    layouts.write_ncd_scans(seq, scans[0], scans[1], layouts.stamps_s(N_SCANS))
    folder = seq / "raw_format" / "ouster_scan"
    first = sorted(folder.iterdir())[0]
    first.rename(folder / "cloud_x.pcd")
    with pytest.raises(FormatError, match="cloud_<seconds>_<nanoseconds>.pcd"):
        open_source(seq).timestamps()


def test_nclt_sequence_reads_uint16_scans_z_up(tmp_path, scans):
    points, _ = scans
    seq = tmp_path / "2012-01-08"
    stamps = layouts.stamps_s(N_SCANS)
    layouts.write_nclt_scans(seq, points, stamps)
    gt = layouts.write_nclt_gt(seq, np.tile(np.eye(4), (N_SCANS, 1, 1)), stamps)
    for given in (seq, seq / "velodyne_sync"):
        source = open_source(given)
        assert find_layout(given).kind == NCLT and find_layout(given).gt == gt
        source.check()
        _check_points(source, points, 0.0025 + 1e-9)  # 5 mm steps
        np.testing.assert_allclose(source.timestamps().stamps_s, stamps, rtol=0, atol=1e-6)
    (seq / "velodyne_sync" / "1.bin").write_bytes(b"\0" * 9)
    with pytest.raises(FormatError, match="9 bytes is not a multiple of 8"):
        open_source(seq).check()


def test_glob_reads_a_dataset_folder_as_plain_files(tmp_path, scans):
    seq = tmp_path / "KAIST01"
    layouts.write_mulran_scans(seq, scans[0], layouts.stamps_s(N_SCANS))
    assert isinstance(open_source(seq / "Ouster", glob="*.bin"), FolderSource)
    with pytest.raises(UsageError, match="--topic selects a topic of a ROS bag; this is a MulRan dataset"):
        open_source(seq, topic="/points")


def test_ouster_pcap_without_its_metadata_says_where_to_put_it(tmp_path):
    """The pcap's decoding is checked in test_ouster.py."""
    pcap = tmp_path / "drive.pcap"
    pcap.write_bytes(b"")
    with pytest.raises(InputError, match="needs the sensor's metadata .json recorded with it; none in .* Put it "
                                         "beside the pcap as drive.json"):
        open_source(pcap)


# ---------------------------------------------------------------------------- subsets


def test_subset_keeps_first_to_last_inclusive_every_kth(tmp_path, scans):
    seq = tmp_path / "KAIST01"
    points = [np.full((3, 3), float(k)) for k in range(10)]
    stamps = layouts.stamps_s(10)
    layouts.write_mulran_scans(seq, points, stamps)
    source = open_source(seq, subset=ScanSubset(first=2, last=8, every=3))
    assert isinstance(source, SubsetSource) and list(source.indices) == [2, 5, 8]
    assert [source.points(k)[0, 0] for k in range(len(source))] == [2.0, 5.0, 8.0]
    np.testing.assert_allclose(source.timestamps().stamps_s, stamps[[2, 5, 8]], rtol=0, atol=1e-6)
    assert "scans 2 to scan 8, one scan in 3 (0-based, inclusive)" in source.timestamps().origin
    T = np.arange(10)[:, None, None] * np.ones((10, 4, 4))
    assert source.select_poses(T)[:, 0, 0].tolist() == [2.0, 5.0, 8.0]
    assert source.select_poses(T[:5]) is None
    assert list(open_source(seq, subset=ScanSubset(last=100)).indices) == list(range(10))
    assert list(open_source(seq, subset=ScanSubset(first=9)).indices) == [9]
    assert not isinstance(open_source(seq, subset=ScanSubset()), SubsetSource)
    with pytest.raises(UsageError, match="--first 10 but the source holds 10 scans"):
        open_source(seq, subset=ScanSubset(first=10))
    with pytest.raises(UsageError, match="--last 1 is before --first 2"):
        ScanSubset(first=2, last=1)
    with pytest.raises(UsageError, match="--every is at least 1"):
        ScanSubset(every=0)


def test_refine_logs_the_layout_and_keeps_the_subset(run_pa, tmp_path):
    """Through the command line: the layout line, the subset line, and bad subsets as usage errors."""
    seq = tmp_path / "sequences" / "00"
    points, _ = _scans(n_points=2 * MIN_VALID_POINTS)  # enough valid points to pass the screen
    layouts.write_kitti_scans(seq, points, layouts.stamps_s(N_SCANS))
    code, _, err = run_pa("refine", seq, "--out", tmp_path / "map.ply", "--first", "5")
    assert code == 2 and "--first 5 but the source holds 4 scans" in " ".join(err.split())
    code, _, err = run_pa("refine", seq, "--out", tmp_path / "map.ply", "--first", "3", "--last", "1")
    assert code == 2 and "--last 1 is before --first 3" in " ".join(err.split())
    assert not (tmp_path / "map.ply").exists() and "Traceback" not in err
    code, _, err = run_pa("refine", seq, "--out", tmp_path / "map.ply", "--first", "1", "--every", "2",
                          "--config", "outdoor")
    assert code == 1 and "found no plane seen by two scans" in err  # random points: the run goes on to the rounds
    unwrapped = "".join(err.split())  # rich wraps long lines anywhere

    def logged(text: str) -> bool:
        return "".join(text.split()) in unwrapped

    assert logged(f"{seq}: {KITTI} layout, {N_SCANS} scans in {seq / 'velodyne'}, timestamps from {seq / 'times.txt'}, "
                  "no per-point times, no ground truth found")
    assert logged(f"{seq}: 2 of 4 scans kept: scans 1 to the last scan, one scan in 2 (0-based, inclusive).")


def test_reads_scans_apart_holds_for_scan_files_not_for_a_bag_or_a_pcap(tmp_path, scans):
    """A window task may open the source itself (`reads_scans_apart`) for a folder of scan files and a dataset's
    files; not for a ROS bag or an Ouster pcap, which opening reads whole."""
    points, _ = scans
    folder = tmp_path / "plain"
    folder.mkdir()
    for k, p in enumerate(points):
        write_pcd(folder / f"{k:06d}.pcd", p)
    seq = tmp_path / "sequences" / "00"
    layouts.write_kitti_scans(seq, points, layouts.stamps_s(N_SCANS))
    assert reads_scans_apart(folder) and reads_scans_apart(seq) and reads_scans_apart(seq, glob="*.bin")
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    ros2 = tmp_path / "ros2_bag"
    ros2.mkdir()
    (ros2 / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    pcap = tmp_path / "drive.pcap"
    pcap.write_bytes(b"")
    (tmp_path / "drive.json").write_text("{}")
    assert not any(reads_scans_apart(path) for path in (bag, ros2, pcap))
