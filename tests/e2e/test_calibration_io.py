"""The extrinsics YAML, the rig file, the rig folder of `pa simulate --rig`, scan matching, and the
errors `pa calibrate` gives for bad inputs (exit codes and messages naming file, expectation, fix)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml

from pa_cli.calibration.rig_scans import match_by_time, open_rig
from pa_cli.core.geometry import exp_so3
from pa_cli.errors import FormatError, InputError, OutputError, UsageError
from pa_cli.io.extrinsics import format_extrinsics, read_extrinsics, write_extrinsics
from pa_cli.simulate.rig import MountedSimulator, read_rig
from pa_cli.simulate.sensor import SimOptions, in_horizontal_fov

RIG = {"lidars": [{"xyz_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0], "beams": 16},
                  {"xyz_m": [0.3, -0.4, 0.2], "rpy_deg": [2.0, 10.0, -30.0], "beams": 16, "hfov_deg": 180.0}]}


def _extrinsics(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[1:, :3, :3] = exp_so3(rng.normal(0, 1.0, (n - 1, 3)))
    T[1:, :3, 3] = rng.normal(0, 1.0, (n - 1, 3))
    return T


def test_extrinsics_round_trip_and_rpy_agree_with_the_matrix(tmp_path) -> None:
    T = _extrinsics(3, 0)
    path = tmp_path / "x.yaml"
    write_extrinsics(path, T, {1: {"unobservable": ["lidar1: translation along base x"]}})
    np.testing.assert_allclose(read_extrinsics(path, 3), T, atol=1e-11)
    data = yaml.safe_load(path.read_text())
    assert data["lidars"]["lidar1"]["unobservable"] == ["lidar1: translation along base x"]
    # xyz + rpy alone give the same transform (a hand-measured --init)
    for entry in data["lidars"].values():
        del entry["T_base_lidar"]
    path.write_text(yaml.safe_dump(data))
    np.testing.assert_allclose(read_extrinsics(path, 3), T, atol=1e-8)
    with pytest.raises(OutputError, match="already exists; pass --force"):
        write_extrinsics(path, T)


def test_extrinsics_errors_name_the_file_and_the_fix(tmp_path) -> None:
    path = tmp_path / "x.yaml"
    path.write_text(format_extrinsics(_extrinsics(2, 1)))
    with pytest.raises(FormatError, match=r"x\.yaml: expected the LiDARs lidar0, lidar1, lidar2.*missing: lidar2"):
        read_extrinsics(path, 3)
    bad = _extrinsics(2, 1)
    bad[0, 0, 3] = 1.0
    path.write_text(format_extrinsics(bad))
    with pytest.raises(FormatError, match="lidar0 is the base frame"):
        read_extrinsics(path, 2)
    path.write_text("lidars: {lidar1: {xyz_m: [1, 2], rpy_deg: [0, 0, 0]}}\n")
    with pytest.raises(FormatError, match=r"lidar1\.xyz_m must be a list of 3 finite numbers"):
        read_extrinsics(path, 2)
    with pytest.raises(InputError, match="extrinsics file not found"):
        read_extrinsics(tmp_path / "missing.yaml")


def test_rig_file_validation(tmp_path) -> None:
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(RIG))
    lidars = read_rig(path)
    assert [lidar.beams for lidar in lidars] == [16, 16] and lidars[1].hfov_deg == 180.0
    for change, message in ((lambda r: r["lidars"][1].update(beams=8), r"lidars\[1\]\.beams must be one of"),
                            (lambda r: r["lidars"][1].update(hfov_deg=400), r"hfov_deg must be in \(0, 360\]"),
                            (lambda r: r["lidars"][0].update(pitch=1), "unknown keys pitch"),
                            (lambda r: r["lidars"].pop(), "expected 'lidars:' with 2 to")):
        rig = yaml.safe_load(yaml.safe_dump(RIG))
        change(rig)
        path.write_text(yaml.safe_dump(rig))
        with pytest.raises(UsageError, match=message):
            read_rig(path)


def test_horizontal_field_of_view_keeps_the_beams_within_it() -> None:
    az = np.deg2rad(np.arange(-180, 180, 5.0))
    dirs = np.column_stack([np.cos(az), np.sin(az), np.zeros_like(az)])
    kept = np.rad2deg(az[in_horizontal_fov(dirs, 90.0)])
    assert kept.min() == -45.0 and kept.max() == 45.0
    assert in_horizontal_fov(dirs, 360.0).all()


def test_mounted_lidar_casts_from_its_mounting_pose() -> None:
    options = SimOptions(scene="office", scans=2, azimuth_steps=64, range_noise_m=0.0)
    mount = np.eye(4)
    mount[:3, 3] = [0.3, -0.2, 0.1]
    mount[:3, :3] = exp_so3(np.array([[0.0, 0.2, 0.5]]))[0]
    sim = MountedSimulator(options, mount, 180.0)
    scan = sim.scan(1)
    assert np.all(scan.points_scan[:, 0] >= -1e-9)  # a 180 deg field of view sees ahead only
    # points are exact in the mounted frame: on their true planes at T_world_vehicle @ mount
    T = sim.gt_poses()[1]
    q = scan.points_scan @ T[:3, :3].T + T[:3, 3]
    labelled = scan.labels >= 0
    planes = sim.planes_world[scan.labels[labelled]]
    assert np.abs(np.einsum("ij,ij->i", planes[:, :3], q[labelled]) + planes[:, 3]).max() < 1e-9


def test_simulate_rig_writes_the_rig_layout(run_pa, tmp_path) -> None:
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(RIG))
    out = tmp_path / "rig"
    code, _, err = run_pa("simulate", "office", str(out), "--rig", str(tmp_path / "rig.yaml"), "--scans", "3",
                          "--azimuth-steps", "64")
    assert code == 0, err
    assert sorted(p.name for p in (out / "lidar1").iterdir()) == ["000000.pcd", "000001.pcd", "000002.pcd"]
    assert {"times.txt", "gt_poses_kitti.txt", "gt_poses_tum.txt", "gt_extrinsics.yaml", "rig.yaml",
            "meta.json"} <= {p.name for p in out.iterdir()}
    X = read_extrinsics(out / "gt_extrinsics.yaml", 2)
    np.testing.assert_allclose(X[1][:3, 3], [0.3, -0.4, 0.2], atol=1e-12)
    rig = open_rig(out, 0.02)
    assert rig.matched_by == "times.txt" and rig.n_lidars == 2 and len(rig.matches[1]) == 3


def test_match_by_time_pairs_nearest_within_tolerance() -> None:
    base = np.arange(5) * 0.1
    own = np.array([0.004, 0.11, 0.13, 0.35, 0.41])  # 0.13 loses to 0.11; 0.35 is 0.05 from both
    pairs = match_by_time(base, own, 0.02)
    assert pairs.tolist() == [[0, 0], [1, 1], [4, 4]]


def test_calibrate_input_errors(run_pa, tmp_path) -> None:
    (tmp_path / "rig").mkdir()
    (tmp_path / "rig" / "lidar0").mkdir()
    code, _, err = run_pa("calibrate", str(tmp_path / "rig"), "--out", str(tmp_path / "x.yaml"))
    assert code == 1 and "lidar0/, lidar1/ a rig needs" in err
    code, _, err = run_pa("calibrate", str(tmp_path / "rig"), "--out", str(tmp_path / "x.txt"))
    assert code == 2 and ".yaml" in err
    (tmp_path / "x.yaml").write_text("taken")
    code, _, err = run_pa("calibrate", str(tmp_path / "rig"), "--out", str(tmp_path / "x.yaml"))
    assert code == 1 and "already exists; pass --force" in err
    assert (tmp_path / "x.yaml").read_text() == "taken"


def test_help_lists_calibrate(run_pa) -> None:
    code, out, _ = run_pa("--help")
    assert code == 0 and "calibrate" in out
    code, out, _ = run_pa("calibrate", "--help")
    assert code == 0 and "--init" in out and "--poses" in out


def test_rig_without_times_matches_by_index(tmp_path, caplog) -> None:
    from pa_cli.io.scans import write_pcd

    rng = np.random.default_rng(0)
    for k, n in ((0, 3), (1, 2)):
        (tmp_path / f"lidar{k}").mkdir()
        for i in range(n):
            write_pcd(tmp_path / f"lidar{k}" / f"{i:06d}.pcd", rng.normal(size=(20, 3)))
    with caplog.at_level(logging.WARNING, logger="pa_cli"):
        rig = open_rig(tmp_path, 0.02)
    assert rig.matched_by == "index" and rig.base_timestamps is None
    assert rig.matches[0].tolist() == [[0, 0], [1, 1], [2, 2]] and rig.matches[1].tolist() == [[0, 0], [1, 1]]
    assert "matching scan k with base scan k for the first 2" in caplog.text


def test_an_empty_scan_written_by_the_simulator_reads_back(tmp_path) -> None:
    from pa_cli.io.scans import read_scan, write_pcd

    # a rig LiDAR mounted inside an obstacle (a pole, a parked car) returns nothing for a scan
    write_pcd(tmp_path / "empty.pcd", np.empty((0, 3)), intensity=np.empty(0, dtype=np.float32))
    scan = read_scan(tmp_path / "empty.pcd")
    assert scan.points_scan.shape == (0, 3)
