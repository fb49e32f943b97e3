"""Scan I/O: a round trip per format, lazy folders, and every error path."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from pypcd4 import Encoding, PointCloud

from pa_cli.errors import FormatError, InputError, PaError
from pa_cli.io import scans as scans_mod
from pa_cli.io.scans import ScanFolder, iter_scans, list_scan_files, read_scan, write_pcd


def _cloud(n=200, seed=0):
    """Points, intensity, time; values on a coarse grid so that LZF (binary_compressed) can
    compress them (pypcd4 silently falls back to plain binary for incompressible data)."""
    rng = np.random.default_rng(seed)
    xyz = (rng.integers(-40, 40, size=(n, 3)) * 0.25).astype(np.float32)
    return xyz, (rng.integers(0, 8, n) * 0.125).astype(np.float32), rng.integers(0, 10, n) * 0.01


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
@pytest.mark.parametrize("time_name", ["time", "t", "timestamp"])
def test_pcd_round_trip_all_encodings(tmp_path, encoding, time_name):
    xyz, intensity, time = _cloud()
    data = np.column_stack([xyz.astype(np.float64), intensity, time])
    cloud = PointCloud.from_points(data, ["x", "y", "z", "intensity", time_name],
                                   [np.float32, np.float32, np.float32, np.float32, np.float64])
    path = tmp_path / "scan.pcd"
    cloud.save(path, encoding=encoding)
    assert f"DATA {encoding.value}".encode() in path.read_bytes()[:400]
    scan = read_scan(path)
    assert scan.points_scan.dtype == np.float64 and scan.points_scan.shape == (200, 3)
    # ascii PCD stores 10 decimals: compare at that precision, binary exactly.
    atol = 1e-8 if encoding == Encoding.ASCII else 0.0
    np.testing.assert_allclose(scan.points_scan, xyz.astype(np.float64), rtol=0, atol=atol)
    np.testing.assert_allclose(scan.intensity, intensity, rtol=0, atol=atol)
    np.testing.assert_allclose(scan.time, time, rtol=0, atol=1e-8 if atol else 0.0)
    assert scan.path == path and scan.n_dropped_nonfinite == 0


def test_write_pcd_round_trip(tmp_path):
    xyz, intensity, time = _cloud()
    write_pcd(tmp_path / "a.pcd", xyz, time=time, intensity=intensity)
    scan = read_scan(tmp_path / "a.pcd")
    np.testing.assert_array_equal(scan.points_scan, xyz.astype(np.float64))
    np.testing.assert_array_equal(scan.intensity, intensity)
    np.testing.assert_array_equal(scan.time, time.astype(np.float32))
    with pytest.raises(PaError, match="--force"):
        write_pcd(tmp_path / "a.pcd", xyz)


def _ply_header(fmt, n, props, extra=""):
    lines = ["ply", f"format {fmt} 1.0", "comment test", f"element vertex {n}"]
    lines += [f"property {t} {name}" for name, t in props]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


PLY_PROPS = [("x", "double"), ("y", "double"), ("z", "double"), ("intensity", "uchar"), ("timestamp", "double")]


def _ply_values(n=150, seed=1):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) * 20, rng.integers(0, 255, n), rng.random(n)


def test_ply_ascii_round_trip(tmp_path):
    xyz, intensity, time = _ply_values()
    rows = zip(xyz.tolist(), intensity.tolist(), time.tolist(), strict=True)
    body = "".join(f"{a!r} {b!r} {c!r} {i} {t!r}\n" for (a, b, c), i, t in rows)
    path = tmp_path / "a.ply"
    path.write_bytes(_ply_header("ascii", len(xyz), PLY_PROPS) + body.encode())
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points_scan, xyz)
    np.testing.assert_array_equal(scan.intensity, intensity)
    np.testing.assert_array_equal(scan.time, time)


@pytest.mark.parametrize("fmt,endian", [("binary_little_endian", "<"), ("binary_big_endian", ">")])
def test_ply_binary_round_trip_with_trailing_face_element(tmp_path, fmt, endian):
    xyz, intensity, time = _ply_values()
    dtype = np.dtype([("x", endian + "f8"), ("y", endian + "f8"), ("z", endian + "f8"),
                      ("intensity", "u1"), ("timestamp", endian + "f8")])
    rows = np.empty(len(xyz), dtype)
    rows["x"], rows["y"], rows["z"] = xyz.T
    rows["intensity"], rows["timestamp"] = intensity, time
    face = "element face 1\nproperty list uchar int vertex_indices\n"
    path = tmp_path / "b.ply"
    path.write_bytes(_ply_header(fmt, len(xyz), PLY_PROPS, face) + rows.tobytes()
                     + np.array([3], "u1").tobytes() + np.array([0, 1, 2], endian + "i4").tobytes())
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points_scan, xyz)
    np.testing.assert_array_equal(scan.intensity, intensity)
    np.testing.assert_array_equal(scan.time, time)


def test_ply_written_by_open3d(tmp_path):
    from pa_cli.runtime.open3d_preload import open3d

    o3d = open3d()
    xyz, _, time = _ply_values()
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(np.arange(len(xyz), dtype=np.float32).reshape(-1, 1))
    cloud.point["time"] = o3d.core.Tensor(time.reshape(-1, 1))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "o.ply"), cloud, write_ascii=False)
    scan = read_scan(tmp_path / "o.ply")
    np.testing.assert_array_equal(scan.points_scan, xyz)
    np.testing.assert_array_equal(scan.intensity, np.arange(len(xyz)))
    np.testing.assert_array_equal(scan.time, time)


def test_kitti_bin_round_trip_and_bad_size(tmp_path):
    xyz, intensity, _ = _cloud()
    np.column_stack([xyz, intensity]).astype("<f4").tofile(tmp_path / "000.bin")
    scan = read_scan(tmp_path / "000.bin")
    np.testing.assert_array_equal(scan.points_scan, xyz.astype(np.float64))
    np.testing.assert_array_equal(scan.intensity, intensity)
    assert scan.time is None
    (tmp_path / "bad.bin").write_bytes(b"\0" * 20)
    with pytest.raises(FormatError, match=r"bad\.bin.*20 bytes.*16"):
        read_scan(tmp_path / "bad.bin")


def test_nonfinite_points_dropped_and_counted(tmp_path, caplog):
    xyz, intensity, time = _cloud(50)
    xyz[[3, 7], 1] = np.nan
    xyz[11, 2] = np.inf
    write_pcd(tmp_path / "n.pcd", xyz, time=time, intensity=intensity)
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        scan = read_scan(tmp_path / "n.pcd")
    keep = np.setdiff1d(np.arange(50), [3, 7, 11])
    assert scan.n_dropped_nonfinite == 3 and len(scan) == 47
    np.testing.assert_array_equal(scan.points_scan, xyz[keep].astype(np.float64))
    np.testing.assert_array_equal(scan.intensity, intensity[keep])
    np.testing.assert_array_equal(scan.time, time[keep].astype(np.float32))
    assert "dropped 3 of 50" in caplog.text


def test_folder_natural_sort_glob_and_lazy_reading(tmp_path, monkeypatch):
    xyz, intensity, _ = _cloud(10)
    for k in (10, 2, 1):
        write_pcd(tmp_path / f"scan_{k}.pcd", xyz + k)
    (tmp_path / "notes.txt").write_text("not a scan")
    assert [p.name for p in list_scan_files(tmp_path)] == ["scan_1.pcd", "scan_2.pcd", "scan_10.pcd"]
    np.column_stack([xyz, intensity]).astype("<f4").tofile(tmp_path / "scan_3.bin")
    with pytest.raises(InputError, match=r"2 formats: 3 \.pcd \(scan_1\.pcd, scan_2\.pcd, \.\.\.\); 1 \.bin"):
        list_scan_files(tmp_path)  # one format per run
    assert [p.name for p in list_scan_files(tmp_path, glob="*.pcd")] == ["scan_1.pcd", "scan_2.pcd", "scan_10.pcd"]

    reads = []
    real_read = scans_mod.read_scan
    monkeypatch.setattr(scans_mod, "read_scan", lambda p: reads.append(p) or real_read(p))
    folder = ScanFolder(tmp_path, glob="*.pcd")
    assert len(folder) == 3 and reads == []
    np.testing.assert_array_equal(folder[2].points_scan, (xyz + 10).astype(np.float64))
    assert len(reads) == 1
    offsets = [scan.points_scan[0, 0] - float(xyz[0, 0]) for scan in folder]
    np.testing.assert_allclose(offsets, [1, 2, 10], atol=1e-5)
    assert len(reads) == 4
    assert len(folder.points) == 3 and folder.points[-1].shape == (10, 3)
    assert len(folder[1:]) == 2
    assert [s.path.name for s in iter_scans(folder.files[:1])] == ["scan_1.pcd"]


def test_folder_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        list_scan_files(tmp_path / "missing")
    (tmp_path / "f.pcd").write_text("x")
    with pytest.raises(InputError, match="is a file"):
        list_scan_files(tmp_path / "f.pcd")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match=r"\.pcd \.ply \.bin.*no files.*--glob"):
        list_scan_files(empty)
    other = tmp_path / "other"
    other.mkdir()
    (other / "a.xyz").write_text("1 2 3")
    (other / "b.las").write_text("")
    with pytest.raises(InputError, match=r"\.pcd \.ply \.bin.*2 files.*\.las \.xyz.*--glob"):
        list_scan_files(other)
    with pytest.raises(InputError, match="matching --glob"):
        list_scan_files(tmp_path, glob="*.ply")


def _corrupt_files(tmp_path):
    xyz, _, _ = _cloud(20)
    cloud = PointCloud.from_points(xyz, ["x", "y", "z"], [np.float32] * 3)
    cloud.save(tmp_path / "ok_bin.pcd", encoding=Encoding.BINARY)
    cloud.save(tmp_path / "ok_cmp.pcd", encoding=Encoding.BINARY_COMPRESSED)
    assert b"DATA binary_compressed" in (tmp_path / "ok_cmp.pcd").read_bytes()[:300]
    cloud.save(tmp_path / "ok_asc.pcd", encoding=Encoding.ASCII)
    files = {
        "trunc_bin.pcd": (tmp_path / "ok_bin.pcd").read_bytes()[:-30],
        "trunc_cmp.pcd": (tmp_path / "ok_cmp.pcd").read_bytes()[:-30],
        "trunc_asc.pcd": b"\n".join((tmp_path / "ok_asc.pcd").read_bytes().splitlines()[:-3]),
        "garbage.pcd": b"hello, not a point cloud\x00\x01",
        "no_xyz.pcd": b"VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\n"
                      b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n",
        "trunc.ply": _ply_header("binary_little_endian", 100, PLY_PROPS) + b"\0" * 50,
        "trunc_ascii.ply": _ply_header("ascii", 3, PLY_PROPS) + b"1 2 3 4 5\n1 2\n",
        "not_ply.ply": b"garbage",
        "word_ascii.ply": _ply_header("ascii", 2, PLY_PROPS) + b"1 2 3 4 5\n1 2 x 4 5\n",
        "no_end.ply": b"ply\nformat ascii 1.0\nelement vertex 1\n",
        "bad_fmt.ply": _ply_header("binary_middle_endian", 1, PLY_PROPS),
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    return list(files)


def test_corrupt_files_are_format_errors_naming_the_file(tmp_path):
    for name in _corrupt_files(tmp_path):
        with pytest.raises(FormatError) as info:
            read_scan(tmp_path / name)
        assert name in str(info.value), (name, str(info.value))


def test_missing_and_unsupported_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_scan(tmp_path / "nope.pcd")
    (tmp_path / "a.xyz").write_text("1 2 3")
    with pytest.raises(FormatError, match=r"a\.xyz.*\.pcd \.ply \.bin"):
        read_scan(tmp_path / "a.xyz")


def test_real_balm_scans_load(shared_data):
    folder = ScanFolder(shared_data / "balm-campus-30" / "scans")
    assert len(folder) == 30
    for k in (0, 29):
        scan = folder[k]
        assert scan.points_scan.shape[1] == 3 and len(scan) > 1000
        assert np.isfinite(scan.points_scan).all() and scan.intensity is not None
        assert 1.0 < np.median(np.linalg.norm(scan.points_scan, axis=1)) < 60.0


def test_header_check_accepts_what_read_scan_reads_and_refuses_what_it_refuses(tmp_path):
    from pa_cli.io.scans import check_scan_header

    xyz, intensity, time = _cloud(40)
    for encoding in (Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED):
        cloud = PointCloud.from_points(np.column_stack([xyz, intensity]), ["x", "y", "z", "intensity"],
                                       [np.float32] * 4)
        cloud.save(tmp_path / f"{encoding.value}.pcd", encoding=encoding)
    xyz64, ints, times = _ply_values(30)
    rows = "".join(f"{a!r} {b!r} {c!r} {i} {t!r}\n" for (a, b, c), i, t in zip(xyz64.tolist(), ints.tolist(),
                                                                              times.tolist(), strict=True))
    (tmp_path / "ascii.ply").write_bytes(_ply_header("ascii", 30, PLY_PROPS) + rows.encode())
    (tmp_path / "binary.ply").write_bytes(_ply_header("binary_little_endian", 2, [("x", "float"), ("y", "float"),
                                                                                ("z", "float")]) + bytes(24))
    np.column_stack([xyz, intensity]).astype("<f4").tofile(tmp_path / "k.bin")
    good = sorted(tmp_path.iterdir())
    for path in good:
        check_scan_header(path)
        read_scan(path)
    names = _corrupt_files(tmp_path)
    refused_by_header = {"trunc_bin.pcd", "trunc_cmp.pcd", "garbage.pcd", "trunc.ply", "not_ply.ply", "no_end.ply",
                         "bad_fmt.ply"}
    for name in names:
        with pytest.raises(FormatError) as full:
            read_scan(tmp_path / name)
        if name in refused_by_header:
            with pytest.raises(FormatError) as header_only:
                check_scan_header(tmp_path / name)
            assert str(header_only.value) == str(full.value), name
        else:  # the values are checked only by the full read
            check_scan_header(tmp_path / name)
    with pytest.raises(FormatError, match="not a multiple of 16"):
        (tmp_path / "short.bin").write_bytes(bytes(30))
        check_scan_header(tmp_path / "short.bin")
    with pytest.raises(InputError, match="not found"):
        check_scan_header(tmp_path / "missing.pcd")
