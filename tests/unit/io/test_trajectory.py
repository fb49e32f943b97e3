"""Trajectory I/O: KITTI / TUM round trips, detection, orthonormalisation and error paths."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.errors import FormatError, InputError, OutputError
from pa_cli.io.trajectory import read_timestamps, read_trajectory, write_kitti, write_trajectory, write_tum


def _poses(n=25, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * 30
    T[0, :3, 3] = [1e-12, -2e-13, 5e-11]  # tiny values must not be written in scientific notation
    return T


def test_kitti_round_trip_fixed_point(tmp_path):
    T = _poses()
    write_kitti(tmp_path / "p.txt", T)
    text = (tmp_path / "p.txt").read_text()
    assert not re.search(r"[eE]", text)
    assert all(len(line.split()) == 12 for line in text.splitlines())
    traj = read_trajectory(tmp_path / "p.txt")
    assert traj.timestamps is None and len(traj) == 25
    np.testing.assert_allclose(traj.T_world_scan, T, rtol=0, atol=2e-9)


def test_tum_round_trip_keeps_timestamps(tmp_path):
    T = _poses()
    stamps = 1630577768.569102 + 0.5 * np.arange(25)
    write_tum(tmp_path / "p.tum", T, stamps)
    text = (tmp_path / "p.tum").read_text()
    assert not re.search(r"[eE]", text)
    assert text.splitlines()[1].split()[0] == f"{stamps[1]:.9f}"
    traj = read_trajectory(tmp_path / "p.tum")
    np.testing.assert_allclose(traj.timestamps, stamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(traj.T_world_scan, T, rtol=0, atol=5e-9)
    write_trajectory(tmp_path / "p2.tum", traj, "tum")
    assert (tmp_path / "p2.tum").read_text() == text


def test_tum_without_timestamps_writes_index_with_warning(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        write_tum(tmp_path / "p.tum", _poses(3), None)
    assert "frame index" in caplog.text
    np.testing.assert_array_equal(read_trajectory(tmp_path / "p.tum").timestamps, [0, 1, 2])


def test_comments_commas_and_format_override(tmp_path):
    T = _poses(3)
    rows = T[:, :3, :4].reshape(3, 12)
    text = "# header comment\n\n" + "\n".join(",".join(f"{v:.12f}" for v in r) for r in rows) + "\n"
    (tmp_path / "p.txt").write_text(text)
    np.testing.assert_allclose(read_trajectory(tmp_path / "p.txt", "kitti").T_world_scan, T, atol=1e-11)
    with pytest.raises(FormatError, match="--format tum expects 8"):
        read_trajectory(tmp_path / "p.txt", "tum")


@pytest.mark.parametrize(("name", "text", "match"), [
    ("seven.txt", "1 2 3 4 5 6 7\n", "7 columns; expected 12 .* or 8"),
    ("mixed.txt", "0 0 0 0 0 0 0 1\n0 0 0 0 0 0 1\n", r"mixed\.txt:2: 7 columns, but earlier rows have 8"),
    ("word.txt", "0 0 0 x 0 0 0 1\n", "non-numeric"),
    ("nan.txt", "0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n", "pose 1 contains NaN"),
    ("empty.txt", "# nothing\n", "no poses"),
])
def test_malformed_rows_are_refused(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(FormatError, match=match):
        read_trajectory(tmp_path / name)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_trajectory(tmp_path / "none.txt")
    with pytest.raises(InputError, match="is a folder"):
        read_trajectory(tmp_path)


def test_rotation_orthonormalised_with_warning_and_non_rotation_rejected(tmp_path, caplog):
    T = _poses(4)
    noisy = T.copy()
    noisy[2, :3, :3] += 2e-3 * np.random.default_rng(1).normal(size=(3, 3))
    write_kitti(tmp_path / "noisy.txt", noisy)
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        R = read_trajectory(tmp_path / "noisy.txt").T_world_scan[:, :3, :3]
    assert "re-orthonormalised" in caplog.text
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.tile(np.eye(3), (4, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # the projection is the nearest rotation: closer to the noisy block than the original
    assert np.linalg.norm(R[2] - noisy[2, :3, :3]) <= np.linalg.norm(T[2, :3, :3] - noisy[2, :3, :3])

    bad = T.copy()
    bad[1, :3, :3] = np.diag([1.0, 1.0, -1.0])  # a reflection
    write_kitti(tmp_path / "bad.txt", bad)
    with pytest.raises(FormatError, match="pose 1 .*not a rotation"):
        read_trajectory(tmp_path / "bad.txt")
    (tmp_path / "q.tum").write_text("0 0 0 0 0 0 0 0.5\n")
    with pytest.raises(FormatError, match="quaternion norm"):
        read_trajectory(tmp_path / "q.tum")


def test_writes_refuse_overwrite(tmp_path):
    write_kitti(tmp_path / "p.txt", _poses(2))
    before = (tmp_path / "p.txt").read_text()
    with pytest.raises(OutputError, match="--force"):
        write_kitti(tmp_path / "p.txt", _poses(3))
    assert (tmp_path / "p.txt").read_text() == before
    write_kitti(tmp_path / "p.txt", _poses(3), force=True)
    assert len(read_trajectory(tmp_path / "p.txt")) == 3
    assert list(tmp_path.iterdir()) == [tmp_path / "p.txt"]  # no temporary files left


def test_read_timestamps(tmp_path):
    (tmp_path / "t.txt").write_text("# unix seconds\n1.5\n2.5\n")
    np.testing.assert_array_equal(read_timestamps(tmp_path / "t.txt"), [1.5, 2.5])
    (tmp_path / "t2.txt").write_text("1 2\n")
    with pytest.raises(FormatError, match="one timestamp per line"):
        read_timestamps(tmp_path / "t2.txt")


def test_real_balm_poses(shared_data):
    folder = shared_data / "balm-campus-30"
    kitti = read_trajectory(folder / "poses_kitti.txt")
    tum = read_trajectory(folder / "poses_tum.txt")
    assert len(kitti) == len(tum) == 30
    np.testing.assert_allclose(kitti.T_world_scan[0], np.eye(4), atol=1e-9)
    assert np.all(np.diff(tum.timestamps) > 0)
    np.testing.assert_allclose(kitti.T_world_scan[:, :3, 3], tum.T_world_scan[:, :3, 3], atol=1e-5)
