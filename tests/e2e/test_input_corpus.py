"""A corpus of inputs from other tools and of malformed inputs, generated here (no downloads).

Every refusal goes through the `pa` command line (`pa_cli.cli.run`) and must exit 1 with one
message naming the file and the problem, print no traceback and leave no output behind. Files
that PCL or Open3D read are read by `read_scan` to the same values.
"""

from __future__ import annotations

import errno
import logging
import pathlib
import tracemalloc
import zipfile

import numpy as np
import pytest

from pa_cli.io.problem import save_problem
from pa_cli.io.scans import check_scan_header, read_scan, write_pcd
from pa_cli.io.trajectory import write_kitti, write_tum
from pa_testing.synthetic_problems import make_scene

XYZ = np.array([[1.5, -2.25, 0.125], [3.0, 4.0, -5.5], [0.0, 0.5, 7.75]])


def _flat(text: str) -> str:
    """Text without whitespace (rich may wrap long messages anywhere)."""
    return "".join(text.split())


def _refused(result, *fragments: str, outputs=()) -> None:
    code, out, err = result
    assert code == 1, (code, err)
    assert "Traceback" not in err and "Traceback" not in out
    for fragment in fragments:
        assert _flat(fragment) in _flat(err), (fragment, err)
    for path in outputs:
        assert not path.exists(), path


def _poses(n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * 0.1
    return T


# --------------------------------------------------------------------------------------------
# text inputs: poses, timestamps, config (encoding, binary content, I/O errors)
# --------------------------------------------------------------------------------------------


def test_poses_with_a_latin1_comment_are_read(run_pa, tmp_path):
    write_kitti(tmp_path / "clean.txt", _poses(3))
    latin1 = "# Kalibrierung: Gerät 3, Straße\n".encode("latin-1")
    (tmp_path / "poses.txt").write_bytes(latin1 + (tmp_path / "clean.txt").read_bytes())
    code, _, err = run_pa("perturb", tmp_path / "poses.txt", "--level", "1", "--out", tmp_path / "noisy.txt")
    assert code == 0, err
    assert len((tmp_path / "noisy.txt").read_text().splitlines()) == 3


def test_poses_with_latin1_in_a_data_row_are_refused(run_pa, tmp_path):
    write_kitti(tmp_path / "clean.txt", _poses(3))
    rows = (tmp_path / "clean.txt").read_bytes().splitlines()
    rows[1] = rows[1] + " é".encode("latin-1")
    (tmp_path / "poses.txt").write_bytes(b"\n".join(rows))
    out = tmp_path / "noisy.txt"
    _refused(run_pa("perturb", tmp_path / "poses.txt", "--level", "1", "--out", out),
             "poses.txt:2: non-numeric value", outputs=[out])


def test_binary_poses_file_is_refused(run_pa, tmp_path):
    (tmp_path / "poses.txt").write_bytes(np.arange(64, dtype=np.float64).tobytes())
    out = tmp_path / "noisy.txt"
    _refused(run_pa("perturb", tmp_path / "poses.txt", "--level", "1", "--out", out),
             "poses.txt:1: binary content", "expected a text trajectory file", outputs=[out])


def _deny_reading(monkeypatch, name: str) -> None:
    real_read_bytes = pathlib.Path.read_bytes

    def failing_read_bytes(self):
        if self.name == name:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_read_bytes(self)

    monkeypatch.setattr(pathlib.Path, "read_bytes", failing_read_bytes)


def test_unreadable_poses_file_is_an_input_error(run_pa, tmp_path, monkeypatch):
    write_kitti(tmp_path / "poses.txt", _poses(3))
    _deny_reading(monkeypatch, "poses.txt")
    out = tmp_path / "noisy.txt"
    _refused(run_pa("perturb", tmp_path / "poses.txt", "--level", "1", "--out", out),
             "poses.txt: cannot read the trajectory file (Permission denied)", outputs=[out])


def test_unreadable_config_file_is_an_input_error(run_pa, tmp_path, monkeypatch):
    (tmp_path / "my.yaml").write_text("refine:\n  max_rounds: 1\n")
    _deny_reading(monkeypatch, "my.yaml")
    _refused(run_pa("refine", "--print-config", "--config", tmp_path / "my.yaml"),
             "my.yaml: cannot read the config file (Permission denied)")


def test_config_with_latin1_or_binary_content_is_refused(run_pa, tmp_path):
    (tmp_path / "latin1.yaml").write_bytes("refine:\n  max_rounds: 1  # für Tests\n".encode("latin-1"))
    _refused(run_pa("refine", "--print-config", "--config", tmp_path / "latin1.yaml"),
             "latin1.yaml:2: a byte that is not UTF-8 (0xfc)", "re-save it as UTF-8")
    (tmp_path / "binary.yaml").write_bytes(b"refine:\n\x00\x01\x02\xff")
    _refused(run_pa("refine", "--print-config", "--config", tmp_path / "binary.yaml"),
             "binary.yaml:2: binary content")
    (tmp_path / "utf8.yaml").write_text("refine:\n  max_rounds: 1  # für Tests\n", encoding="utf-8")
    code, out, err = run_pa("refine", "--print-config", "--config", tmp_path / "utf8.yaml")
    assert code == 0, err
    assert "rounds: 1" in out


def _tiny_scans(folder: pathlib.Path, n: int = 2) -> None:
    """`n` scans of XYZ repeated to the fewest valid points the load step keeps a scan with."""
    from pa_cli.sources.screen import MIN_VALID_POINTS

    folder.mkdir()
    for k in range(n):
        write_pcd(folder / f"{k:03d}.pcd", np.tile(XYZ, (-(-MIN_VALID_POINTS // len(XYZ)), 1)) + k)


def test_binary_times_file_is_refused_before_any_work(run_pa, tmp_path):
    _tiny_scans(tmp_path / "scans")
    write_kitti(tmp_path / "poses.txt", _poses(2))
    (tmp_path / "scans" / "times.txt").write_bytes(b"0.0\n\x00\x10\x20")
    out = tmp_path / "out" / "map.ply"
    (tmp_path / "out").mkdir()
    _refused(run_pa("refine", tmp_path / "scans", "--out", out, "--poses", tmp_path / "poses.txt"),
             "times.txt:2: binary content", "timestamps file", outputs=[out])
    assert list((tmp_path / "out").iterdir()) == []


# --------------------------------------------------------------------------------------------
# plane problems (.npz) through `pa adjust`
# --------------------------------------------------------------------------------------------


@pytest.fixture
def problem_arrays():
    problem, T_gt = make_scene(4, 6, 3, points_per_observation=10, seed=5)
    return {"plane_index": problem.plane_index, "scan_index": problem.scan_index,
            "clusters": problem.clusters, "poses": T_gt}


def _adjust(run_pa, path: pathlib.Path):
    out = path.parent / "refined.txt"
    return run_pa("adjust", path, "--out", out), out


def test_npy_named_npz_is_refused(run_pa, tmp_path, problem_arrays):
    np.save(tmp_path / "problem.npy", problem_arrays["clusters"])
    (tmp_path / "problem.npy").rename(tmp_path / "problem.npz")
    result, out = _adjust(run_pa, tmp_path / "problem.npz")
    _refused(result, "problem.npz: is a .npy file (one array), not an .npz archive", outputs=[out])


def test_text_file_given_to_adjust_does_not_suggest_allow_pickle(run_pa, tmp_path):
    (tmp_path / "problem.npz").write_text("0 0 0 1 0 0 0 1\n")
    result, out = _adjust(run_pa, tmp_path / "problem.npz")
    _refused(result, "problem.npz: not a readable .npz plane problem (not a zip archive)", outputs=[out])
    assert "allow_pickle" not in result[2]


def test_npy_header_claiming_a_huge_shape_is_refused(run_pa, tmp_path, problem_arrays):
    path = tmp_path / "problem.npz"
    clusters = problem_arrays.pop("clusters")
    np.savez(path, **problem_arrays)
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**12, 4, 4)}
    with zipfile.ZipFile(path, "a") as archive, archive.open("clusters.npy", "w") as member:
        np.lib.format.write_array_header_1_0(member, header)
        member.write(clusters.tobytes())
    result, out = _adjust(run_pa, path)
    _refused(result, "problem.npz: array 'clusters' declares shape (1000000000000, 4, 4)", "the file is corrupt",
             outputs=[out])


def test_small_npz_that_expands_hugely_is_refused_before_decompressing(run_pa, tmp_path, problem_arrays):
    """160 MB of zero clusters compress to a few hundred kB; their count disagrees with
    plane_index, which the headers show without decompressing anything."""
    path = tmp_path / "problem.npz"
    n_obs = 1_250_000
    header = {"descr": "<f8", "fortran_order": False, "shape": (n_obs, 4, 4)}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name in ("plane_index", "scan_index"):
            with archive.open(f"{name}.npy", "w") as member:
                np.lib.format.write_array(member, problem_arrays[name])
        with archive.open("clusters.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array_header_1_0(member, header)
            chunk = bytes(16 * 8 * 10_000)
            for _ in range(n_obs // 10_000):
                member.write(chunk)
    assert path.stat().st_size < 2_000_000
    tracemalloc.start()
    result, out = _adjust(run_pa, path)
    _, peak_bytes = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    _refused(result, f"problem.npz: 'clusters' must have shape ({len(problem_arrays['plane_index'])}, 4, 4), "
             f"found ({n_obs}, 4, 4)", outputs=[out])
    assert peak_bytes < n_obs * 16 * 8 / 10


def test_string_typed_clusters_are_refused(run_pa, tmp_path, problem_arrays):
    problem_arrays["clusters"] = problem_arrays["clusters"].astype(str)
    np.savez(tmp_path / "problem.npz", **problem_arrays)
    result, out = _adjust(run_pa, tmp_path / "problem.npz")
    _refused(result, "problem.npz: 'clusters' holds <U", "expected float64 numbers", outputs=[out])


def test_non_rigid_poses_in_npz_are_refused(run_pa, tmp_path, problem_arrays):
    problem_arrays["poses"] = problem_arrays["poses"].copy()
    problem_arrays["poses"][2, :3, :3] *= 1.3  # a scaled rotation
    np.savez(tmp_path / "problem.npz", **problem_arrays)
    result, out = _adjust(run_pa, tmp_path / "problem.npz")
    _refused(result, "problem.npz: pose 2 has a rotation block that deviates from a rotation by", "not a rotation",
             outputs=[out])
    problem_arrays["poses"][2, :3, :3] /= 1.3
    problem_arrays["poses"][1, 3, 0] = 0.5
    np.savez(tmp_path / "problem.npz", **problem_arrays)
    result, out = _adjust(run_pa, tmp_path / "problem.npz")
    _refused(result, "problem.npz: pose 1 has bottom row [0.5, 0.0, 0.0, 1.0]", outputs=[out])


def test_nearly_rigid_poses_in_npz_are_reorthonormalised_with_a_warning(run_pa, tmp_path):
    problem, T_gt = make_scene(6, 30, 4, points_per_observation=12, seed=2)
    T = T_gt.copy()
    T[3, :3, :3] *= 1.004
    problem.T_world_scan = T
    save_problem(tmp_path / "problem.npz", problem)
    out = tmp_path / "refined.txt"
    code, _, err = run_pa("adjust", tmp_path / "problem.npz", "--out", out)
    assert code == 0, err
    assert "rotations of 'poses' re-orthonormalised" in " ".join(err.split())
    written = np.loadtxt(out).reshape(-1, 3, 4)[:, :, :3]
    np.testing.assert_allclose(written @ written.transpose(0, 2, 1), np.tile(np.eye(3), (6, 1, 1)), atol=1e-8)


# --------------------------------------------------------------------------------------------
# PCD written by other tools
# --------------------------------------------------------------------------------------------


def _pcd(header_lines: list[str], data: bytes | str) -> bytes:
    body = data.encode() if isinstance(data, str) else data
    return ("\n".join(header_lines) + "\n").encode() + body


def _ascii_rows(values: np.ndarray, sep: str = " ", trail: str = "") -> str:
    return "".join(sep.join(repr(float(v)) for v in row) + trail + "\n" for row in values)


@pytest.mark.parametrize("version", [".5", ".6", ".7", "0.7"])
def test_pcd_versions_5_to_7(tmp_path, version):
    header = [f"VERSION {version}", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1"]
    if version not in (".5",):  # PCD .5 files have no WIDTH/HEIGHT
        header += ["WIDTH 3", "HEIGHT 1"]
    if version in (".7", "0.7"):
        header += ["VIEWPOINT 0 0 0 1 0 0 0"]
    header += ["POINTS 3", "DATA ascii"]
    (tmp_path / "v.pcd").write_bytes(_pcd(header, _ascii_rows(XYZ)))
    np.testing.assert_array_equal(read_scan(tmp_path / "v.pcd").points_scan, XYZ)


def test_pcd_5_without_size_type_count_defaults_to_float32(tmp_path):
    (tmp_path / "old.pcd").write_bytes(_pcd(["VERSION .5", "FIELDS x y z", "POINTS 3", "DATA binary"],
                                            XYZ.astype("<f4").tobytes()))
    np.testing.assert_array_equal(read_scan(tmp_path / "old.pcd").points_scan, XYZ)


@pytest.mark.parametrize("sep,trail", [("\t", ""), ("   ", ""), (" ", " "), (" \t ", "\t "), (" ", "\r")])
def test_pcd_ascii_whitespace_variants(tmp_path, sep, trail):
    header = ["VERSION 0.7", "FIELDS\tx y  z ", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", "WIDTH 3",
              "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", "POINTS 3", "DATA ascii "]
    (tmp_path / "w.pcd").write_bytes(_pcd(header, _ascii_rows(XYZ, sep, trail)))
    np.testing.assert_array_equal(read_scan(tmp_path / "w.pcd").points_scan, XYZ)


def test_pcd_one_point_ascii(tmp_path):
    header = ["VERSION 0.7", "FIELDS x y z intensity", "SIZE 4 4 4 4", "TYPE F F F F", "COUNT 1 1 1 1",
              "WIDTH 1", "HEIGHT 1", "POINTS 1", "DATA ascii"]
    (tmp_path / "one.pcd").write_bytes(_pcd(header, "1.5 -2 3 7\n"))
    scan = read_scan(tmp_path / "one.pcd")
    np.testing.assert_array_equal(scan.points_scan, [[1.5, -2.0, 3.0]])
    np.testing.assert_array_equal(scan.intensity, [7.0])


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_count_above_one_keeps_the_layout(tmp_path, encoding):
    """A 3-value `normal` field and PCL's padding `_` fields sit between x y z and intensity."""
    import lzf

    xyz = np.tile(XYZ, (10, 1))  # enough points for LZF to compress the padding
    n = len(xyz)
    normal = np.arange(3 * n, dtype=np.float32).reshape(n, 3)
    intensity = np.arange(n, dtype=np.float32) * 10
    header = ["VERSION 0.7", "FIELDS x y z _ normal intensity _", "SIZE 4 4 4 1 4 4 1", "TYPE F F F U F F U",
              "COUNT 1 1 1 4 3 1 2", f"WIDTH {n}", "HEIGHT 1", f"POINTS {n}", f"DATA {encoding}"]
    pad4, pad2 = np.zeros((n, 4), "u1"), np.zeros((n, 2), "u1")
    columns = [xyz[:, :1], xyz[:, 1:2], xyz[:, 2:], pad4, normal, intensity[:, None], pad2]
    dtypes = ["<f4", "<f4", "<f4", "u1", "<f4", "<f4", "u1"]
    if encoding == "ascii":
        data = _ascii_rows(np.hstack([np.asarray(c, np.float64) for c in columns]))
    elif encoding == "binary":
        record = np.dtype([(f"f{k}", dt, (c.shape[1],)) for k, (dt, c) in
                           enumerate(zip(dtypes, columns, strict=True))])
        rows = np.empty(n, record)
        for k, column in enumerate(columns):
            rows[f"f{k}"] = column
        data = rows.tobytes()
    else:  # binary_compressed: LZF of the fields one after the other
        raw = b"".join(np.ascontiguousarray(c, dtype=dt).tobytes() for c, dt in zip(columns, dtypes, strict=True))
        packed = lzf.compress(raw)
        assert packed is not None
        data = np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    (tmp_path / "c.pcd").write_bytes(_pcd(header, data))
    scan = read_scan(tmp_path / "c.pcd")
    np.testing.assert_array_equal(scan.points_scan, xyz)
    np.testing.assert_array_equal(scan.intensity, intensity)


def _scan_refused(run_pa, tmp_path, name: str, content: bytes, *fragments: str) -> str:
    """Refine over a folder holding one good scan of the format of `name` and `name`: exit 1, the file
    named, no outputs."""
    _tiny_scans(tmp_path / "scans", 1)
    if name.endswith(".ply"):  # one format per folder
        (tmp_path / "scans" / "000.pcd").unlink()
        (tmp_path / "scans" / "000.ply").write_bytes(_ply(["x", "y", "z"], len(XYZ)) + XYZ.astype("<f4").tobytes())
    (tmp_path / "scans" / name).write_bytes(content)
    write_kitti(tmp_path / "poses.txt", _poses(2))
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "map.ply"
    result = run_pa("refine", tmp_path / "scans", "--out", out, "--poses", tmp_path / "poses.txt")
    _refused(result, f"{name}:", *fragments)
    assert list((tmp_path / "out").iterdir()) == []
    return result[2]


_GOOD_HEADER = ["VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", "WIDTH 3", "HEIGHT 1",
                "VIEWPOINT 0 0 0 1 0 0 0", "POINTS 3"]


def _with(replacements: dict[str, str], data_line: str = "DATA ascii") -> list[str]:
    lines = [replacements.get(line.split()[0], line) for line in _GOOD_HEADER] + [data_line]
    return [line for line in lines if line]


PCD_REFUSALS = {
    "size_count.pcd": (_pcd(_with({"SIZE": "SIZE 4 4"}), _ascii_rows(XYZ)),
                       ["PCD header line 3 'SIZE 4 4': 2 values, expected 3 values (one per field"]),
    "type.pcd": (_pcd(_with({"TYPE": "TYPE F F Q"}), _ascii_rows(XYZ)),
                 ["PCD field 'z' has TYPE Q with SIZE 4"]),
    "width.pcd": (_pcd(_with({"WIDTH": "WIDTH three"}), _ascii_rows(XYZ)),
                  ["PCD header line 6 'WIDTH three': expected non-negative integers"]),
    "no_fields.pcd": (_pcd(_with({"FIELDS": ""}), _ascii_rows(XYZ)), ["PCD header has no FIELDS line"]),
    "keyword.pcd": (_pcd(_with({"HEIGHT": "HIGHT 1"}), _ascii_rows(XYZ)),
                    ["unknown PCD header keyword: line 7 is 'HIGHT 1'"]),
    "binary_junk.pcd": (bytes(range(256)) * 4, ["not a PCD file: line 1 is"]),
    "no_data.pcd": (_pcd(_GOOD_HEADER, ""), ["no PCD 'DATA' line"]),
    "encoding.pcd": (_pcd(_with({}, "DATA binary_lzma"), ""),
                     ["PCD header line 10 'DATA binary_lzma': expected DATA ascii, DATA binary or"]),
    "wxh.pcd": (_pcd(_with({"WIDTH": "WIDTH 2", "HEIGHT": "HEIGHT 2"}), _ascii_rows(XYZ)),
                ["WIDTH 2 x HEIGHT 2 = 4 points but POINTS 3"]),
    "row.pcd": (_pcd(_with({}), "1 2 3\n4 5\n6 7 8\n"), ["line 12 of the ASCII data has 2 values", "need 3"]),
    "word.pcd": (_pcd(_with({}), "1 2 3\n4 five 6\n6 7 8\n"), ["line 12 of the ASCII data holds a value that is not"]),
    "lzf.pcd": (_pcd(_with({}, "DATA binary_compressed"), np.array([20, 36], "<u4").tobytes() + b"\xff" * 20),
                ["binary_compressed PCD data does not decompress (LZF) to 36 bytes"]),
    "count_x.pcd": (_pcd(_with({"COUNT": "COUNT 2 1 1"}), "1 1 2 3\n4 4 5 6\n7 7 8 9\n"),
                    ["field 'x' holds 2 values per point (COUNT 2); expected one"]),
}


@pytest.mark.parametrize("name", sorted(PCD_REFUSALS))
def test_bad_pcd_is_refused_with_words(run_pa, tmp_path, name):
    content, fragments = PCD_REFUSALS[name]
    err = _scan_refused(run_pa, tmp_path, name, content, *fragments)
    for pass_through in ("ValidationError", "KeyError", "IndexError", "NoneType", "error in compressed data"):
        assert pass_through not in err


# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_pcd_data_beyond_points_is_ignored_with_a_warning_as_pcl_does(tmp_path, caplog, encoding):
    header = _with({"WIDTH": "WIDTH 2", "POINTS": "POINTS 2"}, f"DATA {encoding}")
    data = _ascii_rows(XYZ) if encoding == "ascii" else XYZ.astype("<f4").tobytes()
    (tmp_path / "extra.pcd").write_bytes(_pcd(header, data))
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        check_scan_header(tmp_path / "extra.pcd")  # a checked, then read, file warns once: when read
        scan = read_scan(tmp_path / "extra.pcd")
    np.testing.assert_array_equal(scan.points_scan, XYZ[:2])
    assert f"{tmp_path / 'extra.pcd'}: PCD header says POINTS 2 but the data holds 3 points" in caplog.text
    assert len(caplog.records) == 1


def _ply(props: list[str], n: int, comments: list[str] = (), fmt: str = "binary_little_endian") -> bytes:
    lines = ["ply", f"format {fmt} 1.0", *[f"comment {c}" for c in comments], f"element vertex {n}",
             *[f"property float {p}" for p in props], "end_header"]
    return ("\n".join(lines) + "\n").encode()


def test_ply_comment_mentioning_end_header_does_not_misalign_the_data(tmp_path):
    body = XYZ.astype("<f4").tobytes()
    (tmp_path / "c.ply").write_bytes(_ply(["x", "y", "z"], 3, ["written before end_header", "end_header"]) + body)
    np.testing.assert_array_equal(read_scan(tmp_path / "c.ply").points_scan, XYZ)


def test_negative_ply_vertex_count_is_refused(run_pa, tmp_path):
    _scan_refused(run_pa, tmp_path, "neg.ply", _ply(["x", "y", "z"], -3),
                  "PLY header line 3 'element vertex -3': the element count must be a non-negative integer")


def test_ply_texture_coordinate_t_is_not_a_time(tmp_path):
    values = np.column_stack([XYZ, [[0.1, 0.9], [0.2, 0.8], [0.3, 0.7]]]).astype("<f4")
    (tmp_path / "st.ply").write_bytes(_ply(["x", "y", "z", "s", "t"], 3) + values.tobytes())
    scan = read_scan(tmp_path / "st.ply")
    assert scan.time is None
    np.testing.assert_array_equal(scan.points_scan, XYZ)
    (tmp_path / "t.ply").write_bytes(_ply(["x", "y", "z", "t"], 3) + values[:, [0, 1, 2, 4]].tobytes())
    np.testing.assert_array_equal(read_scan(tmp_path / "t.ply").time, values[:, 4])


def test_empty_and_all_nan_scans_warn_naming_the_file(tmp_path, caplog):
    (tmp_path / "empty.ply").write_bytes(_ply(["x", "y", "z"], 0))
    nan = np.full((3, 3), np.nan, "<f4")
    (tmp_path / "nan.ply").write_bytes(_ply(["x", "y", "z"], 3) + nan.tobytes())
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        assert len(read_scan(tmp_path / "empty.ply")) == 0
        assert len(read_scan(tmp_path / "nan.ply")) == 0
    assert f"{tmp_path / 'empty.ply'}: the scan holds no points" in caplog.text
    assert f"{tmp_path / 'nan.ply'}: all 3 points have NaN/inf coordinates" in caplog.text


# --------------------------------------------------------------------------------------------
# trajectories: one rotation rule for KITTI and TUM
# --------------------------------------------------------------------------------------------


def test_tum_quaternion_norm_follows_the_kitti_rotation_rule(run_pa, tmp_path):
    T = _poses(3)
    write_tum(tmp_path / "ok.tum", T, np.arange(3) * 0.1)
    rows = [line.split() for line in (tmp_path / "ok.tum").read_text().splitlines()]
    rows[1][7] = "1.05"  # qw of pose 1: norm 1.05
    (tmp_path / "warn.tum").write_text("\n".join(" ".join(r) for r in rows) + "\n")
    code, _, err = run_pa("perturb", tmp_path / "warn.tum", "--level", "1", "--out", tmp_path / "noisy.tum")
    assert code == 0, err
    assert _flat("warn.tum: quaternions normalised (largest deviation 0.05 > 0.001 at pose 1)") in _flat(err)
    rows[1][7] = "1.2"
    (tmp_path / "bad.tum").write_text("\n".join(" ".join(r) for r in rows) + "\n")
    out = tmp_path / "noisy_bad.tum"
    _refused(run_pa("perturb", tmp_path / "bad.tum", "--level", "1", "--out", out),
             "bad.tum: pose 1 has quaternion norm deviating from 1 by 0.2 > 0.1", outputs=[out])


@pytest.mark.parametrize("write_ascii,compressed", [(True, False), (False, False), (False, True)])
def test_pcd_written_by_open3d(tmp_path, write_ascii, compressed):
    from pa_cli.runtime.open3d_preload import open3d

    o3d = open3d()
    rng = np.random.default_rng(4)
    xyz = np.round(rng.normal(size=(500, 3)) * 10, 2)
    intensity = rng.integers(0, 100, size=(500, 1)).astype(np.float32)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
    cloud.point["intensity"] = o3d.core.Tensor(intensity)
    path = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(path), cloud, write_ascii=write_ascii, compressed=compressed)
    expected = "ascii" if write_ascii else "binary_compressed" if compressed else "binary"
    assert f"DATA {expected}\n".encode() in path.read_bytes()[:1000]
    scan = read_scan(path)  # Open3D's ASCII rows end with a space; values have two decimals: exact
    np.testing.assert_array_equal(scan.points_scan, xyz)
    np.testing.assert_array_equal(scan.intensity, intensity[:, 0])
